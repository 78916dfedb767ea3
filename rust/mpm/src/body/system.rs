//! The solver's bodies between substeps ([`Bodies`]): their exact state,
//! the poses of the substep under way, the impulses the grid update sums,
//! and the rapier step once per substep.

use std::sync::Mutex;

use nalgebra::{
    Matrix3, Matrix6, Quaternion, Rotation3, SMatrix, SVector, UnitQuaternion, Vector6,
};

use super::world::{BodySpec, ObstacleSpec, RigidWorld, WorldSpec};
use super::{Body, BodyPose, Coupled, ImpulseSum};

/// A body's exact state, rapier's own numbers: what a checkpoint carries.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct BodyState {
    /// Centre of mass [m] (2D: `x, y, 0`).
    pub x: [f32; 3],
    /// Rotation: 2D `cos θ, sin θ, 0, 0`; 3D the unit quaternion `x, y, z, w`.
    pub q: [f32; 4],
    /// Velocity [m/s] (2D: `x, y, 0`).
    pub v: [f32; 3],
    /// Angular velocity [rad/s] (2D: `0, 0, ω`).
    pub w: [f32; 3],
}

impl BodyState {
    /// The state of a body as given ([`Body`]).
    pub fn of<const D: usize>(b: &Body<D>) -> Self {
        let mut s = BodyState {
            w: b.angular_velocity,
            ..Default::default()
        };
        for d in 0..D {
            s.x[d] = b.center[d];
            s.v[d] = b.velocity[d];
        }
        let r = &b.rotation;
        s.q = if D == 2 {
            [r[(0, 0)], r[(1, 0)], 0.0, 0.0]
        } else {
            let m = nalgebra::Matrix3::from_fn(|i, j| r[(i, j)]);
            let q = UnitQuaternion::from_rotation_matrix(&Rotation3::from_matrix_unchecked(m));
            [q.i, q.j, q.k, q.w]
        };
        s
    }

    /// The rotation matrix (columns: the body's axes in world coordinates).
    pub fn rotation<const D: usize>(&self) -> SMatrix<f32, D, D> {
        let q = &self.q;
        if D == 2 {
            SMatrix::from_fn(|i, j| match (i, j) {
                (0, 0) | (1, 1) => q[0],
                (1, 0) => q[1],
                _ => -q[1],
            })
        } else {
            let u = UnitQuaternion::new_unchecked(Quaternion::new(q[3], q[0], q[1], q[2]));
            let m = u.to_rotation_matrix();
            SMatrix::from_fn(|i, j| m[(i, j)])
        }
    }
}

/// The solver's rigid bodies.
#[derive(Default)]
pub struct Bodies<const D: usize> {
    /// Shapes, densities and friction (and the initial state as given).
    pub(crate) bodies: Vec<Body<D>>,
    /// The exact state at the end of the last frame.
    pub(crate) states: Vec<BodyState>,
    /// The poses the grid update reads in the substep under way.
    pub(crate) poses: Vec<BodyPose<D>>,
    /// The rigid-body world of the frame attempt under way.
    world: Option<Box<dyn RigidWorld>>,
    /// The obstacles the next world holds ([`Bodies::set_obstacles`]).
    obstacles: Vec<ObstacleSpec>,
    /// The impulses and coupled masses the team's members summed in this
    /// substep's grid update, and the nodes they held.
    sums: Mutex<(Vec<ImpulseSum>, Vec<Coupled>)>,
    /// The fluid's impulse and torque impulse on each body over the frame
    /// under way, and its mean force and torque over the last frame.
    frame_impulse: Vec<[f64; 6]>,
    last_force: Vec<[f64; 6]>,
}

impl<const D: usize> Bodies<D> {
    pub fn len(&self) -> usize {
        self.bodies.len()
    }

    pub fn is_empty(&self) -> bool {
        self.bodies.is_empty()
    }

    /// The bodies as given.
    pub fn bodies(&self) -> &[Body<D>] {
        &self.bodies
    }

    /// Each body's exact state at the end of the last frame.
    pub fn states(&self) -> &[BodyState] {
        &self.states
    }

