//! Rigid colliders given as signed-distance shapes, static or moving.
//!
//! A grid node whose position has `sdf < 0` lies inside the collider and its
//! velocity is constrained by the collider's [`BoundaryCondition`].
//!
//! One concept a file:
//!
//! - `shape.rs`: [`Shape`] (a box, a sphere, a sampled signed distance), its
//!   signed distance, normal and the particle projection's step;
//! - `sampled.rs`: a sampled signed distance (a triangle mesh's): the one
//!   multilinear stencil of its samples, the plane estimates of its cells'
//!   corners, [`MAX_SAMPLED_NODES`];
//! - `motion.rs`: a collider that translates (its anchor) and the condition
//!   relative to its velocity ([`apply_condition_moving`]);
//! - `validate.rs`: the checks of a collider, and the thinnest one that
//!   holds on a grid ([`Collider::validate_resolution`], with the
//!   measurement behind it);
//! - `projection.rs`: particles that end a substep inside put back on the
//!   surface ([`Collider::project_particle`], [`PROJECT_DEPTH_CELLS`]);
//! - `reach.rs`: where that projection can act ([`Reach`]) and the cells of
//!   a sampled shape where it cannot ([`ShallowCells`]);
//! - `condition.rs`: how a boundary condition acts on a velocity
//!   ([`apply_condition`]).

mod condition;
mod motion;
mod projection;
mod reach;
mod sampled;
mod shape;
mod validate;

pub use condition::apply_condition;
pub use motion::apply_condition_moving;
pub use projection::{PROJECT_DEPTH_CELLS, SOLID_PROJECT_DEPTH_CELLS};
pub use reach::{Reach, ShallowCells};
pub use sampled::MAX_SAMPLED_NODES;
pub use shape::Shape;
pub use validate::{MIN_BOX_THICKNESS_CELLS, MIN_SAMPLED_DEPTH_CELLS, MIN_SPHERE_RADIUS_CELLS};

use crate::boundary::BoundaryCondition;

/// A collider: shape + boundary condition + Coulomb friction, and whether
/// particles that end a substep inside it are put back on its surface
/// ([`Collider::project_particle`]).
#[derive(Clone, Debug, PartialEq)]
pub struct Collider<const D: usize> {
    pub shape: Shape<D>,
    pub condition: BoundaryCondition,
    pub friction: f32,
    /// Project particles out of the collider after each substep's g2p
    /// ([`Collider::project_particle`]). Off, the collider acts on grid
    /// nodes only, as it always did, and particles may end up to about a
    /// cell inside it.
    pub project: bool,
}
