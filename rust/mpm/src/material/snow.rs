//! Snow (Stomakhin et al. 2013, "A material point method for snow
//! simulation"): fixed-corotated elasticity on the elastic part `F_E` of
//! `F = F_E F_P`, which the particle carries (in `f`), with the plastic
//! volume ratio `J_P = det F_P` (in `j`).
//!
//! g2p, from the trial `F* = (I + Δt·C)·F_E`, without singular vectors (an
//! isotropic function of `B = F*·F*ᵀ`, `spectral.rs`): the singular values
//! σ are clamped to `[1 − θc, 1 + θs]`, `F_E = G·F*` with `g(λ) = ĉ/σ`,
//! `J_P ← J_P·|det F*|/Πĉ` (the rest of the deformation goes to `F_P`), and
//! `τ` is the fixed-corotated stress of `F_E` with μ, λ hardened by
//! `e^{ξ(1 − J_P)}`: a function of `B` with the values
//! `2μh(ĉ² − ĉ) + λh J_E(J_E − 1)`. A step that would invert the solid is
//! kept out (`spectral::inverted`). Here its parameters ([`SnowParams`])
//! and their schema table too.

use super::batch::State;
use super::elastic::{corotated, corotated_2d};
use super::lanes::Real;
use super::schema::{DENSITY, MaterialSchema, POISSON, Param, ParamValue, YOUNGS, ge, gt, le, lt};
use super::spectral::{
    Spectral3, abs, det, eig_2d, inverted, iso_2d, k, keep_where, mul_2d, or, plastic_f, quotient,
    trial,
};
use super::vmath;
use super::{Constitutive, lame, p_wave};
use crate::particles::Material;

const JP_LO: f32 = SnowParams::JP_RANGE.0;
const JP_HI: f32 = SnowParams::JP_RANGE.1;

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

const fn theta(name: &'static str, description: &'static str) -> Param {
    Param {
        name,
        alias: None,
        unit: "-",
        lower: gt(0.0),
        upper: lt(1.0),
        choices: &[],
        description,
        source: "Stomakhin et al. 2013, Table 2 (θc = 2.5e-2, θs = 7.5e-3)",
    }
}

impl MaterialSchema for SnowParams {
    const MATERIAL: Material = Material::Snow;
    const PARAMS: &'static [Param] = &[
        DENSITY,
        Param {
            description: "initial Young's modulus E₀",
            ..YOUNGS
        },
        POISSON,
        theta(
            "theta_c",
            "critical compression θc: singular values of F_E ≥ 1 − θc",
        ),
        theta(
            "theta_s",
            "critical stretch θs: singular values of F_E ≤ 1 + θs",
        ),
        Param {
            name: "hardening",
            alias: None,
            unit: "-",
            lower: ge(0.0),
            upper: le(50.0),
            choices: &[],
            description: "hardening coefficient ξ: the Lamé parameters scale by e^{ξ(1 − J_P)}",
            source: "Stomakhin et al. 2013 (ξ = 10); 50 caps the factor e^{0.4ξ} at J_P = 0.6 near 5e8",
        },
    ];
    fn values(&self) -> Vec<ParamValue> {
        use ParamValue::Number as N;
        vec![
            N(self.density),
            N(self.youngs_modulus),
            N(self.poisson_ratio),
            N(self.theta_c),
            N(self.theta_s),
            N(self.hardening),
        ]
    }
}

/// A snow set's parameters and constants.
#[derive(Clone, Debug)]
pub(crate) struct Snow {
    pub(crate) params: SnowParams,
    /// Lamé parameters μ₀, λ₀ [Pa] before hardening.
    pub(crate) mu: f32,
    pub(crate) la: f32,
    /// The clamp of the singular values, `[1 − θc, 1 + θs]`.
    pub(crate) lo: f32,
    pub(crate) hi: f32,
    /// Hardening coefficient ξ.
    pub(crate) xi: f32,
}

impl Snow {
    pub(crate) fn new<const D: usize>(params: &SnowParams) -> Self {
        let (mu, la) = params.lame();
        Snow {
            params: params.clone(),
            mu,
            la,
            lo: 1.0 - params.theta_c,
            hi: 1.0 + params.theta_s,
            xi: params.hardening,
        }
    }