    /// The mean force [N] and torque [N·m] the fluid exerted on each body
    /// over the last frame (lanes as [`ImpulseSum`]'s).
    pub fn last_force(&self) -> &[[f64; 6]] {
        &self.last_force
    }

    /// Appends a body at its given state.
    pub(crate) fn push(&mut self, b: Body<D>) {
        self.states.push(BodyState::of(&b));
        self.bodies.push(b);
        self.last_force.push([0.0; 6]);
        self.refresh_poses();
    }

    /// Removes body `i` (the others keep their order).
    pub(crate) fn remove(&mut self, i: usize) {
        self.bodies.remove(i);
        self.states.remove(i);
        self.last_force.remove(i);
        self.refresh_poses();
    }

    /// Sets the fluid's mean force and torque on body `i` over the last
    /// frame (a checkpoint's; lanes as [`Bodies::last_force`]'s).
    pub(crate) fn set_last_force(&mut self, i: usize, f: [f64; 6]) {
        self.last_force[i] = f;
    }

    /// Sets body `i`'s state (a checkpoint's).
    pub(crate) fn set_state(&mut self, i: usize, s: BodyState) {
        self.states[i] = s;
        self.refresh_poses();
    }

    /// Largest speed of a body's point [m/s]: `|v| + |ω| R`.
    pub fn max_speed(&self) -> f32 {
        self.poses
            .iter()
            .map(|p| {
                let w = p.angular_velocity;
                let wn = (w[0] * w[0] + w[1] * w[1] + w[2] * w[2]).sqrt();
                p.velocity.norm() + wn * p.shape.bounding_radius()
            })
            .fold(0.0, f32::max)
    }

    /// Each body's fastest point's speed [m/s] in `f64` (`|v| + |ω| R`):
    /// what a CFL error names.
    pub fn point_speeds(&self) -> Vec<f64> {
        self.poses
            .iter()
            .map(|p| {
                let norm = |v: &[f32]| v.iter().map(|&x| (x as f64).powi(2)).sum::<f64>().sqrt();
                norm(p.velocity.as_slice())
                    + norm(&p.angular_velocity) * p.shape.bounding_radius() as f64
            })
            .collect()
    }

    fn pose_of(b: &Body<D>, s: &BodyState) -> BodyPose<D> {
        BodyPose {
            shape: b.shape.clone(),
            center: SVector::from_fn(|d, _| s.x[d]),
            rotation: s.rotation(),
            velocity: SVector::from_fn(|d, _| s.v[d]),
            angular_velocity: s.w,
            friction: b.friction,
        }
    }

    fn refresh_poses(&mut self) {
        self.poses = self
            .bodies
            .iter()
            .zip(&self.states)
            .map(|(b, s)| Self::pose_of(b, s))
            .collect();
    }

    /// Start of a frame attempt: the rigid world built from the states,
    /// under `gravity`, with walls at `lo` and `hi` along every axis.
    pub(crate) fn begin(&mut self, gravity: &[f32; D], lo: f32, hi: f32, length_unit: f32) {
        self.refresh_poses();
        let n = self.bodies.len();
        *self.sums.get_mut().expect("not poisoned") = (vec![ImpulseSum::default(); n], Vec::new());
        self.frame_impulse = vec![[0.0; 6]; n];
        if n == 0 {
            self.world = None;
            return;
        }
        let shapes: Vec<BodySpec> = self.bodies.iter().map(Body::spec).collect();
        let spec = WorldSpec {
            bodies: &shapes,
            obstacles: &self.obstacles,
            states: &self.states,
            gravity: std::array::from_fn(|d| if d < D { gravity[d] } else { 0.0 }),
            lo,
            hi,
            length_unit,
        };
        self.world = Some(super::rapier::build(D, &spec));
    }

    /// The obstacles (boxes, balls and mesh obstacles' voxels at the frame's
    /// start) the world of the next frame attempt holds, for the bodies'
    /// contacts with them.
    pub(crate) fn set_obstacles(&mut self, obstacles: Vec<ObstacleSpec>) {
        self.obstacles = obstacles;
    }

