//! One number or sixteen at once: the arithmetic the material updates are
//! written in ([`Real`]), so that the same source runs on one particle
//! (`f32`, the tests) and on sixteen particles in SIMD registers ([`FL`],
//! g2p's [`super::batch::Batch`]).
//!
//! [`FL`]'s operations are loops over its sixteen lanes that the compiler
//! turns into SIMD instructions (two AVX2 ones in the x86-64-v3 copy of the
//! frame loop, four SSE2 ones in the portable copy, see `crate::isa`).
//! Sixteen lanes rather than eight (one AVX2 register): two independent
//! chains of dependent operations to interleave, which made sand2d's frame
//! 6% faster and sand3d's 2% (docs/engine.md). Every lane
//! does exactly what the `f32` operation does, so a lane of [`FL`] gives the
//! bits of the `f32` computation.

use std::ops::{Add, Div, Mul, Neg, Sub};

/// Lanes of an [`FL`].
pub(crate) const LANES: usize = 16;

/// Floating-point arithmetic with comparisons as masks and `select` instead
/// of branches, implemented by `f32` and by [`FL`] lane by lane.
pub(crate) trait Real:
    Copy
    + Add<Output = Self>
    + Sub<Output = Self>
    + Mul<Output = Self>
    + Div<Output = Self>
    + Neg<Output = Self>
{
    /// Result of a comparison: one truth value per lane.
    type Mask: Copy;
    fn splat(x: f32) -> Self;
    fn sqrt(self) -> Self;
    /// As `f32::min`/`max`: a NaN operand yields the other one.
    fn min(self, o: Self) -> Self;
    fn max(self, o: Self) -> Self;
    fn lt(self, o: Self) -> Self::Mask;
    fn le(self, o: Self) -> Self::Mask;
    fn gt(self, o: Self) -> Self::Mask;
    fn ge(self, o: Self) -> Self::Mask;
    fn ne(self, o: Self) -> Self::Mask;
    fn and(a: Self::Mask, b: Self::Mask) -> Self::Mask;
    fn not(a: Self::Mask) -> Self::Mask;
    /// `a` where `m` holds, else `b`.
    fn select(m: Self::Mask, a: Self, b: Self) -> Self;
    /// `self − self`: 0 where `self` is finite, NaN where it is NaN or ±∞.
    #[inline(always)]
    #[allow(clippy::eq_op)]
    fn zero_if_finite(self) -> Self {
        self - self
    }
    /// Whether `m` holds in some lane.
    fn any(m: Self::Mask) -> bool;
    /// Whether `m` holds in every lane.
    #[inline(always)]
    fn all(m: Self::Mask) -> bool {
        !Self::any(Self::not(m))
    }
    /// `a_num/a_den` where `m` holds, else `b_num/b_den`, with one division.
    #[inline(always)]
    fn select_div(m: Self::Mask, a_num: Self, a_den: Self, b_num: Self, b_den: Self) -> Self {
        Self::select(m, a_num, b_num) / Self::select(m, a_den, b_den)
    }
    /// `(e, m)` with `x = m·2^e`, `m ∈ [√½, √2)`, `e` integral, for positive
    /// normal `x` (from the bits; see `vmath::ln`).
    fn split_exponent(self) -> (Self, Self);
    /// `2^k` for the integer `k` whose value is in the low bits of
    /// `self = k + 1.5·2^23` (see `vmath::exp`), `k ∈ [−126, 127]`.
    fn pow2_from_magic(self) -> Self;
}

/// Bits of √½ rounded down: `split_exponent` puts `m` in [√½, √2).
const SQRT_HALF_BITS: i32 = 0x3f35_04f3;
/// 1.5·2^23 (see `vmath::exp`).
pub(crate) const ROUND_MAGIC: f32 = 12_582_912.0;

