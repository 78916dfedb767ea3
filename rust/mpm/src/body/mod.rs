//! Rigid bodies that the fluid moves and that push back (two-way coupling).
//!
//! A body is a collider whose velocity comes from its state and whose
//! grid-node momentum changes are summed into an impulse:
//!
//! - `mod.rs`: a body's shape and initial state ([`Body`]) and its checks
//!   against the grid;
//! - `pose.rs`: a body where it is during a substep ([`BodyPose`]): its
//!   signed distance, outward normal and point velocity `v + ω × r`, what the
//!   grid update's collider pass reads, and the exact sums of the impulses
//!   it writes ([`ImpulseSum`]);
//! - `world.rs`: the bodies' dynamics and contacts, by rapier behind one
//!   small trait ([`world::RigidWorld`]); the only file that names rapier's
//!   types besides `rapier2.rs` / `rapier3.rs`;
//! - `system.rs`: the solver's bodies between substeps ([`Bodies`]): their
//!   exact state (what a checkpoint carries), the poses of the substep under
//!   way, the impulses summed, the rapier step.
//!
//! Coupling, each substep (docs/bodies.md): a grid node with mass whose
//! position lies inside a body or less than [`BODY_REACH_CELLS`] cells
//! outside its surface takes the body's point velocity for its normal
//! component when it approaches the body (the `Separate` condition relative
//! to `v + ω × r`, with Coulomb friction on the tangential part); the node's
//! momentum change `m (v' − v)`, with its sign flipped, is an impulse on the
//! body at the node. The impulses are summed in fixed point (integer sums:
//! the same bits in any order, for any thread count) and applied to rapier
//! before it steps with the substep's `dt`.

mod pose;
mod rapier2;
mod rapier3;
mod system;
pub(crate) mod world;

pub use pose::{BodyPose, Coupled, ImpulseSum, SUM_LANES};
pub use system::{Bodies, BodyState};

use nalgebra::{SMatrix, SVector};

use crate::error::{MpmError, Result};

/// How far outside a body's surface grid nodes are coupled to it, in cells.
/// Coupling only the nodes inside a body lets water sit up to a cell inside
/// its outline and leaves buoyancy 5–15 % short; nodes to about a cell
/// outside close the gap (docs/bodies.md has the measurement).
pub const BODY_REACH_CELLS: f32 = 1.0;

/// Most bodies a solver takes.
pub const MAX_BODIES: usize = 64;

/// The thinnest body (its smallest half extent or radius), in cells: as
/// thin an obstacle is refused, since the fluid leaks through it.
pub const MIN_BODY_HALF_CELLS: f32 = 1.0;

/// A body's shape, centred on its centre of mass, in its own frame.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum BodyShape<const D: usize> {
    /// A box of these half extents [m] along the body's axes.
    Box { half_extents: SVector<f32, D> },
    /// A sphere (a circle in 2D) of this radius [m].
    Ball { radius: f32 },
}

impl<const D: usize> BodyShape<D> {
    /// Volume [m³] (area [m²] in 2D).
    pub fn volume(&self) -> f32 {
        match self {
            BodyShape::Box { half_extents } => half_extents.iter().map(|h| 2.0 * h).product(),
            BodyShape::Ball { radius } => {
                if D == 2 {
                    std::f32::consts::PI * radius * radius
                } else {
                    4.0 / 3.0 * std::f32::consts::PI * radius.powi(3)
                }
            }
        }
    }

    /// Radius of the smallest ball about the centre that holds the shape [m].
    pub fn bounding_radius(&self) -> f32 {
        match self {
            BodyShape::Box { half_extents } => half_extents.norm(),
            BodyShape::Ball { radius } => *radius,
        }
    }

    /// Half of the shape's thinnest extent [m].
    fn thinnest_half(&self) -> f32 {
        match self {
            BodyShape::Box { half_extents } => half_extents.min(),
            BodyShape::Ball { radius } => *radius,
        }
    }
}

/// A rigid body: shape, initial pose and velocity, density, and Coulomb
/// friction against the fluid ([`crate::params::BodyParams::build`]).
#[derive(Clone, Debug, PartialEq)]
pub struct Body<const D: usize> {
    pub shape: BodyShape<D>,
    /// Centre of mass [m].
    pub center: SVector<f32, D>,
    /// Rotation (columns: the body's axes in world coordinates).
    pub rotation: SMatrix<f32, D, D>,
    /// Density [kg/m³].
    pub density: f32,
    /// Velocity of the centre of mass [m/s].
    pub velocity: SVector<f32, D>,
    /// Angular velocity [rad/s] (2D: about z, the last component).
    pub angular_velocity: [f32; 3],
    /// Coulomb friction coefficient against the fluid.
    pub friction: f32,
}

impl<const D: usize> Body<D> {
    /// Mass [kg; per unit depth in 2D].
    pub fn mass(&self) -> f32 {
        self.density * self.shape.volume()
    }

    /// Checks the body against a grid of spacing `dx` whose walls are
    /// `wall_cells` thick: thick enough for the grid (at least
    /// [`MIN_BODY_HALF_CELLS`] cells a half extent or radius, field
    /// `half_extents` / `radius`), inside the walls (field `center`),
    /// finite speeds (`velocity`, `angular_velocity`). `field` prefixes the
    /// names (e.g. `bodies[2]`).
    pub fn validate(&self, field: &str, dx: f32, wall_cells: usize) -> Result<()> {
        let size_field = match self.shape {
            BodyShape::Box { .. } => "half_extents",
            BodyShape::Ball { .. } => "radius",
        };
        let thin = self.shape.thinnest_half();
        if !(thin >= MIN_BODY_HALF_CELLS * dx) {
            return Err(MpmError::invalid(
                format!("{field}.{size_field}"),
                format!(
                    "too thin for the grid: its smallest half extent {thin} m is under {MIN_BODY_HALF_CELLS} cell ({} m); the fluid would leak through",
                    MIN_BODY_HALF_CELLS * dx
                ),
            ));
        }
        let lo = wall_cells as f32 * dx;
        let hi = 1.0 - lo;
        // the body's extent along each axis (its rotated box's, or the ball's)
        for d in 0..D {
            let reach = match self.shape {
                BodyShape::Box { half_extents } => (0..D)
                    .map(|k| (self.rotation[(d, k)] * half_extents[k]).abs())
                    .sum(),
                BodyShape::Ball { radius } => radius,
            };
            let c = self.center[d];
            if !(c - reach >= lo && c + reach <= hi) {
                return Err(MpmError::invalid(
                    format!("{field}.center"),
                    format!(
                        "the body must lie inside the walls, [{lo}, {hi}] m along axis {d}: it spans [{}, {}]",
                        c - reach,
                        c + reach
                    ),
                ));
            }
        }
        if !(self.density.is_finite() && self.density > 0.0) {
            return Err(MpmError::invalid(
                format!("{field}.density"),
                format!("must be a finite number > 0, got {}", self.density),
            ));
        }
        Ok(())
    }
}
