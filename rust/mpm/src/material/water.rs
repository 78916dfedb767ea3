//! Weakly compressible water (Hu et al. 2018, the mpm88 model).
//!
//! The particle carries the volume ratio `J = V/V0` only. Kirchhoff stress
//! `τ = K·J·(J − 1)·I + η·J·(C + Cᵀ)` (pressure from the equation of state
//! `p = K·(1 − J)`, plus Newtonian viscosity with `C ≈ ∇v`); g2p advances
//! `J ← J·(1 + Δt·tr C)` (the discrete `J̇ = J ∇·v`), held at or above
//! [`J_FLOOR`]. The CFL condition takes the sound speed `sqrt(K/ρ)`, or the
//! viscous limit as a speed if larger ([`WaterParams::viscous_speed`]).
//! Here its parameters ([`WaterParams`]) and their schema table too.

use super::Constitutive;
use super::batch::State;
use super::lanes::Real;
use super::schema::{DENSITY, MaterialSchema, Param, ParamValue, at_least_zero, gt};
use crate::particles::Material;

/// The least volume ratio a water particle keeps. The force a particle puts
/// on the grid is its current volume times its pressure, `V0·K·J·(1 − J)`:
/// it peaks at `J = ½` and falls to nothing as `J → 0`, so nothing stops a
/// particle that is squeezed past the peak. Water pressed between an
/// obstacle dragged at 50 m/s and a wall went on to `J → 0`, an underflow
/// that the frame then rolled back as a non-finite state, frame after
/// frame. Held at a quarter, the squeezed particle still pushes back. Water
/// at the Mach numbers the CFL bound allows stays far above it: a block
/// thrown at 4 m/s into a corner reaches 0.46 at its most compressed
/// particle (the golden `water2d` run, unchanged).
pub(crate) const J_FLOOR: f32 = 0.25;

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

impl MaterialSchema for WaterParams {
    const MATERIAL: Material = Material::Water;
    const PARAMS: &'static [Param] = &[
        DENSITY,
        Param {
            name: "bulk_modulus",
            alias: None,
            unit: "Pa",
            lower: gt(0.0),
            upper: None,
            choices: &[],
            description: "bulk modulus K: the sound speed is √(K/ρ)",
            source: "mpm88 (Hu et al. 2018): K/ρ = 400 m²/s², a 20 m/s sound speed",
        },
        at_least_zero(
            "viscosity",
            "Pa·s",
            "dynamic viscosity η (0: inviscid)",
            "Newtonian water: η ≥ 0",
        ),
    ];
    fn values(&self) -> Vec<ParamValue> {
        use ParamValue::Number as N;
        vec![N(self.density), N(self.bulk_modulus), N(self.viscosity)]
    }
}

/// A water set's parameters (its constants: `K`, `η`).
#[derive(Clone, Debug)]
pub(crate) struct Water {
    pub(crate) params: WaterParams,
}

impl Water {
    pub(crate) fn new<const D: usize>(params: &WaterParams) -> Self {
        Water {
            params: params.clone(),
        }
    }

    /// Kirchhoff stress `τ` [Pa] at volume ratio `j` with velocity gradient
    /// `c` (row-major) on lanes of `R`: entry by entry the operations of
    /// `K·J·(J − 1)·I`, then `+ (C + Cᵀ)·(η·J)` when `η > 0`.
    #[inline(always)]
    fn stress_lanes<R: Real, const D: usize>(&self, j: R, c: &[R; 9]) -> [R; 9] {
        let w = &self.params;
        let p = R::splat(w.bulk_modulus) * j * (j - R::splat(1.0));
        let mut tau = [R::splat(0.0); 9];
        for r in 0..D {
            for col in 0..D {
                let eye = if r == col { 1.0 } else { 0.0 };
                tau[r * D + col] = R::splat(eye) * p;
            }
        }
        if w.viscosity > 0.0 {
            let ej = R::splat(w.viscosity) * j;
            for r in 0..D {
                for col in 0..D {
                    tau[r * D + col] = tau[r * D + col] + (c[r * D + col] + c[col * D + r]) * ej;
                }
            }
        }
        tau
    }
}

impl Constitutive for Water {
    const HAS_F: bool = false;
    const SOLID: bool = false;

    /// The sound speed `sqrt(K/ρ)` or, if larger, the viscous limit as a speed.
    fn wave_speed<const D: usize>(&self, cfl: f32, dx: f32, _jp_min: f32) -> f32 {
        let w = &self.params;
        w.wave_speed().max(w.viscous_speed(D, cfl, dx))
    }

    /// `J ← max(J·(1 + Δt·tr C), J_FLOOR)` (`tr C` summed from 0, as
    /// nalgebra's `trace`; a NaN stays NaN for the health check), then the
    /// stress at the new `J`.
    #[inline(always)]
    fn update_lanes<R: Real, const D: usize>(&self, s: &mut State<R>, c: &[R; 9], dt: f32) {
        let mut tr = R::splat(0.0);
        for i in 0..D {
            tr = tr + c[i * D + i];
        }
        let j = s.j * (R::splat(1.0) + R::splat(dt) * tr);
        let floor = R::splat(J_FLOOR);
        s.j = R::select(j.lt(floor), floor, j);
        s.tau = self.stress_lanes::<R, D>(s.j, c);
    }

    /// The stress at `J` with the velocity gradient `C`.
    fn state_stress<const D: usize>(&self, _f: &[f32; 9], j: f32, c: &[f32; 9]) -> [f32; 9] {
        self.stress_lanes::<f32, D>(j, c)
    }
}
