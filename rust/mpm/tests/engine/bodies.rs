//! Rigid bodies coupled two ways with the fluid (docs/bodies.md): floating
//! at their Archimedes depth, sinking, conserving momentum, keeping the
//! fluid out, and the same bits for any thread count.

#![allow(clippy::needless_range_loop)]

use hybridmpm_mpm::{Body, BodyParams, BodyShape, BodyShapeKind, Integrator, Solver, SolverParams};
use nalgebra::SVector;

use crate::common::{sdf, water};

const DT: f32 = 2.5e-3;

fn frames() -> usize {
    std::env::var("BODIES_FRAMES")
        .ok()
        .and_then(|s| s.parse().ok())
        .unwrap_or(1200)
}

/// A box body of half extents `h` at `center`, density `rho`, tilted `angle_deg`.
fn boxed<const D: usize>(center: &[f32], h: &[f32], rho: f32, angle_deg: f64) -> Body<D> {
    BodyParams {
        shape: Some(BodyShapeKind::Box),
        center: Some(center.to_vec()),
        half_extents: Some(h.to_vec()),
        angle_deg: (D == 2 && angle_deg != 0.0).then_some(angle_deg),
        density: Some(rho),
        ..Default::default()
    }
    .build::<D>("body")
    .unwrap()
}

/// The water level [m] in the columns of `x` in `[x0, x1]`: the mean over
/// its columns of a quarter cell above the top particle's centre (the
/// particles start half a cell apart, so the top one sits a quarter cell
/// below the surface).
fn level(s: &Solver<2>, x0: f32, x1: f32) -> f32 {
    let dx = s.params().dx();
    let cols = ((x1 - x0) / dx).ceil().max(1.0) as usize;
    let mut top = vec![f32::MIN; cols];
    s.for_each_particle(|_, p| {
        if p.x[0] >= x0 && p.x[0] < x1 {
            let c = (((p.x[0] - x0) / dx) as usize).min(cols - 1);
            top[c] = top[c].max(p.x[1]);
        }
    });
    let top: Vec<f32> = top.into_iter().filter(|&t| t > f32::MIN).collect();
    top.iter().sum::<f32>() / top.len().max(1) as f32 + 0.25 * dx
}

/// The body's horizontal reach from its centre [m] at its current pose.
fn half_width(s: &Solver<2>, i: usize) -> f32 {
    let r = s.bodies().states()[i].rotation::<2>();
    match &s.bodies().bodies()[i].shape {
        BodyShape::Box { half_extents: h } => (r[(0, 0)] * h[0]).abs() + (r[(0, 1)] * h[1]).abs(),
        shape => shape.bounding_radius(),
    }
}

/// The water level [m] beside body `i`: in the columns from 1 to 4 cells
/// beyond its extent on either side.
fn level_beside(s: &Solver<2>, i: usize) -> f32 {
    let dx = s.params().dx();
    let st = &s.bodies().states()[i];
    let half = half_width(s, i);
    let (a, b) = (st.x[0] - half, st.x[0] + half);
    0.5 * (level(s, a - 4.0 * dx, a - dx) + level(s, b + dx, b + 4.0 * dx))
}

/// The mean level [m] of the columns farther than 4 cells from every body.
fn far_level(s: &Solver<2>) -> (f32, f32, f32) {
    let dx = s.params().dx();
    let lo = (s.params().walls.cells - 1) as f32 * dx;
    let mut tops = Vec::new();
    let mut x = lo;
    while x + dx <= 1.0 - lo {
        let c = x + 0.5 * dx;
        let clear = (0..s.bodies().len()).all(|i| {
            let st = &s.bodies().states()[i];
            (c - st.x[0]).abs() > half_width(s, i) + 4.0 * dx
        });
        if clear {
            tops.push(level(s, x, x + dx));
        }
        x += dx;
    }
    let mean = tops.iter().sum::<f32>() / tops.len().max(1) as f32;
    let lo = tops.iter().cloned().fold(f32::MAX, f32::min);
    let hi = tops.iter().cloned().fold(f32::MIN, f32::max);
    (mean, lo, hi)
}

