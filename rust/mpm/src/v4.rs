//! Four `f32` lanes as one value, for the transfers' 4-lane node vectors.
//!
//! On x86-64 a `V4` is an SSE register (`__m128`, part of the baseline ISA),
//! so each operation is one instruction in both compiled copies of the frame
//! loop ([`crate::isa`]). Written as `[f32; 4]` loops instead, LLVM's
//! vectoriser sees which lanes a result never uses and splits the 4-lane
//! work into 2-lane and scalar pieces, at up to twice the instructions
//! (measured on g2p's stencil sums). Elsewhere a `V4` is a `[f32; 4]`. Every
//! operation is the IEEE operation lane by lane (no fused multiply-add), so
//! both give the same bits (`every_operation_is_the_f32_one`).

use std::ops::{Add, Mul};

#[cfg(target_arch = "x86_64")]
mod imp {
    use core::arch::x86_64::{
        __m128, _mm_add_ps, _mm_loadu_ps, _mm_mul_ps, _mm_set1_ps, _mm_storeu_ps,
    };

    #[derive(Clone, Copy, Debug)]
    pub(crate) struct V4(__m128);

    impl V4 {
        #[inline(always)]
        pub(crate) fn load(a: &[f32; 4]) -> V4 {
            // SAFETY: reads the 4 floats of `a` (unaligned load)
            V4(unsafe { _mm_loadu_ps(a.as_ptr()) })
        }

        #[inline(always)]
        pub(crate) fn splat(x: f32) -> V4 {
            // SAFETY: SSE is part of every x86-64 CPU (the baseline ISA)
            V4(unsafe { _mm_set1_ps(x) })
        }

        #[inline(always)]
        pub(crate) fn to_array(self) -> [f32; 4] {
            let mut a = [0.0f32; 4];
            // SAFETY: writes the 4 floats of `a` (unaligned store)
            unsafe { _mm_storeu_ps(a.as_mut_ptr(), self.0) };
            a
        }

        #[inline(always)]
        pub(super) fn add(self, o: V4) -> V4 {
            // SAFETY: as `splat`
            V4(unsafe { _mm_add_ps(self.0, o.0) })
        }

        #[inline(always)]
        pub(super) fn mul(self, o: V4) -> V4 {
            // SAFETY: as `splat`
            V4(unsafe { _mm_mul_ps(self.0, o.0) })
        }
    }
}

/// The portable `V4` (the one elsewhere than x86-64; also compiled for the
/// tests there, which compare it with the SSE one).
#[cfg(any(test, not(target_arch = "x86_64")))]
mod portable {
    #[derive(Clone, Copy, Debug)]
    pub(crate) struct V4([f32; 4]);

    impl V4 {
        #[inline(always)]
        pub(crate) fn load(a: &[f32; 4]) -> V4 {
            V4(*a)
        }

        #[inline(always)]
        pub(crate) fn splat(x: f32) -> V4 {
            V4([x; 4])
        }

        #[inline(always)]
        pub(crate) fn to_array(self) -> [f32; 4] {
            self.0
        }

        #[inline(always)]
        pub(super) fn add(self, o: V4) -> V4 {
            V4(std::array::from_fn(|l| self.0[l] + o.0[l]))
        }

        #[inline(always)]
        pub(super) fn mul(self, o: V4) -> V4 {
            V4(std::array::from_fn(|l| self.0[l] * o.0[l]))
        }
    }
}

#[cfg(not(target_arch = "x86_64"))]
use portable as imp;

pub(crate) use imp::V4;

impl Add for V4 {
    type Output = V4;
    #[inline(always)]
    fn add(self, o: V4) -> V4 {
        V4::add(self, o)
    }
}

impl Mul for V4 {
    type Output = V4;
    #[inline(always)]
    fn mul(self, o: V4) -> V4 {
        V4::mul(self, o)
    }
}

impl Mul<V4> for f32 {
    type Output = V4;
    /// Every lane times the scalar.
    #[inline(always)]
    fn mul(self, v: V4) -> V4 {
        V4::splat(self) * v
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_operation_is_the_f32_one() {
        // values that round differently in any other order or precision
        let a = [0.1f32, -3.7e-8, 1.0e30, f32::MIN_POSITIVE];
        let b = [0.3f32, 2.9e-8, -1.0e30, 0.5];
        let (va, vb) = (V4::load(&a), V4::load(&b));
        let s = 1.0f32 / 3.0;
        let sum = (va + vb).to_array();
        let prod = (va * vb).to_array();
        let scaled = (s * va).to_array();
        for l in 0..4 {
            assert_eq!(sum[l].to_bits(), (a[l] + b[l]).to_bits());
            assert_eq!(prod[l].to_bits(), (a[l] * b[l]).to_bits());
            assert_eq!(scaled[l].to_bits(), (s * a[l]).to_bits());
        }
        assert_eq!(V4::splat(2.5).to_array(), [2.5; 4]);
        let nan = (V4::load(&[f32::NAN, 0.0, 0.0, 0.0]) * V4::splat(0.0)).to_array();
        assert!(nan[0].is_nan());
    }

    /// The portable `V4` gives the bits of the one in use (on x86-64 the SSE
    /// one), so a build for another architecture simulates the same bits.
    #[test]
    fn the_portable_v4_gives_the_same_bits() {
        use super::portable::V4 as P;
        let mut seed = 7u32;
        let mut rnd = move || {
            seed = seed.wrapping_mul(1_664_525).wrapping_add(1_013_904_223);
            f32::from_bits((seed >> 1) % 0x7f00_0000) // a finite positive float, any exponent
        };
        for _ in 0..1000 {
            let (a, b, s) = ([0; 4].map(|_| rnd()), [0; 4].map(|_| -rnd()), rnd());
            let (va, vb, pa, pb) = (V4::load(&a), V4::load(&b), P::load(&a), P::load(&b));
            let bits = |x: [f32; 4]| x.map(f32::to_bits);
            assert_eq!(bits((va + vb).to_array()), bits(pa.add(pb).to_array()));
            assert_eq!(bits((va * vb).to_array()), bits(pa.mul(pb).to_array()));
            assert_eq!(
                bits((s * va).to_array()),
                bits(P::splat(s).mul(pa).to_array())
            );
        }
    }
}
