//! The solid materials in the solver, against numbers: snow's invariants
//! after every substep; a jelly block dropped on the floor keeps its shape
//! (2D 128² and 3D 32³); elastic squares colliding part, viscoplastic ones
//! stay together; and the solver's contracts with parameter sets: 1 and 2
//! threads give the same bits (2D, and 3D with water and sand interleaved in
//! every block), a checkpoint restores bit for bit, a particle
//! of a set that is not its material's is refused.
//!
//! Slower checks against beam theory and the Bingham slump live in
//! `tests/materials_slow.rs` (run with `--ignored`).

use hybridmpm_mpm::particles::det;
use hybridmpm_mpm::{
    ElasticParams, Material, MaterialParams, MpmError, Particle, SnowParams, Solver, SolverParams,
    ViscoplasticParams, lattice,
};
use nalgebra::SVector;

fn solver<const D: usize>(params: SolverParams<D>, ps: Vec<Particle<D>>) -> Solver<D>
where
    hybridmpm_mpm::Dim<D>: hybridmpm_mpm::DimOps<D>,
{
    let mut s = Solver::new(params, vec![]).unwrap();
    s.set_particles(ps).unwrap();
    s
}

/// A `side^D` lattice block at `origin` (spacing dx/2) of `material` in set `set`.
fn block<const D: usize>(
    origin: [f32; D],
    side: usize,
    dx: f32,
    material: Material,
    set: u16,
    density: f32,
) -> Vec<Particle<D>> {
    let mut ps = lattice(origin, side, dx / 2.0, material, density);
    for p in &mut ps {
        p.set = set;
    }
    ps
}

fn extents<const D: usize>(ps: &[Particle<D>]) -> [f32; D] {
    std::array::from_fn(|d| {
        let (lo, hi) = ps.iter().fold((f32::MAX, f32::MIN), |(a, b), p| {
            (a.min(p.x[d]), b.max(p.x[d]))
        });
        hi - lo
    })
}

/// Every substep (one per call of `step_frame`): the singular values of
/// each snow particle's F_E lie in [1 − θc, 1 + θs], and `J_P · det F_E`
/// follows `det F`, which advances by `det(I + Δt·C)` with the substep's C.
#[test]
fn snow_keeps_its_invariants_after_every_substep() {
    let params = SolverParams::<2> {
        n_grid: 64,
        substeps: Some(1),
        ..Default::default()
    };
    let dx = params.dx();
    let sp = params.snow.clone();
    let mut ps = block([0.35, 0.06], 24, dx, Material::Snow, 3, sp.density);
    for p in &mut ps {
        p.v = SVector::from([0.0, -3.0]);
    }
    let mut s = solver(params, ps);
    let dt = 5e-5f32;
    let mut compacted = 0;
    for _ in 0..600 {
        let before: Vec<f64> = s
            .particles()
            .iter()
            .map(|p| p.j as f64 * det(&p.f) as f64)
            .collect();
        s.step_frame(dt).unwrap();
        for (p, b) in s.particles().iter().zip(&before) {
            let step = (nalgebra::Matrix2::identity() + p.c * dt)
                .cast::<f64>()
                .determinant();
            let after = p.j as f64 * det(&p.f) as f64;
            assert!(
                (after - b * step).abs() < 2e-5 * after,
                "{after} vs {}",
                b * step
            );
            let sv = p.f.svd(false, false).singular_values;
            for &x in sv.iter() {
                assert!(
                    x >= (1.0 - sp.theta_c) * (1.0 - 2e-5)
                        && x <= (1.0 + sp.theta_s) * (1.0 + 2e-5),
                    "σ = {sv}"
                );
            }
            compacted += (p.j < 0.99) as usize;
        }
    }
    // the landing compacted snow: some J_P went down (hardening acts)
    assert!(compacted > 0);
}

