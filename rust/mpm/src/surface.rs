//! The p2g of the fluid surfaces' density field (`hybridmpm.render.surface`):
//! float64, with the quadratic B-spline weights of `kernel.rs` rounded
//! per axis to multiples of `1/weight_scale`, so that the field has the same
//! bits for any particle order where every product and partial sum is exact.

use crate::error::{MpmError, Result};
use crate::kernel::quadratic_weights;

/// Largest grid [`surface_p2g`] fills, in nodes in all (2 GiB of float64).
pub const MAX_SURFACE_NODES: usize = 1 << 28;
/// Largest `weight_scale` of [`surface_p2g`] (weights times it stay far
/// below 2^52, where the rounding without libm holds).
pub const MAX_WEIGHT_SCALE: f64 = (1u64 << 40) as f64;

/// `values` [N] spread from `positions` [N, D] [m] (flat, row-major, of
/// shape `[n, dim]`, `D = dim` ∈ {2, 3}) onto the nodes
/// `(origin + i)·spacing`, `i ∈ [0, shape)`, with the quadratic B-spline
/// weights (`kernel.rs`'s `quadratic_weights`) of the offset
/// `f = x/spacing − ⌊x/spacing − 1/2⌋` rounded per axis to multiples of
/// `1/weight_scale`, `rint(w·weight_scale)·(1/weight_scale)`; returns the
/// field, `shape` row-major (first axis slowest).
///
/// Summed in float64, one particle after the other: where every product
/// and partial sum is exact (`values` quantised, see the surface module),
/// the field has the same bits for any particle order. Serial, so the same
/// bits for any thread count. Errors (`MpmError::InvalidInput`) name, in
/// this order: `positions` (not `n·dim` numbers), `values` (not `n` of
/// them), `spacing` (not finite and > 0),
/// `weight_scale` (not in `(0, 2^40]`), `origin` (not `dim` values),
/// `shape` (not `dim` counts > 0, or more than [`MAX_SURFACE_NODES`] nodes),
/// `values` (one not finite), `positions` (`dim` not 2 or 3, a coordinate
/// not finite, a stencil outside the grid).
pub fn surface_p2g(
    positions: &[f64],
    [n, dim]: [usize; 2],
    values: &[f64],
    spacing: f64,
    origin: &[i64],
    shape: &[usize],
    weight_scale: f64,
) -> Result<Vec<f64>> {
    if n.checked_mul(dim) != Some(positions.len()) {
        return Err(MpmError::invalid(
            "positions",
            format!("expected [{n}, {dim}] numbers, got {}", positions.len()),
        ));
    }
    if values.len() != n {
        return Err(MpmError::invalid(
            "values",
            format!("expected [{n}] values, got [{}]", values.len()),
        ));
    }
    if !(spacing.is_finite() && spacing > 0.0) {
        return Err(MpmError::invalid("spacing", "must be finite and > 0"));
    }
    if !(weight_scale > 0.0 && weight_scale <= MAX_WEIGHT_SCALE) {
        return Err(MpmError::invalid(
            "weight_scale",
            format!("must be in (0, 2^40], got {weight_scale}"),
        ));
    }
    if origin.len() != dim {
        return Err(MpmError::invalid(
            "origin",
            format!("expected {dim} values"),
        ));
    }
    let size = shape.iter().try_fold(1usize, |a, &s| a.checked_mul(s));
    if shape.len() != dim || size.is_none_or(|s| s == 0 || s > MAX_SURFACE_NODES) {
        return Err(MpmError::invalid(
            "shape",
            format!(
                "expected {dim} node counts > 0, at most {MAX_SURFACE_NODES} nodes in all, got {shape:?}"
            ),
        ));
    }
    if let Some(i) = values.iter().position(|x| !x.is_finite()) {
        return Err(MpmError::invalid(
            "values",
            format!("value {i} is not finite"),
        ));
    }
    match dim {
        2 => splat::<2>(positions, values, spacing, origin, shape, weight_scale),
        3 => splat::<3>(positions, values, spacing, origin, shape, weight_scale),
        _ => Err(MpmError::invalid(
            "positions",
            format!("expected shape [N, 2] or [N, 3], got [N, {dim}]"),
        )),
    }
}