    /// The obstacles of the last [`Bodies::set_obstacles`].
    pub(crate) fn obstacles(&self) -> &[ObstacleSpec] {
        &self.obstacles
    }

    /// Where the moving obstacles are at the end of the substep under way:
    /// `x[j]` for obstacle `j` (`None`: it does not move).
    pub(crate) fn move_obstacles(&mut self, x: impl Iterator<Item = Option<[f32; 3]>>) {
        if let Some(world) = self.world.as_mut() {
            for (j, x) in x.enumerate() {
                if let Some(x) = x
                    && self.obstacles.get(j).is_some_and(|o| o.moving)
                {
                    world.move_obstacle(j, x);
                }
            }
        }
    }

    /// A member's sums of this substep's grid update (any order: integer
    /// sums) and the nodes it held (`coupled`, emptied; each node is one
    /// member's, so its entries keep their order).
    pub(crate) fn merge(&self, part: &[ImpulseSum], coupled: &mut Vec<Coupled>) {
        let mut guard = self.sums.lock().expect("no member panicked holding it");
        let (sums, nodes) = &mut *guard;
        for (s, p) in sums.iter_mut().zip(part) {
            s.merge(p);
        }
        nodes.append(coupled);
    }

    /// Body `i`'s mass [kg] and its inertia tensor in world axes [kg·m²]
    /// (2D: about z, entry (2, 2)).
    fn inertia(&self, i: usize) -> (f64, [[f64; 3]; 3]) {
        let b = &self.bodies[i];
        let m = b.mass() as f64;
        let local = b.shape.local_inertia(m);
        let r = self.poses[i].rotation;
        let rot = |a: usize, k: usize| {
            if a < D && k < D {
                r[(a, k)] as f64
            } else {
                (a == k) as u8 as f64
            }
        };
        let mut out = [[0.0; 3]; 3];
        for a in 0..3 {
            for c in 0..3 {
                out[a][c] = (0..3)
                    .map(|k| {
                        (0..3)
                            .map(|l| rot(a, k) * local[k][l] * rot(c, l))
                            .sum::<f64>()
                    })
                    .sum();
            }
        }
        (m, out)
    }

    /// Body `i`'s inverse mass [1/kg] and inverse inertia tensor in world
    /// axes [1/(kg·m²)] at its pose now (2D: only the entry (2, 2), about
    /// z): what a projection step couples it with.
    pub(crate) fn inverse_mass(&self, i: usize) -> (f64, [[f64; 3]; 3]) {
        let (m, inertia) = self.inertia(i);
        let mut inv = [[0.0; 3]; 3];
        if D == 2 {
            inv[2][2] = 1.0 / inertia[2][2];
        } else if let Some(t) = Matrix3::<f64>::from_fn(|r, c| inertia[r][c]).try_inverse() {
            inv = std::array::from_fn(|r| std::array::from_fn(|c| t[(r, c)]));
        }
        (1.0 / m, inv)
    }

    /// After a projection step of `dt` [s]: each body's velocity change
    /// `delta` from the fluid's pressure impulse `impulse` (lanes as
    /// [`ImpulseSum`]'s), then the world stepped by `dt` (gravity,
    /// contacts) and the poses of the next step.
    pub(crate) fn projection_step(&mut self, steps: &[([f64; 6], [f64; 6])], dt: f32) {
        let Some(world) = self.world.as_mut() else {
            return;
        };
        for (i, (impulse, delta)) in steps.iter().enumerate() {
            let f = &mut self.frame_impulse[i];
            for k in 0..6 {
                f[k] += impulse[k];
            }
            world.add_velocity(
                i,
                [delta[0], delta[1], delta[2]].map(|x| x as f32),
                [delta[3], delta[4], delta[5]].map(|x| x as f32),
            );
        }
        world.step(dt);
        for (i, (p, b)) in self.poses.iter_mut().zip(&self.bodies).enumerate() {
            *p = Self::pose_of(b, &world.state(i));
        }
    }

