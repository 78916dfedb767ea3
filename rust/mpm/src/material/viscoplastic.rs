//! The viscoplastic solid (mud, plasticine): von Mises plasticity on the
//! Hencky strain with viscous relaxation (a Bingham material; a
//! Perzyna-type overstress, [`ViscoplasticParams`]). The particle carries the
//! elastic F. Here its parameters and their schema table too.
//!
//! g2p, from the trial `F* = (I + Δt·C)·F`, without singular vectors (an
//! isotropic function of `B = F*·F*ᵀ`, `spectral.rs`): `ε0 = ½ ln λ` (the
//! principal log strains), `s = 2μ·dev ε`; where `‖s‖ > √2 τ_y`
//! (`√J₂ > τ_y`) the deviatoric strain is scaled so that
//! `‖s‖ = √2 τ_y + (‖s*‖ − √2 τ_y)·η/(η + μΔt)`; `F = G·F*` with
//! `g = e^{ε − ε0}`, and `τ` the Hencky stress with values `2μ ε + λ tr ε`
//! (as sand's). A step that would invert the solid is kept out
//! (`spectral::inverted`).

use super::Constitutive;
use super::batch::State;
use super::lanes::Real;
use super::schema::{DENSITY, MaterialSchema, POISSON, Param, ParamValue, YOUNGS, at_least_zero};
use super::spectral::{
    LnDiffs, Spectral3, eig_2d, inverted, iso_2d, k, keep_where, mul_2d, plastic_f, trial,
};
use super::vmath;
use crate::particles::Material;

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

super::isotropic_moduli!(ViscoplasticParams);

impl MaterialSchema for ViscoplasticParams {
    const MATERIAL: Material = Material::Viscoplastic;
    const PARAMS: &'static [Param] = &[
        DENSITY,
        YOUNGS,
        POISSON,
        at_least_zero(
            "yield_stress",
            "Pa",
            "Bingham yield stress τ_y in simple shear (flow when √J₂ > τ_y)",
            "mudflow rheology (Coussot 1997): 10-1000 Pa",
        ),
        at_least_zero(
            "viscosity",
            "Pa·s",
            "plastic (Bingham) viscosity η; 0: perfect plasticity",
            "mudflow rheology (Coussot 1997): 1-100 Pa·s",
        ),
    ];
    fn values(&self) -> Vec<ParamValue> {
        use ParamValue::Number as N;
        vec![
            N(self.density),
            N(self.youngs_modulus),
            N(self.poisson_ratio),
            N(self.yield_stress),
            N(self.viscosity),
        ]
    }
}

/// A viscoplastic set's parameters and constants.
#[derive(Clone, Debug)]
pub(crate) struct Viscoplastic {
    pub(crate) params: ViscoplasticParams,
    /// Lamé parameters μ, λ [Pa].
    pub(crate) mu: f32,
    pub(crate) la: f32,
    /// √2 τ_y: the yield radius of ‖s‖ [Pa].
    pub(crate) radius: f32,
    /// η / μ [s].
    pub(crate) relax: f32,
}

impl Viscoplastic {
    pub(crate) fn new<const D: usize>(params: &ViscoplasticParams) -> Self {
        let (mu, la) = params.lame();
        Viscoplastic {
            params: params.clone(),
            mu,
            la,
            radius: std::f32::consts::SQRT_2 * params.yield_stress,
            relax: params.viscosity / mu,
        }
    }

    /// The Kirchhoff stress [Pa] of the elastic `f` (row-major) on lanes of
    /// `R` (the update without the return).
    #[inline(always)]
    pub(crate) fn stress_lanes<R: Real, const D: usize>(&self, f: &[R; 9]) -> [R; 9] {
        if D == 2 {
            viscoplastic_2d(f, self.mu, self.la, f32::INFINITY, 1.0).1
        } else {
            viscoplastic_3d(f, self.mu, self.la, f32::INFINITY, 1.0).1
        }
    }
}

impl Constitutive for Viscoplastic {
    const HAS_F: bool = true;
    const SOLID: bool = true;

    /// The P-wave speed `sqrt((λ + 2μ)/ρ)`.
    fn wave_speed<const D: usize>(&self, _cfl: f32, _dx: f32, _jp_min: f32) -> f32 {
        self.params.wave_speed()
    }

    #[inline(always)]
    fn update_lanes<R: Real, const D: usize>(&self, s: &mut State<R>, c: &[R; 9], dt: f32) {
        let ft = trial::<R, D>(&s.f, c, dt);
        let (mu, la, radius) = (self.mu, self.la, self.radius);
        // η/(η + μΔt) = relax/(relax + Δt); 0 for η = 0
        let keep = self.relax / (self.relax + dt);
        let (f, tau) = if D == 2 {
            viscoplastic_2d(&ft, mu, la, radius, keep)
        } else {
            viscoplastic_3d(&ft, mu, la, radius, keep)
        };
        let new = (f, s.j, tau);
        (s.f, s.j, s.tau) = match inverted::<R, D>(&f) {
            None => new,
            Some(at) => keep_where(at, (&s.f, s.j, self.stress_lanes::<R, D>(&s.f)), new),
        };
    }

    /// The stress of the elastic F.
    fn state_stress<const D: usize>(&self, f: &[f32; 9], _j: f32, _c: &[f32; 9]) -> [f32; 9] {
        self.stress_lanes::<f32, D>(f)
    }
}

