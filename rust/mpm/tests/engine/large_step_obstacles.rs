//! Colliders in the projection step (`projection/obstacles.rs`): solid
//! cells with their own velocity. Water at rest around a box stays at rest
//! and out of it; a dam break against a tall box is held by it as the
//! explicit engine holds it; a box moving through still water pushes it,
//! the same bits on one thread and two; obstacles that are not free slip are
//! refused naming the field.

use hybridmpm_mpm::particles::lattice_box;
use hybridmpm_mpm::{
    BoundaryCondition, Collider, Integrator, Material, Particle, Shape, Solver, SolverParams,
};
use nalgebra::SVector;

const DT_FRAME: f32 = 2.5e-3;
const N: usize = 64;

fn dx() -> f32 {
    1.0 / N as f32
}

/// A box collider, free slip, projecting particles (as the scenes' obstacles do).
fn block(lo: [f32; 2], hi: [f32; 2]) -> Collider<2> {
    Collider {
        shape: Shape::Box {
            center: SVector::from([(lo[0] + hi[0]) / 2.0, (lo[1] + hi[1]) / 2.0]),
            half_extents: SVector::from([(hi[0] - lo[0]) / 2.0, (hi[1] - lo[1]) / 2.0]),
            rotation: nalgebra::SMatrix::identity(),
        },
        condition: BoundaryCondition::Separate,
        friction: 0.0,
        project: true,
    }
}

/// Water on the lattice of two particles per cell per axis over `[lo, hi]`, less what lies inside `col`.
fn water_around(lo: [f32; 2], hi: [f32; 2], col: &Collider<2>) -> Vec<Particle<2>> {
    let s = dx() / 2.0;
    let n = [
        ((hi[0] - lo[0]) / s).round() as usize,
        ((hi[1] - lo[1]) / s).round() as usize,
    ];
    lattice_box(lo, n, s, Material::Water, 1000.0)
        .into_iter()
        .filter(|p| col.shape.sdf(&p.x) > 0.0)
        .collect()
}

fn solver(integrator: Integrator, threads: usize, cols: Vec<Collider<2>>) -> Solver<2> {
    let p = SolverParams {
        n_grid: N,
        num_threads: threads,
        integrator,
        ..Default::default()
    };
    Solver::new(p, cols).unwrap()
}

/// The deepest a particle lies inside `col` [cells] (0 when none is inside).
fn deepest(s: &Solver<2>, col: &Collider<2>) -> f32 {
    s.particles()
        .iter()
        .map(|p| (-col.shape.sdf(&p.x)).max(0.0) / dx())
        .fold(0.0, f32::max)
}

#[test]
fn water_at_rest_around_a_box_stays_at_rest_and_out_of_it() {
    let floor = 2.0 * dx();
    let col = block([0.45, floor], [0.55, 0.35]);
    let mut s = solver(Integrator::Projection, 0, vec![col.clone()]);
    let ps = water_around([floor, floor], [1.0 - floor, 0.25], &col);
    let count = ps.len();
    s.set_particles(ps).unwrap();
    let cells = |s: &Solver<2>| {
        let mut c = std::collections::HashSet::new();
        for p in s.particles() {
            c.insert(((p.x[0] / dx()) as i32, (p.x[1] / dx()) as i32));
        }
        c.len()
    };
    let c0 = cells(&s);
    let (mut steps, mut vmax) = (0, 0.0f32);
    for _ in 0..400 {
        let st = s.step_frame(DT_FRAME).unwrap();
        steps += st.substeps;
        vmax = vmax.max(st.max_speed);
    }
    assert_eq!(s.particles().len(), count);
    // at rest: no flow starts at the box (a leak through its faces would drain one side into it)
    assert!(vmax < 0.05, "the water moved at {vmax} m/s");
    assert!(steps <= 150, "{steps} steps over 400 frames at rest");
    // out of the box, as the particle projection leaves it
    let d = deepest(&s, &col);
    assert!(d < 0.5, "a particle {d} cells inside the box");
    // and its volume kept: the cells holding a particle within 2 %
    let c1 = cells(&s);
    assert!(
        (c1 as f32 / c0 as f32 - 1.0).abs() < 0.02,
        "{c0} cells held, then {c1}"
    );
}

