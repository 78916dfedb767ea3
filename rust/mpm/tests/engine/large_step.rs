//! The projection integrator as a solver option (`integrator = "projection"`,
//! `solver/large_step.rs`): a dam break's frames are the same bits on one
//! thread and two, a checkpoint restores them bitwise, the step follows the
//! flow (one step a frame where explicit MLS-MPM takes many), the water keeps
//! its volume, and what the projection cannot step is refused naming the
//! field, with the state unchanged.

use hybridmpm_mpm::particles::lattice_box;
use hybridmpm_mpm::{
    BodyParams, BodyShapeKind, BoundaryCondition, Collider, Integrator, Material, MpmError,
    Particle, Shape, Solver, SolverParams,
};
use nalgebra::SVector;

const DT_FRAME: f32 = 2.5e-3;

/// `dam_break2d`'s column on a 64² grid: 12 × 24 cells at 2 particles per cell per axis.
fn column() -> Vec<Particle<2>> {
    let dx = 1.0 / 64.0;
    lattice_box([2.0 * dx; 2], [24, 48], dx / 2.0, Material::Water, 1000.0)
}

fn params(integrator: Integrator, threads: usize) -> SolverParams<2> {
    SolverParams {
        n_grid: 64,
        num_threads: threads,
        integrator,
        ..Default::default()
    }
}

fn solver(integrator: Integrator, threads: usize) -> Solver<2> {
    let mut s = Solver::new(params(integrator, threads), vec![]).unwrap();
    s.set_particles(column()).unwrap();
    s
}

#[test]
fn a_dam_break_is_the_same_bits_on_one_thread_and_two_and_after_a_restore() {
    let (mut one, mut two) = (
        solver(Integrator::Projection, 1),
        solver(Integrator::Projection, 2),
    );
    for _ in 0..30 {
        one.step_frame(DT_FRAME).unwrap();
        two.step_frame(DT_FRAME).unwrap();
    }
    assert!(
        one.checkpoint() == two.checkpoint(),
        "1 and 2 threads differ"
    );
    // a checkpoint inside a step that spans frames keeps the frames left
    while one.drift_frames() == 0 {
        one.step_frame(DT_FRAME).unwrap();
    }
    let (saved, left, frame) = (one.checkpoint(), one.drift_frames(), one.frame());
    for _ in 0..30 {
        one.step_frame(DT_FRAME).unwrap();
    }
    let mut again = solver(Integrator::Projection, 2);
    again.restore(&saved).unwrap();
    assert_eq!(again.drift_frames(), left);
    for _ in 0..30 {
        again.step_frame(DT_FRAME).unwrap();
    }
    assert!(
        one.checkpoint() == again.checkpoint(),
        "a restored run differs"
    );
    assert_eq!(again.frame(), frame + 30);
    // an explicit solver refuses it and is unchanged
    let mut explicit = solver(Integrator::Explicit, 1);
    let before = explicit.checkpoint();
    assert!(explicit.restore(&saved).is_err());
    assert!(explicit.checkpoint() == before);
}

/// The column with a light box (50 kg/m³) and a heavy ball (2,000 kg/m³) on the floor in its path.
fn with_bodies(threads: usize) -> Solver<2> {
    let mut s = solver(Integrator::Projection, threads);
    for (shape, center, size, density) in [
        (BodyShapeKind::Box, [0.5, 0.08], 0.04, 50.0),
        (BodyShapeKind::Sphere, [0.75, 0.1], 0.05, 2000.0),
    ] {
        let body = BodyParams {
            shape: Some(shape),
            center: Some(center.to_vec()),
            half_extents: (shape == BodyShapeKind::Box).then(|| vec![size, 0.75 * size]),
            radius: (shape == BodyShapeKind::Sphere).then_some(size),
            density: Some(density),
            ..Default::default()
        };
        s.add_body(body.build::<2>("body").unwrap()).unwrap();
    }
    s
}

