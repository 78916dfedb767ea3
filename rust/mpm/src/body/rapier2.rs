//! [`RigidWorld`] in 2D, by rapier2d.

use rapier2d::math::{Pose, Rotation, Vector};
use rapier2d::prelude::*;

use super::BodyState;
use super::world::{ObstacleShape, RigidWorld, ShapeSpec, WorldSpec};

pub(crate) struct World2 {
    world: PhysicsWorld,
    handles: Vec<RigidBodyHandle>,
    /// Each obstacle's body and the offset [m] of its collider's frame from
    /// the obstacle's centre (a mesh obstacle's voxels: half a spacing down).
    obstacles: Vec<Option<(RigidBodyHandle, [f32; 3])>>,
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
                let body = RigidBodyBuilder::dynamic()
                    .pose(pose(s))
                    .linvel(Vector::new(s.v[0], s.v[1]))
                    .angvel(s.w[2])
                    .can_sleep(false);
                let collider = ColliderBuilder::new(shared(&b.shape));
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
        let obstacles = spec
            .obstacles
            .iter()
            .map(|o| {
                let collider = match &o.shape {
                    ObstacleShape::Absent => return None,
                    ObstacleShape::Ball(r) => ColliderBuilder::ball(*r),
                    ObstacleShape::Box(h) => ColliderBuilder::cuboid(h[0], h[1]),
                    ObstacleShape::Voxels(v) => {
                        let shape = v.shape.get_or_init(|| {
                            let keys: Vec<IVector> =
                                v.keys.iter().map(|k| IVector::new(k[0], k[1])).collect();
                            Box::new(SharedShape::voxels(Vector::splat(v.size), &keys))
                        });
                        let shape = shape
                            .downcast_ref::<SharedShape>()
                            .expect("made by a 2D world")
                            .clone();
                        ColliderBuilder::new(shape)
                    }
                };
                let (offset, state) = o.collider_frame();
                let body = if o.moving {
                    RigidBodyBuilder::kinematic_position_based()
                } else {
                    RigidBodyBuilder::fixed()
                };
                Some((world.insert(body.pose(pose(&state)), collider).0, offset))
            })
            .collect();
        World2 {
            world,
            handles,
            obstacles,
        }
    }
}

fn pose(s: &BodyState) -> Pose {
    Pose::from_parts(
        Vector::new(s.x[0], s.x[1]),
        Rotation::from_cos_sin_unchecked(s.q[0], s.q[1]),
    )
}

fn shared(s: &ShapeSpec) -> SharedShape {
    match s {
        ShapeSpec::Box(h) => SharedShape::cuboid(h[0], h[1]),
        ShapeSpec::Ball(r) => SharedShape::ball(*r),
        ShapeSpec::Capsule(r, h) => SharedShape::capsule_y(*h, *r),
        ShapeSpec::Hull(_) => unreachable!("hulls are 3D only (BodyParams::build)"),
    }
}

/// [`super::rapier::overlap`] in 2D.
pub(crate) fn overlap(a: (&ShapeSpec, &BodyState), b: (&ShapeSpec, &BodyState)) -> bool {
    let (sa, sb) = (shared(a.0), shared(b.0));
    rapier2d::parry::query::intersection_test(&pose(a.1), &*sa, &pose(b.1), &*sb)
        .map_or(true, |r| r.intersecting)
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

    fn move_obstacle(&mut self, j: usize, x: [f32; 3]) {
        let Some((h, o)) = self.obstacles[j] else {
            return;
        };
        let b = &mut self.world.bodies[h];
        b.set_next_kinematic_translation(Vector::new(x[0] + o[0], x[1] + o[1]));
    }

    fn step(&mut self, dt: f32) {
        self.world.integration_parameters.dt = dt;
        self.world.step();
    }
}
