//! Physics checks of the MLS-MPM solver that do not need Python.

use hybridmpm_mpm::{BoundaryCondition, Material, Particle, Solver, SolverParams};
use nalgebra::{SMatrix, SVector};

fn lcg(seed: &mut u64) -> f32 {
    *seed = seed
        .wrapping_mul(6364136223846793005)
        .wrapping_add(1442695040888963407);
    (*seed >> 40) as f32 / (1u64 << 24) as f32
}

fn block<const D: usize>(
    lo: [f32; D],
    counts: [usize; D],
    spacing: f32,
    mat: Material,
    p: &SolverParams<D>,
) -> Vec<Particle<D>> {
    let vol = spacing.powi(D as i32);
    let rho = if mat == Material::Water {
        p.water.density
    } else {
        p.sand.density
    };
    let total: usize = counts.iter().product();
    (0..total)
        .map(|mut i| {
            let mut x = SVector::<f32, D>::zeros();
            for d in (0..D).rev() {
                x[d] = lo[d] + (i % counts[d]) as f32 * spacing + 0.5 * spacing;
                i /= counts[d];
            }
            Particle::new(x, mat, rho * vol, vol)
        })
        .collect()
}

#[test]
fn free_fall_matches_ballistic_motion() {
    let params = SolverParams::<2>::default();
    let mut s = Solver::new(params.clone(), vec![]).unwrap();
    let dx = params.dx();
    let mut ps = block([0.4, 0.6], [16, 16], dx / 2.0, Material::Water, &params);
    let v0 = SVector::<f32, 2>::new(0.3, 0.5);
    for p in ps.iter_mut() {
        p.v = v0;
    }
    let x0: Vec<_> = ps.iter().map(|p| p.x).collect();
    s.set_particles(ps).unwrap();
    let frames = 40;
    for _ in 0..frames {
        s.step_frame(2.5e-3).unwrap();
    }
    let t = s.time() as f32;
    let g = SVector::<f32, 2>::new(0.0, -9.8);
    let mut max_err = 0.0f32;
    for (p, x0) in s.particles().iter().zip(x0) {
        let expect = x0 + v0 * t + g * (0.5 * t * t);
        max_err = max_err.max((p.x - expect).norm());
    }
    // symplectic Euler adds g·t·dt/2 (≈ 1e-4 m); grid accuracy is dx = 7.8e-3 m
    assert!(max_err < 0.05 * dx, "max deviation {max_err} m");
}

fn momentum<const D: usize>(ps: &[Particle<D>]) -> SVector<f64, D> {
    let mut m = SVector::<f64, D>::zeros();
    for p in ps {
        m += p.v.cast::<f64>() * p.mass as f64;
    }
    m
}

fn random_state<const D: usize>(seed: u64) -> (Solver<D>, Vec<Particle<D>>)
where
    hybridmpm_mpm::Dim<D>: hybridmpm_mpm::DimOps<D>,
{
    let params = SolverParams::<D> {
        gravity: [0.0; D],
        substeps: Some(1),
        ..Default::default()
    };
    let mut seed = seed;
    let dx = params.dx();
    let n = if D == 2 { 2000 } else { 3000 };
    let mut ps = Vec::new();
    for i in 0..n {
        let mut x = SVector::<f32, D>::zeros();
        for d in 0..D {
            x[d] = 0.3 + 0.4 * lcg(&mut seed);
        }
        let mat = if i % 3 == 0 {
            Material::Sand
        } else {
            Material::Water
        };
        let vol = (dx / 2.0).powi(D as i32);
        let mut p = Particle::new(x, mat, 1000.0 * vol * (0.5 + lcg(&mut seed)), vol);
        for d in 0..D {
            p.v[d] = lcg(&mut seed) - 0.5;
        }
        p.c = SMatrix::<f32, D, D>::from_fn(|_, _| 0.0);
        for k in 0..D * D {
            p.c[k] = 2.0 * (lcg(&mut seed) - 0.5);
        }
        p.j = 0.98 + 0.04 * lcg(&mut seed);
        p.f = SMatrix::<f32, D, D>::identity() + SMatrix::<f32, D, D>::from_fn(|_, _| 0.0);
        for k in 0..D * D {
            p.f[k] += 0.02 * (lcg(&mut seed) - 0.5);
        }
        ps.push(p);
    }
    let mut s = Solver::new(params, vec![]).unwrap();
    s.set_particles(ps.clone()).unwrap();
    (s, ps)
}