impl Real for f32 {
    type Mask = bool;
    #[inline(always)]
    fn splat(x: f32) -> Self {
        x
    }
    #[inline(always)]
    fn sqrt(self) -> Self {
        f32::sqrt(self)
    }
    #[inline(always)]
    fn min(self, o: Self) -> Self {
        f32::min(self, o)
    }
    #[inline(always)]
    fn max(self, o: Self) -> Self {
        f32::max(self, o)
    }
    #[inline(always)]
    fn lt(self, o: Self) -> bool {
        self < o
    }
    #[inline(always)]
    fn le(self, o: Self) -> bool {
        self <= o
    }
    #[inline(always)]
    fn gt(self, o: Self) -> bool {
        self > o
    }
    #[inline(always)]
    fn ge(self, o: Self) -> bool {
        self >= o
    }
    #[inline(always)]
    fn ne(self, o: Self) -> bool {
        self != o
    }
    #[inline(always)]
    fn and(a: bool, b: bool) -> bool {
        a & b
    }
    #[inline(always)]
    fn not(a: bool) -> bool {
        !a
    }
    #[inline(always)]
    fn select(m: bool, a: Self, b: Self) -> Self {
        if m { a } else { b }
    }
    #[inline(always)]
    fn any(m: bool) -> bool {
        m
    }
    #[inline(always)]
    fn split_exponent(self) -> (Self, Self) {
        let bits = self.to_bits() as i32;
        let e = bits.wrapping_sub(SQRT_HALF_BITS) >> 23;
        let m = f32::from_bits(bits.wrapping_sub(e << 23) as u32);
        (e as f32, m)
    }
    #[inline(always)]
    fn pow2_from_magic(self) -> Self {
        let k = (self.to_bits() as i32).wrapping_sub(ROUND_MAGIC.to_bits() as i32);
        f32::from_bits((k.wrapping_add(127) << 23) as u32)
    }
}

/// Sixteen `f32` lanes (32-byte aligned: two AVX2 registers).
#[derive(Clone, Copy, Debug, PartialEq)]
#[repr(C, align(32))]
pub(crate) struct FL(pub(crate) [f32; LANES]);

/// Sixteen truth values, one per lane of an [`FL`]: all bits set (−1) for
/// true, 0 for false, as SIMD compares produce them.
#[derive(Clone, Copy, Debug)]
#[repr(C, align(32))]
pub(crate) struct ML([i32; LANES]);

impl FL {
    #[inline(always)]
    fn map(self, f: impl Fn(f32) -> f32) -> FL {
        let mut r = [0.0; LANES];
        for l in 0..LANES {
            r[l] = f(self.0[l]);
        }
        FL(r)
    }
    #[inline(always)]
    fn zip(self, o: FL, f: impl Fn(f32, f32) -> f32) -> FL {
        let mut r = [0.0; LANES];
        for l in 0..LANES {
            r[l] = f(self.0[l], o.0[l]);
        }
        FL(r)
    }
    #[inline(always)]
    fn cmp(self, o: FL, f: impl Fn(f32, f32) -> bool) -> ML {
        let mut r = [0; LANES];
        for l in 0..LANES {
            r[l] = -(f(self.0[l], o.0[l]) as i32);
        }
        ML(r)
    }
}

macro_rules! f8_binop {
    ($trait:ident, $method:ident, $op:tt) => {
        impl $trait for FL {
            type Output = FL;
            #[inline(always)]
            fn $method(self, o: FL) -> FL {
                self.zip(o, |a, b| a $op b)
            }
        }
    };
}
f8_binop!(Add, add, +);
f8_binop!(Sub, sub, -);
f8_binop!(Mul, mul, *);
f8_binop!(Div, div, /);

impl Neg for FL {
    type Output = FL;
    #[inline(always)]
    fn neg(self) -> FL {
        self.map(|a| -a)
    }
}

