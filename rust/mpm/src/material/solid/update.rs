//! The solids' g2p update without singular vectors, on lanes of `R` (one
//! particle or sixteen, [`Real`]): every quantity an update needs is an
//! isotropic function of `B = F*·F*ᵀ` (eigenvalues `λ1 ≥ λ2 (≥ λ3)`,
//! singular values `σ_i = √λ_i`), written as its interpolation at the
//! eigenvalues, as sand's update does (`sand/update_2d.rs`,
//! `sand/update_3d.rs`, whose closed-form eigenvalues and Newton form this
//! uses):
//!
//! - 2D: `g(B) = g(λ2)·I + g[λ2,λ1]·(B − λ2·I)`;
//! - 3D: `g(B) = g(λ3)·I + g[λ3,λ2]·M3 + g[λ3,λ2,λ1]·M3·M2`,
//!   `M_i = B − λ_i·I`, with divided differences `g[·]`.
//!
//! The divided differences are formed without cancellation where one exists
//! in closed form (`√·`: `1/(σa + σb)` and `−1/((σ1+σ2)(σ2+σ3)(σ1+σ3))`), or
//! as quotients that fall back to 0 when the gap is below `1e-6·λ` (where
//! the term they multiply is of the order of that gap: the error stays of
//! the order of the function's derivative times the gap). An error in a
//! node moves the result by about the error times the gaps to the other
//! nodes, so the closed-form eigenvalues' error near a double root does not
//! show (tests against nalgebra's SVD in f64).
//!
//! - fixed-corotated: `τ = 2μ(F − R)Fᵀ + λJ(J − 1)I = 2μ(B − √B) + λJ(J − 1)I`
//!   (`R·Fᵀ = √B`); in 2D with `R` in closed form;
//! - snow: `σ` clamped to `[lo, hi]`, `F_E = G·F*` with `g(λ) = ĉ/σ`,
//!   `J_P ← J_P·|det F*|/Πĉ`, `τ` the hardened fixed-corotated stress of
//!   `F_E`, a function of `B` with the values `2μh(ĉ² − ĉ) + λh J_E(J_E − 1)`;
//! - viscoplastic: `ε0 = ½ ln λ`, the deviator scaled by `scale` (the return),
//!   `τ` with values `2μ ε + λ tr ε`, `F = G·F*` with `g = e^{ε − ε0}`;
//! - neo-Hookean: `τ = μ(F Fᵀ − I) + λ ln J · I`.
//!
//! Matrices are row-major `[R; 9]` (the first `D²` entries used).

use crate::material::lanes::Real;
use crate::material::sand::update_3d::{newton_3, plastic_f, sym3_eigenvalues};
use crate::material::vmath;

#[inline(always)]
fn k<R: Real>(x: f32) -> R {
    R::splat(x)
}

/// `max(x, −x)`.
#[inline(always)]
fn abs<R: Real>(x: R) -> R {
    x.max(-x)
}

/// `a` or `b` (masks).
#[inline(always)]
fn or<R: Real>(a: R::Mask, b: R::Mask) -> R::Mask {
    R::not(R::and(R::not(a), R::not(b)))
}

/// `(a − b)/(la − lb)`, or 0 where `la − lb ≤ 1e-6·lb`.
#[inline(always)]
fn quotient<R: Real>(a: R, b: R, la: R, lb: R) -> R {
    let gap = la - lb;
    R::select_div(gap.gt(k::<R>(1e-6) * lb), a - b, gap, k(0.0), k(1.0))
}

