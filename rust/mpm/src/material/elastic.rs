//! The elastic solid ("jelly"): fixed-corotated (Stomakhin et al. 2012) or
//! compressible neo-Hookean (e.g. Bonet & Wood 2008) hyperelasticity on the
//! whole deformation gradient F, which the particle carries.
//!
//! g2p takes the trial `F* = (I + Δt·C)·F` as the new F and its stress:
//!
//! - fixed-corotated: `τ = 2μ(F − R)Fᵀ + λJ(J − 1)I = 2μ(B − √B) + λJ(J − 1)I`
//!   (`R` the rotation of F's polar decomposition, `R·Fᵀ = √B`,
//!   `B = F·Fᵀ`): in 2D with `R` in closed form, in 3D as the function
//!   `λ − √λ` of `B` ([`Spectral3`]), without singular vectors;
//! - neo-Hookean: `τ = μ(F Fᵀ − I) + λ ln J · I`.
//!
//! Snow's stress is the fixed-corotated one with hardened Lamé parameters
//! (`snow.rs`). A step that would invert the solid is kept out
//! ([`inverted`]). Here its parameters ([`ElasticParams`], [`ElasticModel`])
//! and their schema table too.

use super::Constitutive;
use super::lanes::Real;
use super::schema::{DENSITY, MaterialSchema, POISSON, Param, ParamValue, YOUNGS};
use super::spectral::{Spectral3, det, inverted, k, keep_where};
use super::vmath;
use crate::particles::Material;

use super::batch::State;

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

super::isotropic_moduli!(ElasticParams);

impl MaterialSchema for ElasticParams {
    const MATERIAL: Material = Material::Elastic;
    const PARAMS: &'static [Param] = &[
        DENSITY,
        YOUNGS,
        POISSON,
        Param {
            name: "model",
            alias: None,
            unit: "-",
            lower: None,
            upper: None,
            choices: &["corotated", "neohookean"],
            description: "the energy: fixed-corotated or compressible neo-Hookean",
            source: "Stomakhin et al. 2012 (corotated); Bonet & Wood 2008 (neo-Hookean)",
        },
    ];
    fn values(&self) -> Vec<ParamValue> {
        use ParamValue::Number as N;
        vec![
            N(self.density),
            N(self.youngs_modulus),
            N(self.poisson_ratio),
            ParamValue::Name(self.model.name()),
        ]
    }
}

/// An elastic set's parameters and Lamé constants.
#[derive(Clone, Debug)]
pub(crate) struct Elastic {
    pub(crate) params: ElasticParams,
    /// Lamé parameters μ, λ [Pa].
    pub(crate) mu: f32,
    pub(crate) la: f32,
    /// Neo-Hookean (else fixed-corotated).
    pub(crate) neo: bool,
}

impl Elastic {
    pub(crate) fn new<const D: usize>(params: &ElasticParams) -> Self {
        let (mu, la) = params.lame();
        Elastic {
            params: params.clone(),
            mu,
            la,
            neo: params.model == ElasticModel::Neohookean,
        }
    }

    /// The Kirchhoff stress [Pa] of `f` (row-major) on lanes of `R`.
    #[inline(always)]
    pub(crate) fn stress_lanes<R: Real, const D: usize>(&self, f: &[R; 9]) -> [R; 9] {
        if self.neo {
            neo_hookean::<R, D>(f, self.mu, self.la)
        } else {
            corotated::<R, D>(f, R::splat(self.mu), R::splat(self.la))
        }
    }
}

impl Constitutive for Elastic {
    const HAS_F: bool = true;
    const SOLID: bool = true;

    /// The P-wave speed `sqrt((λ + 2μ)/ρ)`.
    fn wave_speed<const D: usize>(&self, _cfl: f32, _dx: f32, _jp_min: f32) -> f32 {
        self.params.wave_speed()
    }

    #[inline(always)]
    fn update_lanes<R: Real, const D: usize>(&self, s: &mut State<R>, c: &[R; 9], dt: f32) {
        let ft = super::spectral::trial::<R, D>(&s.f, c, dt);
        let new = (ft, s.j, self.stress_lanes::<R, D>(&ft));
        (s.f, s.j, s.tau) = match inverted::<R, D>(&ft) {
            None => new,
            Some(at) => keep_where(at, (&s.f, s.j, self.stress_lanes::<R, D>(&s.f)), new),
        };
    }