impl Real for FL {
    type Mask = ML;
    #[inline(always)]
    fn splat(x: f32) -> Self {
        FL([x; LANES])
    }
    #[inline(always)]
    fn sqrt(self) -> Self {
        self.map(f32::sqrt)
    }
    #[inline(always)]
    fn min(self, o: Self) -> Self {
        self.zip(o, f32::min)
    }
    #[inline(always)]
    fn max(self, o: Self) -> Self {
        self.zip(o, f32::max)
    }
    #[inline(always)]
    fn lt(self, o: Self) -> ML {
        self.cmp(o, |a, b| a < b)
    }
    #[inline(always)]
    fn le(self, o: Self) -> ML {
        self.cmp(o, |a, b| a <= b)
    }
    #[inline(always)]
    fn gt(self, o: Self) -> ML {
        self.cmp(o, |a, b| a > b)
    }
    #[inline(always)]
    fn ge(self, o: Self) -> ML {
        self.cmp(o, |a, b| a >= b)
    }
    #[inline(always)]
    fn ne(self, o: Self) -> ML {
        self.cmp(o, |a, b| a != b)
    }
    #[inline(always)]
    fn and(a: ML, b: ML) -> ML {
        let mut r = [0; LANES];
        for l in 0..LANES {
            r[l] = a.0[l] & b.0[l];
        }
        ML(r)
    }
    #[inline(always)]
    fn not(a: ML) -> ML {
        let mut r = [0; LANES];
        for l in 0..LANES {
            r[l] = !a.0[l];
        }
        ML(r)
    }
    #[inline(always)]
    fn select(m: ML, a: Self, b: Self) -> Self {
        let mut r = [0.0; LANES];
        for l in 0..LANES {
            r[l] = if m.0[l] != 0 { a.0[l] } else { b.0[l] };
        }
        FL(r)
    }
    #[inline(always)]
    fn any(m: ML) -> bool {
        let mut r = 0;
        for l in 0..LANES {
            r |= m.0[l];
        }
        r != 0
    }
    #[inline(always)]
    fn split_exponent(self) -> (Self, Self) {
        let (mut e, mut m) = ([0.0; LANES], [0.0; LANES]);
        for l in 0..LANES {
            (e[l], m[l]) = self.0[l].split_exponent();
        }
        (FL(e), FL(m))
    }
    #[inline(always)]
    fn pow2_from_magic(self) -> Self {
        self.map(<f32 as Real>::pow2_from_magic)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Each lane of every `FL` operation gives the bits of the `f32` one,
    /// NaN, ±0 and ±∞ included.
    #[test]
    fn every_lane_is_the_f32_operation() {
        let vals = [
            1.5f32,
            -2.25,
            0.0,
            -0.0,
            f32::NAN,
            f32::INFINITY,
            1e-30,
            3.0e8,
        ];
        let a = FL(std::array::from_fn(|l| vals[l % vals.len()]));
        let b = FL(std::array::from_fn(|l| vals[(l + 3) % vals.len()]));
        let same = |x: FL, f: &dyn Fn(f32, f32) -> f32| {
            for l in 0..LANES {
                let want = f(a.0[l], b.0[l]);
                assert!(
                    x.0[l].to_bits() == want.to_bits() || (x.0[l].is_nan() && want.is_nan()),
                    "lane {l}: {} vs {want}",
                    x.0[l]
                );
            }
        };
        same(a + b, &|x, y| x + y);
        same(a - b, &|x, y| x - y);
        same(a * b, &|x, y| x * y);
        same(a / b, &|x, y| x / y);
        same(-a, &|x, _| -x);
        same(a.sqrt(), &|x, _| x.sqrt());
        same(Real::min(a, b), &|x, y| x.min(y));
        same(Real::max(a, b), &|x, y| x.max(y));
        same(FL::select(a.lt(b), a, b), &|x, y| if x < y { x } else { y });
        same(FL::select(a.le(b), a, b), &|x, y| {
            if x <= y { x } else { y }
        });
        same(FL::select(a.gt(b), a, b), &|x, y| if x > y { x } else { y });
        same(FL::select(a.ge(b), a, b), &|x, y| {
            if x >= y { x } else { y }
        });
        same(FL::select(a.ne(b), a, b), &|x, y| {
            if x != y { x } else { y }
        });
        same(FL::select_div(a.lt(b), a, b, b, a), &|x, y| {
            if x < y { x / y } else { y / x }
        });
        assert!(FL::any(a.lt(b)) && !FL::any(a.lt(FL::splat(f32::NEG_INFINITY))));
        assert!(!FL::all(a.lt(b)) && FL::all(FL::splat(1.0).gt(FL::splat(0.0))));
        let both = FL::and(a.gt(b), FL::not(a.lt(FL::splat(0.0))));
        same(FL::select(both, a, b), &|x, y| {
            if x > y && !(x < 0.0) { x } else { y }
        });
        let pos = [1.5, 0.7, 1.41, 1e-12, 3e20, 2.0, 1.0, 0.70710677];
        let pos = FL(std::array::from_fn(|l| pos[l % pos.len()]));
        let (e, m) = pos.split_exponent();
        for l in 0..LANES {
            let (es, ms) = pos.0[l].split_exponent();
            assert_eq!((e.0[l], m.0[l]), (es, ms));
            let (lo, hi) = (std::f32::consts::FRAC_1_SQRT_2, std::f32::consts::SQRT_2);
            assert!(ms >= lo * (1.0 - f32::EPSILON) && ms < hi, "{ms}");
            assert_eq!(ms as f64 * 2f64.powf(es as f64), pos.0[l] as f64);
        }
    }
}