fn check_momentum<const D: usize>()
where
    hybridmpm_mpm::Dim<D>: hybridmpm_mpm::DimOps<D>,
{
    for seed in 1..4 {
        let (mut s, ps) = random_state::<D>(seed);
        let before = momentum(&ps);
        let mass_before: f64 = ps.iter().map(|p| p.mass as f64).sum();
        // one substep: p2g, grid update (no gravity, no wall contact), g2p
        s.step_frame(1e-5).unwrap();
        let after = momentum(&s.particles());
        let mass_after: f64 = s.particles().iter().map(|p| p.mass as f64).sum();
        let scale: f64 = ps.iter().map(|p| (p.v.norm() * p.mass) as f64).sum();
        assert!(
            (after - before).norm() < 1e-5 * scale,
            "{D}D momentum {before} -> {after}"
        );
        assert_eq!(mass_before, mass_after);
    }
}

#[test]
fn p2g_g2p_conserve_momentum_2d() {
    check_momentum::<2>();
}

#[test]
fn p2g_g2p_conserve_momentum_3d() {
    check_momentum::<3>();
}

fn run_threads<const D: usize>(threads: usize) -> Vec<u8>
where
    hybridmpm_mpm::Dim<D>: hybridmpm_mpm::DimOps<D>,
{
    let (s0, ps) = random_state::<D>(7);
    let mut params = s0.params().clone();
    params.num_threads = threads;
    params.substeps = None;
    params.gravity[1] = -9.8;
    let mut s = Solver::new(params, vec![]).unwrap();
    s.set_particles(ps).unwrap();
    for _ in 0..5 {
        s.step_frame(2.5e-3).unwrap();
    }
    s.checkpoint()
}

#[test]
fn bitwise_identical_for_one_and_two_threads() {
    assert_eq!(run_threads::<2>(1), run_threads::<2>(2));
    assert_eq!(run_threads::<3>(1), run_threads::<3>(2));
}

#[test]
fn checkpoint_round_trip_continues_identically() {
    let (mut a, _) = random_state::<2>(3);
    a.step_frame(1e-4).unwrap();
    let blob = a.checkpoint();
    let mut b = Solver::new(a.params().clone(), vec![]).unwrap();
    b.restore(&blob).unwrap();
    a.step_frame(1e-4).unwrap();
    b.step_frame(1e-4).unwrap();
    assert_eq!(a.checkpoint(), b.checkpoint());
    assert!(b.restore(&blob[..blob.len() - 3]).is_err());
    assert!(b.restore(b"garbage").is_err());
}

#[test]
fn nonfinite_state_is_reported_and_rolled_back() {
    let params = SolverParams::<2>::default();
    let mut s = Solver::new(params.clone(), vec![]).unwrap();
    let mut ps = block(
        [0.4, 0.4],
        [8, 8],
        params.dx() / 2.0,
        Material::Water,
        &params,
    );
    ps[5].ext = SVector::<f32, 2>::new(f32::MAX, 0.0);
    s.set_particles(ps.clone()).unwrap();
    let before = s.checkpoint();
    let err = s.step_frame(2.5e-3).unwrap_err();
    assert!(
        matches!(err, hybridmpm_mpm::MpmError::NonFinite { substep: 0, .. }),
        "{err:?}"
    );
    assert_eq!(before, s.checkpoint());
}