    /// The Kirchhoff stress [Pa] of `F_E` (`f`, row-major) at `J_P` = `jp`
    /// on lanes of `R`.
    #[inline(always)]
    pub(crate) fn stress_lanes<R: Real, const D: usize>(&self, f: &[R; 9], jp: R) -> [R; 9] {
        let h = hardening(jp, self.xi, JP_LO, JP_HI);
        corotated::<R, D>(f, R::splat(self.mu) * h, R::splat(self.la) * h)
    }
}

impl Constitutive for Snow {
    const HAS_F: bool = true;
    const SOLID: bool = true;

    /// The P-wave speed hardened at the set's smallest `J_P` present.
    fn wave_speed<const D: usize>(&self, _cfl: f32, _dx: f32, jp_min: f32) -> f32 {
        self.params.wave_speed(jp_min)
    }

    const WAVE_READS_J: bool = true;

    #[inline(always)]
    fn update_lanes<R: Real, const D: usize>(&self, s: &mut State<R>, c: &[R; 9], dt: f32) {
        let ft = trial::<R, D>(&s.f, c, dt);
        let consts = (self.mu, self.la, self.lo, self.hi, self.xi);
        let new = if D == 2 {
            snow_2d(&ft, s.j, consts, (JP_LO, JP_HI))
        } else {
            snow_3d(&ft, s.j, consts, (JP_LO, JP_HI))
        };
        (s.f, s.j, s.tau) = match inverted::<R, D>(&new.0) {
            None => new,
            Some(at) => keep_where(at, (&s.f, s.j, self.stress_lanes::<R, D>(&s.f, s.j)), new),
        };
    }

    /// The stress of `F_E` at `J_P`.
    fn state_stress<const D: usize>(&self, f: &[f32; 9], j: f32, _c: &[f32; 9]) -> [f32; 9] {
        self.stress_lanes::<f32, D>(f, j)
    }
}

/// Snow's hardening `e^{ξ(1 − J_P)}`, `J_P` clamped to `[jp_lo, jp_hi]`.
#[inline(always)]
pub(crate) fn hardening<R: Real>(jp: R, xi: f32, jp_lo: f32, jp_hi: f32) -> R {
    vmath::exp(k::<R>(xi) * (k::<R>(1.0) - jp.max(k(jp_lo)).min(k(jp_hi))))
}

/// 2D snow update: `(F_E, J_P, τ)` from the trial `ft` and `J_P` (see the
/// module's doc). Lanes with every σ in `[lo, hi]` keep `F_E = F*`, `J_P`.
#[inline(always)]
pub(crate) fn snow_2d<R: Real>(
    ft: &[R; 9],
    jp: R,
    (mu, la, lo, hi, xi): (f32, f32, f32, f32, f32),
    (jp_lo, jp_hi): (f32, f32),
) -> ([R; 9], R, [R; 9]) {
    let (b, l1, l2, jf) = eig_2d(ft);
    let inside = R::and(
        jf.gt(k(0.0)),
        R::and(l1.le(k(hi * hi)), (jf * jf).ge(k::<R>(lo * lo) * l1)),
    );
    let (mut f, mut jp) = (*ft, jp);
    if !R::all(inside) {
        let (s1, s2) = (l1.sqrt(), l2.sqrt());
        let (c1, c2) = (s1.max(k(lo)).min(k(hi)), s2.max(k(lo)).min(k(hi)));
        let (d1, d2) = ((c1 - s1) / s1, (c2 - s2) / s2);
        // g = ĉ/σ; both clamped to one bound: bound·(1/σ1 − 1/σ2)/(λ1 − λ2)
        let (both_hi, both_lo) = (s2.gt(k(hi)), s1.lt(k(lo)));
        let bound = R::select(both_hi, k(hi), k(lo));
        let exact = -bound / (s1 * s2 * (s1 + s2));
        let g21 = R::select(or::<R>(both_hi, both_lo), exact, quotient(d1, d2, l1, l2));
        let g = iso_2d(&b, l2, k::<R>(1.0) + d2, g21);
        let fe = mul_2d(&g, ft);
        for i in 0..4 {
            f[i] = R::select(inside, ft[i], fe[i]);
        }
        jp = R::select(inside, jp, jp * abs(jf) / (c1 * c2));
    }
    let h = hardening(jp, xi, jp_lo, jp_hi);
    let tau = corotated_2d(&f, k::<R>(mu) * h, k::<R>(la) * h);
    (f, jp, tau)
}