/// Mass of the water [kg per unit depth] lying on body `i`'s top face
/// (within its width, up to 2 cells above it), as a share of the body's mass.
fn water_on_top(s: &Solver<2>, i: usize) -> f32 {
    let dx = s.params().dx();
    let st = &s.bodies().states()[i];
    let r = st.rotation::<2>();
    let BodyShape::Box { half_extents: h } = s.bodies().bodies()[i].shape.clone() else {
        return 0.0;
    };
    let c = SVector::<f32, 2>::new(st.x[0], st.x[1]);
    let mut m = 0.0;
    s.for_each_particle(|_, p| {
        let q = r.tr_mul(&(p.x - c));
        // the face pointing most upwards: the body's axis closest to +y
        for (axis, sign) in [(0usize, 1.0f32), (0, -1.0), (1, 1.0), (1, -1.0)] {
            let up = sign * r[(1, axis)];
            if up > 0.7 {
                let o = 1 - axis;
                let along = sign * q[axis] - h[axis];
                if q[o].abs() < h[o] && along > 0.0 && along < 2.0 * dx {
                    m += p.mass;
                }
            }
        }
    });
    m / s.bodies().bodies()[i].mass()
}

/// The share of a box's area (2D) of half extents `h` at centre height `y0`,
/// rotation `r`, below height `y`, by sampling.
fn share_below(h: &SVector<f32, 2>, r: &nalgebra::Matrix2<f32>, y0: f32, y: f32) -> f32 {
    let k = 200;
    let mut below = 0;
    for a in 0..k {
        for b in 0..k {
            let q = SVector::<f32, 2>::new(
                ((a as f32 + 0.5) / k as f32 * 2.0 - 1.0) * h[0],
                ((b as f32 + 0.5) / k as f32 * 2.0 - 1.0) * h[1],
            );
            if y0 + (r * q)[1] < y {
                below += 1;
            }
        }
    }
    below as f32 / (k * k) as f32
}

/// The share of body `i`'s area (2D) below height `y`.
fn submerged_share(s: &Solver<2>, i: usize, y: f32) -> f32 {
    let st = &s.bodies().states()[i];
    let BodyShape::Box { half_extents: h } = s.bodies().bodies()[i].shape.clone() else {
        unreachable!("boxes only")
    };
    share_below(&h, &st.rotation::<2>(), st.x[1], y)
}

/// One run of the floating boxes ([`float_boxes_2d`]).
struct FloatCase {
    n_grid: usize,
    frames: usize,
    /// Frames at the end over which the shares are measured.
    last: usize,
    /// Every box moved along x by this many cells.
    shift_cells: f32,
    /// Every box tilted by this angle [degrees].
    tilt_deg: f64,
    /// The explicit substeps or the projection (its bodies coupled in the pressure solve).
    integrator: Integrator,
}

/// Per box: mean share below the level, worst error, expected share.
struct Floated {
    mean: Vec<f64>,
    worst: Vec<f32>,
    expected: Vec<f32>,
    tol: f32,
}

