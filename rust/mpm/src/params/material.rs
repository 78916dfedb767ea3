//! The materials' parameters: weakly compressible water and
//! Drucker–Prager sand.

use super::schema::MaterialSchema;
use super::{lame, p_wave};
use crate::error::{MpmError, Result};

/// Weakly compressible water (mpm88 style, Hu et al. 2018): the particle
/// carries `J` only; Kirchhoff stress `τ = K·J·(J − 1)·I + η·J·(C + Cᵀ)`.
#[derive(Clone, Debug, PartialEq)]
#[cfg_attr(
    feature = "serde",
    derive(serde::Serialize, serde::Deserialize),
    serde(default, deny_unknown_fields)
)]
pub struct WaterParams {
    /// Rest density ρ [kg/m³].
    pub density: f32,
    /// Bulk modulus K [Pa]; the sound speed is `sqrt(K/ρ)`.
    pub bulk_modulus: f32,
    /// Dynamic viscosity η [Pa·s] (0 = inviscid).
    pub viscosity: f32,
}

impl Default for WaterParams {
    fn default() -> Self {
        // K/ρ = 400 m²/s²: sound speed 20 m/s, the usual weakly compressible choice.
        WaterParams {
            density: 1000.0,
            bulk_modulus: 4.0e5,
            viscosity: 0.0,
        }
    }
}

impl WaterParams {
    /// Checks every field against its range ([`MaterialSchema::PARAMS`]),
    /// naming the bad one (`water.viscosity`).
    pub fn validate(&self) -> Result<()> {
        self.validate_at("water")
    }

    pub(super) fn validate_at(&self, prefix: &str) -> Result<()> {
        self.check_ranges(prefix)
    }

    /// Longitudinal wave speed [m/s].
    pub fn wave_speed(&self) -> f32 {
        (self.bulk_modulus / self.density).sqrt()
    }

    /// The explicit viscous limit `Δt ≤ ρ Δx² / (2 D η)` (the diffusion
    /// number of `ν = η/ρ` at most 1/(2D); measured in 2D, a block of
    /// honey landing on water ran at 0.36 and 0.29 and went non-finite at
    /// 0.72 and 0.58) written as the speed that gives the same step in the
    /// CFL condition `Δt ≤ cfl·Δx / c`: `2 D cfl η / (ρ Δx)` [m/s] (0 when
    /// inviscid). Honey (η = 10 Pa·s) on a 128² grid: 1.4 m/s, under the
    /// sound speed; 2e3 Pa·s there: 290 m/s, about 230 substeps a frame.
    pub fn viscous_speed(&self, dim: usize, cfl: f32, dx: f32) -> f32 {
        if self.viscosity > 0.0 {
            2.0 * dim as f32 * cfl * self.viscosity / (self.density * dx)
        } else {
            0.0
        }
    }
}

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

impl SandParams {
    /// Checks every field against its range ([`MaterialSchema::PARAMS`])
    /// and that cohesion comes with friction, naming the bad field (`sand.cohesion`).
    pub fn validate(&self) -> Result<()> {
        self.validate_at("sand")
    }

    pub(super) fn validate_at(&self, prefix: &str) -> Result<()> {
        self.check_ranges(prefix)?;
        if self.cohesion > 0.0 && self.friction_angle_deg <= 0.0 {
            return Err(MpmError::invalid(
                format!("{prefix}.cohesion"),
                "cohesion needs a friction angle > 0",
            ));
        }
        Ok(())
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
