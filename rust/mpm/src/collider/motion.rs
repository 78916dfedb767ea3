//! A collider that translates (a paddle, a dragged obstacle): its *anchor*
//! ([`Shape::anchor`]: a box's or sphere's centre, a sampled shape's
//! `origin`) moves and the shape moves with it, unrotated. A moving
//! collider's condition acts on the grid velocity relative to its own
//! ([`apply_condition_moving`]), so it pushes the fluid. The solver moves
//! it ([`crate::Solver::move_collider`]); a collider that does not move
//! takes the static path ([`apply_condition`]) bit for bit.

use nalgebra::SVector;

use super::{BoundaryCondition, Shape, apply_condition};

impl<const D: usize> Shape<D> {
    /// The point that places the shape: a box's or sphere's `center`, a
    /// sampled shape's `origin` [m].
    pub fn anchor(&self) -> SVector<f32, D> {
        match self {
            Shape::Box { center, .. } | Shape::Sphere { center, .. } => *center,
            Shape::Sampled { origin, .. } => *origin,
        }
    }

    /// Moves the shape (no rotation) so that its [`Shape::anchor`] is `anchor`.
    pub fn set_anchor(&mut self, anchor: SVector<f32, D>) {
        match self {
            Shape::Box { center, .. } | Shape::Sphere { center, .. } => *center = anchor,
            Shape::Sampled { origin, .. } => *origin = anchor,
        }
    }
}

/// Apply a boundary condition with outward normal `n` of a collider moving
/// at `v_obs` [m/s] to grid velocity `v`: the condition acts on the velocity
/// relative to the collider's, `v_rel = v − v_obs` ([`apply_condition`]),
/// and `v = v_obs + v_rel'`. `Sticky` gives the node the collider's velocity,
/// `Slip` its normal velocity with the tangential velocity kept, `Separate`
/// the same only while the node approaches the surface (`v_rel·n < 0`),
/// with Coulomb friction on the relative tangential speed. (A rigid
/// translation has one velocity everywhere: no rotation is modelled.)
#[inline]
pub fn apply_condition_moving<const D: usize>(
    v: &mut SVector<f32, D>,
    n: &SVector<f32, D>,
    condition: BoundaryCondition,
    friction: f32,
    v_obs: &SVector<f32, D>,
) {
    let mut rel = *v - v_obs;
    apply_condition(&mut rel, n, condition, friction);
    *v = v_obs + rel;
}
