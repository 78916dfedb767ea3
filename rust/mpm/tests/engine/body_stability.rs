//! Rigid bodies stay stable (docs/bodies.md "Stability"): a light body in a
//! dam break and 20 bodies piled in a 3D tank run without a solver error,
//! and the coupled system's mechanical energy (particles and bodies:
//! kinetic, gravitational above the floor, and the water's elastic energy)
//! never exceeds its start by more than 1 %.
//!
//! The tests here run a short version (`BODY_STABILITY_FRAMES` frames,
//! default 300 in 2D and 120 in 3D); `benchmarks/bodies/run.py` runs them
//! for 2,000 frames and records the figures.

#![allow(clippy::needless_range_loop)]

use hybridmpm_mpm::{
    Body, BodyParams, BodyShape, BodyShapeKind, Dim, DimOps, Integrator, Material, Solver,
    SolverParams,
};

use crate::common::water;

const DT: f32 = 2.5e-3;

/// Allowed rise of the mechanical energy above its start, as a share of it.
const ENERGY_RISE: f64 = 0.01;

fn frames(default: usize) -> usize {
    std::env::var("BODY_STABILITY_FRAMES")
        .ok()
        .and_then(|s| s.parse().ok())
        .unwrap_or(default)
}

/// A body: a box of half extents `size` (or a ball of radius `size[0]`),
/// density `rho`, tilted `angle_deg` (2D) or rotated by `axis_angle` (3D).
fn body<const D: usize>(
    ball: bool,
    center: &[f32],
    size: &[f32],
    rho: f32,
    rotation: Option<Vec<Vec<f32>>>,
) -> Body<D> {
    BodyParams {
        shape: Some(if ball {
            BodyShapeKind::Sphere
        } else {
            BodyShapeKind::Box
        }),
        center: Some(center.to_vec()),
        half_extents: (!ball).then(|| size.to_vec()),
        radius: ball.then_some(size[0]),
        rotation,
        density: Some(rho),
        ..Default::default()
    }
    .build::<D>("body")
    .unwrap()
}

/// A body's inertia tensor about its centre of mass in its own axes
/// [kg·m²] (2D: about z, entry (2, 2)): a box's and a ball's from their
/// formulas here (the shapes these runs build); any other shape's as the
/// engine computes it.
fn inertia<const D: usize>(b: &Body<D>) -> [[f64; 3]; 3] {
    let m = b.mass() as f64;
    let diag = |d: [f64; 3]| {
        std::array::from_fn(|i| std::array::from_fn(|j| if i == j { d[i] } else { 0.0 }))
    };
    match &b.shape {
        BodyShape::Box { half_extents } => {
            let h2: [f64; 3] = std::array::from_fn(|d| {
                if d < D {
                    (half_extents[d] as f64).powi(2)
                } else {
                    0.0
                }
            });
            diag([
                m / 3.0 * (h2[1] + h2[2]),
                m / 3.0 * (h2[0] + h2[2]),
                m / 3.0 * (h2[0] + h2[1]),
            ])
        }
        BodyShape::Ball { radius } => {
            let k = if D == 2 { 0.5 } else { 0.4 };
            diag([k * m * (*radius as f64).powi(2); 3])
        }
        other => other.local_inertia(m),
    }
}

/// Mechanical energy [J; per unit depth in 2D] of particles and bodies:
/// kinetic (bodies: also rotational), gravitational above the water's floor
/// (a cell inside the wall band),
/// and the water's elastic energy `V0 K (1 − J)² / 2`.
fn energy<const D: usize>(s: &Solver<D>) -> f64
where
    Dim<D>: DimOps<D>,
{
    let p = s.params();
    let g = -p.gravity[1] as f64;
    let lo = ((p.walls.cells - 1) as f32 * p.dx()) as f64;
    let k = p.water.bulk_modulus as f64;
    let mut e = 0.0f64;
    s.for_each_particle(|_, q| {
        let m = q.mass as f64;
        e += 0.5 * m * (q.v.norm_squared() as f64) + m * g * (q.x[1] as f64 - lo);
        if q.material == Material::Water {
            e += 0.5 * q.volume as f64 * k * (1.0 - q.j as f64).powi(2);
        }
    });
    for (b, st) in s.bodies().bodies().iter().zip(s.bodies().states()) {
        let m = b.mass() as f64;
        let v2: f64 = st.v.iter().map(|v| (*v as f64).powi(2)).sum();
        let i = inertia(b);
        // ω in the body's axes: Rᵀ ω (2D: ω about z is the same)
        let w_body: [f64; 3] = if D == 2 {
            [0.0, 0.0, st.w[2] as f64]
        } else {
            let r = st.rotation::<D>();
            std::array::from_fn(|a| (0..3).map(|c| r[(c, a)] as f64 * st.w[c] as f64).sum())
        };
        let rot: f64 = (0..3)
            .flat_map(|a| (0..3).map(move |c| (a, c)))
            .map(|(a, c)| w_body[a] * i[a][c] * w_body[c])
            .sum();
        e += 0.5 * m * v2 + 0.5 * rot + m * g * (st.x[1] as f64 - lo);
    }
    e
}