/// Water 0.4 m deep in a tank of `c.n_grid`², at rest (its volume ratio
/// `J` hydrostatic), and boxes of 0.12 × 0.08 m of 250, 500 and 750 kg/m³
/// placed, tilted, with their share below the surface at ρ_b / ρ_w; the
/// share of each box's area below the level beside it ([`level_beside`]),
/// over the last `c.last` of `c.frames` frames.
fn float_boxes_2d(c: &FloatCase) -> Floated {
    let p = SolverParams::<2> {
        n_grid: c.n_grid,
        num_threads: 2,
        integrator: c.integrator,
        ..Default::default()
    };
    let dx = p.dx();
    // the water rests a cell inside the wall band (`wall_face` in
    // python/hybridmpm/scenes/core.py): it starts there, at rest
    let lo = (p.walls.cells - 1) as f32 * dx;
    // 0.4 m of water, rounded to the lattice's rows (dx/2 apart)
    let surface = lo + (0.4 / (0.5 * dx)).round() * 0.5 * dx;
    let h = SVector::<f32, 2>::new(0.06, 0.04);
    let rhos = [250.0f32, 500.0, 750.0];
    let xs = [0.3f32, 0.55, 0.8];
    let rot = nalgebra::Rotation2::new(c.tilt_deg.to_radians() as f32).into_inner();
    let bodies: Vec<Body<2>> = rhos
        .iter()
        .zip(xs)
        .map(|(&rho, x)| {
            // the centre height at which the share below the surface is ρ_b / ρ_w
            let want = rho / p.water.density;
            let (mut a, mut b) = (surface - h.norm(), surface + h.norm());
            for _ in 0..40 {
                let m = 0.5 * (a + b);
                if share_below(&h, &rot, m, surface) > want {
                    a = m;
                } else {
                    b = m;
                }
            }
            let centre = [x + c.shift_cells * dx, 0.5 * (a + b)];
            boxed::<2>(&centre, h.as_slice(), rho, c.tilt_deg)
        })
        .collect();
    let mut s = Solver::new(p.clone(), vec![]).unwrap();
    for b in &bodies {
        s.add_body(b.clone()).unwrap();
    }
    let mut ps = water([lo, lo], [1.0 - lo, surface], &p, &bodies, 0.0, false);
    let g = -p.gravity[1];
    for q in ps.iter_mut() {
        // at rest: the pressure K (1 − J) of the water above
        q.j = 1.0 - p.water.density * g * (surface - q.x[1]) / p.water.bulk_modulus;
    }
    s.set_particles(ps).unwrap();
    let trace = std::env::var_os("BODIES_TRACE").is_some();
    let nb = bodies.len();
    let mut worst = vec![0.0f32; nb];
    let mut mean = vec![0.0f64; nb];
    let mut counted = 0;
    for f in 0..c.frames {
        s.step_frame(DT).unwrap();
        if trace && f % 20 == 0 {
            let (far, far_lo, far_hi) = far_level(&s);
            eprintln!("f {f} far level {far:.4} [{far_lo:.4}, {far_hi:.4}]");
            for i in 0..nb {
                let y = level_beside(&s, i);
                let st = &s.bodies().states()[i];
                let m = s.bodies().bodies()[i].mass();
                eprintln!(
                    "  body {i} level {y:.4} y {:.4} vy {:.4} tilt {:.2} share {:.3} far {:.3} on top {:.3} F/mg {:.3}",
                    st.x[1],
                    st.v[1],
                    st.q[1].atan2(st.q[0]).to_degrees(),
                    submerged_share(&s, i, y),
                    submerged_share(&s, i, far),
                    water_on_top(&s, i),
                    s.bodies().last_force()[i][1] / (m as f64 * g as f64)
                );
            }
        }
        if f + c.last >= c.frames {
            counted += 1;
            for i in 0..nb {
                let share = submerged_share(&s, i, level_beside(&s, i));
                let err = (share - rhos[i] / p.water.density).abs();
                worst[i] = worst[i].max(err);
                mean[i] += share as f64;
            }
        }
    }
    let tol = (dx + 0.02 * 2.0 * h[1]) / (2.0 * h[1]);
    let expected: Vec<f32> = rhos.iter().map(|r| r / p.water.density).collect();
    for i in 0..nb {
        mean[i] /= counted as f64;
        eprintln!(
            "n_grid {} shift {} cells tilt {}°: density {}: mean share {:.4} (expected {:.3}), worst error {:.4} (tolerance {tol:.4})",
            c.n_grid, c.shift_cells, c.tilt_deg, rhos[i], mean[i], expected[i], worst[i]
        );
    }
    Floated {
        mean,
        worst,
        expected,
        tol,
    }
}

fn assert_floated(r: &Floated) {
    for i in 0..r.worst.len() {
        assert!(
            r.worst[i] <= r.tol,
            "box {i} (expected share {}): mean share {}, worst error {} > {}",
            r.expected[i],
            r.mean[i],
            r.worst[i],
            r.tol
        );
    }
}

/// The full run: 128², the last 400 of 1,200 frames (`BODIES_FRAMES`
/// changes the length), untilted and unshifted or as `BODIES_SHIFT` cells
/// and `BODIES_TILT` degrees say.
#[test]
#[ignore = "slow (about a minute): benchmarks/bodies/run.py runs it"]
fn boxes_float_at_their_archimedes_depth_2d() {
    let env = |k: &str, d: f64| {
        std::env::var(k)
            .ok()
            .and_then(|s| s.parse().ok())
            .unwrap_or(d)
    };
    let r = float_boxes_2d(&FloatCase {
        n_grid: 128,
        frames: frames(),
        last: 400.min(frames() / 3),
        shift_cells: env("BODIES_SHIFT", 0.0) as f32,
        tilt_deg: env("BODIES_TILT", 0.0),
        integrator: integrator(),
    });
    assert_floated(&r);
}

/// The short run in the test suite: 128², the last 120 of 240 frames, the
/// boxes shifted by 3 cells and tilted by 10° (the full runs, untilted and
/// tilted, are benchmarks/bodies/run.py's).
#[test]
fn boxes_float_at_their_archimedes_depth_2d_short() {
    boxes_float_short(Integrator::Explicit);
}

