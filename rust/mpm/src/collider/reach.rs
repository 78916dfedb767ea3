//! Where a collider's particle projection can act ([`Reach`]): the ball the
//! shape lies in, or a sampled shape's grid with the cells where it cannot
//! act marked once per collider ([`ShallowCells`]).

use std::sync::Arc;

use nalgebra::SVector;

use super::sampled::corner0_estimate;
use super::{Collider, MAX_SAMPLED_NODES, Shape};

impl<const D: usize> Collider<D> {
    /// Where [`Collider::project_particle`] with threshold `depth` can act,
    /// at the collider's current pose ([`Reach`]): given `shallow`, the
    /// [`ShallowCells`] of this sampled shape for `depth` (made once per
    /// collider: they read every sample), its grid; else the ball the shape
    /// lies in.
    pub fn reach<'a>(&'a self, depth: f32, shallow: Option<&'a ShallowCells>) -> Reach<'a, D> {
        let r = self.shape.bounding_radius() * 1.001 + 1e-6;
        let (centre, r2) = (self.shape.center(), r * r);
        let ball = Reach {
            depth,
            region: Region::Ball(centre, r2),
        };
        let (
            Shape::Sampled {
                origin,
                cell,
                dims,
                values,
                normals: Some(normals),
            },
            Some(shallow),
        ) = (&self.shape, shallow)
        else {
            return ball;
        };
        if !(Arc::ptr_eq(values, &shallow.values)
            && Arc::ptr_eq(normals, &shallow.normals)
            && depth == shallow.depth)
            || dims.iter().any(|&n| n > MAX_SAMPLED_NODES)
        {
            // made for other samples or another threshold; or not a valid
            // shape (`GridReach` counts on dims ≤ 2^24)
            return ball;
        }
        // four times the rounding of the quotient either way (`GridReach`)
        let eps: [f32; D] = std::array::from_fn(|d| (dims[d] + 1) as f32 / (1u32 << 20) as f32);
        Reach {
            depth,
            region: Region::Grid(GridReach {
                centre,
                r2,
                nonnegative_outside: shallow.nonnegative_outside,
                origin: *origin,
                cell: *cell,
                inv_cell: 1.0 / cell,
                u_range: std::array::from_fn(|d| (-eps[d], (dims[d] - 1) as f32 + eps[d])),
                frac_range: std::array::from_fn(|d| (eps[d], 1.0 - eps[d])),
                last_cell: std::array::from_fn(|d| (dims[d] - 2) as u32),
                dims,
                values,
                normals,
                shallow: &shallow.bits,
            }),
        }
    }
}

/// Where a collider's particle projection with threshold `depth` can act
/// ([`Collider::reach`]): a particle elsewhere is left alone after this one
/// test ([`Reach::may_act`]).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Reach<'a, const D: usize> {
    pub(super) depth: f32,
    region: Region<'a, D>,
}

#[derive(Clone, Copy, Debug, PartialEq)]
enum Region<'a, const D: usize> {
    /// The ball the shape lies in (its centre, [`Shape::center`], and
    /// squared radius, [`Shape::bounding_radius`] widened by a thousandth
    /// and a micrometre against rounding): a point outside it has `sdf > 0`.
    Ball(SVector<f32, D>, f32),
    /// A sampled shape's grid.
    Grid(GridReach<'a, D>),
}

impl<const D: usize> Reach<'_, D> {
    /// Whether the projection may act at `x`: false only where
    /// [`Shape::step_below`] is sure to return `None` (for a NaN coordinate
    /// too).
    #[inline(always)]
    pub fn may_act(&self, x: &SVector<f32, D>) -> bool {
        match &self.region {
            Region::Ball(centre, r2) => (x - centre).norm_squared() < *r2,
            Region::Grid(g) => g.may_act(x, self.depth),
        }
    }
}

/// [`Reach`] of a sampled shape with normals: [`Shape::step_below`]'s first
/// test without its division, and most often without its sample loads.
///
/// Outside the grid the projection cannot act if the distance is `≥ 0`
/// there ([`Shape::nonnegative_outside_grid`]: a mesh's margin of samples),
/// else outside the bounding ball. Inside it, `step_below` finds the
/// point's cell by dividing by `cell`, `u = (x − origin) / cell`, and
/// returns `None` where corner 0's plane estimate is at least `−depth`.
/// Here `u` is found by multiplying by `1 / cell`, within `eps =
/// 2^−20·(dims + 1)` of the quotient (four times the rounding of either):
/// where it is farther than `eps` from the grid's range, the quotient is
/// outside it too; where it is farther than `eps` from a cell's sides, the
/// quotient is in the same cell, `step_below`'s cell. There
/// [`ShallowCells`] says whether the estimate is at least `−depth`
/// anywhere in the cell, and where it cannot tell, the estimate is computed
/// as `step_below` computes it. A point within `eps` of a cell's side
/// (about one in 10^4 on a 64³ grid) is left to `step_below`. So the
/// projection's result is the same bit for bit, and most particles near a
/// mesh cost a multiply and a bit test (a bit per cell: in L1) where they
/// cost three divisions, three calls of libm's `floorf` (the portable
/// build's `f32::floor`) and four loads from the samples' 16 bytes per node,
/// and those outside the grid an interpolated distance as well.
#[derive(Clone, Copy, Debug, PartialEq)]
struct GridReach<'a, const D: usize> {
    centre: SVector<f32, D>,
    r2: f32,
    nonnegative_outside: bool,
    origin: SVector<f32, D>,
    cell: f32,
    inv_cell: f32,
    /// Per axis: `[−eps, dims − 1 + eps]`, outside which the quotient is
    /// surely outside the grid; `[eps, 1 − eps]`, the fraction of the
    /// product in which the quotient is surely in the same cell; the last
    /// cell's index (`dims − 2`).
    u_range: [(f32, f32); D],
    frac_range: [(f32, f32); D],
    last_cell: [u32; D],
    dims: &'a [usize; D],
    values: &'a [f32],
    normals: &'a [f32],
    shallow: &'a [u64],
}