/// Snow's hardening `e^{ξ(1 − J_P)}`, `J_P` clamped to `[jp_lo, jp_hi]`.
#[inline(always)]
pub(crate) fn hardening<R: Real>(jp: R, xi: f32, jp_lo: f32, jp_hi: f32) -> R {
    vmath::exp(k::<R>(xi) * (k::<R>(1.0) - jp.max(k(jp_lo)).min(k(jp_hi))))
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

/// `det F` of a row-major `D × D` F.
#[inline(always)]
pub(crate) fn det<R: Real, const D: usize>(f: &[R; 9]) -> R {
    if D == 2 {
        f[0] * f[3] - f[1] * f[2]
    } else {
        f[0] * (f[4] * f[8] - f[5] * f[7]) - f[1] * (f[3] * f[8] - f[5] * f[6])
            + f[2] * (f[3] * f[7] - f[4] * f[6])
    }
}

// ---------------------------------------------------------------- 2D

/// `B = F·Fᵀ` of a 2×2 F: `(b11, b12, b22)`, its eigenvalues `λ1 ≥ λ2` (each
/// at least 1e-12; `λ2 = det(F)²/λ1`, no cancellation when F is nearly
/// singular) and `det F`.
#[inline(always)]
fn eig_2d<R: Real>(f: &[R; 9]) -> ([R; 3], R, R, R) {
    let (a, b, c, d) = (f[0], f[1], f[2], f[3]);
    let (b11, b12, b22) = (a * a + b * b, a * c + b * d, c * c + d * d);
    let half = k::<R>(0.5) * (b11 - b22);
    let l1 = (k::<R>(0.5) * (b11 + b22) + (half * half + b12 * b12).sqrt()).max(k(1e-12));
    let jf = a * d - b * c;
    let l2 = (jf * jf / l1).max(k(1e-12));
    ([b11, b12, b22], l1, l2, jf)
}

/// `g2·I + slope·(B − λ2·I)` (2D, row-major).
#[inline(always)]
fn iso_2d<R: Real>(b: &[R; 3], l2: R, g2: R, slope: R) -> [R; 4] {
    let off = slope * b[1];
    [g2 + slope * (b[0] - l2), off, off, g2 + slope * (b[2] - l2)]
}

/// `G·F` for a 2×2 `G` and F.
#[inline(always)]
fn mul_2d<R: Real>(g: &[R; 4], f: &[R; 9]) -> [R; 9] {
    let mut out = *f;
    out[0] = g[0] * f[0] + g[1] * f[2];
    out[1] = g[0] * f[1] + g[1] * f[3];
    out[2] = g[2] * f[0] + g[3] * f[2];
    out[3] = g[2] * f[1] + g[3] * f[3];
    out
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

/// 2D snow update: `(F_E, J_P, τ)` from the trial `ft` and `J_P` (see the
/// module's doc). Lanes with every σ in `[lo, hi]` keep `F_E = F*`, `J_P`.
#[inline(always)]
#[allow(clippy::too_many_arguments)]
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
    let yields = s_norm.gt(k(radius));
    let scale = R::select_div(
        yields,
        k::<R>(radius) + (s_norm - k(radius)) * k(keep),
        s_norm,
        k(1.0),
        k(1.0),
    );
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

// ---------------------------------------------------------------- 3D

/// The spectral data of a 3×3 F: `B = F·Fᵀ`'s eigenvalues `λ1 ≥ λ2 ≥ λ3`
/// (each at least 1e-12), `M3 = B − λ3·I`, `P = M3·M2`.
pub(crate) struct Spectral3<R> {
    pub(crate) l: [R; 3],
    pub(crate) m3: [[R; 3]; 3],
    pub(crate) pr: [[R; 3]; 3],
}

#[inline(always)]
fn spectral_3<R: Real>(f: &[R; 9]) -> Spectral3<R> {
    let row = |i: usize| [f[3 * i], f[3 * i + 1], f[3 * i + 2]];
    let (r0, r1, r2) = (row(0), row(1), row(2));
    let dot = |a: [R; 3], b: [R; 3]| a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
    let (b00, b01, b02) = (dot(r0, r0), dot(r0, r1), dot(r0, r2));
    let (b11, b12, b22) = (dot(r1, r1), dot(r1, r2), dot(r2, r2));
    let (l1, l2, l3) = sym3_eigenvalues(b00, b01, b02, b11, b12, b22);
    let m3 = [
        [b00 - l3, b01, b02],
        [b01, b11 - l3, b12],
        [b02, b12, b22 - l3],
    ];
    let m2 = [
        [b00 - l2, b01, b02],
        [b01, b11 - l2, b12],
        [b02, b12, b22 - l2],
    ];
    let pm = |i: usize, j: usize| m3[i][0] * m2[0][j] + m3[i][1] * m2[1][j] + m3[i][2] * m2[2][j];
    let pr = [
        [pm(0, 0), pm(0, 1), pm(0, 2)],
        [pm(0, 1), pm(1, 1), pm(1, 2)],
        [pm(0, 2), pm(1, 2), pm(2, 2)],
    ];
    Spectral3 {
        l: [l1, l2, l3],
        m3,
        pr,
    }
}

/// 3D fixed-corotated stress `2μ(B − √B) + λJ(J − 1)I`: the function
/// `λ − √λ` of `B` (`σ(σ − 1)` at λ3; divided differences `1 − 1/(σa + σb)`
/// and `1/((σ1+σ2)(σ2+σ3)(σ1+σ3))`), `J = det F`.
#[inline(always)]
pub(crate) fn corotated_3d<R: Real>(f: &[R; 9], mu: R, la: R) -> [R; 9] {
    let sp = spectral_3(f);
    let [s1, s2, s3] = sp.l.map(|l| l.sqrt());
    let one = k::<R>(1.0);
    let jf = det::<R, 3>(f);
    let two_mu = k::<R>(2.0) * mu;
    let h3 = two_mu * (s3 * (s3 - one)) + la * jf * (jf - one);
    let h32 = two_mu * (one - one / (s2 + s3));
    let h321 = two_mu / ((s1 + s2) * (s2 + s3) * (s1 + s3));
    newton_3(&sp.m3, &sp.pr, h3, h32, h321)
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
    let sp = spectral_3(ft);
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
        let g = newton_3(&sp.m3, &sp.pr, one + d3, g32, g321);
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
    let tau = newton_3(&sp.m3, &sp.pr, h3, two_mu * k32, two_mu * k321);
    (f, jp, tau)
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
    let sp = spectral_3(ft);
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
    let yields = s_norm.gt(k(radius));
    let scale = R::select_div(
        yields,
        k::<R>(radius) + (s_norm - k(radius)) * k(keep),
        s_norm,
        k(1.0),
        k(1.0),
    );
    // divided differences of ln at λ3, λ2, λ1
    let zero = k::<R>(0.0);
    let (g32, g21) = (l2 - l3, l1 - l2);
    let (lp32, lp21) = (vmath::ln_1p(g32 / l3), vmath::ln_1p(g21 / l2));
    let (gap32, gap21) = (g32.gt(zero), g21.gt(zero));
    let ln32 = R::select_div(gap32, lp32, g32, k(1.0), l3);
    let ln21 = R::select_div(gap21, lp21, g21, k(1.0), l2);
    let near = (l1 - l3).le(k::<R>(1e-4) * l3);
    let ln321 = R::select_div(near, k(-0.5), l2 * l2, ln21 - ln32, l1 - l3);
    let plastic = scale.ne(k(1.0));
    let mut f = *ft;
    if R::any(plastic) {
        let pw = half * (scale - k(1.0));
        // e^{ε_i − ε0_i} = e^{(scale − 1)·dev_i}
        let (g2, g3) = (
            vmath::exp(k::<R>(2.0) * pw * dev[1]),
            vmath::exp(k::<R>(2.0) * pw * dev[2]),
        );
        let d32 = R::select_div(gap32, g3 * vmath::exp_m1(pw * lp32), g32, pw * g3, l3);
        let d21 = R::select_div(gap21, g2 * vmath::exp_m1(pw * lp21), g21, pw * g2, l2);
        let d321 = R::select_div(
            near,
            half * pw * (pw - k(1.0)) * g2,
            l2 * l2,
            d21 - d32,
            l1 - l3,
        );
        f = plastic_f(&newton_3(&sp.m3, &sp.pr, g3, d32, d321), ft, plastic);
    }
    let e3 = mean + scale * dev[2];
    let h3 = k::<R>(2.0 * mu) * e3 + k::<R>(3.0 * la) * mean;
    let ms = k::<R>(mu) * scale;
    (f, newton_3(&sp.m3, &sp.pr, h3, ms * ln32, ms * ln321))
}
