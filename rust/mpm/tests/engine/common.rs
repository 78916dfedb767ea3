//! Helpers the bodies' test modules share: the bodies they build, their
//! signed distance, and the water around them.

use hybridmpm_mpm::{Body, BodyParams, BodyShape, BodyShapeKind, Material, Particle, SolverParams};
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

/// Water particles on a lattice of spacing `dx/2` filling `[lo, hi)`, none
/// inside the bodies or within `gap` [m] of them; with `hydrostatic`, each
/// at the volume ratio of water at rest below `hi[1]`
/// (`J = 1 − ρ g (hi[1] − y) / K`), else `J = 1`.
pub fn water<const D: usize>(
    lo: [f32; D],
    hi: [f32; D],
    p: &SolverParams<D>,
    bodies: &[Body<D>],
    gap: f32,
    hydrostatic: bool,
) -> Vec<Particle<D>> {
    let s = p.dx() / 2.0;
    let vol = s.powi(D as i32);
    let g = -p.gravity[1];
    let n: [usize; D] = std::array::from_fn(|d| ((hi[d] - lo[d]) / s).round() as usize);
    let total: usize = n.iter().product();
    let mut out = Vec::new();
    for mut i in 0..total {
        let mut x = SVector::<f32, D>::zeros();
        for d in 0..D {
            x[d] = lo[d] + ((i % n[d]) as f32 + 0.5) * s;
            i /= n[d];
        }
        if bodies.iter().any(|b| sdf(b, &x) < gap) {
            continue;
        }
        let mut q = Particle::new(x, Material::Water, p.water.density * vol, vol);
        if hydrostatic {
            q.j = 1.0 - p.water.density * g * (hi[1] - x[1]) / p.water.bulk_modulus;
        }
        out.push(q);
    }
    out
}
