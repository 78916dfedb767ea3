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

use nalgebra::{SMatrix, SVector};

use crate::dim::{Dim, DimOps};
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
}

impl SandModel {
    pub(crate) fn new<const D: usize>(sand: &SandParams) -> Self
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

/// g2p update of one sand particle: elastic predictor `(I + Δt·c)·f`, return
/// mapping onto the Drucker–Prager cone (updates `vc`), new `f`. Returns the
/// new Kirchhoff stress.
#[inline(always)]
pub(crate) fn advance<const D: usize>(
    f: &mut SMatrix<f32, D, D>,
    vc: &mut f32,
    c: &SMatrix<f32, D, D>,
    dt: f32,
    m: &SandModel,
) -> SMatrix<f32, D, D>
where
    Dim<D>: DimOps<D>,
{
    let f_trial = (SMatrix::<f32, D, D>::identity() + c * dt) * *f;
    let svd = Dim::<D>::svd(&f_trial);
    let e0 = svd.sigma.map(|s| s.max(1e-6).ln());
    let e_new = drucker_prager_project::<D>(&e0, vc, m.alpha, m.mu, m.la, m.tr_apex);
    if e_new == e0 {
        // inside the cone: elastic, F is the trial F
        *f = f_trial;
    } else {
        *f = svd.u * SMatrix::<f32, D, D>::from_diagonal(&e_new.map(f32::exp)) * svd.v.transpose();
    }
    kirchhoff_stress(&svd.u, &e_new, m.mu, m.la)
}

/// Drucker–Prager return mapping in Hencky strain (Klár et al. 2016, Sec. 7.3,
/// with the volume correction of Tampubolon et al. 2017, Eq. 26–27).
///
/// `e0`: principal log strains of the trial elastic F; `vc`: accumulated log
/// volume correction (updated); `alpha`: cone coefficient; `mu`, `la`: Lamé
/// parameters; `tr_apex`: trace of the strain at the cone apex (cohesion).
/// Returns the projected principal log strains.
pub fn drucker_prager_project<const D: usize>(
    e0: &SVector<f32, D>,
    vc: &mut f32,
    alpha: f32,
    mu: f32,
    la: f32,
    tr_apex: f32,
) -> SVector<f32, D> {
    let dd = D as f32;
    let shift = tr_apex / dd;
    let e = e0.map(|x| x + *vc / dd - shift);
    let tr = e.sum();
    let ehat = e.map(|x| x - tr / dd);
    let ehat_norm = ehat.norm();
    let e_new = if tr >= 0.0 {
        // expansion: project to the cone tip
        SVector::<f32, D>::from_element(shift)
    } else {
        let dgamma = ehat_norm + (dd * la + 2.0 * mu) / (2.0 * mu) * tr * alpha;
        if dgamma <= 0.0 {
            // inside the cone: elastic, no volume correction applied
            *e0
        } else {
            (e - ehat * (dgamma / ehat_norm)).map(|x| x + shift)
        }
    };
    *vc += e0.sum() - e_new.sum();
    e_new
}