#[test]
fn bodies_in_the_projection_are_the_same_bits_on_one_thread_and_two_and_after_a_restore() {
    let (mut one, mut two) = (with_bodies(1), with_bodies(2));
    for _ in 0..40 {
        one.step_frame(DT_FRAME).unwrap();
        two.step_frame(DT_FRAME).unwrap();
        // a frame with bodies steps within itself
        assert_eq!(one.drift_frames(), 0);
    }
    assert!(
        one.checkpoint() == two.checkpoint() && one.bodies().states() == two.bodies().states(),
        "1 and 2 threads differ"
    );
    // a checkpoint: the particles' (`checkpoint`) and the bodies' exact states and last forces
    let saved = (
        one.checkpoint(),
        one.bodies().states().to_vec(),
        one.bodies().last_force().to_vec(),
    );
    for _ in 0..40 {
        one.step_frame(DT_FRAME).unwrap();
    }
    let mut again = with_bodies(2);
    again.restore(&saved.0).unwrap();
    for (i, (st, f)) in saved.1.iter().zip(&saved.2).enumerate() {
        again.set_body_state(i, *st).unwrap();
        again.set_body_force(i, *f).unwrap();
    }
    for _ in 0..40 {
        again.step_frame(DT_FRAME).unwrap();
    }
    assert!(
        one.checkpoint() == again.checkpoint() && one.bodies().states() == again.bodies().states(),
        "a restored run differs"
    );
    // the surge carries the light box along +x; the heavy ball rests on the floor; nothing runs away
    let states = one.bodies().states();
    assert!(
        states[0].x[0] > 0.505 && states[0].v[0] > 0.1,
        "{:?}",
        states[0]
    );
    assert!((states[1].x[1] - 0.1).abs() < 0.01, "{:?}", states[1]);
    for st in states {
        assert!(
            st.v.iter().all(|v| v.is_finite() && v.abs() < 5.0),
            "{st:?}"
        );
    }
}

#[test]
fn a_body_added_inside_a_step_that_spans_frames_ends_it_and_the_next_frame_steps() {
    let mut s = solver(Integrator::Projection, 0);
    while s.drift_frames() == 0 {
        s.step_frame(DT_FRAME).unwrap();
    }
    let body = BodyParams {
        shape: Some(BodyShapeKind::Box),
        center: Some(vec![0.6, 0.1]),
        half_extents: Some(vec![0.04, 0.03]),
        density: Some(500.0),
        ..Default::default()
    };
    s.add_body(body.build::<2>("body").unwrap()).unwrap();
    assert_eq!(s.drift_frames(), 0);
    assert!(s.substeps_for(DT_FRAME).unwrap() >= 1);
    let before = s.particles();
    let stats = s.step_frame(DT_FRAME).unwrap();
    assert!(stats.substeps >= 1 && stats.dt.is_finite(), "{stats:?}");
    assert!(s.particles().iter().zip(&before).any(|(a, b)| a.x != b.x));
    assert!(s.bodies().states()[0].v[1] < 0.0, "the body falls");
}

#[test]
fn a_step_spans_frames_where_the_flow_allows_and_each_frame_moves_the_particles() {
    let mut s = solver(Integrator::Projection, 0);
    let (mut steps, mut inside) = (0, 0);
    let mut last = s.particles();
    for _ in 0..200 {
        let drifting = s.drift_frames() > 0;
        assert_eq!(s.substeps_for(DT_FRAME).unwrap() == 0, drifting);
        let stats = s.step_frame(DT_FRAME).unwrap();
        steps += stats.substeps;
        inside += usize::from(drifting);
        assert_eq!(stats.substeps == 0, drifting);
        // every frame moves the falling column: no frame repeats the last one's positions
        let now = s.particles();
        assert!(now.iter().zip(&last).any(|(a, b)| a.x != b.x));
        last = now;
    }
    assert!(
        inside > 0 && steps < 200,
        "{steps} steps, {inside} frames inside a step"
    );
    // a change to the particles ends the step: the next frame steps
    while s.drift_frames() == 0 {
        s.step_frame(DT_FRAME).unwrap();
    }
    s.modify_particles(false, |_, p| p.v[0] += 0.1).unwrap();
    assert_eq!(s.drift_frames(), 0);
    assert!(s.step_frame(DT_FRAME).unwrap().substeps >= 1);
}