impl<const D: usize> GridReach<'_, D> {
    #[inline(always)]
    fn may_act(&self, x: &SVector<f32, D>, depth: f32) -> bool {
        // as `Shape::local`
        let rel = x - self.origin;
        let mut idx = [0usize; D];
        let mut one_cell = true;
        for d in 0..D {
            let u = rel[d] * self.inv_cell;
            let (lo, hi) = self.u_range[d];
            if !(u >= lo && u <= hi) {
                // surely outside the grid (or NaN)
                return !self.nonnegative_outside && (x - self.centre).norm_squared() < self.r2;
            }
            // SAFETY: −eps ≤ u ≤ dims − 1 + eps with eps ≤ 2^5 and dims ≤
            // 2^24 (`Collider::reach`): within i32
            let i = unsafe { u.to_int_unchecked::<i32>() };
            // ⌊u⌋ where i ≥ 0 (exact where it counts: i < 2^24)
            let f = u - i as f32;
            // the quotient surely in cell i, a cell of the grid (as u32 a
            // negative i is beyond the last cell)
            let (f_lo, f_hi) = self.frac_range[d];
            one_cell &= (f >= f_lo) & (f <= f_hi) & (i as u32 <= self.last_cell[d]);
            idx[d] = i as usize;
        }
        if !one_cell {
            // at a cell's side or the grid's: `step_below` decides
            return true;
        }
        let mut cell = 0usize;
        for d in 0..D {
            cell = cell * (self.last_cell[d] as usize + 1) + idx[d];
        }
        if self.shallow[cell / 64] >> (cell % 64) & 1 == 1 {
            return false;
        }
        let (_, _, est0) =
            corner0_estimate(self.cell, self.dims, self.values, self.normals, &rel, &idx);
        est0 < -depth
    }
}

/// What the particle projection of a sampled shape with normals finds once
/// per collider ([`ShallowCells::new`]) and [`Collider::reach`] takes.
#[derive(Clone, Debug, PartialEq)]
pub struct ShallowCells {
    /// The samples and the threshold it was made for.
    values: Arc<[f32]>,
    normals: Arc<[f32]>,
    depth: f32,
    /// [`Shape::nonnegative_outside_grid`].
    nonnegative_outside: bool,
    /// A bit per cell of the grid (row-major by its lowest corner, the
    /// corner [`Shape::step_below`] estimates from): whether that corner's
    /// plane estimate `φ_0 + n_0·off` is at least `−depth` at every offset
    /// `off` in the cell: `φ_0 + Σ_d min(0, n_0d)·cell ≥ −depth`, with a
    /// margin some forty times the estimate's rounding.
    bits: Vec<u64>,
}

impl ShallowCells {
    /// The cells of a sampled `shape` with normals (valid:
    /// [`Collider::validate`]) for the projection threshold `depth ≥ 0`;
    /// `None` for any other shape or threshold. A bit per cell.
    pub fn new<const D: usize>(shape: &Shape<D>, depth: f32) -> Option<Self> {
        let Shape::Sampled {
            cell,
            dims,
            values,
            normals: Some(normals),
            ..
        } = shape
        else {
            return None;
        };
        if !(depth >= 0.0 && depth.is_finite()) {
            return None;
        }
        let cells: [usize; D] = std::array::from_fn(|d| dims[d] - 1);
        let total: usize = cells.iter().product();
        let c = *cell as f64;
        let mut bits = vec![0u64; total.div_ceil(64)];
        let mut idx = [0usize; D];
        for k in 0..total {
            // corner 0's estimate at its lowest over the cell, less a
            // margin some forty times its rounding in f32 (a few units in
            // the last place of the sample, of its terms and of the offsets,
            // which are below dims·cell)
            let mut lin = 0usize;
            for d in 0..D {
                lin = lin * dims[d] + idx[d];
            }
            let phi = values[lin] as f64;
            let (mut low, mut scale) = (phi, phi.abs());
            for d in 0..D {
                let n = normals[lin * D + d] as f64;
                low += n.min(0.0) * c;
                scale += n.abs() * (dims[d] + 1) as f64 * c;
            }
            if low - 1e-5 * scale >= -(depth as f64) {
                bits[k / 64] |= 1 << (k % 64);
            }
            // the next cell, the last axis fastest
            for d in (0..D).rev() {
                idx[d] += 1;
                if idx[d] < cells[d] {
                    break;
                }
                idx[d] = 0;
            }
        }
        Some(ShallowCells {
            values: values.clone(),
            normals: normals.clone(),
            depth,
            nonnegative_outside: shape.nonnegative_outside_grid(),
            bits,
        })
    }
}
