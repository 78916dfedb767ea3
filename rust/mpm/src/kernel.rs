//! The interpolation kernel: quadratic B-splines on the node lattice `i·dx`
//! (Hu et al. 2018, MLS-MPM; Jiang et al. 2015, APIC).
//!
//! A particle at `x` touches the 3 nodes `base, base + 1, base + 2` per
//! dimension, with `base = ⌊x/dx − 1/2⌋` and the offset `f = x/dx − base`
//! in `[0.5, 1.5)`; the weights of those nodes are
//!
//! ```text
//! w0 = ½ (3/2 − f)²,   w1 = 3/4 − (f − 1)²,   w2 = ½ (f − 1/2)²
//! ```
//!
//! They sum to 1 and reproduce linear functions, which is what makes the
//! APIC/MLS transfers conserve linear and angular momentum. This module is
//! the one place the weights are written: the solver and the grid model's
//! transfers (f32), the grid-mass metric and the surfaces' p2g (f64) all
//! call [`quadratic_weights`].

use std::ops::{Add, Mul, Sub};

use nalgebra::SVector;

use crate::v4::V4;

/// Quadratic B-spline weights of the 3 stencil nodes for the offset `f ∈ [0.5, 1.5)`
/// (in cells, from the stencil's base node). Generic over `f32` / `f64`; the
/// constants are exact in both, so each precision evaluates the same expression.
#[inline(always)]
pub fn quadratic_weights<T>(f: T) -> [T; 3]
where
    T: Copy + From<f32> + Add<Output = T> + Sub<Output = T> + Mul<Output = T>,
{
    let (half, three_halves, three_quarters, one) =
        (T::from(0.5), T::from(1.5), T::from(0.75), T::from(1.0));
    [
        half * (three_halves - f) * (three_halves - f),
        three_quarters - (f - one) * (f - one),
        half * (f - half) * (f - half),
    ]
}

/// Where a particle sits in the grid: its block's key, the index of its
/// 3^D stencil's base node in the block's padded `(B+2)^D` buffer, and its
/// offset from that node (in cells, in [0.5, 1.5)). Computed once per
/// substep (in g2p, for the next one).
#[derive(Clone, Copy, Debug, Default)]
pub(crate) struct Cell {
    pub(crate) key: u32,
    pub(crate) pad_off: u32,
    pub(crate) fx: [f32; 3],
}

/// The [`Cell`] of position `x`: `inv_dx = 1/dx`, blocks of `2^log2_b` cells,
/// `lat` the strides of the block lattice, `pad` those of a padded buffer.
#[inline(always)]
pub(crate) fn cell_of<const D: usize>(
    x: &SVector<f32, D>,
    inv_dx: f32,
    log2_b: u32,
    lat: &[usize; D],
    pad: &[usize; D],
) -> Cell {
    let mut c = Cell::default();
    let mut key = 0usize;
    let mut pad_off = 0usize;
    let mask = (1usize << log2_b) - 1;
    for d in 0..D {
        let xg = x[d] * inv_dx;
        // xg ≥ 1 inside the domain [dx, 1 − dx], so truncation is floor
        let b = truncate_in_domain(xg - 0.5);
        c.fx[d] = xg - b as f32;
        key += (b as usize >> log2_b) * lat[d];
        // the base node's place in its own block's padded buffer
        pad_off += (b as usize & mask) * pad[d];
    }
    c.key = key as u32;
    c.pad_off = pad_off as u32;
    c
}

/// `v` truncated toward zero, for `0 ≤ v < 2^31` (a stencil base in cells:
/// positions are kept in the domain [dx, 1 − dx]). On x86-64 one
/// `cvttss2si` instead of `as i32`'s saturating conversion (two more
/// compares and selects for NaN and overflow, which cannot occur here): the
/// same value for every such `v`.
#[inline(always)]
fn truncate_in_domain(v: f32) -> u32 {
    #[cfg(target_arch = "x86_64")]
    {
        use std::arch::x86_64::{_mm_cvttss_si32, _mm_set_ss};
        // SSE is part of the x86-64 baseline; the intrinsic is defined for
        // every input (out of range gives i32::MIN)
        #[allow(unused_unsafe)]
        unsafe {
            _mm_cvttss_si32(_mm_set_ss(v)) as u32
        }
    }
    #[cfg(not(target_arch = "x86_64"))]
    {
        v as i32 as u32
    }
}

/// The offsets `fx` of a [`Cell`] and the quadratic B-spline weights of its
/// stencil, per dimension.
#[inline(always)]
pub(crate) fn weights<const D: usize>(cell: &Cell) -> (SVector<f32, D>, [[f32; 3]; D]) {
    let mut fx = SVector::<f32, D>::zeros();
    for d in 0..D {
        fx[d] = cell.fx[d];
    }
    // every dimension at once, one lane each (the same f32 operations; the
    // unused lanes hold finite values from offsets 0)
    let [w0, w1, w2] =
        quadratic_weights(V4::load(&[cell.fx[0], cell.fx[1], cell.fx[2], 0.0])).map(V4::to_array);
    let w = std::array::from_fn(|d| [w0[d], w1[d], w2[d]]);
    (fx, w)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn weights_partition_unity_and_reproduce_linear_functions() {
        for i in 0..=100 {
            let f = 0.5 + i as f64 / 100.0 * (1.0 - 1e-9);
            let w = quadratic_weights(f);
            assert!((w.iter().sum::<f64>() - 1.0).abs() < 1e-12);
            // Σ w_k (k − f) = 0: the weighted node positions reproduce x
            let first: f64 = (0..3).map(|k| w[k] * (k as f64 - f)).sum();
            assert!(first.abs() < 1e-12, "{f}: {first}");
            assert!(w.iter().all(|&x| x >= 0.0));
        }
    }

    #[test]
    fn truncation_is_the_saturating_conversion_in_the_domain() {
        // every stencil base of a position in [dx, 1 − dx] (and beyond, up to
        // 2^24 cells) truncates as `as i32` does
        let mut v = 0.0f32;
        while v < (1u32 << 24) as f32 {
            for x in [v, v + 0.5, v + 0.999_99, v.next_up()] {
                assert_eq!(truncate_in_domain(x), x as i32 as u32, "{x}");
            }
            v = if v < 4096.0 { v + 1.0 } else { v * 1.01 };
        }
    }

    #[test]
    fn f32_and_f64_evaluate_the_same_expression() {
        for i in 0..=64 {
            let f = 0.5f32 + i as f32 / 64.0 * 0.999;
            let w32 = quadratic_weights(f);
            let w64 = quadratic_weights(f as f64);
            for k in 0..3 {
                assert!((w32[k] as f64 - w64[k]).abs() < 1e-6);
            }
        }
    }
}