/// A jelly block (E = 1e6 Pa) dropped on the floor keeps its width and
/// height within 10 % and its area (mean det F) within 5 %.
#[test]
fn a_jelly_block_dropped_keeps_its_shape_2d() {
    let params = SolverParams::<2> {
        n_grid: 128,
        elastic: ElasticParams {
            youngs_modulus: 1.0e6,
            poisson_ratio: 0.3,
            ..Default::default()
        },
        ..Default::default()
    };
    let dx = params.dx();
    let ps = block([0.4, 0.25], 40, dx, Material::Elastic, 2, 1000.0);
    let e0 = extents(&ps);
    let mut s = solver(params, ps);
    let mut miny = f32::MAX;
    for _ in 0..240 {
        s.step_frame(2.5e-3).unwrap();
        s.for_each_particle(|_, p| miny = miny.min(p.x[1]));
    }
    let ps = s.particles();
    let e = extents(&ps);
    assert!(
        miny < 0.1,
        "the block never reached the floor (lowest at {miny})"
    );
    for d in 0..2 {
        let r = e[d] / e0[d];
        assert!((0.9..=1.1).contains(&r), "extent {d}: {r}");
    }
    let area = ps.iter().map(|p| det(&p.f)).sum::<f32>() / ps.len() as f32;
    eprintln!("2D jelly: area ratio {area}");
    assert!((area - 1.0).abs() <= 0.05, "area ratio {area}");
}

/// A snow block (the paper's defaults) dropped the same way ends compacted:
/// flatter by at least 8 % or smaller by at least 5 % (its bounding box).
#[test]
fn a_snow_block_dropped_ends_compacted() {
    let params = SolverParams::<2> {
        n_grid: 128,
        ..Default::default()
    };
    let dx = params.dx();
    let ps = block([0.4, 0.25], 40, dx, Material::Snow, 3, params.snow.density);
    let e0 = extents(&ps);
    let mut s = solver(params, ps);
    for _ in 0..240 {
        s.step_frame(2.5e-3).unwrap();
    }
    let e = extents(&s.particles());
    let flatter = 1.0 - (e[1] / e[0]) / (e0[1] / e0[0]);
    let smaller = 1.0 - (e[0] * e[1]) / (e0[0] * e0[1]);
    eprintln!("snow: flatter by {flatter:.3}, smaller by {smaller:.3}");
    assert!(
        flatter >= 0.08 || smaller >= 0.05,
        "flatter {flatter}, smaller {smaller}"
    );
}

/// The same in 3D on a 32³ grid: each extent within 10 %.
#[test]
fn a_jelly_cube_dropped_keeps_its_shape_3d() {
    let params = SolverParams::<3> {
        n_grid: 32,
        elastic: ElasticParams {
            youngs_modulus: 1.0e6,
            poisson_ratio: 0.3,
            ..Default::default()
        },
        ..Default::default()
    };
    let dx = params.dx();
    let ps = block([0.35, 0.3, 0.35], 16, dx, Material::Elastic, 2, 1000.0);
    let e0 = extents(&ps);
    let mut s = solver(params, ps);
    let mut miny = f32::MAX;
    for _ in 0..200 {
        s.step_frame(2.5e-3).unwrap();
        s.for_each_particle(|_, p| miny = miny.min(p.x[1]));
    }
    let ps = s.particles();
    assert!(
        miny < 0.12,
        "the cube never reached the floor (lowest at {miny})"
    );
    let e = extents(&ps);
    eprintln!("3D jelly: extents {:?} of {:?}", e, e0);
    for d in 0..3 {
        let r = e[d] / e0[d];
        assert!((0.9..=1.1).contains(&r), "extent {d}: {r}");
    }
}

/// Two squares of `material` (set `set`) meeting head-on at ±1 m/s without
/// gravity: the ratio of their centroids' parting speed to their approach
/// speed, 0.2 s after the start.
fn collide(material: Material, params: SolverParams<2>) -> f32 {
    let dx = params.dx();
    let set = material as u16;
    let mut a = block([0.25, 0.45], 20, dx, material, set, 1000.0);
    let mut b = block([0.65, 0.45], 20, dx, material, set, 1000.0);
    for p in &mut a {
        p.v = SVector::from([1.0, 0.0]);
    }
    for p in &mut b {
        p.v = SVector::from([-1.0, 0.0]);
    }
    let na = a.len();
    a.extend(b);
    let mut s = solver(params, a);
    for _ in 0..80 {
        s.step_frame(2.5e-3).unwrap();
    }
    let ps = s.particles();
    let mean = |q: &[Particle<2>]| q.iter().map(|p| p.v[0]).sum::<f32>() / q.len() as f32;
    (mean(&ps[na..]) - mean(&ps[..na])) / 2.0
}

