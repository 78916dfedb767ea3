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

use std::ops::{Add, Mul, Sub};

#[cfg(target_arch = "x86_64")]
mod imp {
    use core::arch::x86_64::{
        __m128, _mm_add_ps, _mm_loadu_ps, _mm_movehl_ps, _mm_movelh_ps, _mm_mul_ps, _mm_set1_ps,
        _mm_storeu_ps, _mm_sub_ps, _mm_unpackhi_ps, _mm_unpacklo_ps,
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

        /// Writes the lanes to `out[..4]`. Panics if `out` is shorter.
        #[inline(always)]
        pub(crate) fn store(self, out: &mut [f32]) {
            let out = &mut out[..4];
            // SAFETY: writes the 4 floats of `out` (unaligned store)
            unsafe { _mm_storeu_ps(out.as_mut_ptr(), self.0) };
        }

        /// The 4 × 4 transpose: lane `l` of result `i` is lane `i` of `r[l]`.
        #[inline(always)]
        pub(crate) fn transpose(r: [V4; 4]) -> [V4; 4] {
            // SAFETY: as `splat`
            unsafe {
                let t0 = _mm_unpacklo_ps(r[0].0, r[1].0); // a0 b0 a1 b1
                let t1 = _mm_unpacklo_ps(r[2].0, r[3].0); // c0 d0 c1 d1
                let t2 = _mm_unpackhi_ps(r[0].0, r[1].0); // a2 b2 a3 b3
                let t3 = _mm_unpackhi_ps(r[2].0, r[3].0); // c2 d2 c3 d3
                [
                    V4(_mm_movelh_ps(t0, t1)),
                    V4(_mm_movehl_ps(t1, t0)),
                    V4(_mm_movelh_ps(t2, t3)),
                    V4(_mm_movehl_ps(t3, t2)),
                ]
            }
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

        #[inline(always)]
        pub(super) fn sub(self, o: V4) -> V4 {
            // SAFETY: as `splat`
            V4(unsafe { _mm_sub_ps(self.0, o.0) })
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
        pub(crate) fn store(self, out: &mut [f32]) {
            out[..4].copy_from_slice(&self.0);
        }

        #[inline(always)]
        pub(crate) fn transpose(r: [V4; 4]) -> [V4; 4] {
            std::array::from_fn(|i| V4(std::array::from_fn(|l| r[l].0[i])))
        }

        #[inline(always)]
        pub(super) fn add(self, o: V4) -> V4 {
            V4(std::array::from_fn(|l| self.0[l] + o.0[l]))
        }

        #[inline(always)]
        pub(super) fn mul(self, o: V4) -> V4 {
            V4(std::array::from_fn(|l| self.0[l] * o.0[l]))
        }

        #[inline(always)]
        pub(super) fn sub(self, o: V4) -> V4 {
            V4(std::array::from_fn(|l| self.0[l] - o.0[l]))
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

impl Sub for V4 {
    type Output = V4;
    #[inline(always)]
    fn sub(self, o: V4) -> V4 {
        V4::sub(self, o)
    }
}

impl Mul for V4 {
    type Output = V4;
    #[inline(always)]
    fn mul(self, o: V4) -> V4 {
        V4::mul(self, o)
    }
}

impl From<f32> for V4 {
    /// Every lane `x` (so that scalar-generic code, such as
    /// [`crate::kernel::quadratic_weights`], runs on four lanes).
    #[inline(always)]
    fn from(x: f32) -> V4 {
        V4::splat(x)
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
        let diff = (va - vb).to_array();
        let prod = (va * vb).to_array();
        let scaled = (s * va).to_array();
        for l in 0..4 {
            assert_eq!(sum[l].to_bits(), (a[l] + b[l]).to_bits());
            assert_eq!(diff[l].to_bits(), (a[l] - b[l]).to_bits());
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
            assert_eq!(bits((va - vb).to_array()), bits(pa.sub(pb).to_array()));
            assert_eq!(
                bits((s * va).to_array()),
                bits(P::splat(s).mul(pa).to_array())
            );
        }
    }

    /// The transpose against its definition (for both `V4`s), and `store`.
    #[test]
    fn transpose_swaps_lanes_and_values() {
        use super::portable::V4 as P;
        let m: [[f32; 4]; 4] =
            std::array::from_fn(|i| std::array::from_fn(|l| (10 * i + l) as f32));
        let t = V4::transpose(m.map(|r| V4::load(&r)));
        let tp = P::transpose(m.map(|r| P::load(&r)));
        for i in 0..4 {
            let expected: [f32; 4] = std::array::from_fn(|l| m[l][i]);
            assert_eq!(t[i].to_array(), expected);
            assert_eq!(tp[i].to_array(), expected);
            let (mut out, mut out_p) = ([f32::NAN; 6], [f32::NAN; 6]);
            t[i].store(&mut out[1..]);
            tp[i].store(&mut out_p[1..]);
            for o in [out, out_p] {
                assert_eq!(o[1..5], expected);
                assert!(o[0].is_nan() && o[5].is_nan());
            }
        }
    }
}
