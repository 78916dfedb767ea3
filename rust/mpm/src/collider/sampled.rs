//! A sampled signed distance ([`Shape::Sampled`], a triangle mesh's, made
//! by the Python scene layer): the multilinear stencil of its samples,
//! written once for the distance and the normals, and the plane estimate of
//! a cell's lowest corner that the particle projection and its reach use.

use nalgebra::SVector;

use super::Shape;

/// Most samples a [`Shape::Sampled`] may hold (64 MiB of `f32`).
pub const MAX_SAMPLED_NODES: usize = 1 << 24;

/// `⌊u⌋` as an index, for `0 ≤ u < 2^32` (the index of a sampled grid's
/// node or below; NaN gives 0 as `floor` would): the cast truncates, which
/// is the floor there. `f32::floor` would be a call to libm's `floorf` in
/// the portable x86-64 build (SSE2 has no rounding instruction).
#[inline(always)]
pub(super) fn floor_index(u: f32) -> usize {
    debug_assert!(
        u.is_nan() || (0.0..4294967296.0).contains(&u),
        "floor_index of {u}"
    );
    u as u32 as usize
}

/// The row-major position of corner `corner` (bit `d` set: the upper node
/// on axis `d`) of the grid's cell `idx`.
#[inline(always)]
pub(super) fn corner_node<const D: usize>(
    dims: &[usize; D],
    idx: &[usize; D],
    corner: usize,
) -> usize {
    let mut lin = 0usize;
    for d in 0..D {
        lin = lin * dims[d] + idx[d] + ((corner >> d) & 1);
    }
    lin
}

/// The multilinear stencil of a sampled grid, the one place it is written:
/// at the nearest point of the grid's box to `rel` (the point relative to
/// the grid's origin, [`Shape::local`]), `visit(w, node)` for each of the
/// 2^D corners of the cell around it, in order, with its weight `w` (the
/// product over the axes of `t` or `1 − t`, `t` the fraction of the cell)
/// and row-major position `node`. Returns the squared distance [m²] from
/// `rel` to the box (0 inside it).
#[inline(always)]
fn multilinear<const D: usize>(
    cell: f32,
    dims: &[usize; D],
    rel: &SVector<f32, D>,
    mut visit: impl FnMut(f32, usize),
) -> f32 {
    let mut outside2 = 0.0f32;
    let mut idx = [0usize; D];
    let mut t = [0.0f32; D];
    for d in 0..D {
        let u = rel[d] / cell;
        let top = (dims[d] - 1) as f32;
        let uc = u.clamp(0.0, top);
        let excess = (u - uc) * cell;
        outside2 += excess * excess;
        let i = floor_index(uc).min(dims[d] - 2);
        idx[d] = i;
        t[d] = uc - i as f32;
    }
    for corner in 0..(1usize << D) {
        let mut w = 1.0f32;
        for d in 0..D {
            w *= if (corner >> d) & 1 == 1 {
                t[d]
            } else {
                1.0 - t[d]
            };
        }
        visit(w, corner_node(dims, &idx, corner));
    }
    outside2
}

/// The multilinear interpolant of the node vectors `normals` (`D` per node)
/// at the nearest point of the grid's box to `rel`, the point relative to
/// the grid's origin ([`Shape::local`]).
pub(super) fn sampled_normal<const D: usize>(
    cell: f32,
    dims: &[usize; D],
    normals: &[f32],
    rel: &SVector<f32, D>,
) -> SVector<f32, D> {
    let mut acc = SVector::<f32, D>::zeros();
    multilinear(cell, dims, rel, |w, node| {
        if w != 0.0 {
            for d in 0..D {
                acc[d] += w * normals[node * D + d];
            }
        }
    });
    acc
}

/// The multilinear interpolant of a sampled grid at `rel`, the point
/// relative to the grid's origin ([`Shape::local`]), extended outside the
/// grid's box by the distance to the box (see [`Shape::Sampled`]).
pub(super) fn sampled_sdf<const D: usize>(
    cell: f32,
    dims: &[usize; D],
    values: &[f32],
    rel: &SVector<f32, D>,
) -> f32 {
    let mut acc = 0.0f32;
    let outside2 = multilinear(cell, dims, rel, |w, node| acc += w * values[node]);
    acc + outside2.sqrt()
}

/// The plane estimate `φ_0 + n_0·off` of the distance at `rel` (the point
/// relative to a sampled grid's origin, [`Shape::local`]) of corner 0 (the
/// lowest) of the grid's cell `idx`, with `off = rel − x_0`: a lower bound
/// of the cell's largest corner estimate ([`Shape::step_below`]). Returns
/// the corner's row-major position, `off` and the estimate.
#[inline(always)]
pub(super) fn corner0_estimate<const D: usize>(
    cell: f32,
    dims: &[usize; D],
    values: &[f32],
    normals: &[f32],
    rel: &SVector<f32, D>,
    idx: &[usize; D],
) -> (usize, SVector<f32, D>, f32) {
    let mut lin = 0usize;
    let mut off = SVector::<f32, D>::zeros();
    for d in 0..D {
        lin = lin * dims[d] + idx[d];
        // (idx < 2^24, MAX_SAMPLED_NODES: exact through u32, which converts
        // in one instruction where usize does not)
        off[d] = rel[d] - idx[d] as u32 as f32 * cell;
    }
    let mut est = values[lin];
    for d in 0..D {
        est += normals[lin * D + d] * off[d];
    }
    (lin, off, est)
}

impl<const D: usize> Shape<D> {
    /// Whether the signed distance is `≥ 0` everywhere outside the shape's
    /// sampled grid's box: a sampled shape whose border samples are all
    /// `≥ 0` (a mesh's, with its margin of samples around the mesh, unless
    /// the mesh reaches the domain's side): outside the box the distance is
    /// the interpolant of border samples (nonnegative weights) plus a
    /// distance ([`Shape::Sampled`]). False for a box or sphere. Reads every
    /// border sample.
    pub(super) fn nonnegative_outside_grid(&self) -> bool {
        let Shape::Sampled { dims, values, .. } = self else {
            return false;
        };
        let total: usize = dims.iter().product();
        // row-major strides
        let mut stride = [1usize; D];
        for d in (0..D.saturating_sub(1)).rev() {
            stride[d] = stride[d + 1] * dims[d + 1];
        }
        // each face: the samples with index 0 or dims[d] − 1 on axis d
        for d in 0..D {
            for side in [0, dims[d] - 1] {
                for k in 0..total / dims[d] {
                    // k over the other axes (row-major), index `side` on axis d
                    let (mut rest, mut lin) = (k, side * stride[d]);
                    for e in (0..D).rev().filter(|&e| e != d) {
                        lin += (rest % dims[e]) * stride[e];
                        rest /= dims[e];
                    }
                    if !(values[lin] >= 0.0) {
                        return false;
                    }
                }
            }
        }
        true
    }
}