#[test]
fn elastic_squares_part_and_viscoplastic_ones_stay_together() {
    let base = SolverParams::<2> {
        n_grid: 128,
        gravity: [0.0, 0.0],
        ..Default::default()
    };
    let elastic = collide(
        Material::Elastic,
        SolverParams {
            elastic: ElasticParams {
                youngs_modulus: 1.0e5,
                poisson_ratio: 0.3,
                ..Default::default()
            },
            ..base.clone()
        },
    );
    eprintln!("elastic squares: parting/approach = {elastic}");
    assert!(elastic >= 0.6, "elastic: parting/approach = {elastic}");
    let mud = collide(
        Material::Viscoplastic,
        SolverParams {
            viscoplastic: ViscoplasticParams {
                yield_stress: 20.0,
                viscosity: 0.0,
                youngs_modulus: 1.0e5,
                ..Default::default()
            },
            ..base
        },
    );
    eprintln!("viscoplastic squares: parting/approach = {mud}");
    assert!(mud.abs() <= 0.3, "viscoplastic: parting/approach = {mud}");
}

/// Water, two sand sets, two jellies, snow and mud: the bits of one thread
/// on two, and a checkpoint taken mid-run continues bit for bit.
#[test]
fn parameter_sets_are_deterministic_and_checkpoint_bitwise() {
    let run = |threads: usize| {
        let params = SolverParams::<2> {
            n_grid: 64,
            num_threads: threads,
            sets: vec![
                MaterialParams::Elastic(ElasticParams {
                    youngs_modulus: 3.0e4,
                    ..Default::default()
                }),
                MaterialParams::Sand(hybridmpm_mpm::SandParams {
                    friction_angle_deg: 40.0,
                    ..Default::default()
                }),
                MaterialParams::Snow(SnowParams::default()),
            ],
            ..Default::default()
        };
        let dx = params.dx();
        let mut ps = block([0.1, 0.1], 12, dx, Material::Water, 0, 1000.0);
        ps.extend(block([0.3, 0.1], 12, dx, Material::Sand, 1, 1000.0));
        ps.extend(block([0.3, 0.3], 12, dx, Material::Sand, 6, 1000.0));
        ps.extend(block([0.5, 0.1], 12, dx, Material::Elastic, 2, 1000.0));
        ps.extend(block([0.5, 0.3], 12, dx, Material::Elastic, 5, 1000.0));
        ps.extend(block([0.7, 0.1], 12, dx, Material::Snow, 7, 400.0));
        ps.extend(block([0.7, 0.4], 12, dx, Material::Viscoplastic, 4, 1500.0));
        // interleave the sand sets in storage (a batch flushes at a set change)
        ps.swap(150, 300);
        for p in &mut ps {
            p.v = SVector::from([0.5, -1.0]);
        }
        let mut s = solver(params, ps);
        for _ in 0..15 {
            s.step_frame(2.5e-3).unwrap();
        }
        let mid = s.checkpoint();
        for _ in 0..15 {
            s.step_frame(2.5e-3).unwrap();
        }
        s.restore(&mid).unwrap();
        let again: Vec<u8> = {
            for _ in 0..15 {
                s.step_frame(2.5e-3).unwrap();
            }
            s.checkpoint()
        };
        (mid, again)
    };
    let (mid1, end1) = run(1);
    let (mid2, end2) = run(2);
    assert_eq!(mid1, mid2);
    assert_eq!(end1, end2);
    assert_ne!(mid1, end1);
}

