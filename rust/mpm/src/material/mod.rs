//! Constitutive models: what each material contributes to a substep.
//!
//! A particle carries its Kirchhoff stress `τ` (derived from its state); p2g
//! turns it into grid forces, and g2p updates the material state from the new
//! velocity gradient `C` and recomputes `τ`. A model is one file behind one
//! trait, [`Constitutive`]:
//!
//! - [`water`]: weakly compressible water, state `J` (Hu et al. 2018, mpm88).
//! - [`sand`]: Drucker–Prager elastoplasticity in Hencky strain, state `F`
//!   and the volume correction (Klár et al. 2016; Tampubolon et al. 2017).
//! - [`elastic`]: the elastic solid, fixed-corotated (Stomakhin et al. 2012)
//!   or neo-Hookean, state `F`.
//! - [`snow`]: Stomakhin et al. 2013, state `F_E` and `J_P`.
//! - [`viscoplastic`]: von Mises on the Hencky strain with viscous
//!   relaxation, state the elastic `F`.
//!
//! Each model's file declares its parameters too: the params struct (serde,
//! `Default`), the constants derived from it and its table of the schema
//! (`impl MaterialSchema`, which gives it `validate()`; the row type and
//! the shared rows in `schema.rs`). Here the registration, one list
//! (`materials!`, a line per model), from which `registry.rs` makes
//! [`Material`] (the codes), [`MaterialParams`] (one parameter set of any
//! model), [`Model`] and [`material_schema`] (every model's table), and
//! `params` the default sets of `SolverParams`.
//!
//! Beside them: [`Models`], each parameter set's [`Model`] (the table
//! particles index by `Particle::set`), which g2p, the stress refresh and
//! the CFL condition go through; `batch.rs`, the update of sixteen
//! particles of one set at once in SIMD lanes; `spectral.rs`, the matrix
//! tools on lanes several models share; `lanes.rs` and `vmath.rs`, the
//! arithmetic they are written in.

mod batch;
pub(crate) mod codes;
mod elastic;
mod lanes;
mod registry;
pub mod sand;
pub mod schema;
#[cfg(all(test, feature = "serde"))]
mod schema_tests;
mod snow;
mod spectral;
mod viscoplastic;
mod vmath;
mod water;

#[cfg(test)]
mod registry_tests;
#[cfg(test)]
mod solid_lane_tests;
#[cfg(test)]
mod solid_tests;

pub(crate) use batch::{Batch, LaneHealth, ParticleSink, State};
pub use elastic::ElasticModel;
pub(crate) use lanes::LANES;

use nalgebra::SMatrix;

use crate::dim::{Dim, DimOps};
use crate::error::Result;
use crate::isa::Isa;
use crate::particles::Particle;
use lanes::Real;
use registry::register;
use schema::{MaterialSchema, Param, ParamValue};
use spectral::{from_lanes, to_lanes};

pub use codes::Material;
pub(crate) use codes::materials;

materials!(register);

impl MaterialParams {
    /// The material code this set belongs to.
    pub fn material(&self) -> Material {
        each_set!(self, type M => <M as MaterialSchema>::MATERIAL)
    }

    /// Density ρ [kg/m³].
    pub fn density(&self) -> f32 {
        each_set!(self, p => p.density)
    }

    /// Validates the set at `field` (`sets[2]`), naming a bad key under it
    /// and its material (`sets[2].elastic.youngs_modulus`).
    pub fn validate(&self, field: &str) -> Result<()> {
        let prefix = format!("{field}.{}", self.material().name());
        each_set!(self, p => p.validate_at(&prefix))
    }
}

/// Lamé parameters (μ, λ) [Pa] of Young's modulus `e` and Poisson's ratio `nu`:
/// `μ = E / (2(1 + ν))`, `λ = E ν / ((1 + ν)(1 − 2ν))`.
pub fn lame(e: f32, nu: f32) -> (f32, f32) {
    (
        e / (2.0 * (1.0 + nu)),
        e * nu / ((1.0 + nu) * (1.0 - 2.0 * nu)),
    )
}

/// P-wave speed `sqrt((λ + 2μ)·stiffen/ρ)` [m/s] of Young's modulus `e`
/// [Pa], Poisson's ratio `nu` and density `density` [kg/m³], the moduli
/// scaled by `stiffen` (snow's hardening; 1 for the others, which leaves
/// the bits of `sqrt((λ + 2μ)/ρ)`).
fn p_wave(e: f32, nu: f32, density: f32, stiffen: f32) -> f32 {
    let (mu, la) = lame(e, nu);
    ((la + 2.0 * mu) * stiffen / density).sqrt()
}

/// `lame()` and `wave_speed()` (the P-wave speed) of a params struct with
/// the fields `density`, `youngs_modulus` and `poisson_ratio`: the
/// inherent methods sand, the elastic solid and the viscoplastic solid
/// share.
macro_rules! isotropic_moduli {
    ($params:ty) => {
        impl $params {
            /// Lamé parameters (μ, λ) [Pa].
            pub fn lame(&self) -> (f32, f32) {
                $crate::material::lame(self.youngs_modulus, self.poisson_ratio)
            }

            /// P-wave speed `sqrt((λ + 2μ)/ρ)` [m/s].
            pub fn wave_speed(&self) -> f32 {
                let (e, nu, rho) = (self.youngs_modulus, self.poisson_ratio, self.density);
                $crate::material::p_wave(e, nu, rho, 1.0)
            }
        }
    };
}
use isotropic_moduli;

