//! Which rapier a body runs on: the world and the overlap test of dimension
//! `d`, from `rapier2.rs` (2D) or `rapier3.rs` (3D). The trait and the specs
//! they speak are in `world.rs`, which names neither.

use super::BodyState;
use super::world::{RigidWorld, ShapeSpec, WorldSpec};

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