#[test]
fn a_tall_box_turns_a_dam_break_up_its_face_as_the_explicit_engine_does() {
    let floor = 2.0 * dx();
    // the column 12 × 24 cells; the box 4 cells thick, 56 tall (the surge cannot top it in 120 frames), 8 cells
    // downstream of the column
    let (x0, x1) = (floor + 20.0 * dx(), floor + 24.0 * dx());
    let col = block([x0, floor], [x1, floor + 56.0 * dx()]);
    let column = || lattice_box([floor; 2], [24, 48], dx() / 2.0, Material::Water, 1000.0);
    let mut runs = Vec::new();
    for integrator in [Integrator::Explicit, Integrator::Projection] {
        let mut s = solver(integrator, 0, vec![col.clone()]);
        s.set_particles(column()).unwrap();
        let (mut steps, mut hit, mut deep) = (0, None, 0.0f32);
        for f in 0..120 {
            steps += s.step_frame(DT_FRAME).unwrap().substeps;
            let xmax = s.particles().iter().map(|p| p.x[0]).fold(0.0f32, f32::max);
            if hit.is_none() && xmax > x0 - dx() {
                hit = Some(f);
            }
            deep = deep.max(deepest(&s, &col));
        }
        let ps = s.particles();
        let beyond = ps.iter().filter(|p| p.x[0] > x1).count();
        let run_up = ps.iter().map(|p| p.x[1]).fold(0.0f32, f32::max);
        runs.push((steps, hit.unwrap_or(usize::MAX), beyond, run_up, deep));
    }
    let ((se, he, be, ye, de), (sp, hp, bp, yp, dp)) = (runs[0], runs[1]);
    // the box holds the surge on the projection: nothing passes it (a few of the explicit engine's particles
    // slip under it along the floor), and the particles stay out of it
    assert_eq!(
        bp, 0,
        "particles past the box: {bp} projection ({be} explicit)"
    );
    assert!(
        dp < 0.5,
        "a projection particle {dp} cells inside the box (explicit: {de})"
    );
    // the surge reaches the box as soon (within 15 %: the projection's front leads the explicit one's a little,
    // as on Martin & Moyce's dam break) and runs up its face as high (within a tenth)
    assert!(
        (he.abs_diff(hp) as f32) < 0.15 * he as f32,
        "the surge reaches the box at frame {he} explicit, {hp} projection"
    );
    assert!(
        (ye - yp).abs() < 0.1 * ye,
        "the run-up reaches {ye} m explicit, {yp} m projection"
    );
    assert!(ye > 0.55, "the run-up reaches {ye} m only");
    assert!(
        sp * 4 <= se,
        "{sp} projection steps against {se} explicit substeps"
    );
}

#[test]
fn a_moving_box_pushes_still_water_the_same_bits_on_one_thread_and_two() {
    let floor = 2.0 * dx();
    let col = block([0.2, floor], [0.25, 0.3]);
    let ps = water_around([floor, floor], [1.0 - floor, 0.2], &col);
    let mut runs = Vec::new();
    for threads in [1, 2] {
        let mut s = solver(Integrator::Projection, threads, vec![col.clone()]);
        s.set_particles(ps.clone()).unwrap();
        for _ in 0..20 {
            s.step_frame(DT_FRAME).unwrap();
        }
        // pushed right at 0.5 m/s for 60 frames: every frame steps (no step spans a moving frame)
        let mut anchor = s.collider_anchor(0).unwrap();
        for _ in 0..60 {
            anchor[0] += 0.5 * DT_FRAME;
            s.move_collider(0, anchor, None).unwrap();
            assert!(s.step_frame(DT_FRAME).unwrap().substeps >= 1);
            assert_eq!(s.drift_frames(), 0);
        }
        runs.push(s);
    }
    assert!(
        runs[0].checkpoint() == runs[1].checkpoint(),
        "1 and 2 threads differ"
    );
    let s = &runs[0];
    let px: f32 = s.particles().iter().map(|p| p.v[0]).sum::<f32>() / s.particles().len() as f32;
    assert!(px > 0.01, "the water's mean x velocity is {px} m/s");
    let d = deepest(s, &s.colliders()[0]);
    assert!(d < 0.5, "a particle {d} cells inside the moving box");
}

#[test]
fn an_obstacle_that_is_not_free_slip_is_refused_naming_colliders() {
    let floor = 2.0 * dx();
    for (condition, friction) in [
        (BoundaryCondition::Separate, 0.3),
        (BoundaryCondition::Sticky, 0.0),
    ] {
        let mut col = block([0.45, floor], [0.55, 0.35]);
        col.condition = condition;
        col.friction = friction;
        let mut s = solver(Integrator::Projection, 1, vec![col.clone()]);
        s.set_particles(water_around([floor, floor], [0.4, 0.2], &col))
            .unwrap();
        let before = s.checkpoint();
        assert_eq!(
            s.step_frame(DT_FRAME).unwrap_err().field(),
            Some("colliders")
        );
        assert!(
            s.checkpoint() == before,
            "a refused frame changed the state"
        );
    }
}