/// The return's factor on the deviatoric strain: `(radius + (‖s‖ −
/// radius)·keep)/‖s‖` where `‖s‖ = s_norm > radius`, else 1.
#[inline(always)]
fn return_scale<R: Real>(s_norm: R, radius: f32, keep: f32) -> R {
    R::select_div(
        s_norm.gt(k(radius)),
        k::<R>(radius) + (s_norm - k(radius)) * k(keep),
        s_norm,
        k(1.0),
        k(1.0),
    )
}

/// 2D viscoplastic update: `(F, τ)` from the trial `ft` (`keep` =
/// `η/(η + μΔt)`, `radius` = `√2 τ_y`). `ε0_i = ½ ln λ_i`; where
/// `‖s‖ = √2·μ·(ε0_1 − ε0_2) > radius` the deviator is scaled by `scale`;
/// `τ` with `g(λ_i) = 2μ ε_i + λ tr ε`, `F = G·F*` with `g = e^{ε_i − ε0_i}`;
/// divided differences become their limits when `λ1 − λ2 ≤ 1e-6·λ2`.
#[inline(always)]
pub(crate) fn viscoplastic_2d<R: Real>(
    ft: &[R; 9],
    mu: f32,
    la: f32,
    radius: f32,
    keep: f32,
) -> ([R; 9], [R; 9]) {
    let (b, l1, l2, _) = eig_2d(ft);
    let half = k::<R>(0.5);
    let (e1, e2) = (half * vmath::ln(l1), half * vmath::ln(l2));
    let mean = half * (e1 + e2);
    let diff = e1 - e2;
    // ‖s‖ = 2μ‖dev ε‖ = √2·μ·(ε1 − ε2)
    let s_norm = k::<R>(std::f32::consts::SQRT_2 * mu) * diff;
    let scale = return_scale(s_norm, radius, keep);
    let dl = l1 - l2;
    let near = dl.le(k::<R>(1e-6) * l2);
    let tau_slope = R::select_div(
        near,
        k::<R>(mu) * scale,
        l2,
        k::<R>(2.0 * mu) * scale * diff,
        dl,
    );
    let e2_new = mean - half * scale * diff;
    let t = iso_2d(
        &b,
        l2,
        k::<R>(2.0 * mu) * e2_new + k::<R>(2.0 * la) * mean,
        tau_slope,
    );
    let mut tau = [k::<R>(0.0); 9];
    tau[..4].copy_from_slice(&t);
    let plastic = scale.ne(k(1.0));
    let mut f = *ft;
    if R::any(plastic) {
        // g_i = e^{(scale − 1)(ε_i − mean)}: g2 = e^{−x}, g1 − g2 = g2·(e^{2x} − 1)
        let x = half * (scale - k(1.0)) * diff;
        let g2 = vmath::exp(-x);
        let g_slope = R::select_div(
            near,
            g2 * (scale - k(1.0)),
            k::<R>(2.0) * l2,
            g2 * vmath::exp_m1(k::<R>(2.0) * x),
            dl,
        );
        let fe = mul_2d(&iso_2d(&b, l2, g2, g_slope), ft);
        for i in 0..4 {
            f[i] = R::select(plastic, fe[i], ft[i]);
        }
    }
    (f, tau)
}

/// 3D viscoplastic update: `(F, τ)` from the trial `ft` (`keep`, `radius`
/// as in 2D). `ε0_i = ½ ln λ_i`, `ε_i = mean + scale·(ε0_i − mean)`; `τ` the
/// function `h(λ) = μ·scale·ln λ + const`, `F = G·F*` with
/// `g(λ) = e^{(1 − scale)·mean}·λ^{(scale − 1)/2}` (the Newton form and
/// divided differences of sand's `advance_3d_eigen`).
#[inline(always)]
pub(crate) fn viscoplastic_3d<R: Real>(
    ft: &[R; 9],
    mu: f32,
    la: f32,
    radius: f32,
    keep: f32,
) -> ([R; 9], [R; 9]) {
    let sp = Spectral3::of_f(ft);
    let [l1, l2, l3] = sp.l;
    let half = k::<R>(0.5);
    let e0 = [
        half * vmath::ln(l1),
        half * vmath::ln(l2),
        half * vmath::ln(l3),
    ];
    let mean = (e0[0] + e0[1] + e0[2]) * k(1.0 / 3.0);
    let dev = [e0[0] - mean, e0[1] - mean, e0[2] - mean];
    let s_norm = k::<R>(2.0 * mu) * (dev[0] * dev[0] + dev[1] * dev[1] + dev[2] * dev[2]).sqrt();
    let scale = return_scale(s_norm, radius, keep);
    // divided differences of ln at λ3, λ2, λ1
    let dl = LnDiffs::new(sp.l);
    let plastic = scale.ne(k(1.0));
    let mut f = *ft;
    if R::any(plastic) {
        let pw = half * (scale - k(1.0));
        // e^{ε_i − ε0_i} = e^{(scale − 1)·dev_i}
        let (g2, g3) = (
            vmath::exp(k::<R>(2.0) * pw * dev[1]),
            vmath::exp(k::<R>(2.0) * pw * dev[2]),
        );
        let (d32, d321) = dl.power(pw, g2, g3);
        f = plastic_f(&sp.newton(g3, d32, d321), ft, plastic);
    }
    let e3 = mean + scale * dev[2];
    let h3 = k::<R>(2.0 * mu) * e3 + k::<R>(3.0 * la) * mean;
    let ms = k::<R>(mu) * scale;
    (f, sp.newton(h3, ms * dl.ln32, ms * dl.ln321))
}
