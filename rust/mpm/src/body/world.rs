//! The bodies' dynamics and contacts, by rapier (rapier2d / rapier3d, `f32`,
//! `enhanced-determinism`), behind one small trait ([`RigidWorld`]) that
//! speaks in plain arrays: the solver never sees rapier's types, and 2D and
//! 3D differ only in `rapier2.rs` / `rapier3.rs`.
//!
//! A world is built from the bodies' exact state at the start of each frame
//! attempt (`rapier::build`) and read back at its end: a frame that fails is
//! retried from the same state, and a checkpoint (the state) restores the
//! same bits as a run that never stopped. Contacts' warm-start impulses live
//! within a frame only.

use std::any::Any;
use std::sync::{Arc, OnceLock};

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

/// An obstacle's shape in rapier's terms.
#[derive(Clone, Debug, PartialEq)]
pub(crate) enum ObstacleShape {
    /// Half extents [m].
    Box([f32; 3]),
    /// Radius [m].
    Ball(f32),
    /// A mesh obstacle (sampled distances) as voxels.
    Voxels(Arc<Voxelized>),
    /// None in the world (a mesh obstacle past [`MAX_OBSTACLE_VOXELS`]): its
    /// place in the list stays, so that obstacle `j` is collider `j`.
    Absent,
}

/// An obstacle in rapier's terms: a fixed collider, or a kinematic one
/// (moved to each substep's pose) when it moves in the frame.
#[derive(Clone, Debug, PartialEq)]
pub(crate) struct ObstacleSpec {
    pub shape: ObstacleShape,
    /// Centre [m] (a mesh obstacle: its anchor, the samples' first node) and
    /// rotation (2D: `cos θ, sin θ, 0, 0`; 3D: quaternion `x, y, z, w`) at
    /// the frame's start.
    pub x: [f32; 3],
    pub q: [f32; 4],
    pub moving: bool,
}

impl ObstacleSpec {
    /// Where its collider's frame lies: the offset [m] from the obstacle's
    /// centre (a mesh obstacle's voxels: half a spacing down every axis, so
    /// that voxel `i` is centred on node `i`; 2D reads `x, y`) and the pose
    /// there at the frame's start.
    pub fn collider_frame(&self) -> ([f32; 3], BodyState) {
        let offset = match &self.shape {
            ObstacleShape::Voxels(v) => [-0.5 * v.size; 3],
            _ => [0.0; 3],
        };
        let state = BodyState {
            x: std::array::from_fn(|d| self.x[d] + offset[d]),
            q: self.q,
            ..Default::default()
        };
        (offset, state)
    }
}

/// Most voxels a mesh obstacle takes in the bodies' world (the shell of
/// [`Voxelized::SHELL_CELLS`] samples under the surface of a mesh filling
/// the largest sampled grid is far below it); beyond, the obstacle meets the
/// bodies through the fluid only.
pub(crate) const MAX_OBSTACLE_VOXELS: usize = 1 << 21;

/// A mesh obstacle's sampled distances as rapier voxels: one voxel of side
/// `size` (the samples' spacing) centred on each node whose sample lies
/// inside the surface, to [`Voxelized::SHELL_CELLS`] spacings deep. The
/// voxels' faces lie within half a spacing of the surface (a staircase on a
/// slope). `source` is the samples they were made from, so that a world of
/// the next frame reuses them while the obstacle keeps its samples, and
/// `shape` rapier's shape of them, made by the first world that holds them.
#[derive(Debug)]
pub(crate) struct Voxelized {
    pub size: f32,
    /// Each voxel's node `i` (2D: `i_0, i_1, 0`); voxel `i` spans
    /// `[i, i + 1] · size` in the collider's frame, whose origin lies half a
    /// spacing below the anchor on every axis (so that it is centred on node `i`).
    pub keys: Vec<[i32; 3]>,
    pub source: Arc<[f32]>,
    /// rapier2d's or rapier3d's `SharedShape` of the voxels.
    pub shape: OnceLock<Box<dyn Any + Send + Sync>>,
}

impl PartialEq for Voxelized {
    fn eq(&self, other: &Self) -> bool {
        self.size == other.size && self.keys == other.keys
    }
}

impl Voxelized {
    /// Depth [spacings] of the shell of inside nodes taken: thicker than the
    /// distance a body moves into an obstacle in a substep.
    pub const SHELL_CELLS: f32 = 3.0;

    /// The voxels of the samples `values` (row-major over `dims`, the last
    /// axis fastest, `cell` apart); `None` beyond [`MAX_OBSTACLE_VOXELS`] or
    /// without an inside node.
    pub fn of_samples(values: &Arc<[f32]>, dims: &[usize], cell: f32) -> Option<Self> {
        let deepest = -Self::SHELL_CELLS * cell;
        let mut keys = Vec::new();
        for (lin, &v) in values.iter().enumerate() {
            if v <= 0.0 && v > deepest {
                if keys.len() == MAX_OBSTACLE_VOXELS {
                    return None;
                }
                let mut key = [0i32; 3];
                let mut rest = lin;
                for d in (0..dims.len()).rev() {
                    key[d] = (rest % dims[d]) as i32;
                    rest /= dims[d];
                }
                keys.push(key);
            }
        }
        (!keys.is_empty()).then(|| Voxelized {
            size: cell,
            keys,
            source: Arc::clone(values),
            shape: OnceLock::new(),
        })
    }
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
