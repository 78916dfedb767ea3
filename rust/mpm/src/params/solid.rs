//! The parameters of the solid materials (elastic, snow, viscoplastic) and
//! a parameter set of the table that particles index ([`MaterialParams`]).
//!
//! Moduli in Pa, densities in kg/m³, viscosities in Pa·s. Lamé parameters
//! from Young's modulus E and Poisson's ratio ν:
//! `μ = E / (2(1 + ν))`, `λ = E ν / ((1 + ν)(1 − 2ν))`.

use super::schema::MaterialSchema;
use super::{SandParams, WaterParams, lame, p_wave};
use crate::error::Result;
use crate::particles::Material;

/// The hyperelastic energy of an [`ElasticParams`] set.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Default)]
#[cfg_attr(
    feature = "serde",
    derive(serde::Serialize, serde::Deserialize),
    serde(rename_all = "lowercase")
)]
pub enum ElasticModel {
    /// Fixed-corotated (Stomakhin et al. 2012):
    /// `τ = 2μ(F − R)Fᵀ + λJ(J − 1)I`, `R` the rotation of `F`'s polar decomposition.
    #[default]
    Corotated,
    /// Compressible neo-Hookean (e.g. Bonet & Wood 2008): `τ = μ(FFᵀ − I) + λ ln J · I`.
    Neohookean,
}

impl ElasticModel {
    /// Its name in the parameter dict (`corotated`, `neohookean`).
    pub fn name(self) -> &'static str {
        match self {
            ElasticModel::Corotated => "corotated",
            ElasticModel::Neohookean => "neohookean",
        }
    }
}

/// Elastic solid ("jelly"): the particle carries its deformation gradient F.
#[derive(Clone, Debug, PartialEq)]
#[cfg_attr(
    feature = "serde",
    derive(serde::Serialize, serde::Deserialize),
    serde(default, deny_unknown_fields)
)]
pub struct ElasticParams {
    /// Density ρ [kg/m³].
    pub density: f32,
    /// Young's modulus E [Pa].
    pub youngs_modulus: f32,
    /// Poisson's ratio ν [-], in [0, 0.5).
    pub poisson_ratio: f32,
    /// The energy: fixed-corotated or neo-Hookean.
    pub model: ElasticModel,
}

impl Default for ElasticParams {
    fn default() -> Self {
        // a stiff jelly: E = 1e5 Pa (wave speed 11.6 m/s at ν = 0.3)
        ElasticParams {
            density: 1000.0,
            youngs_modulus: 1.0e5,
            poisson_ratio: 0.3,
            model: ElasticModel::Corotated,
        }
    }
}

impl ElasticParams {
    pub fn validate(&self) -> Result<()> {
        self.validate_at("elastic")
    }

    fn validate_at(&self, prefix: &str) -> Result<()> {
        self.check_ranges(prefix)
    }

    /// Lamé parameters (μ, λ) [Pa].
    pub fn lame(&self) -> (f32, f32) {
        lame(self.youngs_modulus, self.poisson_ratio)
    }

    /// P-wave speed `sqrt((λ + 2μ)/ρ)` [m/s].
    pub fn wave_speed(&self) -> f32 {
        p_wave(self.youngs_modulus, self.poisson_ratio, self.density, 1.0)
    }
}

/// Snow (Stomakhin et al. 2013, "A material point method for snow
/// simulation"): fixed-corotated elasticity on the elastic part `F_E` of
/// `F = F_E F_P`; after each update the singular values of `F_E` are clamped
/// to `[1 − θc, 1 + θs]` and the rest goes to `F_P`; the Lamé parameters are
/// hardened by `e^{ξ(1 − J_P)}`, `J_P = det F_P`. The particle carries `F_E`
/// (in `f`) and `J_P` (in `j`).
#[derive(Clone, Debug, PartialEq)]
#[cfg_attr(
    feature = "serde",
    derive(serde::Serialize, serde::Deserialize),
    serde(default, deny_unknown_fields)
)]
pub struct SnowParams {
    /// Density ρ [kg/m³] (Stomakhin et al. 2013: 400).
    pub density: f32,
    /// Initial Young's modulus E₀ [Pa] (1.4e5).
    pub youngs_modulus: f32,
    /// Poisson's ratio ν [-] (0.2), in [0, 0.5).
    pub poisson_ratio: f32,
    /// Critical compression θc [-] (2.5e-2), in (0, 1).
    pub theta_c: f32,
    /// Critical stretch θs [-] (7.5e-3), in (0, 1).
    pub theta_s: f32,
    /// Hardening coefficient ξ [-] (10), ≥ 0.
    pub hardening: f32,
}

impl Default for SnowParams {
    fn default() -> Self {
        SnowParams {
            density: 400.0,
            youngs_modulus: 1.4e5,
            poisson_ratio: 0.2,
            theta_c: 2.5e-2,
            theta_s: 7.5e-3,
            hardening: 10.0,
        }
    }
}

impl SnowParams {
    /// The range of `J_P` that enters the hardening exponent (the MLS-MPM
    /// reference code's clamp): `J_P` itself is kept unclamped, so that
    /// `J_P · det F_E = det F` holds, and the stiffness stays bounded.
    pub const JP_RANGE: (f32, f32) = (0.6, 20.0);

    pub fn validate(&self) -> Result<()> {
        self.validate_at("snow")
    }

    fn validate_at(&self, prefix: &str) -> Result<()> {
        self.check_ranges(prefix)
    }

    /// Lamé parameters (μ₀, λ₀) [Pa] before hardening.
    pub fn lame(&self) -> (f32, f32) {
        lame(self.youngs_modulus, self.poisson_ratio)
    }

