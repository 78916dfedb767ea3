//! Moving colliders (`Solver::move_collider`): the boundary condition acts
//! on the grid velocity relative to the collider's, the pose follows the
//! move exactly, and a collider that does not move is the static one bit
//! for bit.

use hybridmpm_mpm::{
    BoundaryCondition, Collider, Integrator, Material, Particle, Shape, Solver, SolverParams,
};
use nalgebra::{SMatrix, SVector};

const DT: f32 = 2.5e-3;

fn paddle(center: [f32; 2], condition: BoundaryCondition) -> Collider<2> {
    Collider {
        shape: Shape::Box {
            center: SVector::<f32, 2>::from(center),
            half_extents: SVector::<f32, 2>::new(0.03, 0.15),
            rotation: SMatrix::<f32, 2, 2>::identity(),
        },
        condition,
        friction: 0.0,
        project: true,
    }
}

/// Water particles on a lattice of `spacing` filling `[lo, hi)`, outside `skip`.
fn water(
    lo: [f32; 2],
    hi: [f32; 2],
    spacing: f32,
    p: &SolverParams<2>,
    skip: Option<&Collider<2>>,
) -> Vec<Particle<2>> {
    let vol = spacing * spacing;
    let nx = ((hi[0] - lo[0]) / spacing).round() as usize;
    let ny = ((hi[1] - lo[1]) / spacing).round() as usize;
    let mut out = Vec::new();
    for i in 0..nx {
        for j in 0..ny {
            let x = SVector::<f32, 2>::new(
                lo[0] + (i as f32 + 0.5) * spacing,
                lo[1] + (j as f32 + 0.5) * spacing,
            );
            if skip.is_some_and(|c| c.shape.sdf(&x) < 0.0) {
                continue;
            }
            out.push(Particle::new(
                x,
                Material::Water,
                p.water.density * vol,
                vol,
            ));
        }
    }
    out
}

fn tank(paddle_col: &Collider<2>) -> (SolverParams<2>, Solver<2>) {
    tank_of(paddle_col, Integrator::Explicit, 0.25)
}

/// A 64² tank around `paddle_col`, stepped by `integrator`, water from 0.05 m up to `top`.
fn tank_of(
    paddle_col: &Collider<2>,
    integrator: Integrator,
    top: f32,
) -> (SolverParams<2>, Solver<2>) {
    let params = SolverParams::<2> {
        n_grid: 64,
        num_threads: 1,
        integrator,
        ..Default::default()
    };
    let mut s = Solver::new(params.clone(), vec![paddle_col.clone()]).unwrap();
    let ps = water(
        [0.05, 0.05],
        [0.95, top],
        params.dx() / 2.0,
        &params,
        Some(paddle_col),
    );
    s.set_particles(ps).unwrap();
    (params, s)
}

fn momentum(s: &Solver<2>) -> SVector<f64, 2> {
    let mut m = SVector::<f64, 2>::zeros();
    s.for_each_particle(|_, p| {
        m[0] += (p.mass * p.v[0]) as f64;
        m[1] += (p.mass * p.v[1]) as f64;
    });
    m
}

/// A collider moved every frame to where it is, or with a velocity of
/// zero, gives the static collider's run bit for bit.
#[test]
fn a_collider_that_does_not_move_is_the_static_one_bit_for_bit() {
    let col = paddle([0.4, 0.2], BoundaryCondition::Separate);
    let (_, mut fixed) = tank(&col);
    let (_, mut still) = tank(&col);
    let (_, mut zero) = tank(&col);
    let here = col.shape.anchor();
    for _ in 0..30 {
        fixed.step_frame(DT).unwrap();
        still.move_collider(0, here, None).unwrap();
        still.step_frame(DT).unwrap();
        zero.move_collider(0, here, Some(SVector::zeros())).unwrap();
        zero.step_frame(DT).unwrap();
    }
    assert_eq!(fixed.checkpoint(), still.checkpoint());
    assert_eq!(fixed.checkpoint(), zero.checkpoint());
}

