//! [`RigidWorld`] in 3D, by rapier3d.

use rapier3d::math::{Pose, Rotation, Vector};
use rapier3d::prelude::*;

use super::BodyState;
use super::world::{ObstacleShape, RigidWorld, ShapeSpec, WorldSpec};

pub(crate) struct World3 {
    world: PhysicsWorld,
    handles: Vec<RigidBodyHandle>,
    /// Each obstacle's body and the offset [m] of its collider's frame from
    /// the obstacle's centre (a mesh obstacle's voxels: half a spacing down).
    obstacles: Vec<Option<(RigidBodyHandle, [f32; 3])>>,
}

impl World3 {
    pub(crate) fn new(spec: &WorldSpec<'_>) -> Self {
        let mut world = PhysicsWorld::new();
        let g = spec.gravity;
        world.gravity = Vector::new(g[0], g[1], g[2]);
        world.integration_parameters.length_unit = spec.length_unit;
        // the walls: six fixed boxes outside [lo, hi]³
        let (lo, hi) = (spec.lo, spec.hi);
        let t = 1.0;
        let mid = 0.5 * (lo + hi);
        for axis in 0..3 {
            for c in [lo - t, hi + t] {
                let mut centre = [mid; 3];
                centre[axis] = c;
                let mut h = [t + hi; 3];
                h[axis] = t;
                world.insert(
                    RigidBodyBuilder::fixed().translation(Vector::from(centre)),
                    ColliderBuilder::cuboid(h[0], h[1], h[2]),
                );
            }
        }
        let handles = spec
            .bodies
            .iter()
            .zip(spec.states)
            .map(|(b, s)| {
                let body = RigidBodyBuilder::dynamic()
                    .pose(pose(s))
                    .linvel(Vector::from(s.v))
                    .angvel(Vector::from(s.w))
                    .can_sleep(false);
                let collider = ColliderBuilder::new(shared(&b.shape));
                let collider = match b.mass {
                    Some((m, i)) => {
                        let cols = i.map(|row| Vector::from(row.map(|x| x as f32)));
                        // symmetric: rows are columns
                        let tensor = Matrix::from_cols(cols[0], cols[1], cols[2]);
                        collider.mass_properties(MassProperties::with_inertia_matrix(
                            Vector::ZERO,
                            m,
                            tensor,
                        ))
                    }
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
                    ObstacleShape::Box(h) => ColliderBuilder::cuboid(h[0], h[1], h[2]),
                    ObstacleShape::Voxels(v) => {
                        let shape = v.shape.get_or_init(|| {
                            let keys: Vec<IVector> =
                                v.keys.iter().map(|k| IVector::from(*k)).collect();
                            Box::new(SharedShape::voxels(Vector::splat(v.size), &keys))
                        });
                        let shape = shape
                            .downcast_ref::<SharedShape>()
                            .expect("made by a 3D world")
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
        World3 {
            world,
            handles,
            obstacles,
        }
    }
}

fn pose(s: &BodyState) -> Pose {
    Pose::from_parts(
        Vector::from(s.x),
        Rotation::from_xyzw(s.q[0], s.q[1], s.q[2], s.q[3]),
    )
}

fn shared(s: &ShapeSpec) -> SharedShape {
    match s {
        ShapeSpec::Box(h) => SharedShape::cuboid(h[0], h[1], h[2]),
        ShapeSpec::Ball(r) => SharedShape::ball(*r),
        ShapeSpec::Capsule(r, h) => SharedShape::capsule_y(*h, *r),
        ShapeSpec::Hull(hull) => {
            let points = hull.vertices.iter().map(|p| Vector::from(*p)).collect();
            SharedShape::convex_mesh(points, &hull.faces)
                .expect("a hull's own faces make a convex mesh (Hull::new)")
        }
    }
}

/// [`super::rapier::overlap`] in 3D.
pub(crate) fn overlap(a: (&ShapeSpec, &BodyState), b: (&ShapeSpec, &BodyState)) -> bool {
    let (sa, sb) = (shared(a.0), shared(b.0));
    rapier3d::parry::query::intersection_test(&pose(a.1), &*sa, &pose(b.1), &*sb)
        .map_or(true, |r| r.intersecting)
}

impl RigidWorld for World3 {
    fn state(&self, i: usize) -> BodyState {
        let b = &self.world.bodies[self.handles[i]];
        let (x, r, v, w) = (b.translation(), b.rotation(), b.linvel(), b.angvel());
        BodyState {
            x: x.to_array(),
            q: [r.x, r.y, r.z, r.w],
            v: v.to_array(),
            w: w.to_array(),
        }
    }

    fn add_velocity(&mut self, i: usize, dv: [f32; 3], dw: [f32; 3]) {
        let b = &mut self.world.bodies[self.handles[i]];
        let v = b.linvel() + Vector::from(dv);
        let w = b.angvel() + Vector::from(dw);
        b.set_linvel(v, true);
        b.set_angvel(w, true);
    }

    fn move_obstacle(&mut self, j: usize, x: [f32; 3]) {
        let Some((h, o)) = self.obstacles[j] else {
            return;
        };
        let b = &mut self.world.bodies[h];
        b.set_next_kinematic_translation(Vector::new(x[0] + o[0], x[1] + o[1], x[2] + o[2]));
    }

    fn step(&mut self, dt: f32) {
        self.world.integration_parameters.dt = dt;
        self.world.step();
    }
}
