//! Branch-free f32 elementary functions for the material updates across a
//! batch of particles ([`super::batch::Batch`]).
//!
//! libm's `lnf`, `expf`, `acosf`, … are calls the compiler cannot vectorise;
//! they were about a fifth of a sand3d frame, one particle at a time. These
//! use only `+ − × ÷ √`, comparisons (which become selects) and integer
//! operations on the bits, so a loop over a batch's lanes compiles to SIMD
//! instructions in either compiled copy of the frame loop (`crate::isa`).
//! They never fuse a multiply and an add, so both copies give the same bits.
//!
//! Accuracy (the tests measure it against f64 `std`): within a few units in
//! the last place over the domains the sand update uses. NaN in gives NaN
//! out (the frame's blow-up check relies on it); the domain of each function
//! is stated on it.
//!
//! Methods (textbook range reduction; Muller, "Elementary Functions", 2016):
//! `ln` by `x = m·2^e`, `m ∈ [√½, √2)`, and the series of `2·atanh(s)`,
//! `s = (m − 1)/(m + 1)`; `exp` and `exp_m1` by Cody–Waite reduction
//! `x = k·ln 2 + r`, `|r| ≤ ln 2 / 2`, and Taylor series of `e^r` and
//! `e^r − 1`; [`cos_two_thirds_acos`] (the trigonometric solution of the
//! eigenvalue cubic) by a least-squares fit at Chebyshev nodes. Polynomials
//! are evaluated by Estrin's scheme ([`poly`]).

use super::lanes::{ROUND_MAGIC, Real};

/// ln 2 split so that `k·LN2_HI` is exact for `|k| < 2^12`.
const LN2_HI: f32 = 1420.0 / 2048.0;
const LN2_LO: f32 = -2.121_944_4e-4;
const LOG2_E: f32 = std::f32::consts::LOG2_E;

#[inline(always)]
fn c<R: Real>(x: f32) -> R {
    R::splat(x)
}

/// `Σ a_i·x^i` by Estrin's scheme: the pairs `a_2i + a_2i+1·x` combined with
/// `x²`, `x⁴`, … as a tree, so its chain of dependent operations is about
/// log₂ N multiply-adds long instead of Horner's N (the sand update's time is
/// bound by such chains, not by its count of operations).
#[inline(always)]
fn poly<R: Real, const N: usize>(x: R, a: [f32; N]) -> R {
    let mut t = [c::<R>(0.0); N];
    let mut n = 0;
    let mut i = 0;
    while i < N {
        t[n] = if i + 1 < N {
            c::<R>(a[i]) + c::<R>(a[i + 1]) * x
        } else {
            c(a[i])
        };
        n += 1;
        i += 2;
    }
    let mut xp = x * x;
    while n > 1 {
        let mut m = 0;
        let mut i = 0;
        while i < n {
            t[m] = if i + 1 < n {
                t[i] + t[i + 1] * xp
            } else {
                t[i]
            };
            m += 1;
            i += 2;
        }
        n = m;
        if n > 1 {
            xp = xp * xp;
        }
    }
    t[0]
}

/// Natural logarithm of a positive normal `x` (NaN for `x ≤ 0`, NaN and +∞).
#[inline(always)]
pub(crate) fn ln<R: Real>(x: R) -> R {
    let (e, m) = x.split_exponent();
    let s = (m - c(1.0)) / (m + c(1.0));
    let z = s * s;
    // 2·atanh(s) = 2s·(1 + z/3 + z²/5 + …); |s| ≤ 0.172, so z⁵/11 < 1e-9
    let series = poly(z, [2.0, 2.0 / 3.0, 2.0 / 5.0, 2.0 / 7.0, 2.0 / 9.0]);
    let r = e * c(LN2_HI) + (s * series + e * c(LN2_LO));
    // NaN and +∞ give NaN (adding 0 changes no bit)
    R::select(x.gt(c(0.0)), r + x.zero_if_finite(), c(f32::NAN))
}

/// `ln(1 + t)` for `t > −1`, accurate for small `t` (Goldberg's correction
/// of the rounding of `1 + t`).
#[inline(always)]
pub(crate) fn ln_1p<R: Real>(t: R) -> R {
    let u = c::<R>(1.0) + t;
    ln(u) - ((u - c(1.0)) - t) / u
}