/// What a run measured: the energy's start, its largest rise over the start
/// (a share of it) and its end (a share), the most retries of a frame.
struct Run {
    e0: f64,
    rise: f64,
    end: f64,
    retries: usize,
}

fn run<const D: usize>(name: &str, s: &mut Solver<D>, n: usize) -> Run
where
    Dim<D>: DimOps<D>,
{
    let e0 = energy(s);
    let (mut rise, mut retries) = (f64::MIN, 0);
    for f in 0..n {
        let st = s
            .step_frame(DT)
            .unwrap_or_else(|e| panic!("{name}: frame {f}: {e}"));
        retries = retries.max(st.retries);
        let e = energy(s);
        assert!(e.is_finite(), "{name}: frame {f}: energy {e}");
        rise = rise.max((e - e0) / e0);
    }
    let end = energy(s) / e0;
    eprintln!(
        "{name}: {n} frames, energy at start {e0:.4} J, largest rise {:.4} %, at the end {:.2} % of the start, most retries in a frame {retries}",
        100.0 * rise,
        100.0 * end
    );
    Run {
        e0,
        rise,
        end,
        retries,
    }
}

fn check(name: &str, r: &Run) {
    assert!(
        r.rise <= ENERGY_RISE,
        "{name}: the energy rose {:.3} % above its start ({} J); at most {} %",
        100.0 * r.rise,
        r.e0,
        100.0 * ENERGY_RISE
    );
    assert!(
        r.end <= 1.0 + ENERGY_RISE,
        "{name}: energy at the end {}",
        r.end
    );
    let _ = r.retries;
}

/// Martin & Moyce's water column (0.2 × 0.4 m) on 128² collapsing onto a
/// box of 100 kg/m³ (0.08 × 0.05 m) resting on the floor in its path.
#[test]
fn light_body_in_a_dam_break() {
    light_body_in_a_dam_break_on(Integrator::Explicit, "light body in a dam break");
}

/// The same on the projection: the body coupled in the pressure solve.
#[test]
fn light_body_in_a_dam_break_projection() {
    light_body_in_a_dam_break_on(
        Integrator::Projection,
        "light body in a dam break (projection)",
    );
}

fn light_body_in_a_dam_break_on(integrator: Integrator, name: &str) {
    let p = SolverParams::<2> {
        n_grid: 128,
        num_threads: 2,
        integrator,
        ..Default::default()
    };
    let dx = p.dx();
    // the water rests a cell inside the wall band (`wall_face` in
    // python/hybridmpm/scenes/core.py): it starts there, at rest
    let lo = (p.walls.cells - 1) as f32 * dx;
    let a = 0.2;
    let h = [0.04f32, 0.025];
    // on the floor of the bodies (the wall band's inner face)
    let floor = p.walls.cells as f32 * dx;
    let b = body::<2>(
        false,
        &[lo + a + 0.2, floor + h[1] + 0.5 * dx],
        &h,
        100.0,
        None,
    );
    let mut s = Solver::new(p.clone(), vec![]).unwrap();
    s.add_body(b).unwrap();
    s.set_particles(water([lo, lo], [lo + a, lo + 2.0 * a], &p, &[], 0.0, true))
        .unwrap();
    let r = run(name, &mut s, frames(300));
    check(name, &r);
}

/// A rotation about axis `a` (unit) by `deg` degrees, as columns.
fn rotation3(a: [f32; 3], deg: f32) -> Vec<Vec<f32>> {
    let r = nalgebra::Rotation3::from_axis_angle(
        &nalgebra::Unit::new_normalize(nalgebra::Vector3::from(a)),
        deg.to_radians(),
    );
    (0..3)
        .map(|c| (0..3).map(|k| r[(k, c)]).collect())
        .collect()
}

/// 20 bodies (boxes and balls of 300 to 2500 kg/m³, tilted) stacked 5
/// high over a 2 × 2 footprint in the middle of a 32³ tank of water 0.25 m
/// deep, released at rest: they fall, float, sink and pile on each other.
#[test]
fn twenty_bodies_piled_in_a_3d_tank() {
    twenty_bodies_on(Integrator::Explicit, "20 bodies piled in a 3D tank");
}

/// The same on the projection.
#[test]
fn twenty_bodies_piled_in_a_3d_tank_projection() {
    twenty_bodies_on(
        Integrator::Projection,
        "20 bodies piled in a 3D tank (projection)",
    );
}