/// The body of [`surface_p2g`] in `D` dimensions; the error names the first
/// particle that is not finite or whose stencil leaves the grid.
fn splat<const D: usize>(
    xs: &[f64],
    vals: &[f64],
    spacing: f64,
    origin: &[i64],
    shape: &[usize],
    scale: f64,
) -> Result<Vec<f64>> {
    let mut out = vec![0.0f64; shape.iter().product()];
    let mut stride = [1usize; D];
    for k in (0..D - 1).rev() {
        stride[k] = stride[k + 1] * shape[k + 1];
    }
    let inv = 1.0 / scale;
    for (p, (x, &value)) in xs.as_chunks::<D>().0.iter().zip(vals).enumerate() {
        let mut w = [[0.0f64; 3]; D];
        let mut first = 0usize;
        for k in 0..D {
            if !x[k].is_finite() {
                return Err(MpmError::invalid(
                    "positions",
                    format!("particle {p} has a non-finite coordinate"),
                ));
            }
            let u = x[k] / spacing;
            let b = floor(u - 0.5);
            for (wq, r) in w[k].iter_mut().zip(quadratic_weights(u - b)) {
                *wq = round_ties_even(r * scale) * inv;
            }
            let i = b - origin[k] as f64;
            if !(i >= 0.0 && i + 3.0 <= shape[k] as f64) {
                return Err(MpmError::invalid(
                    "positions",
                    format!("particle {p}: its stencil leaves the grid along axis {k}"),
                ));
            }
            first += i as usize * stride[k];
        }
        if D == 2 {
            for a in 0..3 {
                let wa = value * w[0][a];
                let row = first + a * stride[0];
                for b in 0..3 {
                    out[row + b] += wa * w[1][b];
                }
            }
        } else {
            for a in 0..3 {
                let wa = value * w[0][a];
                for b in 0..3 {
                    let wab = wa * w[1][b];
                    let row = first + a * stride[0] + b * stride[1];
                    for c in 0..3 {
                        out[row + c] += wab * w[D - 1][c];
                    }
                }
            }
        }
    }
    Ok(out)
}

/// `x.floor()` without a libm call (the x86-64 baseline has no rounding
/// instruction): exact for |x| < 2^63 (beyond, the stencil check fails).
#[inline]
fn floor(x: f64) -> f64 {
    let t = x as i64 as f64; // toward zero
    if t > x { t - 1.0 } else { t }
}

/// `x.round_ties_even()` for `0 <= x < 2^52` (the weights times the scale)
/// without a libm call: adding 2^52 leaves no fraction bits, so the sum is
/// rounded to the nearest integer, ties to even.
#[inline]
fn round_ties_even(x: f64) -> f64 {
    const TWO52: f64 = 4_503_599_627_370_496.0;
    (x + TWO52) - TWO52
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The weights as the binding wrote them before they came from
    /// [`quadratic_weights`]: `t0·t0·0.5, 0.75 − t1·t1, t2·t2·0.5`.
    fn written_out(f: f64) -> [f64; 3] {
        let (t0, t1, t2) = (1.5 - f, f - 1.0, f - 0.5);
        [t0 * t0 * 0.5, 0.75 - t1 * t1, t2 * t2 * 0.5]
    }

    #[test]
    fn the_kernel_weights_have_the_bits_of_the_written_out_ones() {
        // ½·t·t and t·t·½ differ only by the place of an exact halving
        let mut state = 0x9e37_79b9_7f4a_7c15u64;
        for i in 0..200_000 {
            state ^= state << 13;
            state ^= state >> 7;
            state ^= state << 17;
            let x = (state >> 11) as f64 / (1u64 << 53) as f64 * 64.0 - 32.0;
            let u = x / if i % 2 == 0 { 1.0 / 64.0 } else { 0.037 };
            let f = u - floor(u - 0.5);
            let (a, b) = (quadratic_weights(f), written_out(f));
            for k in 0..3 {
                assert_eq!(a[k].to_bits(), b[k].to_bits(), "f = {f:e}, weight {k}");
            }
        }
    }

    #[test]
    fn a_particle_spreads_its_value_over_its_stencil() {
        // a particle on node (4, 2): weights 1/8, 3/4, 1/8 per axis, exact
        let p2g = |origin: &[i64]| {
            surface_p2g(
                &[0.5, 0.25],
                [1, 2],
                &[16.0],
                0.125,
                origin,
                &[5, 5],
                1024.0,
            )
        };
        let out = p2g(&[1, 0]).unwrap();
        assert_eq!(out.iter().sum::<f64>(), 16.0);
        // node (4, 2) is (3, 2) of the grid from origin (1, 0)
        assert_eq!(out[3 * 5 + 2], 16.0 * 0.75 * 0.75);
        assert_eq!(out[2 * 5 + 1], 16.0 * 0.125 * 0.125);
        let e = p2g(&[4, 0]).unwrap_err().to_string();
        assert!(
            e.starts_with("positions: particle 0: its stencil leaves the grid along axis 0"),
            "{e}"
        );
    }
}
