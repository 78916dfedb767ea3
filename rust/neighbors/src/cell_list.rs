//! The cell grid of the search ([`CellList`]) and the candidate list shared
//! by the receivers of one cell ([`Union`]).

use rayon::prelude::*;

use crate::compact::{LANES, compact};
use crate::sort::{BitSorter, insertion_sort, sort_distinct};

/// Most cells per particle before the cell size is grown (outlier guard),
/// beyond [`MIN_CELLS`]. At 4 (an earlier value), sand run out over a 3D
/// floor (1 900 particles, a bounding box of 86 000 cells of size `R`) got
/// cells 2.3 `R` wide and 6 times the candidates per receiver; at 16 they
/// are 1.4 `R` (2.2 times). More cells cost more than they save: the grid's
/// counting sort and first touch are per cell (64 per particle: 226 µs
/// against 154 for that cloud's graph).
const CELLS_PER_PARTICLE: f64 = 16.0;

/// Cells a grid may always have, whatever the number of particles.
const MIN_CELLS: f64 = 4096.0;

/// Largest exact separation that can pass `dd <= rr` in f32: `d` and `dd`
/// carry a relative rounding error of a few 2^-24 (margin 1e-4), and
/// underflow of `d[k]*d[k]` lets separations below ~5e-23 pass (1e-22).
pub(crate) fn reach(rr: f32) -> f64 {
    if rr.is_finite() {
        (rr as f64).sqrt() * (1.0 + 1e-4) + 1e-22
    } else {
        f64::INFINITY
    }
}

/// Uniform grid over the bounding box of the data (cell size `h >= reach`),
/// particles counting-sorted into cells (CSR layout). Cells are numbered with
/// axis 0 fastest, so the cells of one row along axis 0 are contiguous. The
/// grid has one empty layer of cells on every side, so the `3^D`
/// neighbourhood of an occupied cell is always inside it: its rows are fixed
/// offsets of the cell's id ([`CellList::rows`]), found without bounds tests.
pub(crate) struct CellList<const D: usize> {
    lo: [f64; D],
    inv_h: f64,
    /// Cells along each axis, the two padding layers included.
    dims: [usize; D],
    /// `start[c]..start[c + 1]` is the slice of `sorted_idx` in cell `c`.
    pub(crate) start: Vec<u32>,
    /// Original particle indices in cell order (ascending within a cell).
    pub(crate) sorted_idx: Vec<u32>,
    /// The cell of each slot of `sorted_idx` ([`CellList::cell_at`]).
    slot_cell: Vec<u32>,
    /// Coordinates in cell order (`xs[k][slot]` of particle
    /// `sorted_idx[slot]`), followed by [`LANES`] padding entries so that a
    /// row is read [`LANES`] at a time.
    xs: [Vec<f32>; D],
    /// Id offsets of the `3^(D-1)` rows of the neighbourhood, relative to
    /// the cell's id: row `r` covers cells `id + rows[r] - 1 ..= id + rows[r] + 1`.
    rows: Vec<isize>,
}