#[test]
fn the_projection_steps_at_the_flows_pace_and_keeps_the_volume() {
    let (mut explicit, mut projection) = (
        solver(Integrator::Explicit, 0),
        solver(Integrator::Projection, 0),
    );
    let (mut sub_e, mut sub_p) = (0, 0);
    for _ in 0..120 {
        sub_e += explicit.step_frame(DT_FRAME).unwrap().substeps;
        sub_p += projection.step_frame(DT_FRAME).unwrap().substeps;
    }
    // explicit: the sound speed (20 m/s) binds; the projection: the flow (< 2 m/s at 0.3 s)
    assert!(sub_e >= 4 * 120, "explicit took {sub_e} substeps");
    assert!(sub_p <= 2 * 120, "projection took {sub_p} steps");
    // the fronts agree (the surge's toe, as the dam-break check reads it)
    let toe = |s: &Solver<2>| s.particles().iter().map(|p| p.x[0]).fold(0.0f32, f32::max);
    let (te, tp) = (toe(&explicit), toe(&projection));
    assert!(
        (te - tp).abs() < 0.05,
        "toe at {te} m (explicit) and {tp} m (projection)"
    );
    // incompressible: the occupied area, cells holding a particle, within 5 % of the column's 12 × 24 cells
    let mut cells = std::collections::HashSet::new();
    for p in projection.particles() {
        cells.insert(((p.x[0] * 64.0) as i32, (p.x[1] * 64.0) as i32));
    }
    let area = cells.len() as f32 / (12.0 * 24.0);
    assert!(
        area > 0.95 && area < 1.25,
        "occupied cells {} against 288",
        cells.len()
    );
}

fn field_of(e: MpmError) -> String {
    match e {
        MpmError::InvalidInput { field, .. } => field,
        other => panic!("expected InvalidInput, got {other:?}"),
    }
}

#[test]
fn what_the_projection_cannot_step_is_refused_naming_the_field() {
    // sand
    let mut s = solver(Integrator::Projection, 1);
    let mut ps = column();
    ps[7].material = Material::Sand;
    ps[7].set = 1;
    s.set_particles(ps).unwrap();
    assert_eq!(field_of(s.step_frame(DT_FRAME).unwrap_err()), "integrator");
    assert_eq!(s.frame(), 0);
    // a collider with friction (free-slip ones step: large_step_obstacles.rs)
    let c = Collider {
        shape: Shape::Sphere {
            center: SVector::from([0.7, 0.2]),
            radius: 0.05,
        },
        condition: BoundaryCondition::Slip,
        friction: 0.2,
        project: false,
    };
    let mut s = Solver::new(params(Integrator::Projection, 1), vec![c]).unwrap();
    s.set_particles(column()).unwrap();
    let before = s.checkpoint();
    assert_eq!(field_of(s.step_frame(DT_FRAME).unwrap_err()), "colliders");
    assert!(
        s.checkpoint() == before,
        "a refused frame changed the state"
    );
    // sticky walls
    let mut p = params(Integrator::Projection, 1);
    p.walls.condition = BoundaryCondition::Sticky;
    let mut s = Solver::new(p, vec![]).unwrap();
    s.set_particles(column()).unwrap();
    assert_eq!(
        field_of(s.step_frame(DT_FRAME).unwrap_err()),
        "walls.condition"
    );
}

/// Past 32,768 particles the step's scans of the particles and its rollback copy go to the pool: a
/// 36,000-particle column is the same bits on one thread and two, and a frame that cannot be stepped
/// (one particle pushed at 10³⁰ m/s²) leaves the particles as they were before it.
#[test]
fn a_large_column_is_the_same_bits_on_one_thread_and_two_and_a_failed_frame_leaves_it_as_it_was() {
    let dx = 1.0 / 128.0;
    let column = lattice_box([2.0 * dx; 2], [200, 180], dx / 2.0, Material::Water, 1000.0);
    assert!(column.len() > 32_768);
    let large = |threads| {
        let p = SolverParams {
            n_grid: 128,
            ..params(Integrator::Projection, threads)
        };
        let mut s = Solver::new(p, vec![]).unwrap();
        s.set_particles(column.clone()).unwrap();
        for _ in 0..12 {
            s.step_frame(DT_FRAME).unwrap();
        }
        s
    };
    let (one, mut two) = (large(1), large(2));
    assert!(
        one.checkpoint() == two.checkpoint(),
        "1 and 2 threads differ"
    );
    while two.drift_frames() > 0 {
        two.step_frame(DT_FRAME).unwrap();
    }
    two.modify_particles(true, |i, p| {
        if i == 1000 {
            p.ext[1] = 1e30;
        }
    })
    .unwrap();
    let before = two.checkpoint();
    assert!(two.step_frame(DT_FRAME).is_err());
    assert!(
        two.checkpoint() == before,
        "the failed frame changed the state"
    );
}