#[test]
fn invalid_parameters_name_the_field() {
    let mut p = SolverParams::<2>::default();
    p.water.bulk_modulus = -1.0;
    let e = Solver::new(p, vec![]).err().unwrap();
    assert!(e.to_string().starts_with("water.bulk_modulus"), "{e}");
    let mut p = SolverParams::<3>::default();
    p.sand.friction_angle_deg = 95.0;
    assert!(
        Solver::new(p, vec![])
            .err()
            .unwrap()
            .to_string()
            .starts_with("sand.friction_angle_deg")
    );
    let p = SolverParams::<2>::default();
    let mut s = Solver::new(p.clone(), vec![]).unwrap();
    let mut ps = block([0.4, 0.4], [2, 2], p.dx() / 2.0, Material::Water, &p);
    ps[1].x[0] = 1.5;
    assert!(
        s.set_particles(ps)
            .err()
            .unwrap()
            .to_string()
            .starts_with("positions")
    );
}

#[test]
fn drucker_prager_limit_stress_ratio_is_sin_phi_in_2d() {
    // Plane-strain match: at yield (σ1 − σ2)/|σ1 + σ2| = sin φ.
    let sand = hybridmpm_mpm::SandParams::default();
    let (mu, la) = sand.lame();
    for phi_deg in [20.0f32, 30.0, 40.0] {
        let phi = phi_deg.to_radians();
        let alpha = <hybridmpm_mpm::Dim<2> as hybridmpm_mpm::DimOps<2>>::drucker_prager_alpha(phi);
        // strongly sheared, compressed trial strain: must be projected onto the cone
        let e0 = SVector::<f32, 2>::new(0.03, -0.09);
        let mut vc = 0.0;
        let e =
            hybridmpm_mpm::solver::drucker_prager_project::<2>(&e0, &mut vc, alpha, mu, la, 0.0);
        let tr = e.sum();
        let s1 = 2.0 * mu * e[0] + la * tr;
        let s2 = 2.0 * mu * e[1] + la * tr;
        let ratio = (s1 - s2).abs() / (s1 + s2).abs();
        assert!(
            (ratio - phi.sin()).abs() < 1e-3,
            "phi {phi_deg}: ratio {ratio} vs sin φ {}",
            phi.sin()
        );
    }
}

#[test]
fn sticky_collider_stops_particles() {
    use hybridmpm_mpm::{Collider, Shape};
    let params = SolverParams::<2>::default();
    let col = Collider {
        shape: Shape::Box {
            center: SVector::<f32, 2>::new(0.5, 0.3),
            half_extents: SVector::<f32, 2>::new(0.2, 0.03),
            rotation: SMatrix::<f32, 2, 2>::identity(),
        },
        condition: BoundaryCondition::Sticky,
        friction: 0.0,
        project: true,
    };
    let mut s = Solver::new(params.clone(), vec![col.clone()]).unwrap();
    let ps = block(
        [0.45, 0.4],
        [8, 8],
        params.dx() / 2.0,
        Material::Water,
        &params,
    );
    s.set_particles(ps).unwrap();
    for _ in 0..200 {
        s.step_frame(2.5e-3).unwrap();
    }
    // water rests on the plate: nothing inside it or below it
    for p in s.particles() {
        assert!(
            col.shape.sdf(&p.x) > -0.5 * params.dx(),
            "particle inside the collider at {}",
            p.x
        );
        assert!(p.x[1] > 0.3, "particle fell through: {}", p.x);
    }
}

#[test]
fn cfl_violation_halves_the_substep_and_retries() {
    // One fixed substep per frame and a strong uniform push: particles would
    // cross several cells in that substep. The frame must restart with the
    // substep halved until no particle travels more than dx per substep, and
    // the result must still be a free block accelerated uniformly (internal
    // forces cancel, so the mean velocity gains a·dt_frame exactly).
    let params = SolverParams::<2> {
        substeps: Some(1),
        gravity: [0.0, 0.0],
        ..Default::default()
    };
    let mut s = Solver::new(params.clone(), vec![]).unwrap();
    let mut ps = block(
        [0.45, 0.45],
        [8, 8],
        params.dx() / 2.0,
        Material::Water,
        &params,
    );
    let a = 1.0e4f32;
    for p in ps.iter_mut() {
        p.ext = SVector::<f32, 2>::new(a, 0.0);
    }
    s.set_particles(ps).unwrap();
    let dt_frame = 2.5e-3f32;
    let st = s.step_frame(dt_frame).unwrap();
    assert!(st.retries >= 1, "{st:?}");
    assert_eq!(st.substeps, 1 << st.retries);
    assert!(st.max_speed * st.dt <= params.dx(), "{st:?}");
    let n = s.particles().len() as f32;
    let vx: f32 = s.particles().iter().map(|p| p.v[0]).sum::<f32>() / n;
    let vy: f32 = s.particles().iter().map(|p| p.v[1]).sum::<f32>() / n;
    assert!(
        (vx - a * dt_frame).abs() < 1e-3 * a * dt_frame,
        "vx {vx} vs {}",
        a * dt_frame
    );
    assert!(vy.abs() < 1e-3 * a * dt_frame, "vy {vy}");
}