impl<const D: usize> CellList<D> {
    /// `reach` (> 0): every pair accepted by the `f32` criterion is at most
    /// `reach` apart in exact arithmetic (may be infinite).
    pub(crate) fn build(pos: &[[f32; D]], reach: f64) -> Self {
        let n = pos.len();
        let mut lo = [f64::INFINITY; D];
        let mut hi = [f64::NEG_INFINITY; D];
        for p in pos {
            for k in 0..D {
                lo[k] = lo[k].min(p[k] as f64);
                hi[k] = hi[k].max(p[k] as f64);
            }
        }
        // Cell size h >= reach, grown while the grid would have too many
        // cells (an outlier far away from the bulk of the particles). Cell
        // ids are u32.
        let cap = (CELLS_PER_PARTICLE * n as f64 + MIN_CELLS).min(u32::MAX as f64 / 2.0);
        let count = |h: f64| -> ([f64; D], f64) {
            let mut dims = [1.0f64; D];
            let mut total = 1.0f64;
            for k in 0..D {
                dims[k] = ((hi[k] - lo[k]) / h).floor() + 3.0;
                total *= dims[k];
            }
            (dims, total)
        };
        let mut h = reach;
        let (mut dims_f, mut total) = count(h);
        while total > cap {
            let grow = (total / cap).powf(1.0 / D as f64).max(1.0) * 1.01;
            h *= grow;
            (dims_f, total) = count(h);
        }
        let dims = dims_f.map(|d| d as usize);
        let mut rows = Vec::with_capacity(3usize.pow(D as u32 - 1));
        for r in 0..3usize.pow(D as u32 - 1) {
            let (mut code, mut off, mut stride) = (r, 0isize, 1isize);
            for &d in &dims[..D - 1] {
                stride *= d as isize;
                off += (code % 3) as isize * stride - stride;
                code /= 3;
            }
            rows.push(off);
        }
        let mut cl = CellList {
            lo,
            // Cell coordinates u = (p - lo) / h carry a relative f64 error of
            // ~1e-16, far inside the 1e-4 margin of `reach`: two particles
            // that pass the f32 test lie in the same or adjacent cells.
            inv_h: if h.is_finite() { 1.0 / h } else { 0.0 },
            dims,
            start: Vec::new(),
            sorted_idx: Vec::new(),
            slot_cell: Vec::new(),
            xs: std::array::from_fn(|_| Vec::new()),
            rows,
        };
        let ncells = total as usize;

        // Counting sort by cell id (stable: ascending index within a cell).
        let cell_id = |p: &[f32; D]| cl.linear(&cl.coords(p)) as u32;
        // (Cheap per particle: not worth waking the pool for small inputs.)
        let cell_of: Vec<u32> = if n < 1 << 16 {
            pos.iter().map(cell_id).collect()
        } else {
            pos.par_iter().with_min_len(1 << 14).map(cell_id).collect()
        };
        // start[c + 1] = particles in cells <= c, then every particle, taken
        // from the last, is put at its cell's end, which moves down: at the
        // end start[c] is where cell c begins and indices ascend within it.
        let mut start = vec![0u32; ncells + 1];
        for &c in &cell_of {
            start[c as usize + 1] += 1;
        }
        for c in 0..ncells {
            start[c + 1] += start[c];
        }
        let mut sorted_idx = vec![0u32; n];
        for (i, &c) in cell_of.iter().enumerate().rev() {
            let end = &mut start[c as usize + 1];
            *end -= 1;
            sorted_idx[*end as usize] = i as u32;
        }
        // start[c + 1] now holds the beginning of cell c: shift back by one.
        start.remove(0);
        start.push(n as u32);
        for (k, col) in cl.xs.iter_mut().enumerate() {
            col.reserve_exact(n + LANES);
            col.extend(sorted_idx.iter().map(|&i| pos[i as usize][k]));
            col.resize(n + LANES, 0.0);
        }
        cl.slot_cell = sorted_idx.iter().map(|&i| cell_of[i as usize]).collect();
        cl.start = start;
        cl.sorted_idx = sorted_idx;
        cl
    }

    /// Writes to `out` the particles `j` of the row ranges (of `sorted_idx`)
    /// with `d·d <= rr` (`d = p_j - p`, the crate's edge criterion), sorted
    /// ascending, and returns how many. `out` must hold the ranges' total.
    ///
    /// The squared distances are computed [`LANES`] candidates at a time
    /// (vectorisable), then compacted branch-free; the accepted list is
    /// sorted by insertion (a receiver has a few dozen neighbours at most,
    /// found in nearly ascending order along the rows).
    #[inline(always)]
    pub(crate) fn accept(
        &self,
        p: &[f32; D],
        ranges: &[(usize, usize)],
        rr: f32,
        out: &mut [u32],
    ) -> usize {
        let mut len = 0;
        for &(a, b) in ranges {
            let cols: [&[f32]; D] = std::array::from_fn(|k| &self.xs[k][a..b]);
            len = compact(cols, &self.sorted_idx[a..b], b - a, p, rr, out, len);
        }
        insertion_sort(&mut out[..len]);
        len
    }