/// The short run on the projection: its pressure solve holds the boxes up
/// (`crate::projection`'s `bodies.rs`), within the explicit run's tolerance.
#[test]
fn boxes_float_at_their_archimedes_depth_2d_short_projection() {
    boxes_float_short(Integrator::Projection);
}

fn boxes_float_short(integrator: Integrator) {
    assert_floated(&float_boxes_2d(&FloatCase {
        n_grid: 128,
        frames: 240,
        last: 120,
        shift_cells: 3.0,
        tilt_deg: 10.0,
        integrator,
    }));
}

/// `BODIES_INTEGRATOR=projection` runs the full checks on the projection.
fn integrator() -> Integrator {
    match std::env::var("BODIES_INTEGRATOR").as_deref() {
        Ok("projection") => Integrator::Projection,
        _ => Integrator::Explicit,
    }
}

/// The share of a 3D box's volume of half extents `h`, centre height
/// `y0`, rotation `r`, below height `y`, by sampling.
fn share_below_3d(h: &SVector<f32, 3>, r: &nalgebra::Matrix3<f32>, y0: f32, y: f32) -> f32 {
    let k = 40;
    let mut below = 0;
    for a in 0..k {
        for b in 0..k {
            for c in 0..k {
                let t = |i: usize, d: usize| ((i as f32 + 0.5) / k as f32 * 2.0 - 1.0) * h[d];
                let q = SVector::<f32, 3>::new(t(a, 0), t(b, 1), t(c, 2));
                if y0 + (r * q)[1] < y {
                    below += 1;
                }
            }
        }
    }
    below as f32 / (k * k * k) as f32
}

/// The water level [m] beside body `i` in 3D: the mean over the columns
/// (one cell square) from 1 to 4 cells beyond the body's extent in x or z
/// of a quarter cell above the top particle's centre.
fn level_beside_3d(s: &Solver<3>, i: usize) -> f32 {
    let dx = s.params().dx();
    let n = s.params().n_grid;
    let st = &s.bodies().states()[i];
    let r = st.rotation::<3>();
    let BodyShape::Box { half_extents: h } = s.bodies().bodies()[i].shape.clone() else {
        unreachable!("boxes only")
    };
    let ext = |d: usize| (0..3).map(|k| (r[(d, k)] * h[k]).abs()).sum::<f32>();
    let (ex, ez) = (ext(0), ext(2));
    let mut top = vec![f32::MIN; n * n];
    s.for_each_particle(|_, p| {
        let (cx, cz) = ((p.x[0] / dx) as usize, (p.x[2] / dx) as usize);
        let t = &mut top[cx.min(n - 1) * n + cz.min(n - 1)];
        *t = t.max(p.x[1]);
    });
    let (mut sum, mut cols) = (0.0f32, 0);
    for cx in 0..n {
        for cz in 0..n {
            let x = (cx as f32 + 0.5) * dx - st.x[0];
            let z = (cz as f32 + 0.5) * dx - st.x[2];
            let away = ((x.abs() - ex).max(z.abs() - ez)) / dx;
            let t = top[cx * n + cz];
            if (1.0..=4.0).contains(&away) && t > f32::MIN {
                sum += t;
                cols += 1;
            }
        }
    }
    sum / cols.max(1) as f32 + 0.25 * dx
}

