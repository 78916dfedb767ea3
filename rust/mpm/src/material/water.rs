//! Weakly compressible water (Hu et al. 2018, the mpm88 model).
//!
//! The particle carries the volume ratio `J = V/V0` only. Kirchhoff stress
//! `τ = K·J·(J − 1)·I + η·J·(C + Cᵀ)` (pressure from the equation of state
//! `p = K·(1 − J)`, plus Newtonian viscosity with `C ≈ ∇v`); g2p advances
//! `J ← J·(1 + Δt·tr C)` (the discrete `J̇ = J ∇·v`).

use nalgebra::SMatrix;

use crate::params::WaterParams;

/// Kirchhoff stress `τ` [Pa] of water at volume ratio `j` with velocity gradient `c`.
#[inline(always)]
pub(crate) fn kirchhoff_stress<const D: usize>(
    w: &WaterParams,
    j: f32,
    c: &SMatrix<f32, D, D>,
) -> SMatrix<f32, D, D> {
    let mut tau = SMatrix::<f32, D, D>::identity() * (w.bulk_modulus * j * (j - 1.0));
    if w.viscosity > 0.0 {
        tau += (c + c.transpose()) * (w.viscosity * j);
    }
    tau
}

/// g2p update: advance `j` over `dt` with the new velocity gradient `c`.
#[inline(always)]
pub(crate) fn advance_volume_ratio<const D: usize>(j: &mut f32, dt: f32, c: &SMatrix<f32, D, D>) {
    *j *= 1.0 + dt * c.trace();
}