    /// Hardening factor `e^{ξ(1 − J_P)}` with `J_P` clamped to [`Self::JP_RANGE`].
    pub fn hardening_factor(&self, jp: f32) -> f32 {
        let jp = jp.clamp(Self::JP_RANGE.0, Self::JP_RANGE.1);
        (self.hardening * (1.0 - jp)).exp()
    }

    /// P-wave speed [m/s] of snow whose smallest `J_P` is `jp_min`.
    pub fn wave_speed(&self, jp_min: f32) -> f32 {
        p_wave(
            self.youngs_modulus,
            self.poisson_ratio,
            self.density,
            self.hardening_factor(jp_min),
        )
    }
}

/// Viscoplastic solid (mud, plasticine): von Mises plasticity on the Hencky
/// strain with viscous relaxation (a Bingham material; Perzyna-type
/// overstress). With `ε = ln σ` the principal log strains of the trial
/// elastic F and `s = 2μ·dev ε` the deviatoric Kirchhoff stress, the material
/// flows when `√J₂ = ‖s‖/√2 > τ_y`, and then
/// `‖s‖ ← √2 τ_y + (‖s_trial‖ − √2 τ_y) / (1 + μΔt/η)` (backward Euler of
/// `ṡ = 2μ(D − D_p)`, `D_p = (‖s‖ − √2 τ_y)/(2η) · s/‖s‖`): in steady simple
/// shear at rate γ̇ the shear stress is `τ_y + η γ̇`. `η = 0`: perfect
/// plasticity (plasticine). The particle carries the elastic F.
#[derive(Clone, Debug, PartialEq)]
#[cfg_attr(
    feature = "serde",
    derive(serde::Serialize, serde::Deserialize),
    serde(default, deny_unknown_fields)
)]
pub struct ViscoplasticParams {
    /// Density ρ [kg/m³].
    pub density: f32,
    /// Young's modulus E [Pa] of the elastic part.
    pub youngs_modulus: f32,
    /// Poisson's ratio ν [-], in [0, 0.5).
    pub poisson_ratio: f32,
    /// Bingham yield stress in simple shear τ_y [Pa] (flow when `√J₂ > τ_y`), ≥ 0.
    pub yield_stress: f32,
    /// Plastic (Bingham) viscosity η [Pa·s], ≥ 0.
    pub viscosity: f32,
}

impl Default for ViscoplasticParams {
    fn default() -> Self {
        // a mud: τ_y = 100 Pa, η = 10 Pa·s
        ViscoplasticParams {
            density: 1500.0,
            youngs_modulus: 1.0e6,
            poisson_ratio: 0.3,
            yield_stress: 100.0,
            viscosity: 10.0,
        }
    }
}

impl ViscoplasticParams {
    pub fn validate(&self) -> Result<()> {
        self.validate_at("viscoplastic")
    }

    fn validate_at(&self, prefix: &str) -> Result<()> {
        self.check_ranges(prefix)
    }

    /// Lamé parameters (μ, λ) [Pa].
    pub fn lame(&self) -> (f32, f32) {
        lame(self.youngs_modulus, self.poisson_ratio)
    }

    /// P-wave speed `sqrt((λ + 2μ)/ρ)` [m/s].
    pub fn wave_speed(&self) -> f32 {
        p_wave(self.youngs_modulus, self.poisson_ratio, self.density, 1.0)
    }
}

/// One parameter set of the table particles index (`Particle::set`). The
/// parameter dict names it by its material, the one key of a dict
/// (`{"elastic": {"youngs_modulus": 1e6}}`, serde's externally tagged form;
/// the keys inside as each struct's, unknown ones refused);
/// [`super::SolverParams::sets`] lists them.
#[derive(Clone, Debug, PartialEq)]
#[cfg_attr(
    feature = "serde",
    derive(serde::Serialize, serde::Deserialize),
    serde(rename_all = "lowercase")
)]
pub enum MaterialParams {
    Water(WaterParams),
    Sand(SandParams),
    Elastic(ElasticParams),
    Snow(SnowParams),
    Viscoplastic(ViscoplasticParams),
}

impl MaterialParams {
    /// The material code this set belongs to.
    pub fn material(&self) -> Material {
        match self {
            MaterialParams::Water(_) => Material::Water,
            MaterialParams::Sand(_) => Material::Sand,
            MaterialParams::Elastic(_) => Material::Elastic,
            MaterialParams::Snow(_) => Material::Snow,
            MaterialParams::Viscoplastic(_) => Material::Viscoplastic,
        }
    }

    /// Density ρ [kg/m³].
    pub fn density(&self) -> f32 {
        match self {
            MaterialParams::Water(p) => p.density,
            MaterialParams::Sand(p) => p.density,
            MaterialParams::Elastic(p) => p.density,
            MaterialParams::Snow(p) => p.density,
            MaterialParams::Viscoplastic(p) => p.density,
        }
    }

    /// Validates the set at `field` (`sets[2]`), naming a bad key under it
    /// and its material (`sets[2].elastic.youngs_modulus`).
    pub fn validate(&self, field: &str) -> Result<()> {
        let prefix = format!("{field}.{}", self.material().name());
        match self {
            MaterialParams::Water(p) => p.validate_at(&prefix),
            MaterialParams::Sand(p) => p.validate_at(&prefix),
            MaterialParams::Elastic(p) => p.validate_at(&prefix),
            MaterialParams::Snow(p) => p.validate_at(&prefix),
            MaterialParams::Viscoplastic(p) => p.validate_at(&prefix),
        }
    }
}