/// A cube of 500 kg/m³ (0.14 m a side) on a 32³ tank of water 0.25 m deep
/// at rest, placed at its Archimedes depth: over the last `last` of
/// `frames` frames the share of its volume below the level beside it stays
/// within (one cell + 2 % of its height) / height of ρ_b / ρ_w. Returns
/// (mean share, worst error, tolerance).
fn float_cube_3d(
    frames: usize,
    last: usize,
    tilt_deg: f32,
    integrator: Integrator,
) -> (f64, f32, f32) {
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
    let surface = lo + (0.25 / (0.5 * dx)).round() * 0.5 * dx;
    let h = SVector::<f32, 3>::new(0.07, 0.07, 0.07);
    let rho = 500.0;
    let rot =
        nalgebra::Rotation3::from_axis_angle(&nalgebra::Vector3::z_axis(), tilt_deg.to_radians());
    let want = rho / p.water.density;
    let (mut a, mut b) = (surface - h.norm(), surface + h.norm());
    for _ in 0..30 {
        let m = 0.5 * (a + b);
        if share_below_3d(&h, rot.matrix(), m, surface) > want {
            a = m;
        } else {
            b = m;
        }
    }
    let cube: Body<3> = BodyParams {
        shape: Some(BodyShapeKind::Box),
        center: Some(vec![0.45, 0.5 * (a + b), 0.55]),
        half_extents: Some(h.as_slice().to_vec()),
        rotation: Some(
            (0..3)
                .map(|c| (0..3).map(|k| rot[(k, c)]).collect())
                .collect(),
        ),
        density: Some(rho),
        ..Default::default()
    }
    .build::<3>("body")
    .unwrap();
    let mut s = Solver::new(p.clone(), vec![]).unwrap();
    s.add_body(cube.clone()).unwrap();
    let mut ps = water(
        [lo, lo, lo],
        [1.0 - lo, surface, 1.0 - lo],
        &p,
        &[cube],
        0.0,
        false,
    );
    let g = -p.gravity[1];
    for q in ps.iter_mut() {
        q.j = 1.0 - p.water.density * g * (surface - q.x[1]) / p.water.bulk_modulus;
    }
    s.set_particles(ps).unwrap();
    let (mut worst, mut mean, mut counted) = (0.0f32, 0.0f64, 0);
    for f in 0..frames {
        s.step_frame(DT).unwrap();
        if f + last >= frames {
            let st = &s.bodies().states()[0];
            let share = share_below_3d(&h, &st.rotation::<3>(), st.x[1], level_beside_3d(&s, 0));
            worst = worst.max((share - want).abs());
            mean += share as f64;
            counted += 1;
        }
    }
    let tol = (dx + 0.02 * 2.0 * h[1]) / (2.0 * h[1]);
    mean /= counted as f64;
    eprintln!(
        "cube 32³ tilt {tilt_deg}°: density {rho}: mean share {mean:.4} (expected {want:.3}), worst error {worst:.4} (tolerance {tol:.4})"
    );
    (mean, worst, tol)
}

/// The cube's short run in the test suite: the last 120 of 240 frames,
/// tilted by 10° (the full run is benchmarks/bodies/run.py's).
#[test]
fn cube_floats_at_its_archimedes_depth_3d_short() {
    cube_floats_short(Integrator::Explicit);
}

/// The cube's short run on the projection.
#[test]
fn cube_floats_at_its_archimedes_depth_3d_short_projection() {
    cube_floats_short(Integrator::Projection);
}

fn cube_floats_short(integrator: Integrator) {
    let (mean, worst, tol) = float_cube_3d(240, 120, 10.0, integrator);
    assert!(
        worst <= tol,
        "mean share {mean}, worst error {worst} > {tol}"
    );
}

/// The cube's full run: the last 400 of 1,200 frames (`BODIES_FRAMES`),
/// tilted by `BODIES_TILT` degrees (default 0).
#[test]
#[ignore = "slow: benchmarks/bodies/run.py runs it"]
fn cube_floats_at_its_archimedes_depth_3d() {
    let tilt = std::env::var("BODIES_TILT")
        .ok()
        .and_then(|s| s.parse().ok())
        .unwrap_or(0.0);
    let (mean, worst, tol) = float_cube_3d(frames(), 400.min(frames() / 3), tilt, integrator());
    assert!(
        worst <= tol,
        "mean share {mean}, worst error {worst} > {tol}"
    );
}

/// Deepest a particle sits inside a body [m] (0: none inside).
fn deepest(s: &Solver<2>) -> f32 {
    let mut worst = 0.0f32;
    let bodies = s.bodies();
    s.for_each_particle(|_, p| {
        for (b, st) in bodies.bodies().iter().zip(bodies.states()) {
            let mut at = b.clone();
            at.center = SVector::from_fn(|d, _| st.x[d]);
            at.rotation = st.rotation();
            worst = worst.max(-sdf(&at, &p.x));
        }
    });
    worst
}

/// Total momentum of the particles and the bodies [kg·m/s per unit depth].
fn momentum(s: &Solver<2>) -> ([f64; 2], [f64; 2]) {
    let mut fluid = [0.0f64; 2];
    s.for_each_particle(|_, p| {
        for d in 0..2 {
            fluid[d] += (p.mass * p.v[d]) as f64;
        }
    });
    let mut body = [0.0f64; 2];
    for (b, st) in s.bodies().bodies().iter().zip(s.bodies().states()) {
        for d in 0..2 {
            body[d] += b.mass() as f64 * st.v[d] as f64;
        }
    }
    (fluid, body)
}