/// The anchor after each frame is the move's end exactly, and the move is
/// used once: a frame without a move leaves the collider where it is.
#[test]
fn the_pose_follows_the_moves_exactly() {
    let col = paddle([0.3, 0.2], BoundaryCondition::Sticky);
    let (_, mut s) = tank(&col);
    let ends: Vec<SVector<f32, 2>> = (1..=12)
        .map(|k| SVector::<f32, 2>::new(0.3 + 0.00125 * k as f32, 0.2 + 0.0003 * k as f32))
        .collect();
    for end in &ends {
        s.move_collider(0, *end, None).unwrap();
        assert_eq!(s.collider_move(0).unwrap().end, *end);
        s.step_frame(DT).unwrap();
        assert_eq!(s.collider_anchor(0).unwrap(), *end);
        assert!(s.collider_move(0).is_none());
    }
    s.step_frame(DT).unwrap();
    assert_eq!(s.collider_anchor(0).unwrap(), *ends.last().unwrap());
    // placed: at once, and a pending move dropped
    let there = SVector::<f32, 2>::new(0.5, 0.2);
    s.move_collider(0, SVector::<f32, 2>::new(0.6, 0.2), None)
        .unwrap();
    s.place_collider(0, there).unwrap();
    assert!(s.collider_move(0).is_none());
    s.step_frame(DT).unwrap();
    assert_eq!(s.collider_anchor(0).unwrap(), there);
}

/// Particles deep inside a sticky collider (every node of their stencil
/// inside it) take its velocity: the condition gives nodes the collider's
/// velocity, not zero. No gravity, so nothing else moves them.
#[test]
fn a_sticky_collider_gives_nodes_its_velocity() {
    let params = SolverParams::<2> {
        n_grid: 64,
        num_threads: 1,
        gravity: [0.0, 0.0],
        ..Default::default()
    };
    let dx = params.dx();
    let col = Collider {
        shape: Shape::Box {
            center: SVector::<f32, 2>::new(0.5, 0.5),
            half_extents: SVector::<f32, 2>::new(0.1, 0.1),
            rotation: SMatrix::<f32, 2, 2>::identity(),
        },
        condition: BoundaryCondition::Sticky,
        friction: 0.0,
        project: true,
    };
    let mut s = Solver::new(params.clone(), vec![col]).unwrap();
    // a block 8 cells across around the centre: 2 cells or more from the faces
    s.set_particles(water(
        [0.4375, 0.4375],
        [0.5625, 0.5625],
        dx / 2.0,
        &params,
        None,
    ))
    .unwrap();
    let u = SVector::<f32, 2>::new(0.4, -0.2);
    for _ in 0..10 {
        let end = s.collider_anchor(0).unwrap() + u * DT;
        s.move_collider(0, end, None).unwrap();
        s.step_frame(DT).unwrap();
    }
    let mut worst = 0.0f32;
    s.for_each_particle(|_, p| worst = worst.max((p.v - u).norm()));
    // the velocity derived from the anchors in f64 differs from u by float rounding
    assert!(
        worst < 1e-3 * u.norm(),
        "particle velocity off by {worst} m/s"
    );
}

