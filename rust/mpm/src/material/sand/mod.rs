//! Sand: Drucker–Prager elastoplasticity in Hencky (log) strain with an SVD
//! return mapping (Klár et al. 2016, "Drucker–Prager elastoplasticity for
//! sand animation", Sec. 7) and the volume correction of Tampubolon et al.
//! 2017 ("Multi-species simulation of porous sand and water mixtures",
//! Eq. 26–27).
//!
//! The particle carries the elastic deformation gradient `F` and the
//! accumulated log-volume correction `vc`. Per g2p: trial `F* = (I + Δt·C)·F`,
//! `F* = U·diag(σ)·Vᵀ`, project the principal log strains `ε = ln σ` onto the
//! yield cone ([`drucker_prager_project`]), `F = U·diag(exp ε)·Vᵀ`; the
//! Kirchhoff stress of the St. Venant–Kirchhoff model in Hencky strain is
//! `τ = U·diag(2μ·ε + λ·tr ε)·Uᵀ`.
//!
//! That is the model; g2p computes it without singular vectors, as isotropic
//! functions of `B = F*·F*ᵀ` ([`advance_2d`](update_2d::advance_2d),
//! [`advance_3d`](update_3d::advance_3d); in 3D as matrix series when the
//! deviatoric strain is small), which is faster and closer to an f64 SVD
//! reference than the f32 SVD route
//! ([`advance_svd`](return_map::advance_svd), kept as the tests'
//! comparison), and sixteen particles at a time in SIMD lanes
//! ([`SandBatch`]).
//!
//! Files: `return_map.rs` (the projection onto the cone, on one particle and
//! on SIMD lanes, and the SVD route), `update_2d.rs` and `update_3d.rs` (the
//! g2p update without singular vectors), `batch.rs` ([`SandBatch`]),
//! `tests.rs` (every route against an f64 SVD reference, the batch against
//! one particle at a time).

mod batch;
mod return_map;
#[cfg(test)]
mod tests;
mod update_2d;
pub(crate) mod update_3d;

pub(crate) use batch::{ParticleSink, SandBatch, SandHealth};
pub use return_map::drucker_prager_project;

use nalgebra::{SMatrix, SVector};

use super::lanes::Real;
use crate::dim::{Dim, DimOps};
use crate::isa::Isa;
use crate::params::SandParams;

/// The constants of the sand model derived from [`SandParams`] once per substep.
#[derive(Clone, Copy, Debug)]
pub(crate) struct SandModel {
    /// Lamé parameters μ, λ [Pa].
    pub(crate) mu: f32,
    pub(crate) la: f32,
    /// Drucker–Prager cone coefficient α (see [`DimOps::drucker_prager_alpha`]).
    pub(crate) alpha: f32,
    /// Trace of the log strain at the cone apex (0 without cohesion).
    pub(crate) tr_apex: f32,
    /// The compiled copy of [`SandBatch::run`] to use (`crate::isa`).
    pub(crate) isa: Isa,
}

impl SandModel {
    /// The constants for `sand`; `isa` must be [`available`](Isa::available).
    pub(crate) fn new<const D: usize>(sand: &SandParams, isa: Isa) -> Self
    where
        Dim<D>: DimOps<D>,
    {
        let (mu, la) = sand.lame();
        let alpha = Dim::<D>::drucker_prager_alpha(sand.friction_angle_deg.to_radians());
        let tan_phi = sand.friction_angle_deg.to_radians().tan();
        let tr_apex = if sand.cohesion > 0.0 {
            D as f32 * sand.cohesion / (tan_phi * (D as f32 * la + 2.0 * mu))
        } else {
            0.0
        };
        SandModel {
            mu,
            la,
            alpha,
            tr_apex,
            isa,
        }
    }
}

/// Kirchhoff stress `τ = U·diag(2μ·ε + λ·tr ε)·Uᵀ` [Pa] from the left singular
/// vectors `u` and the principal log strains `eps`.
#[inline(always)]
pub(crate) fn kirchhoff_stress<const D: usize>(
    u: &SMatrix<f32, D, D>,
    eps: &SVector<f32, D>,
    mu: f32,
    la: f32,
) -> SMatrix<f32, D, D> {
    let tr = eps.sum();
    let diag = eps.map(|e| 2.0 * mu * e + la * tr);
    u * SMatrix::<f32, D, D>::from_diagonal(&diag) * u.transpose()
}

/// Kirchhoff stress of the elastic deformation gradient `f` (no plasticity).
#[inline(always)]
pub(crate) fn stress_of<const D: usize>(
    f: &SMatrix<f32, D, D>,
    mu: f32,
    la: f32,
) -> SMatrix<f32, D, D>
where
    Dim<D>: DimOps<D>,
{
    let svd = Dim::<D>::svd(f);
    let eps = svd.sigma.map(|s| s.max(1e-6).ln());
    kirchhoff_stress(&svd.u, &eps, mu, la)
}

#[inline(always)]
fn k<R: Real>(x: f32) -> R {
    R::splat(x)
}

#[inline(always)]
fn sum<R: Real, const D: usize>(a: &[R; D]) -> R {
    let mut s = a[0];
    for i in 1..D {
        s = s + a[i];
    }
    s
}
