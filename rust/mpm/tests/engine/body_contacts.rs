//! Bodies against each other and the obstacles (docs/bodies.md "Shapes"):
//! a body overlapping another or an obstacle is refused naming its centre,
//! a body rests on an obstacle, and a moving obstacle pushes a body.

use hybridmpm_mpm::{BodyParams, BodyShapeKind, Material, Particle, Solver, SolverParams};
use nalgebra::SVector;

use crate::common::capsule;

/// A body overlapping another where that one is now, or an obstacle, is
/// refused naming its centre, and nothing changes; as a checkpoint gives
/// them (`add_given_body`) bodies are not checked against each other.
#[test]
fn overlapping_bodies_are_refused_naming_the_centre() {
    let p = SolverParams::<2> {
        n_grid: 64,
        ..Default::default()
    };
    let post = hybridmpm_mpm::Collider {
        shape: hybridmpm_mpm::Shape::Sphere {
            center: SVector::<f32, 2>::new(0.2, 0.2),
            radius: 0.06,
        },
        condition: hybridmpm_mpm::BoundaryCondition::Separate,
        friction: 0.0,
        project: false,
    };
    let mut s = Solver::new(p, vec![post]).unwrap();
    s.add_body(capsule::<2>(&[0.5, 0.5], 0.04, 0.06, 500.0, 0.0))
        .unwrap();
    // a box whose corner reaches into the capsule's round end (0.5, 0.56 + 0.04)
    let corner = BodyParams {
        shape: Some(BodyShapeKind::Box),
        center: Some(vec![0.53, 0.62]),
        half_extents: Some(vec![0.04, 0.03]),
        angle_deg: Some(30.0),
        density: Some(500.0),
        ..Default::default()
    };
    let b = corner.build::<2>("bodies[1]").unwrap();
    let e = s.add_body(b.clone()).unwrap_err();
    assert_eq!(e.field(), Some("bodies[1].center"), "{e}");
    assert_eq!(s.bodies().len(), 1);
    // its lowest corner (0.510, 0.574) lies 1.7 cm from the capsule's end;
    // 4 cm higher it lies 5.5 cm from it, clear
    let clear = BodyParams {
        center: Some(vec![0.53, 0.66]),
        ..corner.clone()
    };
    s.add_body(clear.build::<2>("bodies[1]").unwrap()).unwrap();
    // a ball reaching into the obstacle
    let ball = |x: f32| BodyParams {
        shape: Some(BodyShapeKind::Sphere),
        center: Some(vec![x, 0.2]),
        radius: Some(0.04),
        density: Some(500.0),
        ..Default::default()
    };
    let e = s.add_body(ball(0.27).build::<2>("b").unwrap()).unwrap_err();
    assert_eq!(e.field(), Some("bodies[2].center"), "{e}");
    assert_eq!(s.bodies().len(), 2);
    s.add_body(ball(0.32).build::<2>("b").unwrap()).unwrap();
    // as given (a checkpoint's), an overlap is taken
    s.add_given_body(b).unwrap();
    assert_eq!(s.bodies().len(), 4);
}

fn obstacle_box(center: [f32; 2], half: [f32; 2]) -> hybridmpm_mpm::Collider<2> {
    collider(hybridmpm_mpm::Shape::Box {
        center: SVector::from(center),
        half_extents: SVector::from(half),
        rotation: nalgebra::Matrix2::identity(),
    })
}

fn collider(shape: hybridmpm_mpm::Shape<2>) -> hybridmpm_mpm::Collider<2> {
    hybridmpm_mpm::Collider {
        shape,
        condition: hybridmpm_mpm::BoundaryCondition::Separate,
        friction: 0.0,
        project: false,
    }
}

/// The box `(center, half)` as a mesh obstacle gives it: its distance
/// sampled `cell` apart from `origin` (3 cells round it), and the faces of
/// the voxels the bodies' world makes of it (half a spacing past the last
/// inside node on each side: `[x_lo, x_hi, y_lo, y_hi]`).
fn sampled_box(
    center: [f32; 2],
    half: [f32; 2],
    origin: [f32; 2],
    cell: f32,
) -> (hybridmpm_mpm::Collider<2>, [f32; 4]) {
    let exact = obstacle_box(center, half).shape;
    let dims: [usize; 2] =
        std::array::from_fn(|d| ((center[d] + half[d] - origin[d]) / cell) as usize + 4);
    let mut values = Vec::with_capacity(dims[0] * dims[1]);
    let mut faces = [f32::MAX, f32::MIN, f32::MAX, f32::MIN];
    for i in 0..dims[0] {
        for j in 0..dims[1] {
            let p =
                SVector::<f32, 2>::new(origin[0] + cell * i as f32, origin[1] + cell * j as f32);
            let v = exact.sdf(&p);
            if v <= 0.0 {
                faces = [
                    faces[0].min(p[0] - 0.5 * cell),
                    faces[1].max(p[0] + 0.5 * cell),
                    faces[2].min(p[1] - 0.5 * cell),
                    faces[3].max(p[1] + 0.5 * cell),
                ];
            }
            values.push(v);
        }
    }
    let shape = hybridmpm_mpm::Shape::Sampled {
        origin: SVector::from(origin),
        cell,
        dims,
        values: std::sync::Arc::from(values),
        normals: None,
    };
    (collider(shape), faces)
}