/// A paddle moved through a tank at constant speed pushes the water: the
/// water's x momentum, less that of the same tank with the paddle still
/// (the water settles and sloshes), exceeds that of a piston: the water the
/// paddle's immersed face has swept, `ρ·h·U·t` per metre of depth, moving at
/// the paddle's speed U (the water ahead of it is pushed too, so the gain
/// is larger: 13.6 against 3.75 kg·m/s).
#[test]
fn a_moving_paddle_pushes_the_water() {
    let col = paddle([0.3, 0.25], BoundaryCondition::Separate);
    let (params, mut moving) = tank(&col);
    let (_, mut fixed) = tank(&col);
    let speed = 0.5f32;
    let frames = 40;
    for _ in 0..frames {
        let end = moving.collider_anchor(0).unwrap() + SVector::<f32, 2>::new(speed * DT, 0.0);
        moving.move_collider(0, end, None).unwrap();
        moving.step_frame(DT).unwrap();
        fixed.step_frame(DT).unwrap();
    }
    let pm = momentum(&moving);
    let pf = momentum(&fixed);
    // the paddle's immersed height: water surface 0.25 m, paddle bottom 0.10 m
    let immersed = 0.25 - 0.10;
    let t = frames as f32 * DT;
    // water the face has swept [kg per m of depth], all of it moving at least
    // at the paddle's speed is the momentum of a piston: ρ·h·U·t·U
    let swept = params.water.density * immersed * speed * t;
    let piston = (swept * speed) as f64;
    assert!(
        pm[0] - pf[0] > piston,
        "x momentum {} (static {}) vs piston {piston}",
        pm[0],
        pf[0]
    );
    // nothing inside the paddle by more than half a cell
    let shape = &moving.colliders()[0].shape;
    let dx = params.dx();
    moving.for_each_particle(|_, p| {
        assert!(
            shape.sdf(&p.x) > -0.5 * dx,
            "particle {} inside the paddle",
            p.x
        )
    });
}

#[test]
fn bad_moves_name_the_field() {
    let col = paddle([0.3, 0.2], BoundaryCondition::Slip);
    let (_, mut s) = tank(&col);
    let ok = SVector::<f32, 2>::new(0.3, 0.2);
    let field = |e: hybridmpm_mpm::MpmError| e.to_string();
    assert!(field(s.move_collider(1, ok, None).unwrap_err()).starts_with("index"));
    assert!(field(s.collider_anchor(3).unwrap_err()).starts_with("index"));
    let nan = SVector::<f32, 2>::new(f32::NAN, 0.2);
    assert!(field(s.move_collider(0, nan, None).unwrap_err()).starts_with("position"));
    assert!(
        field(
            s.place_collider(0, SVector::<f32, 2>::new(2e3, 0.0))
                .unwrap_err()
        )
        .starts_with("position")
    );
    let inf = SVector::<f32, 2>::new(f32::INFINITY, 0.0);
    assert!(field(s.move_collider(0, ok, Some(inf)).unwrap_err()).starts_with("velocity"));
    assert!(s.collider_move(0).is_none());
    // a move too fast for the substep budget: refused by the frame, nothing moved
    s.move_collider(0, SVector::<f32, 2>::new(900.0, 0.2), None)
        .unwrap();
    assert!(s.step_frame(DT).is_err());
    assert_eq!(s.collider_anchor(0).unwrap(), ok);
}

/// Water squeezed between a paddle driven at 40 m/s and the wall it is
/// pushed against: a particle's push on the grid, `V0·K·J·(1 − J)`, falls
/// to nothing as `J → 0`, so its volume ratio is held at a quarter
/// (`J_FLOOR`) and the squeezed water pushes back instead of collapsing. No
/// frame is rolled back, and no particle's `J` falls below ¼. (Without the
/// floor the volume ratio underflowed and frames were rolled back while the
/// paddle pressed.)
#[test]
fn water_squeezed_against_a_wall_by_a_fast_paddle_keeps_a_quarter_of_its_volume_and_needs_no_retry()
{
    let col = paddle([0.3, 0.25], BoundaryCondition::Separate);
    let (params, mut s) = tank(&col);
    let dx = params.dx();
    // the paddle's left face stops one cell from the wall's face
    let wall = params.walls.cells as f32 * dx;
    let stop = wall + dx + 0.03;
    let speed = 40.0f32;
    let mut retries = 0;
    let mut least_j = f32::INFINITY;
    for _ in 0..60 {
        let at = s.collider_anchor(0).unwrap();
        let x = (at[0] - speed * DT).max(stop);
        s.move_collider(0, SVector::<f32, 2>::new(x, at[1]), None)
            .unwrap();
        retries += s.step_frame(DT).unwrap().retries;
        s.for_each_particle(|_, p| least_j = least_j.min(p.j));
    }
    assert!((s.collider_anchor(0).unwrap()[0] - stop).abs() < 1e-6);
    assert_eq!(retries, 0, "frames rolled back while the paddle pressed");
    assert!(least_j >= 0.25, "a water particle's J fell to {least_j}");
    assert!(
        s.particles()
            .iter()
            .all(|p| p.v.iter().all(|v| v.is_finite()))
    );
}