/// No gravity: a water block moving at 1 m/s hits a free box; while nothing
/// reaches a wall the total momentum (particles and body) holds within 3 %,
/// the body carries at least 5 % of it, and no particle is inside the box
/// by more than a quarter cell.
#[test]
fn water_hitting_a_free_box_conserves_momentum() {
    let p = SolverParams::<2> {
        n_grid: 128,
        gravity: [0.0, 0.0],
        num_threads: 2,
        ..Default::default()
    };
    let dx = p.dx();
    let body = boxed::<2>(&[0.55, 0.5], &[0.04, 0.06], 500.0, 0.0);
    let mut s = Solver::new(p.clone(), vec![]).unwrap();
    s.add_body(body.clone()).unwrap();
    let mut ps = water([0.2, 0.42], [0.4, 0.58], &p, &[], 0.0, false);
    for q in ps.iter_mut() {
        q.v[0] = 1.0;
    }
    s.set_particles(ps).unwrap();
    let (f0, _) = momentum(&s);
    let mut worst_leak = 0.0f32;
    let mut share = 0.0;
    let mut worst_err = 0.0f64;
    for _ in 0..100 {
        s.step_frame(DT).unwrap();
        let (f, b) = momentum(&s);
        let err = ((f[0] + b[0] - f0[0]).powi(2) + (f[1] + b[1]).powi(2)).sqrt() / f0[0];
        worst_err = worst_err.max(err);
        share = b[0] / f0[0];
        worst_leak = worst_leak.max(deepest(&s));
    }
    eprintln!(
        "momentum error {worst_err:.5}, body's share {share:.4}, deepest particle {:.3} cells",
        worst_leak / dx
    );
    assert!(worst_err <= 0.03, "momentum error {worst_err}");
    assert!(share >= 0.05, "body's share {share}");
    assert!(
        worst_leak <= 0.25 * dx,
        "a particle {} cells inside",
        worst_leak / dx
    );
}

/// A box of 2000 kg/m³ sinks to the floor.
#[test]
fn heavy_box_sinks_to_the_floor() {
    let p = SolverParams::<2> {
        n_grid: 64,
        num_threads: 2,
        ..Default::default()
    };
    let dx = p.dx();
    let lo = p.walls.cells as f32 * dx;
    let h = [0.06f32, 0.05];
    let body = boxed::<2>(&[0.5, lo + 0.3], &h, 2000.0, 0.0);
    let mut s = Solver::new(p.clone(), vec![]).unwrap();
    s.add_body(body.clone()).unwrap();
    s.set_particles(water(
        [lo, lo],
        [1.0 - lo, lo + 0.35],
        &p,
        &[body],
        0.0,
        false,
    ))
    .unwrap();
    for _ in 0..400 {
        s.step_frame(DT).unwrap();
    }
    let bottom = s.bodies().states()[0].x[1] - h[1];
    eprintln!("bottom {:.3} cells above the floor", (bottom - lo) / dx);
    assert!(
        bottom - lo < 0.5 * dx,
        "bottom {} m above the floor",
        bottom - lo
    );
}

/// 1 and 2 threads give the same bits, bodies included.
#[test]
fn one_and_two_threads_same_bits_with_bodies() {
    let run = |threads: usize| {
        let p = SolverParams::<2> {
            n_grid: 64,
            num_threads: threads,
            ..Default::default()
        };
        let dx = p.dx();
        let lo = p.walls.cells as f32 * dx;
        let bodies = [
            boxed::<2>(&[0.6, 0.45], &[0.05, 0.04], 400.0, 20.0),
            boxed::<2>(&[0.8, 0.3], &[0.04, 0.04], 1500.0, 0.0),
        ];
        let mut s = Solver::new(p.clone(), vec![]).unwrap();
        for b in &bodies {
            s.add_body(b.clone()).unwrap();
        }
        s.set_particles(water([lo, lo], [0.45, 0.6], &p, &bodies, 0.0, false))
            .unwrap();
        for _ in 0..60 {
            s.step_frame(DT).unwrap();
        }
        let xs: Vec<u32> = s
            .particles()
            .iter()
            .flat_map(|q| {
                q.x.iter()
                    .chain(q.v.iter())
                    .map(|x| x.to_bits())
                    .collect::<Vec<_>>()
            })
            .collect();
        (xs, s.bodies().states().to_vec())
    };
    let (a, ba) = run(1);
    let (b, bb) = run(2);
    assert!(a == b, "particles differ between 1 and 2 threads");
    assert_eq!(ba, bb, "bodies differ between 1 and 2 threads");
}