/// `(r, 2^k)` with `x = k·ln 2 + r`, `|r| ≤ ln 2 / 2`, for `x` clamped to
/// [−87, 88] (NaN stays NaN, in `r`).
#[inline(always)]
fn reduce<R: Real>(x: R) -> (R, R) {
    let x = R::select(
        x.lt(c(-87.0)),
        c(-87.0),
        R::select(x.gt(c(88.0)), c(88.0), x),
    );
    // adding and subtracting 1.5·2^23 rounds to the nearest integer k, whose
    // value is then in the low bits of the sum
    let t = x * c(LOG2_E) + c(ROUND_MAGIC);
    let k = t - c(ROUND_MAGIC);
    let r = (x - k * c(LN2_HI)) - k * c(LN2_LO);
    (r, t.pow2_from_magic())
}

/// `e^r − 1 − r` for `|r| ≤ ln 2 / 2` (Taylor to r⁷: error below 6e-9·|r|).
#[inline(always)]
fn exp_m1_tail<R: Real>(r: R) -> R {
    let p = poly(
        r,
        [
            1.0 / 2.0,
            1.0 / 6.0,
            1.0 / 24.0,
            1.0 / 120.0,
            1.0 / 720.0,
            1.0 / 5040.0,
        ],
    );
    r * r * p
}

/// `e^x`; saturates at `e^−87` and `e^88`.
#[inline(always)]
pub(crate) fn exp<R: Real>(x: R) -> R {
    let (r, two_k) = reduce(x);
    (c::<R>(1.0) + (r + exp_m1_tail(r))) * two_k
}

/// `e^x − 1`, accurate for small `x`; saturates as [`exp`] does.
#[inline(always)]
pub(crate) fn exp_m1<R: Real>(x: R) -> R {
    let (r, two_k) = reduce(x);
    two_k * (r + exp_m1_tail(r)) + (two_k - c(1.0))
}

