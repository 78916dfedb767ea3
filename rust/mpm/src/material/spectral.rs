//! The matrix tools on lanes (one particle or sixteen, [`Real`]) that several
//! models share: the trial `F* = (I + Δt·C)·F` and `det F`, the solids'
//! guard against inversion, and isotropic functions of `B = F·Fᵀ` without
//! singular vectors, as their interpolation at B's eigenvalues:
//!
//! - 2D ([`eig_2d`]): `g(B) = g(λ2)·I + g[λ2,λ1]·(B − λ2·I)`;
//! - 3D ([`sym3_eigenvalues`], [`Spectral3`], [`newton_3`]):
//!   `g(B) = g(λ3)·I + g[λ3,λ2]·M3 + g[λ3,λ2,λ1]·M3·M2`, `M_i = B − λ_i·I`,
//!   with divided differences `g[·]`.
//!
//! An error in a node moves the result by about the error times the gaps to
//! the other nodes, so the closed-form eigenvalues' error near a double root
//! does not show (the models' tests compare against an f64 SVD). Sand
//! (`sand/update_2d.rs`, `sand/update_3d.rs`), the elastic solid, snow and
//! the viscoplastic solid use them. Matrices are row-major `[R; 9]` (the
//! first `D²` entries used).

use nalgebra::SMatrix;

use super::lanes::Real;
use super::vmath;

#[inline(always)]
pub(crate) fn k<R: Real>(x: f32) -> R {
    R::splat(x)
}

/// `max(x, −x)`.
#[inline(always)]
pub(crate) fn abs<R: Real>(x: R) -> R {
    x.max(-x)
}

/// `a` or `b` (masks).
#[inline(always)]
pub(crate) fn or<R: Real>(a: R::Mask, b: R::Mask) -> R::Mask {
    R::not(R::and(R::not(a), R::not(b)))
}

/// `(a − b)/(la − lb)`, or 0 where `la − lb ≤ 1e-6·lb`.
#[inline(always)]
pub(crate) fn quotient<R: Real>(a: R, b: R, la: R, lb: R) -> R {
    let gap = la - lb;
    R::select_div(gap.gt(k::<R>(1e-6) * lb), a - b, gap, k(0.0), k(1.0))
}

// ---------------------------------------------------------------- F

/// Row-major `[f32; 9]` of a `D × D` matrix (the first `D²` entries).
#[inline(always)]
pub(crate) fn to_lanes<const D: usize>(m: &SMatrix<f32, D, D>) -> [f32; 9] {
    let mut a = [0.0; 9];
    for r in 0..D {
        for c in 0..D {
            a[r * D + c] = m[(r, c)];
        }
    }
    a
}

/// The `D × D` matrix of a row-major `[f32; 9]`.
#[inline(always)]
pub(crate) fn from_lanes<const D: usize>(a: &[f32; 9]) -> SMatrix<f32, D, D> {
    SMatrix::<f32, D, D>::from_fn(|r, c| a[r * D + c])
}