/// Obstacles are in the bodies' rigid world: a heavy box dropped onto a
/// shelf rests on it (without it, it falls to the floor), and a paddle
/// moved into a ball on the floor pushes it ahead without overlapping it.
/// The same with the shelf and the paddle as mesh obstacles (sampled
/// distances, the grid's spacing apart, off the grid's nodes): the bodies
/// meet their voxels, whose faces lie within half a spacing of the boxes'.
#[test]
fn bodies_rest_on_obstacles_and_moving_ones_push_them() {
    let dx = 1.0 / 64.0;
    let analytic = (
        obstacle_box([0.5, 0.3], [0.2, 0.03]),
        obstacle_box([0.2, 0.1], [0.03, 0.05]),
    );
    let (pushed, _) = rest_and_push(analytic, [0.3, 0.7, 0.27, 0.33], 0.0);
    assert!(pushed > 0.2, "the capsule was not pushed ({pushed} m)");
    // the mesh twins, their samples 0.37 spacings off the grid's nodes
    let off = 0.37 * dx;
    let (shelf, top) = sampled_box([0.5, 0.3], [0.2, 0.03], [0.27 + off, 0.24 + off], dx);
    let (paddle, face) = sampled_box([0.2, 0.1], [0.03, 0.05], [0.14 + off, 0.02 + off], dx);
    assert!((top[3] - 0.33).abs() <= 0.5 * dx && (face[1] - 0.23).abs() <= 0.5 * dx);
    let (meshed, _) = rest_and_push(
        (shelf, paddle),
        [top[0], top[1], top[2], top[3]],
        face[1] - 0.23,
    );
    assert!(
        (meshed - pushed).abs() < 0.1 * pushed,
        "the mesh paddle pushed the capsule {meshed} m, the box {pushed} m"
    );
}

/// The crate dropped on `shelf` and the capsule pushed by `paddle` (moved
/// from x = 0.2 at 0.5 m/s after frame 20), for 120 frames: checks every
/// frame that the capsule lies outside the paddle (its right face
/// `0.23 + face` when it starts) and at the end that the crate rests on the
/// shelf's top face (`faces[3]`); returns how far the capsule moved and the
/// crate's bottom.
fn rest_and_push(
    (shelf, paddle): (hybridmpm_mpm::Collider<2>, hybridmpm_mpm::Collider<2>),
    faces: [f32; 4],
    face: f32,
) -> (f32, f32) {
    let p = SolverParams::<2> {
        n_grid: 64,
        ..Default::default()
    };
    let anchor = paddle.shape.anchor();
    let mut s = Solver::new(p.clone(), vec![shelf, paddle]).unwrap();
    let crate_ = BodyParams {
        shape: Some(BodyShapeKind::Box),
        center: Some(vec![0.5, 0.45]),
        half_extents: Some(vec![0.05, 0.05]),
        density: Some(2000.0),
        ..Default::default()
    };
    s.add_body(crate_.build::<2>("b").unwrap()).unwrap();
    let ball = capsule::<2>(&[0.4, 0.1], 0.04, 0.02, 800.0, 90.0);
    s.add_body(ball).unwrap();
    // a little water in the far corner: a frame without particles does nothing
    let dx = p.dx();
    let vol = (0.5 * dx) * (0.5 * dx);
    let ps: Vec<Particle<2>> = (0..100)
        .map(|k| {
            let x = SVector::<f32, 2>::new(
                0.85 + (k % 10) as f32 * 0.5 * dx,
                0.06 + (k / 10) as f32 * 0.5 * dx,
            );
            Particle::new(x, Material::Water, p.water.density * vol, vol)
        })
        .collect();
    s.set_particles(ps).unwrap();
    let x0 = s.bodies().states()[1].x[0];
    let mut moved = 0.0f32;
    for f in 0..120 {
        if f >= 20 {
            moved += 0.5 * 0.01; // 0.5 m/s for frames of 10 ms
            s.move_collider(1, anchor + SVector::<f32, 2>::new(moved, 0.0), None)
                .unwrap();
        }
        s.step_frame(0.01).unwrap();
        let st = &s.bodies().states()[1];
        if std::env::var_os("SHAPES_TRACE").is_some() {
            eprintln!(
                "f {f} crate y {} capsule x {} paddle moved {moved}",
                s.bodies().states()[0].x[1],
                st.x[0]
            );
        }
        // the ball's left end against the paddle's right face
        let left = st.x[0] - 0.06;
        let right = 0.23 + face + moved;
        assert!(
            left >= right - 0.1 * dx,
            "frame {f}: the capsule ({left}) inside the paddle ({right})"
        );
    }
    let st = &s.bodies().states()[0];
    let (bottom, pushed) = (st.x[1] - 0.05, s.bodies().states()[1].x[0] - x0);
    eprintln!(
        "crate bottom {bottom} (shelf top {}); capsule moved {pushed} m",
        faces[3]
    );
    assert!(
        (bottom - faces[3]).abs() < 0.1 * dx,
        "crate bottom {bottom} vs shelf top {}",
        faces[3]
    );
    (pushed, bottom)
}