/// 3D snow update: `(F_E, J_P, τ)` from the trial `ft` and `J_P` (see the
/// module's doc). Lanes with every σ in `[lo, hi]` keep `F_E = F*`, `J_P`.
#[inline(always)]
pub(crate) fn snow_3d<R: Real>(
    ft: &[R; 9],
    jp: R,
    (mu, la, lo, hi, xi): (f32, f32, f32, f32, f32),
    (jp_lo, jp_hi): (f32, f32),
) -> ([R; 9], R, [R; 9]) {
    let sp = Spectral3::of_f(ft);
    let [l1, l2, l3] = sp.l;
    let [s1, s2, s3] = sp.l.map(|l| l.sqrt());
    let one = k::<R>(1.0);
    let jf = det::<R, 3>(ft);
    let inside = R::and(jf.gt(k(0.0)), R::and(l1.le(k(hi * hi)), l3.ge(k(lo * lo))));
    let (mut f, mut jp) = (*ft, jp);
    // the values ĉ and the divided differences of ĉ(ĉ − 1) (unclamped: σ)
    let mut c3 = s3;
    let mut k32 = one - one / (s2 + s3);
    let mut k321 = one / ((s1 + s2) * (s2 + s3) * (s1 + s3));
    if !R::all(inside) {
        let clamp = |s: R| s.max(k(lo)).min(k(hi));
        let (c1, c2) = (clamp(s1), clamp(s2));
        c3 = clamp(s3);
        let (d1, d2, d3) = ((c1 - s1) / s1, (c2 - s2) / s2, (c3 - s3) / s3);
        // g = ĉ/σ: for two σ clamped to one bound, bound·(1/σa − 1/σb)/(λa − λb)
        let g_pair = |sa: R, sb: R, la_: R, lb: R, da: R, db: R| {
            let (both_hi, both_lo) = (sb.gt(k(hi)), sa.lt(k(lo)));
            let bound = R::select(both_hi, k(hi), k(lo));
            let exact = -bound / (sa * sb * (sa + sb));
            R::select(or::<R>(both_hi, both_lo), exact, quotient(da, db, la_, lb))
        };
        let g32 = g_pair(s2, s3, l2, l3, d2, d3);
        let g21 = g_pair(s1, s2, l1, l2, d1, d2);
        let g321 = quotient(g21, g32, l1, l3);
        let g = sp.newton(one + d3, g32, g321);
        f = plastic_f(&g, ft, R::not(inside));
        jp = R::select(inside, jp, jp * abs(jf) / (c1 * c2 * c3));
        // ĉ(ĉ − 1): σ(σ − 1)'s differences where both are unclamped
        let kv = |c: R| c * (c - one);
        let (kv1, kv2, kv3) = (kv(c1), kv(c2), kv(c3));
        let k_pair = |sa: R, sb: R, la_: R, lb: R, ka: R, kb: R| {
            let both_in = R::and(sa.le(k(hi)), sb.ge(k(lo)));
            R::select(both_in, one - one / (sa + sb), quotient(ka, kb, la_, lb))
        };
        let k21 = k_pair(s1, s2, l1, l2, kv1, kv2);
        let k32m = k_pair(s2, s3, l2, l3, kv2, kv3);
        let all_in = R::and(s1.le(k(hi)), s3.ge(k(lo)));
        k321 = R::select(all_in, k321, quotient(k21, k32m, l1, l3));
        k32 = k32m;
    }
    let h = hardening(jp, xi, jp_lo, jp_hi);
    let two_mu = k::<R>(2.0 * mu) * h;
    let je = det::<R, 3>(&f);
    let h3 = two_mu * (c3 * (c3 - one)) + k::<R>(la) * h * je * (je - one);
    let tau = sp.newton(h3, two_mu * k32, two_mu * k321);
    (f, jp, tau)
}