/// The trial `F* = (I + Δt·C)·F` (row-major), each entry summed over `j`
/// in order.
#[inline(always)]
pub(crate) fn trial<R: Real, const D: usize>(f: &[R; 9], c: &[R; 9], dt: f32) -> [R; 9] {
    let dtv = R::splat(dt);
    let mut ft = [R::splat(0.0); 9];
    for r in 0..D {
        for kk in 0..D {
            let mut acc = R::splat(0.0);
            for j in 0..D {
                let a = c[r * D + j] * dtv;
                let a = if r == j { R::splat(1.0) + a } else { a };
                acc = if j == 0 {
                    a * f[j * D + kk]
                } else {
                    acc + a * f[j * D + kk]
                };
            }
            ft[r * D + kk] = acc;
        }
    }
    ft
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

/// The lanes of an updated solid whose `det F ≤ 0` (or NaN), if there are
/// any: the solids' guard against inversion. A step that would invert a
/// solid particle (compression past zero volume in one substep, as when a
/// soft solid is driven into a wall at speed) keeps its `F` and `J_P` of the
/// start of the substep and their stress ([`keep_where`]): the compression
/// beyond inversion is taken as plastic, so `det F > 0` always holds and the
/// particle's stress pushes it back out. Lanes with `det F > 0` (and NaN,
/// which the health check reports) are unchanged: the same bits as without
/// it.
#[inline(always)]
pub(crate) fn inverted<R: Real, const D: usize>(f: &[R; 9]) -> Option<R::Mask> {
    let at = det::<R, D>(f).le(R::splat(0.0));
    if R::any(at) { Some(at) } else { None }
}

/// `old` (F, J, τ) in the lanes of `at`, `new` elsewhere ([`inverted`]).
#[inline(always)]
pub(crate) fn keep_where<R: Real>(
    at: R::Mask,
    (f0, j0, tau0): (&[R; 9], R, [R; 9]),
    (f, j, tau): ([R; 9], R, [R; 9]),
) -> ([R; 9], R, [R; 9]) {
    (
        std::array::from_fn(|i| R::select(at, f0[i], f[i])),
        R::select(at, j0, j),
        std::array::from_fn(|i| R::select(at, tau0[i], tau[i])),
    )
}

// ---------------------------------------------------------------- 2D

/// `B = F·Fᵀ` of a 2×2 F: `(b11, b12, b22)`, its eigenvalues `λ1 ≥ λ2` (each
/// at least 1e-12, as the SVD route clamps σ to 1e-6; `λ2 = det(F)²/λ1`, no
/// cancellation when F is nearly singular) and `det F`.
#[inline(always)]
pub(crate) fn eig_2d<R: Real>(f: &[R; 9]) -> ([R; 3], R, R, R) {
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
pub(crate) fn iso_2d<R: Real>(b: &[R; 3], l2: R, g2: R, slope: R) -> [R; 4] {
    let off = slope * b[1];
    [g2 + slope * (b[0] - l2), off, off, g2 + slope * (b[2] - l2)]
}

/// `G·F` for a 2×2 `G` and F.
#[inline(always)]
pub(crate) fn mul_2d<R: Real>(g: &[R; 4], f: &[R; 9]) -> [R; 9] {
    let mut out = *f;
    out[0] = g[0] * f[0] + g[1] * f[2];
    out[1] = g[0] * f[1] + g[1] * f[3];
    out[2] = g[2] * f[0] + g[3] * f[2];
    out[3] = g[2] * f[1] + g[3] * f[3];
    out
}

// ---------------------------------------------------------------- 3D

/// Eigenvalues `λ1 ≥ λ2 ≥ λ3` (each at least `1e-12`) of the symmetric 3×3
/// matrix `[[b00, b01, b02], [b01, b11, b12], [b02, b12, b22]]` in closed form
/// (the trigonometric solution of the characteristic cubic, Smith 1961):
/// `q = tr B / 3`, `p² = ‖B − qI‖²_F / 6`, `r = det(B − qI) / (2p³)`,
/// `φ = acos(r) / 3`, `λ1 = q + 2p cos φ`, `λ3 = q + 2p cos(φ + 2π/3)`
/// (both cosines through [`vmath::cos_two_thirds_acos`]),
/// `λ2 = 3q − λ1 − λ3`. Near a double eigenvalue (`r → ±1`) the pair comes out
/// with an error of about `p·√ε`; the updates only interpolate at these
/// nodes, which makes that error second order (see the module's doc).
#[inline(always)]
pub(crate) fn sym3_eigenvalues<R: Real>(
    b00: R,
    b01: R,
    b02: R,
    b11: R,
    b12: R,
    b22: R,
) -> (R, R, R) {
    let q = (b00 + b11 + b22) / k(3.0);
    let (d0, d1, d2) = (b00 - q, b11 - q, b22 - q);
    let p2 =
        (d0 * d0 + d1 * d1 + d2 * d2 + k::<R>(2.0) * (b01 * b01 + b02 * b02 + b12 * b12)) / k(6.0);
    // isotropic to f32 rounding (and p³ below would underflow): λ1 = λ2 = λ3 = q
    let iso = p2.le(k::<R>(1e-14) * q * q);
    let p = p2.sqrt();
    let det =
        d0 * (d1 * d2 - b12 * b12) - b01 * (b01 * d2 - b12 * b02) + b02 * (b01 * b12 - d1 * b02);
    let r = det / (k::<R>(2.0) * p2 * p);
    // clamp to [−1, 1]; NaN stays NaN (a blow-up the frame reports)
    let r = R::select(r.lt(k(-1.0)), k(-1.0), R::select(r.gt(k(1.0)), k(1.0), r));
    // cos(acos(r)/3) = C(√((1 + r)/2)) and cos(acos(r)/3 + 2π/3) =
    // −cos(acos(−r)/3) = −C(√((1 − r)/2)), C = `vmath::cos_two_thirds_acos`
    let half = k::<R>(0.5);
    let c1 = vmath::cos_two_thirds_acos(((k::<R>(1.0) + r) * half).sqrt());
    let c3 = vmath::cos_two_thirds_acos(((k::<R>(1.0) - r) * half).sqrt());
    let two_p = k::<R>(2.0) * p;
    let l1 = q + two_p * c1;
    let l3 = q - two_p * c3;
    let l2 = (k::<R>(3.0) * q - l1 - l3).min(l1).max(l3);
    let (qc, tiny) = (q.max(k(1e-12)), k::<R>(1e-12));
    (
        R::select(iso, qc, l1.max(tiny)),
        R::select(iso, qc, l2.max(tiny)),
        R::select(iso, qc, l3.max(tiny)),
    )
}

/// The spectral data of a symmetric 3×3 `B` (`F·Fᵀ`): its eigenvalues
/// `λ1 ≥ λ2 ≥ λ3` (each at least 1e-12, [`sym3_eigenvalues`]),
/// `M3 = B − λ3·I` and `P = M3·M2`, the Newton basis of [`newton_3`].
pub(crate) struct Spectral3<R> {
    pub(crate) l: [R; 3],
    pub(crate) m3: [[R; 3]; 3],
    pub(crate) pr: [[R; 3]; 3],
}

impl<R: Real> Spectral3<R> {
    /// Of `B` given by its upper triangle `[00, 01, 02, 11, 12, 22]`.
    #[inline(always)]
    pub(crate) fn of_b(b: &[R; 6]) -> Self {
        let [b00, b01, b02, b11, b12, b22] = *b;
        let (l1, l2, l3) = sym3_eigenvalues(b00, b01, b02, b11, b12, b22);
        // M3 and P = M3·M2 (symmetric: both are polynomials in B)
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
        let pm =
            |i: usize, j: usize| m3[i][0] * m2[0][j] + m3[i][1] * m2[1][j] + m3[i][2] * m2[2][j];
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

    /// Of `B = F·Fᵀ` for a row-major 3×3 F.
    #[inline(always)]
    pub(crate) fn of_f(f: &[R; 9]) -> Self {
        Self::of_b(&gram_3(f))
    }

    /// The isotropic function of `B` with value `g0` at λ3 and divided
    /// differences `g1 = g[λ3,λ2]`, `g2 = g[λ3,λ2,λ1]` ([`newton_3`]).
    #[inline(always)]
    pub(crate) fn newton(&self, g0: R, g1: R, g2: R) -> [R; 9] {
        newton_3(&self.m3, &self.pr, g0, g1, g2)
    }
}

/// `B = F·Fᵀ` of a row-major 3×3 F: its upper triangle
/// `[00, 01, 02, 11, 12, 22]`.
#[inline(always)]
pub(crate) fn gram_3<R: Real>(f: &[R; 9]) -> [R; 6] {
    let row = |i: usize| [f[3 * i], f[3 * i + 1], f[3 * i + 2]];
    let (r0, r1, r2) = (row(0), row(1), row(2));
    let dot = |a: [R; 3], b: [R; 3]| a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
    [
        dot(r0, r0),
        dot(r0, r1),
        dot(r0, r2),
        dot(r1, r1),
        dot(r1, r2),
        dot(r2, r2),
    ]
}

/// `g0·I + g1·M3 + g2·P` (row-major) for symmetric `M3`, `P`: the Newton
/// form of an isotropic function of `B` ([`Spectral3`]). (A function, not
/// a closure: a closure may be left out of line, outside the compiled copy
/// of the frame loop it runs in.)
#[inline(always)]
pub(crate) fn newton_3<R: Real>(m3: &[[R; 3]; 3], pr: &[[R; 3]; 3], g0: R, g1: R, g2: R) -> [R; 9] {
    let mut out = [g0; 9];
    for i in 0..3 {
        for j in 0..3 {
            let x = g1 * m3[i][j] + g2 * pr[i][j];
            out[3 * i + j] = if i == j { g0 + x } else { x };
        }
    }
    out
}

/// The new elastic F of a 3D return mapping: `G·F_trial` (row-major) in the
/// lanes where `plastic` holds, `F_trial` elsewhere.
#[inline(always)]
pub(crate) fn plastic_f<R: Real>(g: &[R; 9], ft: &[R; 9], plastic: R::Mask) -> [R; 9] {
    let mut f = *ft;
    for i in 0..3 {
        for j in 0..3 {
            let gf = g[3 * i] * ft[j] + g[3 * i + 1] * ft[3 + j] + g[3 * i + 2] * ft[6 + j];
            f[3 * i + j] = R::select(plastic, gf, ft[3 * i + j]);
        }
    }
    f
}

/// The divided differences of `ln` and of a power map at the eigenvalues
/// `λ1 ≥ λ2 ≥ λ3 > 0` of `B = F·Fᵀ`, what a 3D return mapping in Hencky
/// strain needs for `sp.newton` (sand and viscoplastic): `ln[λ3, λ2]`,
/// `ln[λ2, λ1]`, `ln[λ3, λ2, λ1]`, with the derivative where eigenvalues
/// meet (`near`: `λ1 − λ3 ≤ 1e-4·λ3`).
#[derive(Clone, Copy)]
pub(crate) struct LnDiffs<R: Real> {
    l: [R; 3],
    g32: R,
    g21: R,
    lp32: R,
    lp21: R,
    gap32: R::Mask,
    gap21: R::Mask,
    near: R::Mask,
    /// `ln[λ3, λ2]`.
    pub(crate) ln32: R,
    /// `ln[λ3, λ2, λ1]`.
    pub(crate) ln321: R,
}

impl<R: Real> LnDiffs<R> {
    /// The differences at `l = [λ1, λ2, λ3]`.
    #[inline(always)]
    pub(crate) fn new(l: [R; 3]) -> Self {
        let [l1, l2, l3] = l;
        let zero = k::<R>(0.0);
        let (g32, g21) = (l2 - l3, l1 - l2);
        let (lp32, lp21) = (vmath::ln_1p(g32 / l3), vmath::ln_1p(g21 / l2));
        let (gap32, gap21) = (g32.gt(zero), g21.gt(zero));
        let ln32 = R::select_div(gap32, lp32, g32, k(1.0), l3);
        let ln21 = R::select_div(gap21, lp21, g21, k(1.0), l2);
        let near = (l1 - l3).le(k::<R>(1e-4) * l3);
        let ln321 = R::select_div(near, k(-0.5), l2 * l2, ln21 - ln32, l1 - l3);
        LnDiffs {
            l,
            g32,
            g21,
            lp32,
            lp21,
            gap32,
            gap21,
            near,
            ln32,
            ln321,
        }
    }

    /// `(g[λ3, λ2], g[λ3, λ2, λ1])` of the plastic map `g(λ) = e^c·λ^pw`,
    /// given its values `g2 = g(λ2)`, `g3 = g(λ3)`.
    #[inline(always)]
    pub(crate) fn power(&self, pw: R, g2: R, g3: R) -> (R, R) {
        let ([l1, l2, l3], half) = (self.l, k::<R>(0.5));
        let d32 = R::select_div(
            self.gap32,
            g3 * vmath::exp_m1(pw * self.lp32),
            self.g32,
            pw * g3,
            l3,
        );
        let d21 = R::select_div(
            self.gap21,
            g2 * vmath::exp_m1(pw * self.lp21),
            self.g21,
            pw * g2,
            l2,
        );
        let d321 = R::select_div(
            self.near,
            half * pw * (pw - k(1.0)) * g2,
            l2 * l2,
            d21 - d32,
            l1 - l3,
        );
        (d32, d321)
    }
}