    /// The stress of F.
    fn state_stress<const D: usize>(&self, f: &[f32; 9], _j: f32, _c: &[f32; 9]) -> [f32; 9] {
        self.stress_lanes::<f32, D>(f)
    }
}

/// Fixed-corotated stress `2μ(F − R)Fᵀ + λJ(J − 1)I` of a row-major F
/// ([`corotated_2d`], [`corotated_3d`]).
#[inline(always)]
pub(crate) fn corotated<R: Real, const D: usize>(f: &[R; 9], mu: R, la: R) -> [R; 9] {
    if D == 2 {
        corotated_2d(f, mu, la)
    } else {
        corotated_3d(f, mu, la)
    }
}

/// Neo-Hookean stress `μ(F Fᵀ − I) + λ ln J · I` (`J` clamped to 1e-6).
#[inline(always)]
pub(crate) fn neo_hookean<R: Real, const D: usize>(f: &[R; 9], mu: f32, la: f32) -> [R; 9] {
    let jf = det::<R, D>(f);
    let iso = k::<R>(la) * vmath::ln(jf.max(k(1e-6))) - k(mu);
    let mut tau = [k::<R>(0.0); 9];
    for r in 0..D {
        for c in 0..D {
            let mut b = f[r * D] * f[c * D];
            for i in 1..D {
                b = b + f[r * D + i] * f[c * D + i];
            }
            tau[r * D + c] = if r == c {
                k::<R>(mu) * b + iso
            } else {
                k::<R>(mu) * b
            };
        }
    }
    tau
}

/// 2D fixed-corotated stress `2μ(F − R)Fᵀ + λJ(J − 1)I` with the polar
/// rotation in closed form, `R = [c −s; s c]`, `(c, s) ∝ (F00 + F11, F10 −
/// F01)` (`R = I` where that vector vanishes).
#[inline(always)]
pub(crate) fn corotated_2d<R: Real>(f: &[R; 9], mu: R, la: R) -> [R; 9] {
    let (a, b, c, d) = (f[0], f[1], f[2], f[3]);
    let (x, y) = (a + d, c - b);
    let r2 = x * x + y * y;
    let ok = r2.gt(k(1e-30));
    let inv = k::<R>(1.0) / R::select(ok, r2, k(1.0)).sqrt();
    let (co, si) = (
        R::select(ok, x * inv, k(1.0)),
        R::select(ok, y * inv, k(0.0)),
    );
    let (p, q, r, s) = (a - co, b + si, c - si, d - co);
    let jf = a * d - b * c;
    let vol = la * jf * (jf - k(1.0));
    let two_mu = k::<R>(2.0) * mu;
    let mut tau = [k::<R>(0.0); 9];
    tau[0] = two_mu * (p * a + q * b) + vol;
    tau[1] = two_mu * (p * c + q * d);
    tau[2] = two_mu * (r * a + s * b);
    tau[3] = two_mu * (r * c + s * d) + vol;
    tau
}

/// 3D fixed-corotated stress `2μ(B − √B) + λJ(J − 1)I`: the function
/// `λ − √λ` of `B` (`σ(σ − 1)` at λ3; divided differences `1 − 1/(σa + σb)`
/// and `1/((σ1+σ2)(σ2+σ3)(σ1+σ3))`, without cancellation), `J = det F`.
#[inline(always)]
pub(crate) fn corotated_3d<R: Real>(f: &[R; 9], mu: R, la: R) -> [R; 9] {
    let sp = Spectral3::of_f(f);
    let [s1, s2, s3] = sp.l.map(|l| l.sqrt());
    let one = k::<R>(1.0);
    let jf = det::<R, 3>(f);
    let two_mu = k::<R>(2.0) * mu;
    let h3 = two_mu * (s3 * (s3 - one)) + la * jf * (jf - one);
    let h32 = two_mu * (one - one / (s2 + s3));
    let h321 = two_mu / ((s1 + s2) * (s2 + s3) * (s1 + s3));
    sp.newton(h3, h32, h321)
}
