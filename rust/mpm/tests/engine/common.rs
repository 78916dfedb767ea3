//! Helpers the bodies' test modules share.

use hybridmpm_mpm::{Body, BodyParams, BodyShape, BodyShapeKind};
use nalgebra::SVector;

/// A capsule body of radius `r` and half height `h` [m], density `rho`
/// [kg/m³] at `center`, turned `angle_deg` in 2D.
pub fn capsule<const D: usize>(
    center: &[f32],
    r: f32,
    h: f32,
    rho: f32,
    angle_deg: f64,
) -> Body<D> {
    BodyParams {
        shape: Some(BodyShapeKind::Capsule),
        center: Some(center.to_vec()),
        radius: Some(r),
        half_height: Some(h),
        angle_deg: (D == 2).then_some(angle_deg),
        density: Some(rho),
        ..Default::default()
    }
    .build::<D>("body")
    .unwrap()
}

/// Signed distance [m] of `x` to a body as given (its initial pose),
/// negative inside: the analytic distance of a box, ball or capsule, and a
/// hull's largest face-plane distance (exact inside, a lower bound outside).
pub fn sdf<const D: usize>(b: &Body<D>, x: &SVector<f32, D>) -> f32 {
    let q = b.rotation.tr_mul(&(x - b.center));
    match &b.shape {
        BodyShape::Ball { radius } => q.norm() - radius,
        BodyShape::Box { half_extents } => {
            let e = q.abs() - half_extents;
            e.map(|v| v.max(0.0)).norm() + e.max().min(0.0)
        }
        BodyShape::Capsule {
            radius,
            half_height,
        } => {
            let mut p = q;
            p[1] -= q[1].clamp(-half_height, *half_height);
            p.norm() - radius
        }
        BodyShape::Hull(hull) => {
            let p = std::array::from_fn(|d| if d < D { q[d] } else { 0.0 });
            hull.sdf_normal(p).0
        }
    }
}