/// The same squeeze on the projection: the water leaves the gap as a jet
/// faster than the step was planned for, and the step stops before its
/// particles move and the rest of the frame takes shorter steps
/// (`FrameStats::replans`), so no frame is rolled back.
#[test]
fn water_squeezed_by_a_fast_paddle_on_the_projection_replans_its_steps_and_needs_no_retry() {
    let col = paddle([0.3, 0.25], BoundaryCondition::Separate);
    let (params, mut s) = tank_of(&col, Integrator::Projection, 0.25);
    let dx = params.dx();
    let wall = params.walls.cells as f32 * dx;
    let stop = wall + dx + 0.03;
    let speed = 40.0f32;
    let (mut retries, mut replans) = (0, 0);
    for _ in 0..60 {
        let at = s.collider_anchor(0).unwrap();
        let x = (at[0] - speed * DT).max(stop);
        s.move_collider(0, SVector::<f32, 2>::new(x, at[1]), None)
            .unwrap();
        let st = s.step_frame(DT).unwrap();
        retries += st.retries;
        replans += st.replans;
    }
    eprintln!("projection squeeze: {retries} retries, {replans} replans");
    assert!((s.collider_anchor(0).unwrap()[0] - stop).abs() < 1e-6);
    assert_eq!(retries, 0, "frames rolled back while the paddle pressed");
    assert!(
        s.particles()
            .iter()
            .all(|p| p.v.iter().all(|v| v.is_finite()))
    );
}

/// A paddle dragged at 50 m/s through the water on the projection (the page's fastest drag),
/// standing on the floor, overtakes particles: they lie in its cells, in no fluid cell, so the
/// solve never sees them. They move with the paddle until its projection puts them back on its
/// surface, instead of reading back the faces their own p2g set (on `paddle3d` those ran away to
/// hundreds of m/s and rolled frames back). No frame is rolled back, and no particle moves much
/// faster than the paddle throws the water.
#[test]
fn a_paddle_dragged_fast_through_the_water_on_the_projection_carries_what_it_overtakes() {
    let col = paddle([0.2, 0.17], BoundaryCondition::Separate);
    let (_, mut s) = tank_of(&col, Integrator::Projection, 0.35);
    let speed = 50.0f32;
    let (mut retries, mut fastest, mut direction) = (0, 0.0f32, 1.0f32);
    for _ in 0..120 {
        let at = s.collider_anchor(0).unwrap();
        if !(0.2..=0.8).contains(&(at[0] + direction * speed * DT)) {
            direction = -direction;
        }
        let x = at[0] + direction * speed * DT;
        s.move_collider(0, SVector::<f32, 2>::new(x, at[1]), None)
            .unwrap();
        let st = s.step_frame(DT).unwrap();
        retries += st.retries;
        fastest = s.particles().iter().fold(fastest, |m, p| m.max(p.v.norm()));
    }
    eprintln!("dragged paddle: {retries} retries, fastest particle {fastest} m/s");
    assert_eq!(
        retries, 0,
        "frames rolled back while the paddle was dragged"
    );
    // 155.9 m/s here (the paddle throws water ahead of it); 173.7 when the overtaken particles read
    // back their own faces
    assert!(fastest < 3.2 * speed, "a particle reached {fastest} m/s");
}