/// `cos(⅔·acos u)` for `u ∈ [0, 1]`: a polynomial of degree 8 (least
/// squares at Chebyshev nodes, error 3.3e-9). It gives the trigonometric
/// solution of a cubic without `acos` and `cos`:
/// `cos(acos(r)/3) = cos(⅔·acos √((1 + r)/2))`. The function is analytic on
/// [0, 1] (near `u = 1`, `acos u ∝ √(1 − u)` and cosine is even), so a low
/// degree suffices.
#[inline(always)]
pub(crate) fn cos_two_thirds_acos<R: Real>(u: R) -> R {
    poly(
        u,
        [
            0.5,
            0.577_349_7,
            -0.111_095_68,
            0.053_288_657,
            -0.031_961_296,
            0.019_675_719,
            -0.010_325_493,
            0.003_707_686_4,
            -0.000_639_314_36,
        ],
    )
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::material::lanes::{FL, LANES};

    /// The largest error of `f` against `reference` over `xs`, in units of
    /// f32's epsilon times `max(|reference|, floor)`.
    fn worst(
        xs: impl Iterator<Item = f32>,
        f: impl Fn(f32) -> f32,
        reference: impl Fn(f64) -> f64,
        floor: f64,
    ) -> f64 {
        xs.map(|x| {
            let r = reference(x as f64);
            let e = (f(x) as f64 - r).abs()
                / (r.abs().max(floor).max(f64::MIN_POSITIVE) * f32::EPSILON as f64);
            assert!(e.is_finite(), "x {x}: {} vs {r}", f(x));
            e
        })
        .fold(0.0, f64::max)
    }

    /// `n` points spread logarithmically over [lo, hi] (both > 0).
    fn log_grid(lo: f32, hi: f32, n: usize) -> impl Iterator<Item = f32> {
        let (a, b) = ((lo as f64).ln(), (hi as f64).ln());
        (0..=n).map(move |i| (a + (b - a) * i as f64 / n as f64).exp() as f32)
    }

    fn lin_grid(lo: f32, hi: f32, n: usize) -> impl Iterator<Item = f32> {
        (0..=n).map(move |i| lo + (hi - lo) * i as f32 / n as f32)
    }

    /// Every function within a few ulps of f64 `std` over the domain the
    /// sand update uses (eigenvalues of `F·Fᵀ` from 1e-12 up, strains and
    /// their scaled differences, `acos` on all of [−1, 1]).
    #[test]
    fn close_to_f64_std() {
        let n = 200_000;
        let e_ln = worst(log_grid(1e-12, 1e12, n), ln::<f32>, f64::ln, 1.0);
        let near_one = lin_grid(0.9, 1.1, n).chain(log_grid(0.999_999, 1.000_001, 1000));
        let e_ln1 = worst(near_one, ln::<f32>, f64::ln, 0.0);
        let e_ln1p = worst(log_grid(1e-10, 1e6, n), ln_1p::<f32>, f64::ln_1p, 0.0);
        let e_exp = worst(lin_grid(-80.0, 80.0, n), exp::<f32>, f64::exp, 0.0);
        let e_expm1 = worst(lin_grid(-20.0, 20.0, n), exp_m1::<f32>, f64::exp_m1, 0.0);
        let e_expm1_small = worst(
            log_grid(1e-10, 0.5, n).flat_map(|x| [x, -x]),
            exp_m1,
            f64::exp_m1,
            0.0,
        );
        let cos_2_3_acos = |u: f64| (2.0 / 3.0 * u.acos()).cos();
        let e_c23 = worst(
            lin_grid(0.0, 1.0, n).chain(log_grid(1e-7, 0.1, n).map(|d| 1.0 - d)),
            cos_two_thirds_acos::<f32>,
            cos_2_3_acos,
            0.0,
        );
        eprintln!(
            "ulps: ln {e_ln:.2} (near 1: {e_ln1:.2}), ln_1p {e_ln1p:.2}, exp {e_exp:.2}, \
             exp_m1 {e_expm1:.2} (small: {e_expm1_small:.2}), cos(2/3 acos) {e_c23:.2}"
        );
        for (name, e, bound) in [
            ("ln", e_ln, 2.0),
            ("ln near 1", e_ln1, 3.0),
            ("ln_1p", e_ln1p, 3.0),
            ("exp", e_exp, 2.0),
            ("exp_m1", e_expm1, 3.0),
            ("exp_m1 small", e_expm1_small, 3.0),
            ("cos(2/3 acos)", e_c23, 3.0),
        ] {
            assert!(e <= bound, "{name}: {e} ulps > {bound}");
        }
    }

    /// Each lane of the many-lane functions gives the bits of the one-lane
    /// ones (what makes a batched sand update equal to one particle's).
    #[test]
    fn all_lanes_give_the_bits_of_one() {
        let xs: Vec<f32> = lin_grid(-3.0, 3.0, 8 * 1000)
            .chain(log_grid(1e-12, 1e6, 8 * 1000))
            .collect();
        for chunk in xs.chunks_exact(LANES) {
            let v = FL(chunk.try_into().unwrap());
            type Pair = (fn(FL) -> FL, fn(f32) -> f32);
            let fs: [Pair; 5] = [
                (ln, ln),
                (ln_1p, ln_1p),
                (exp, exp),
                (exp_m1, exp_m1),
                (cos_two_thirds_acos, cos_two_thirds_acos),
            ];
            for (f8, f1) in fs {
                let out = f8(v);
                for l in 0..LANES {
                    let want = f1(chunk[l]);
                    assert!(
                        out.0[l].to_bits() == want.to_bits()
                            || (want.is_nan() && out.0[l].is_nan())
                    );
                }
            }
        }
    }

    /// NaN in gives NaN out; out-of-domain arguments give NaN; saturation.
    #[test]
    fn nan_and_domain() {
        for f in [ln::<f32>, ln_1p, exp, exp_m1, cos_two_thirds_acos] {
            assert!(f(f32::NAN).is_nan());
        }
        assert!(ln(0.0).is_nan() && ln(-1.0).is_nan() && ln(f32::INFINITY).is_nan());
        assert_eq!(ln(1.0), 0.0);
        assert_eq!(exp(0.0), 1.0);
        assert_eq!(exp_m1(0.0), 0.0);
        assert_eq!(cos_two_thirds_acos(0.0f32), 0.5);
        assert!(exp(1000.0).is_finite() && exp(-1000.0) > 0.0);
        assert_eq!(exp_m1(-1000.0), -1.0);
    }
}