    /// Upper bound on the number of edges: every receiver's candidates (the
    /// particles of its cell's 3^D neighbourhood, less itself without
    /// self-edges), at most `cap` each. Saturates at `u64::MAX`.
    pub(crate) fn edge_bound(&self, cap: Option<usize>, self_edges: bool) -> u64 {
        let mut ranges = Vec::new();
        let mut total = 0u64;
        let mut slot = 0;
        while slot < self.sorted_idx.len() {
            let cell = self.cell_at(slot);
            let end = self.start[cell + 1] as usize;
            let count = (end - slot) as u64;
            self.neighbourhood(cell, &mut ranges);
            let mut cand: u64 = ranges.iter().map(|&(a, b)| (b - a) as u64).sum();
            if !self_edges {
                cand -= 1;
            }
            if let Some(k) = cap {
                cand = cand.min(k as u64);
            }
            total = total.saturating_add(count.saturating_mul(cand));
            slot = end;
        }
        total
    }

    /// Cell coordinates of `p`, the padding included: the one function that
    /// maps positions to cells.
    #[inline(always)]
    pub(crate) fn coords(&self, p: &[f32; D]) -> [usize; D] {
        let mut c = [0usize; D];
        for k in 0..D {
            // u >= 0 (p >= lo, rounding is monotonic), so truncation is
            // floor; `as` saturates and the clamp guards the top edge.
            let u = (p[k] as f64 - self.lo[k]) * self.inv_h;
            c[k] = (u as usize).min(self.dims[k] - 3) + 1;
        }
        c
    }

    #[inline(always)]
    pub(crate) fn linear(&self, c: &[usize; D]) -> usize {
        let mut id = 0;
        for k in (0..D).rev() {
            id = id * self.dims[k] + c[k];
        }
        id
    }

    /// The cell of the particle at `slot` of `sorted_idx` (looked up: a
    /// binary search of `start` per cell was a fifth of a 2D search's time).
    #[inline(always)]
    pub(crate) fn cell_at(&self, slot: usize) -> usize {
        self.slot_cell[slot] as usize
    }

    /// Index ranges of `sorted_idx` covering the 3^D cells around `cell`
    /// (an occupied cell, so not in the padding), one contiguous range per
    /// row of cells along axis 0.
    #[inline(always)]
    pub(crate) fn neighbourhood(&self, cell: usize, out: &mut Vec<(usize, usize)>) {
        out.clear();
        for &off in &self.rows {
            let first = (cell as isize + off - 1) as usize;
            let a = self.start[first] as usize;
            let b = self.start[first + 3] as usize;
            if a < b {
                out.push((a, b));
            }
        }
    }
}

/// The candidate senders shared by all receivers of one cell: the particles
/// of its 3^D neighbourhood, in ascending index order, positions as SoA.
pub(crate) struct Union<const D: usize> {
    pub(crate) idx: Vec<u32>,
    pub(crate) pos: [Vec<f32>; D],
}

impl<const D: usize> Union<D> {
    pub(crate) fn build(
        &mut self,
        cells: &CellList<D>,
        positions: &[[f32; D]],
        cell: usize,
        ranges: &mut Vec<(usize, usize)>,
        bits: &mut BitSorter,
    ) {
        cells.neighbourhood(cell, ranges);
        self.idx.clear();
        for &(a, b) in ranges.iter() {
            // (a loop, not `extend_from_slice`: the rows are a few entries
            // long, shorter than a `memcpy` call costs)
            for &j in &cells.sorted_idx[a..b] {
                self.idx.push(j);
            }
        }
        sort_distinct(&mut self.idx, bits);
        for (k, col) in self.pos.iter_mut().enumerate() {
            col.clear();
            col.extend(self.idx.iter().map(|&j| positions[j as usize][k]));
        }
    }

    /// Writes to `out[..len]` the candidates `j` with `d·d <= rr`
    /// (`d = p_j - p`), in ascending order, and returns `len`. `out` must
    /// hold at least `self.idx.len()` entries.
    ///
    /// The squared distances are tested and the accepted candidates
    /// compacted by [`compact`].
    #[inline(always)]
    pub(crate) fn gather(&self, p: &[f32; D], rr: f32, out: &mut [u32]) -> usize {
        let cols: [&[f32]; D] = std::array::from_fn(|k| &self.pos[k][..]);
        compact(cols, &self.idx, self.idx.len(), p, rr, out, 0)
    }
}