    /// After a substep's grid update: each body's velocity change from the
    /// fluid's impulse with the held nodes moving with it (the coupled mass
    /// matrix: `(M + Σ m jᵀj) Δ = [J, τ]`, the reduced mass of every
    /// contact at once), the held nodes' normal velocities in `out_v`
    /// following the bodies' new ones, then the world stepped by `dt` and
    /// the poses of the next substep.
    pub(crate) fn substep(&mut self, dt: f32, out_v: &mut [[f32; 4]]) {
        if self.world.is_none() {
            return;
        }
        let (mut sums, nodes) = std::mem::take(self.sums.get_mut().expect("not poisoned"));
        let mut deltas = vec![[0.0f64; 6]; sums.len()];
        for (i, s) in sums.iter_mut().enumerate() {
            let (j, t) = s.value();
            let c = s.coupled();
            let (m, inertia) = self.inertia(i);
            let mut a = Matrix6::<f64>::from_fn(|r, k| c[r][k]);
            for k in 0..3 {
                a[(k, k)] += m;
                for l in 0..3 {
                    a[(3 + k, 3 + l)] += inertia[k][l];
                }
            }
            let rhs = Vector6::<f64>::new(j[0], j[1], j[2], t[0], t[1], t[2]);
            // 2D: no z motion and no rotation about x or y
            let free = |k: usize| D == 3 || k < 2 || k == 5;
            for k in 0..6 {
                if !free(k) {
                    for l in 0..6 {
                        a[(k, l)] = 0.0;
                        a[(l, k)] = 0.0;
                    }
                    a[(k, k)] = 1.0;
                }
            }
            let rhs = Vector6::from_fn(|k, _| if free(k) { rhs[k] } else { 0.0 });
            let x = a.lu().solve(&rhs).unwrap_or_else(Vector6::zeros);
            deltas[i] = std::array::from_fn(|k| x[k]);
            let du = [x[0], x[1], x[2]];
            let dw = [x[3], x[4], x[5]];
            let f = &mut self.frame_impulse[i];
            for k in 0..3 {
                f[k] += m * du[k];
                f[3 + k] += (0..3).map(|l| inertia[k][l] * dw[l]).sum::<f64>();
            }
            *s = ImpulseSum::default();
        }
        for c in &nodes {
            let d = &deltas[c.body as usize];
            let (n, r) = (c.n.map(|x| x as f64), c.r.map(|x| x as f64));
            let wr = [
                d[4] * r[2] - d[5] * r[1],
                d[5] * r[0] - d[3] * r[2],
                d[3] * r[1] - d[4] * r[0],
            ];
            let un: f64 = (0..3).map(|k| (d[k] + wr[k]) * n[k]).sum();
            let v = &mut out_v[c.node as usize];
            for k in 0..D {
                v[k] += (un * n[k]) as f32;
            }
        }
        let world = self.world.as_mut().expect("checked above");
        for (i, d) in deltas.iter().enumerate() {
            world.add_velocity(
                i,
                [d[0], d[1], d[2]].map(|x| x as f32),
                [d[3], d[4], d[5]].map(|x| x as f32),
            );
        }
        world.step(dt);
        for (i, (p, b)) in self.poses.iter_mut().zip(&self.bodies).enumerate() {
            *p = Self::pose_of(b, &world.state(i));
        }
        // the buffers back for the next substep
        let guard = self.sums.get_mut().expect("not poisoned");
        guard.0 = sums;
        guard.1 = nodes;
        guard.1.clear();
    }

    /// End of a frame attempt of `dt_frame` seconds: done, the states are
    /// the world's and the last frame's forces its mean impulses; not done,
    /// the states stay the frame's start.
    pub(crate) fn end(&mut self, done: bool, dt_frame: f32) {
        if let Some(world) = self.world.take()
            && done
        {
            for i in 0..self.bodies.len() {
                self.states[i] = world.state(i);
            }
            let inv = 1.0 / dt_frame as f64;
            for (f, j) in self.last_force.iter_mut().zip(&self.frame_impulse) {
                *f = j.map(|x| x * inv);
            }
        }
        self.refresh_poses();
    }
}
