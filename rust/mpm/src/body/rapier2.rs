//! [`RigidWorld`] in 2D, by rapier2d.

use rapier2d::math::{Pose, Rotation, Vector};
use rapier2d::prelude::*;

use super::BodyState;
use super::world::{RigidWorld, ShapeSpec, WorldSpec};

pub(crate) struct World2 {
    world: PhysicsWorld,
    handles: Vec<RigidBodyHandle>,
}

impl World2 {
    pub(crate) fn new(spec: &WorldSpec<'_>) -> Self {
        let mut world = PhysicsWorld::new();
        world.gravity = Vector::new(spec.gravity[0], spec.gravity[1]);
        world.integration_parameters.length_unit = spec.length_unit;
        // the walls: four fixed boxes outside [lo, hi]²
        let (lo, hi) = (spec.lo, spec.hi);
        let t = 1.0;
        let mid = 0.5 * (lo + hi);
        for (cx, cy, hx, hy) in [
            (lo - t, mid, t, t + hi),
            (hi + t, mid, t, t + hi),
            (mid, lo - t, t + hi, t),
            (mid, hi + t, t + hi, t),
        ] {
            world.insert(
                RigidBodyBuilder::fixed().translation(Vector::new(cx, cy)),
                ColliderBuilder::cuboid(hx, hy),
            );
        }
        let handles = spec
            .bodies
            .iter()
            .zip(spec.states)
            .map(|(b, s)| {
                let pose = Pose::from_parts(
                    Vector::new(s.x[0], s.x[1]),
                    Rotation::from_cos_sin_unchecked(s.q[0], s.q[1]),
                );
                let body = RigidBodyBuilder::dynamic()
                    .pose(pose)
                    .linvel(Vector::new(s.v[0], s.v[1]))
                    .angvel(s.w[2])
                    .can_sleep(false);
                let collider = match &b.shape {
                    ShapeSpec::Box(h) => ColliderBuilder::cuboid(h[0], h[1]),
                    ShapeSpec::Ball(r) => ColliderBuilder::ball(*r),
                    ShapeSpec::Capsule(r, h) => ColliderBuilder::capsule_y(*h, *r),
                    ShapeSpec::Hull(_) => unreachable!("hulls are 3D only (BodyParams::build)"),
                };
                let collider = match b.mass {
                    Some((m, i)) => collider.mass_properties(MassProperties::new(
                        Vector::ZERO,
                        m,
                        i[2][2] as f32,
                    )),
                    None => collider.density(b.density),
                };
                world.insert(body, collider).0
            })
            .collect();
        World2 { world, handles }
    }
}

impl RigidWorld for World2 {
    fn state(&self, i: usize) -> BodyState {
        let b = &self.world.bodies[self.handles[i]];
        let (x, r, v) = (b.translation(), b.rotation(), b.linvel());
        BodyState {
            x: [x.x, x.y, 0.0],
            q: [r.re, r.im, 0.0, 0.0],
            v: [v.x, v.y, 0.0],
            w: [0.0, 0.0, b.angvel()],
        }
    }

    fn add_velocity(&mut self, i: usize, dv: [f32; 3], dw: [f32; 3]) {
        let b = &mut self.world.bodies[self.handles[i]];
        let v = b.linvel() + Vector::new(dv[0], dv[1]);
        let w = b.angvel() + dw[2];
        b.set_linvel(v, true);
        b.set_angvel(w, true);
    }

    fn step(&mut self, dt: f32) {
        self.world.integration_parameters.dt = dt;
        self.world.step();
    }
}
