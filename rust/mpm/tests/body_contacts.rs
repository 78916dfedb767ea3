//! Bodies against each other and the obstacles (docs/bodies.md "Shapes"):
//! a body overlapping another or an obstacle is refused naming its centre,
//! a body rests on an obstacle, and a moving obstacle pushes a body.

use hybridmpm_mpm::{Body, BodyParams, BodyShapeKind, Material, Particle, Solver, SolverParams};
use nalgebra::SVector;

fn capsule<const D: usize>(center: &[f32], r: f32, h: f32, rho: f32, angle_deg: f64) -> Body<D> {
    BodyParams {
        shape: Some(BodyShapeKind::Capsule),
        center: Some(center.to_vec()),
        radius: Some(r),
        half_height: Some(h),
        angle_deg: (D == 2).then_some(angle_deg),
        density: Some(rho),
        ..Default::default()
    }
    .build::<D>("body")
    .unwrap()
}

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
    hybridmpm_mpm::Collider {
        shape: hybridmpm_mpm::Shape::Box {
            center: SVector::from(center),
            half_extents: SVector::from(half),
            rotation: nalgebra::Matrix2::identity(),
        },
        condition: hybridmpm_mpm::BoundaryCondition::Separate,
        friction: 0.0,
        project: false,
    }
}

/// Obstacles are in the bodies' rigid world: a heavy box dropped onto a
/// shelf rests on it (without it, it falls to the floor), and a paddle
/// moved into a ball on the floor pushes it ahead without overlapping it.
#[test]
fn bodies_rest_on_obstacles_and_moving_ones_push_them() {
    let p = SolverParams::<2> {
        n_grid: 64,
        ..Default::default()
    };
    let shelf = obstacle_box([0.5, 0.3], [0.2, 0.03]);
    let paddle = obstacle_box([0.2, 0.1], [0.03, 0.05]);
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
    let mut paddle_x = 0.2f32;
    for f in 0..120 {
        if f >= 20 {
            paddle_x += 0.5 * 0.01; // 0.5 m/s for frames of 10 ms
            s.move_collider(1, SVector::<f32, 2>::new(paddle_x, 0.1), None)
                .unwrap();
        }
        s.step_frame(0.01).unwrap();
        let st = &s.bodies().states()[1];
        if std::env::var_os("SHAPES_TRACE").is_some() {
            eprintln!(
                "f {f} crate y {} capsule x {} paddle {paddle_x}",
                s.bodies().states()[0].x[1],
                st.x[0]
            );
        }
        // the ball's left end against the paddle's right face
        let left = st.x[0] - 0.06;
        assert!(
            left >= paddle_x + 0.03 - 0.1 * p.dx(),
            "frame {f}: the capsule ({left}) inside the paddle ({})",
            paddle_x + 0.03
        );
    }
    let st = &s.bodies().states()[0];
    let top = 0.33f32;
    eprintln!(
        "crate bottom {} (shelf top {top}); capsule moved {} m",
        st.x[1] - 0.05,
        s.bodies().states()[1].x[0] - x0
    );
    assert!(
        (st.x[1] - 0.05 - top).abs() < 0.1 * p.dx(),
        "crate bottom {} vs shelf top {top}",
        st.x[1] - 0.05
    );
    assert!(
        s.bodies().states()[1].x[0] - x0 > 0.2,
        "the capsule was not pushed"
    );
}
