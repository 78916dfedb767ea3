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
//! functions of `B = F*·F*ᵀ` ([`advance_2d`], [`advance_3d`]; in 3D as
//! matrix series when the deviatoric strain is small), which is faster and
//! closer to an f64 SVD reference than the f32 SVD route (`advance_svd` in
//! `return_map.rs`, kept as the tests' comparison), and sixteen particles
//! at a time in SIMD lanes (g2p's [`Batch`](super::batch::Batch)). The
//! stress of a particle's state (set, restored or changed between frames)
//! is that of the SVD route ([`stress_of`]).
//!
//! Files: this one (the model: [`SandParams`], its schema table and the
//! constants derived from it, [`Sand`]), `return_map.rs` (the projection
//! onto the cone, on one particle and on SIMD lanes, and the SVD route),
//! `update_2d.rs` and `update_3d.rs` (the g2p update without singular
//! vectors), `tests.rs` (every route against an f64 SVD reference, the batch
//! against one particle at a time).

mod return_map;
#[cfg(test)]
mod tests;
mod update_2d;
mod update_3d;

pub use return_map::drucker_prager_project;

use nalgebra::{SMatrix, SVector};

use super::Constitutive;
use super::batch::State;
use super::lanes::Real;
use super::schema::{
    DENSITY, MaterialSchema, POISSON, Param, ParamValue, YOUNGS, at_least_zero, ge, gt, le,
};
use super::spectral::{from_lanes, to_lanes, trial};
use crate::dim::{Dim, DimOps};
use crate::error::{MpmError, Result};
use crate::particles::Material;
use update_2d::advance_2d;
use update_3d::advance_3d;

/// Sand: Drucker–Prager elastoplasticity in Hencky strain with SVD return
/// mapping (Klár et al. 2016) and the volume correction of Tampubolon et al. 2017.
#[derive(Clone, Debug, PartialEq)]
#[cfg_attr(
    feature = "serde",
    derive(serde::Serialize, serde::Deserialize),
    serde(default, deny_unknown_fields)
)]
pub struct SandParams {
    /// Density ρ [kg/m³].
    pub density: f32,
    /// Young's modulus E [Pa].
    pub youngs_modulus: f32,
    /// Poisson's ratio ν [-], in (−1, 0.5).
    pub poisson_ratio: f32,
    /// Internal friction angle φ [degrees], in [0, 80].
    pub friction_angle_deg: f32,
    /// Cohesion c [Pa] (≥ 0): shifts the cone apex to the tensile mean stress `c / tan φ`.
    pub cohesion: f32,
}

impl Default for SandParams {
    fn default() -> Self {
        SandParams {
            density: 1000.0,
            youngs_modulus: 3.5e5,
            poisson_ratio: 0.3,
            friction_angle_deg: 30.0,
            cohesion: 0.0,
        }
    }
}

super::isotropic_moduli!(SandParams);

impl MaterialSchema for SandParams {
    const MATERIAL: Material = Material::Sand;
    const PARAMS: &'static [Param] = &[
        DENSITY,
        YOUNGS,
        Param {
            lower: gt(-1.0),
            source: "μ = E/(2(1 + ν)) > 0 and λ finite for ν in (−1, 0.5)",
            ..POISSON
        },
        Param {
            name: "friction_angle_deg",
            alias: None,
            unit: "deg",
            lower: ge(0.0),
            upper: le(80.0),
            choices: &[],
            description: "internal friction angle φ of the Drucker–Prager cone",
            source: "Klár et al. 2016 (dry sand about 30°); the cone closes at 90°",
        },
        at_least_zero(
            "cohesion",
            "Pa",
            "cohesion c: the cone's apex at the tensile mean stress c / tan φ",
            "Tampubolon et al. 2017; c > 0 needs φ > 0",
        ),
    ];
    fn values(&self) -> Vec<ParamValue> {
        use ParamValue::Number as N;
        vec![
            N(self.density),
            N(self.youngs_modulus),
            N(self.poisson_ratio),
            N(self.friction_angle_deg),
            N(self.cohesion),
        ]
    }

    /// The ranges, and that cohesion comes with friction (`sand.cohesion`).
    fn validate_at(&self, prefix: &str) -> Result<()> {
        self.check_ranges(prefix)?;
        if self.cohesion > 0.0 && self.friction_angle_deg <= 0.0 {
            return Err(MpmError::invalid(
                format!("{prefix}.cohesion"),
                "cohesion needs a friction angle > 0",
            ));
        }
        Ok(())
    }
}

/// A sand set's parameters and the constants of the model derived from
/// them once per solver.
#[derive(Clone, Debug)]
pub(crate) struct Sand {
    pub(crate) params: SandParams,
    /// Lamé parameters μ, λ [Pa].
    pub(crate) mu: f32,
    pub(crate) la: f32,
    /// Drucker–Prager cone coefficient α (see [`DimOps::drucker_prager_alpha`]).
    pub(crate) alpha: f32,
    /// Trace of the log strain at the cone apex (0 without cohesion).
    pub(crate) tr_apex: f32,
}

impl Sand {
    /// The constants for `sand` in `D` dimensions.
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
        Sand {
            params: sand.clone(),
            mu,
            la,
            alpha,
            tr_apex,
        }
    }
}

impl Constitutive for Sand {
    const HAS_F: bool = true;
    const SOLID: bool = false;

    /// In 3D: one route per batch, matrix series or eigenvalues ([`advance_3d`]).
    fn shares_route<const D: usize>() -> bool {
        D == 3
    }

    /// The P-wave speed `sqrt((λ + 2μ)/ρ)`.
    fn wave_speed<const D: usize>(&self, _cfl: f32, _dx: f32, _jp_min: f32) -> f32 {
        self.params.wave_speed()
    }

    /// The elastic predictor `F* = (I + Δt·C)·F`, then the return mapping
    /// (Klár et al. 2016, Sec. 7; [`advance_2d`], [`advance_3d`]): the new
    /// F, `vc` and stress.
    #[inline(always)]
    fn update_lanes<R: Real, const D: usize>(&self, s: &mut State<R>, c: &[R; 9], dt: f32) {
        let ft = trial::<R, D>(&s.f, c, dt);
        if D == 2 {
            let (f, vc, tau) = advance_2d(&ft, s.vc, self);
            s.f[..4].copy_from_slice(&f);
            s.tau[..4].copy_from_slice(&tau);
            s.vc = vc;
        } else {
            (s.f, s.vc, s.tau) = advance_3d(&ft, s.vc, self);
        }
    }

    /// The stress of the SVD route ([`stress_of`]) of F.
    fn state_stress<const D: usize>(&self, f: &[f32; 9], _j: f32, _c: &[f32; 9]) -> [f32; 9]
    where
        Dim<D>: DimOps<D>,
    {
        to_lanes(&stress_of::<D>(&from_lanes(f), self.mu, self.la))
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
fn sum<R: Real, const D: usize>(a: &[R; D]) -> R {
    let mut s = a[0];
    for i in 1..D {
        s = s + a[i];
    }
    s
}