/// One constitutive model: a parameter set's constants (derived once per
/// solver, by the model's `new::<D>(&params)`, which `Model::new` calls;
/// `D` for sand's cone) and what the solver asks of them. Static dispatch:
/// [`Model`] forwards to the implementations, and g2p runs one [`Batch`]
/// per set.
pub(crate) trait Constitutive {
    /// Whether the particle carries a deformation gradient F, which g2p
    /// updates and whose `det F > 0` it checks (every model but water).
    const HAS_F: bool;

    /// Whether it is a solid: a body whose `F` keeps its shape
    /// ([`Material::is_solid`]; sand's `F` is only the elastic part of a
    /// granular flow).
    const SOLID: bool;

    /// Whether [`wave_speed`](Self::wave_speed) reads `jp_min`, the
    /// smallest `J` of the set's particles (snow's `J_P`).
    const WAVE_READS_J: bool = false;

    /// Whether in `D` dimensions a lane's result depends on its batch mates
    /// ([`update_lanes`](Self::update_lanes) takes one route for the whole
    /// batch: sand's in 3D, `sand/update_3d.rs`); g2p then ends such a
    /// batch at every window of its block (`solver/grid.rs`, `G2P_WINDOW`),
    /// so that its batches are the same for any thread count.
    fn shares_route<const D: usize>() -> bool {
        false
    }

    /// The fastest wave speed [m/s] of the set, for the CFL condition
    /// `Δt ≤ cfl·Δx / (c + |v|max)` (`cfl`, `dx` [m]: water's viscous limit
    /// as a speed; `jp_min`: see [`WAVE_READS_J`](Self::WAVE_READS_J),
    /// `+∞` where it is not).
    fn wave_speed<const D: usize>(&self, cfl: f32, dx: f32, jp_min: f32) -> f32;

    /// g2p's update on lanes of `R` (one particle or sixteen): from the
    /// state `s` at the start of the substep and the new velocity gradient
    /// `c` [1/s] (row-major) over `dt` [s], the new state and its Kirchhoff
    /// stress in `s`.
    fn update_lanes<R: Real, const D: usize>(&self, s: &mut State<R>, c: &[R; 9], dt: f32);

    /// The Kirchhoff stress [Pa] of one particle's state, row-major: of its
    /// F (`f`), `J` (`j`: water's volume ratio, snow's `J_P`) and velocity
    /// gradient `c` (water's viscous stress reads it), each model reading
    /// what its stress depends on.
    fn state_stress<const D: usize>(&self, f: &[f32; 9], j: f32, c: &[f32; 9]) -> [f32; 9]
    where
        Dim<D>: DimOps<D>;

    /// The Kirchhoff stress [Pa] of a particle's state, as set, restored or
    /// changed between frames: [`state_stress`](Self::state_stress) of its
    /// `F`, `J` and `C`.
    fn stress<const D: usize>(&self, p: &Particle<D>) -> SMatrix<f32, D, D>
    where
        Dim<D>: DimOps<D>,
    {
        from_lanes(&self.state_stress::<D>(&to_lanes(&p.f), p.j, &to_lanes(&p.c)))
    }
}

impl Model {
    /// [`Constitutive::HAS_F`].
    pub(crate) fn has_f(&self) -> bool {
        each_model!(self, type M => M::HAS_F)
    }

    /// [`Constitutive::shares_route`].
    #[inline(always)]
    pub(crate) fn shares_route<const D: usize>(&self) -> bool {
        each_model!(self, type M => M::shares_route::<D>())
    }

    /// [`Constitutive::WAVE_READS_J`].
    pub(crate) fn wave_reads_j(&self) -> bool {
        each_model!(self, type M => M::WAVE_READS_J)
    }

    /// [`Constitutive::wave_speed`].
    pub(crate) fn wave_speed<const D: usize>(&self, cfl: f32, dx: f32, jp_min: f32) -> f32 {
        each_model!(self, m => m.wave_speed::<D>(cfl, dx, jp_min))
    }

    /// [`Constitutive::stress`].
    pub(crate) fn stress<const D: usize>(&self, p: &Particle<D>) -> SMatrix<f32, D, D>
    where
        Dim<D>: DimOps<D>,
    {
        each_model!(self, m => m.stress(p))
    }

    /// [`Batch::run`] under this model, in the copy compiled for `isa`.
    pub(crate) fn run<const D: usize>(&self, batch: &mut Batch, isa: Isa, dt: f32) -> LaneHealth {
        each_model!(self, m => batch.run::<D, _>(m, isa, dt))
    }

    /// [`Constitutive::update_lanes`] (the tests' one particle at a time).
    #[cfg(test)]
    pub(crate) fn update_lanes<R: Real, const D: usize>(
        &self,
        s: &mut State<R>,
        c: &[R; 9],
        dt: f32,
    ) {
        each_model!(self, m => m.update_lanes::<R, D>(s, c, dt))
    }
}

/// The table of parameter sets (`SolverParams::table`, `crate::params`) and each set's
/// [`Model`], indexed by `Particle::set`.
#[derive(Clone, Debug)]
pub(crate) struct Models {
    pub(crate) params: Vec<MaterialParams>,
    pub(crate) models: Vec<Model>,
    /// The compiled copy of the lanes' updates to run (`crate::isa`).
    pub(crate) isa: Isa,
}

impl Models {
    /// The models of `table` (validated) in `D` dimensions; `isa` must be
    /// [`available`](Isa::available).
    pub(crate) fn new<const D: usize>(table: Vec<MaterialParams>, isa: Isa) -> Self
    where
        Dim<D>: DimOps<D>,
    {
        let models = table.iter().map(Model::new::<D>).collect();
        Models {
            params: table,
            models,
            isa,
        }
    }

    /// Runs the lanes' updates in the copy for `isa` from now on.
    pub(crate) fn set_isa(&mut self, isa: Isa) {
        self.isa = isa;
    }
}