/// A parameter set appended in place mid-run (`add_parameter_set`, what a
/// pour does) steps on bit for bit as a solver made with the set from the
/// start and restored from the same state; a bad set is refused naming its
/// key, the table unchanged.
#[test]
fn a_parameter_set_appended_in_place_steps_as_one_given_at_the_start() {
    let elastic = ElasticParams {
        youngs_modulus: 5.0e4,
        ..Default::default()
    };
    let jelly = MaterialParams::Elastic(elastic.clone());
    let params = SolverParams::<2> {
        n_grid: 64,
        ..Default::default()
    };
    let dx = params.dx();
    let mut a = solver(
        params.clone(),
        block([0.1, 0.1], 12, dx, Material::Water, 0, 1000.0),
    );
    for _ in 0..10 {
        a.step_frame(2.5e-3).unwrap();
    }
    let mid = a.checkpoint();
    let mut b = Solver::<2>::new(
        SolverParams {
            sets: vec![jelly.clone()],
            ..params
        },
        Vec::new(),
    )
    .unwrap();
    b.restore(&mid).unwrap();
    let bad = MaterialParams::Elastic(ElasticParams {
        youngs_modulus: -1.0,
        ..elastic
    });
    match a.add_parameter_set(bad) {
        Err(MpmError::InvalidInput { field, .. }) => {
            assert!(field.starts_with("sets[0]."), "{field}")
        }
        other => panic!("{other:?}"),
    }
    assert_eq!(a.material_table().len(), 5);
    assert_eq!(a.add_parameter_set(jelly).unwrap(), 5);
    assert_eq!(a.material_table(), b.material_table());
    for s in [&mut a, &mut b] {
        s.add_particles(block([0.5, 0.3], 8, dx, Material::Elastic, 5, 1000.0))
            .unwrap();
        for _ in 0..20 {
            s.step_frame(2.5e-3).unwrap();
        }
    }
    assert_eq!(a.checkpoint(), b.checkpoint());
}

/// A particle whose set is not of its material, or past the table, is
/// refused naming `material_set`; the solver keeps its particles.
#[test]
fn a_particle_of_a_foreign_set_is_refused() {
    let params = SolverParams::<2>::default();
    let dx = params.dx();
    let mut s = solver(params, block([0.4, 0.4], 4, dx, Material::Water, 0, 1000.0));
    for set in [1u16, 9] {
        let bad = block([0.6, 0.4], 4, dx, Material::Elastic, set, 1000.0);
        match s.add_particles(bad) {
            Err(MpmError::InvalidInput { field, .. }) => assert_eq!(field, "material_set"),
            other => panic!("{other:?}"),
        }
        assert_eq!(s.num_particles(), 16);
    }
    let bad_e = SolverParams::<2> {
        sets: vec![MaterialParams::Viscoplastic(ViscoplasticParams {
            yield_stress: -1.0,
            ..Default::default()
        })],
        ..Default::default()
    };
    match Solver::new(bad_e, vec![]) {
        Err(MpmError::InvalidInput { field, .. }) => {
            assert_eq!(field, "sets[0].viscoplastic.yield_stress")
        }
        Err(e) => panic!("{e}"),
        Ok(_) => panic!("accepted a negative yield stress"),
    }
}

/// Water and two sand sets interleaved particle by particle in 3D (every
/// grid block holds all three, in turn in storage order), thrown into a
/// corner so that sand yields: one and two threads give the same bits.
/// (g2p updates sand sixteen particles at a time, and its 3D route is one
/// per batch: the batches must not depend on how a team cuts a block.)
#[test]
fn interleaved_water_and_sand_sets_give_one_threads_bits_in_3d() {
    let run = |threads: usize| {
        let params = SolverParams::<3> {
            n_grid: 32,
            num_threads: threads,
            sets: vec![MaterialParams::Sand(hybridmpm_mpm::SandParams {
                friction_angle_deg: 40.0,
                youngs_modulus: 2.0e4,
                ..Default::default()
            })],
            ..Default::default()
        };
        let dx = params.dx();
        let water = block([0.3; 3], 14, dx, Material::Water, 0, 1000.0);
        let sand = block([0.3; 3], 14, dx, Material::Sand, 1, 1500.0);
        let ps: Vec<Particle<3>> = water
            .into_iter()
            .zip(sand)
            .enumerate()
            .map(|(i, (w, s))| {
                let mut p = if i % 3 == 0 { w } else { s };
                if i % 3 == 2 {
                    p.set = 5;
                }
                p.v = SVector::from([3.0, -6.0, 2.0]);
                p
            })
            .collect();
        let mut s = solver(params, ps);
        for _ in 0..20 {
            s.step_frame(2.5e-3).unwrap();
        }
        (s.checkpoint(), s.mode_runs())
    };
    let (one, _) = run(1);
    let (two, (_, team)) = run(2);
    assert!(team > 0, "the team never ran");
    assert!(one == two, "two threads changed the bits");
}
