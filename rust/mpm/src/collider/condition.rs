//! How a boundary condition acts on a velocity: a grid node's inside a
//! collider ([`apply_condition`]) and a projected particle's.

use nalgebra::SVector;

use crate::boundary::BoundaryCondition;

/// Apply a boundary condition with outward normal `n` (pointing out of the
/// solid, into the fluid) to grid velocity `v`.
#[inline]
pub fn apply_condition<const D: usize>(
    v: &mut SVector<f32, D>,
    n: &SVector<f32, D>,
    condition: BoundaryCondition,
    friction: f32,
) {
    match condition {
        BoundaryCondition::Sticky => *v = SVector::zeros(),
        BoundaryCondition::Slip => {
            let vn = v.dot(n);
            *v -= n * vn;
        }
        BoundaryCondition::Separate => {
            let vn = v.dot(n);
            if vn < 0.0 {
                let vt = *v - n * vn;
                let vt_len = crate::dim::norm(&vt);
                if friction > 0.0 && vt_len > 0.0 {
                    // Coulomb: the tangential speed drops by μ·|v_n|.
                    let scale = (vt_len + friction * vn).max(0.0) / vt_len;
                    *v = vt * scale;
                } else {
                    *v = vt;
                }
            }
        }
    }
}

/// The velocity `v` (relative to the collider's) of a particle projected
/// onto a collider's surface with outward normal `n`: `Sticky` zero, `Slip`
/// and `Separate` without an inward normal part (`v·n < 0`), `Separate`
/// with Coulomb friction μ on the tangential speed ([`apply_condition`]).
#[inline]
pub(super) fn project_velocity<const D: usize>(
    v: &mut SVector<f32, D>,
    n: &SVector<f32, D>,
    condition: BoundaryCondition,
    friction: f32,
) {
    match condition {
        BoundaryCondition::Sticky => *v = SVector::zeros(),
        BoundaryCondition::Slip => apply_condition(v, n, BoundaryCondition::Separate, 0.0),
        BoundaryCondition::Separate => apply_condition(v, n, condition, friction),
    }
}