fn twenty_bodies_on(integrator: Integrator, name: &str) {
    let p = SolverParams::<3> {
        n_grid: 32,
        num_threads: 2,
        integrator,
        ..Default::default()
    };
    let dx = p.dx();
    // the water rests a cell inside the wall band (`wall_face` in
    // python/hybridmpm/scenes/core.py): it starts there, at rest
    let lo = (p.walls.cells - 1) as f32 * dx;
    let rhos = [300.0f32, 600.0, 900.0, 1500.0, 2500.0];
    let mut bodies = Vec::new();
    for k in 0..20 {
        let (layer, slot) = (k / 4, k % 4);
        let c = [
            0.5 + if slot % 2 == 0 { -0.07 } else { 0.07 },
            lo + 0.1 + 0.13 * layer as f32,
            0.5 + if slot / 2 == 0 { -0.07 } else { 0.07 },
        ];
        let rho = rhos[(k * 3) % rhos.len()];
        let b = if k % 3 == 2 {
            body::<3>(true, &c, &[0.05], rho, None)
        } else {
            let axis = [1.0, (k % 5) as f32 - 2.0, 0.5 * (k % 3) as f32];
            let size = [0.05, 0.04 + 0.005 * (k % 3) as f32, 0.045];
            body::<3>(false, &c, &size, rho, Some(rotation3(axis, 7.0 * k as f32)))
        };
        bodies.push(b);
    }
    let mut s = Solver::new(p.clone(), vec![]).unwrap();
    for b in &bodies {
        s.add_body(b.clone()).unwrap();
    }
    s.set_particles(water(
        [lo, lo, lo],
        [1.0 - lo, lo + 0.25, 1.0 - lo],
        &p,
        &bodies,
        0.0,
        true,
    ))
    .unwrap();
    let r = run(name, &mut s, frames(120));
    check(name, &r);
}

/// `dam_break3d` as the Python scene builds it (34³, walls 2 cells, a
/// column 7 × 14 cells wall to wall in z at hydrostatic rest), with
/// `bodies`.
fn dam_break3d(bodies: &[Body<3>]) -> Solver<3> {
    let mut p = SolverParams::<3> {
        n_grid: 34,
        ..Default::default()
    };
    p.walls.cells = 2;
    let dx = p.dx();
    let lo = (p.walls.cells - 1) as f32 * dx;
    let a = 7.0 * dx;
    let mut s = Solver::new(p.clone(), vec![]).unwrap();
    for b in bodies {
        s.add_body(b.clone()).unwrap();
    }
    s.set_particles(water(
        [lo, lo, lo],
        [lo + a, lo + 2.0 * a, 1.0 - lo],
        &p,
        bodies,
        0.0,
        true,
    ))
    .unwrap();
    s
}

/// 8 bodies in `dam_break3d`'s surge path: boxes and spheres of 300 to
/// 1500 kg/m³ resting on the floor in two rows across the channel.
fn eight_bodies() -> Vec<Body<3>> {
    let dx = 1.0 / 34.0;
    let floor = 2.0 * dx;
    (0..8)
        .map(|k| {
            let x = 0.42 + 0.12 * (k % 4) as f32;
            let z = if k < 4 { 0.33 } else { 0.67 };
            let rho = [300.0, 600.0, 900.0, 1500.0][k % 4];
            if k % 2 == 1 {
                body::<3>(true, &[x, floor + 0.05 + 0.5 * dx, z], &[0.05], rho, None)
            } else {
                let h = [0.045, 0.04, 0.06];
                body::<3>(false, &[x, floor + h[1] + 0.5 * dx, z], &h, rho, None)
            }
        })
        .collect()
}

/// The cost of 8 bodies in `dam_break3d` (benchmarks/bodies/run.py runs
/// it): `BODY_COST_REPEATS` (default 5) pairs of runs of
/// `BODY_COST_FRAMES` (default 200) frames, without and with the bodies
/// interleaved, fresh solvers each; prints each run's ms per frame and per
/// substep, and the ratios.
#[test]
#[ignore = "a timing, not a check: benchmarks/bodies/run.py runs it"]
fn cost_of_eight_bodies_in_dam_break3d() {
    let env = |k: &str, d: usize| {
        std::env::var(k)
            .ok()
            .and_then(|s| s.parse().ok())
            .unwrap_or(d)
    };
    let (repeats, n) = (env("BODY_COST_REPEATS", 5), env("BODY_COST_FRAMES", 200));
    let bodies = eight_bodies();
    for rep in 0..repeats {
        for (name, bs) in [("without", &[][..]), ("with", &bodies[..])] {
            let mut s = dam_break3d(bs);
            let mut substeps = 0;
            let t0 = std::time::Instant::now();
            for _ in 0..n {
                substeps += s.step_frame(DT).unwrap().substeps;
            }
            let secs = t0.elapsed().as_secs_f64();
            eprintln!(
                "cost repeat {rep} {name} bodies: {n} frames, {substeps} substeps, {:.3} ms per frame, {:.4} ms per substep",
                1e3 * secs / n as f64,
                1e3 * secs / substeps as f64
            );
        }
    }
}