#[test]
fn wall_face_overrides_name_the_bad_field() {
    use hybridmpm_mpm::{WallFace, WallParams};
    let face = |friction| {
        Some(WallFace {
            condition: BoundaryCondition::Separate,
            friction,
        })
    };
    let mut p = SolverParams::<2>::default();
    let (axis, side) = WallParams::face_index("y-").unwrap();
    assert_eq!((axis, side), (1, 0));
    p.walls.faces[axis][side] = face(-0.5);
    let e = Solver::new(p.clone(), vec![]).err().unwrap().to_string();
    assert!(
        e.starts_with("walls.faces.y-.friction: must be >= 0"),
        "{e}"
    );
    p.walls.faces[1][0] = face(0.5);
    assert!(Solver::new(p.clone(), vec![]).is_ok());
    // no z walls in 2D; in 3D they are fine
    p.walls.faces[2][1] = face(0.5);
    let e = Solver::new(p, vec![]).err().unwrap().to_string();
    assert!(e.starts_with("walls.faces.z+"), "{e}");
    let mut p3 = SolverParams::<3>::default();
    p3.walls.faces[2][1] = face(0.5);
    assert!(Solver::new(p3, vec![]).is_ok());
    assert_eq!(WallParams::face_index("floor"), None);
}

#[test]
fn rough_floor_with_slip_walls_decelerates_a_sliding_block_at_mu_g() {
    // The inclined-plane problem with gravity tilted instead of the floor: a
    // cohesive sand block (it slides as one body) on the floor y-, pushed
    // along it by g_t and pressed onto it by g_n, accelerates at
    // g_t − μ·g_n. Only the floor is rough; the slip side walls do not touch it.
    use hybridmpm_mpm::WallFace;
    let (g_t, g_n) = (4.0f32, 9.8f32);
    for mu in [0.0f32, 0.2, 0.3] {
        let mut params = SolverParams::<2> {
            n_grid: 64,
            gravity: [g_t, -g_n],
            ..Default::default()
        };
        params.sand.cohesion = 500.0;
        params.walls.condition = BoundaryCondition::Slip;
        params.walls.faces[1][0] = Some(WallFace {
            condition: BoundaryCondition::Separate,
            friction: mu,
        });
        let dx = params.dx();
        let face = (params.walls.cells - 1) as f32 * dx;
        let mut s = Solver::new(params.clone(), vec![]).unwrap();
        s.set_particles(block(
            [0.2, face],
            [20, 8],
            dx / 2.0,
            Material::Sand,
            &params,
        ))
        .unwrap();
        let mean_vx = |s: &Solver<2>| {
            let ps = s.particles();
            ps.iter().map(|p| p.v[0]).sum::<f32>() / ps.len() as f32
        };
        for _ in 0..10 {
            s.step_frame(2.5e-3).unwrap();
        }
        let (t0, v0) = (s.time() as f32, mean_vx(&s));
        for _ in 0..80 {
            s.step_frame(2.5e-3).unwrap();
        }
        let a = (mean_vx(&s) - v0) / (s.time() as f32 - t0);
        let expect = g_t - mu * g_n;
        assert!(
            (a - expect).abs() < 0.05 * g_t,
            "mu {mu}: a {a} vs {expect}"
        );
    }
}
