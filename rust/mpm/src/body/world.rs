//! The bodies' dynamics and contacts, by rapier (rapier2d / rapier3d, `f32`,
//! `enhanced-determinism`), behind one small trait ([`RigidWorld`]) that
//! speaks in plain arrays: the solver never sees rapier's types, and 2D and
//! 3D differ only in `rapier2.rs` / `rapier3.rs`.
//!
//! A world is built from the bodies' exact state at the start of each frame
//! attempt ([`build`]) and read back at its end: a frame that fails is
//! retried from the same state, and a checkpoint (the state) restores the
//! same bits as a run that never stopped. Contacts' warm-start impulses live
//! within a frame only.

use std::sync::Arc;

use super::{BodyState, Hull};

/// A body's shape in rapier's terms (dimension-free: 2D reads `x, y`).
#[derive(Clone, Debug, PartialEq)]
pub(crate) enum ShapeSpec {
    Box([f32; 3]),
    Ball(f32),
    /// Radius and half height along y.
    Capsule(f32, f32),
    /// 3D only.
    Hull(Arc<Hull>),
}

/// A body in rapier's terms: its shape, density [kg/m³], and its mass
/// [kg] and inertia tensor about the centre of mass in its axes [kg·m²]
/// where rapier's own would differ from the coupling's (a capsule: parry's
/// 2D capsule places its half discs' centroids as half balls', 3r/8 from
/// the flat side instead of 4r/(3π); a hull: its tensor, as the coupling
/// reads it); `None`: rapier's from the density.
#[derive(Clone, Debug, PartialEq)]
pub(crate) struct BodySpec {
    pub shape: ShapeSpec,
    pub density: f32,
    pub mass: Option<(f32, [[f64; 3]; 3])>,
}

/// An obstacle in rapier's terms: a fixed collider, or a kinematic one
/// (moved to each substep's pose) when it moves in the frame. Mesh
/// obstacles (sampled distances) take no part.
#[derive(Clone, Debug, PartialEq)]
pub(crate) struct ObstacleSpec {
    /// Half extents (a box) or `[r, 0, 0]` with `ball` (a ball) [m].
    pub half: [f32; 3],
    pub ball: bool,
    /// False for a mesh obstacle: it takes no part (its place in the list
    /// stays, so that obstacle `j` is collider `j`).
    pub solid: bool,
    /// Centre [m] and rotation (2D: `cos θ, sin θ, 0, 0`; 3D: quaternion
    /// `x, y, z, w`) at the frame's start.
    pub x: [f32; 3],
    pub q: [f32; 4],
    pub moving: bool,
}

/// What a world is built from.
pub(crate) struct WorldSpec<'a> {
    /// Each body's shape and mass.
    pub bodies: &'a [BodySpec],
    /// The obstacles (boxes and balls), after the bodies in the world.
    pub obstacles: &'a [ObstacleSpec],
    /// Each body's state.
    pub states: &'a [BodyState],
    /// Gravity [m/s²] (2D: `x, y`).
    pub gravity: [f32; 3],
    /// The walls' inner faces: `lo` and `hi` [m] along every axis.
    pub lo: f32,
    pub hi: f32,
    /// A length scale of the scene [m] (rapier's `length_unit`: its contact
    /// tolerances scale with it).
    pub length_unit: f32,
}

/// The rigid-body world of one frame attempt.
pub(crate) trait RigidWorld: Send + Sync {
    /// Body `i`'s state.
    fn state(&self, i: usize) -> BodyState;
    /// Adds `dv` [m/s] to body `i`'s velocity and `dw` [rad/s] to its
    /// angular velocity (2D: lane 2).
    fn add_velocity(&mut self, i: usize, dv: [f32; 3], dw: [f32; 3]);
    /// Sets where obstacle `j` (a moving one) is at the end of the next
    /// step: its centre [m].
    fn move_obstacle(&mut self, j: usize, x: [f32; 3]);
    /// Steps the world by `dt` seconds (gravity, contacts, integration).
    fn step(&mut self, dt: f32);
}

/// Whether two bodies' shapes overlap at their states (parry's
/// intersection test on rapier's shapes; in dimension `d`, 2 or 3).
pub(crate) fn overlap(d: usize, a: (&ShapeSpec, &BodyState), b: (&ShapeSpec, &BodyState)) -> bool {
    if d == 2 {
        super::rapier2::overlap(a, b)
    } else {
        super::rapier3::overlap(a, b)
    }
}

/// The world of dimension `d` (2 or 3) built from `spec`.
pub(crate) fn build(d: usize, spec: &WorldSpec<'_>) -> Box<dyn RigidWorld> {
    if d == 2 {
        Box::new(super::rapier2::World2::new(spec))
    } else {
        Box::new(super::rapier3::World3::new(spec))
    }
}
