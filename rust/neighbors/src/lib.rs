//! Cell-list radius graph for 2D and 3D particles: the neighbour search of
//! Graph Network-based Simulators (GNS; Sanchez-Gonzalez et al., "Learning to
//! Simulate Complex Physics with Graph Networks", ICML 2020, App. A).
//!
//! [`radius_graph`] connects every pair of particles closer than a radius and
//! returns the directed edges (`senders[e] -> receivers[e]`) together with the
//! relative displacement and distance of each edge.
//!
//! # Edge criterion (exact, in `f32`)
//!
//! The pair (sender `j`, receiver `i`) is an edge iff, in `f32` arithmetic and
//! in exactly this order (no fused multiply-add),
//!
//! ```text
//! d  = p_j - p_i                              (component-wise)
//! dd = d[0]*d[0] + d[1]*d[1] (+ d[2]*d[2])    (summed left to right)
//! dd <= r*r                                   (r*r rounded to f32)
//! ```
//!
//! i.e. `|p_i - p_j| <= r` with `<=` like `scipy.spatial.cKDTree.query_ball_point`.
//! Because `a - b == -(b - a)` exactly in IEEE arithmetic, the relation is
//! symmetric: (j, i) is an edge iff (i, j) is. `distance = sqrt(dd)` of the
//! same `dd`.
//!
//! # Output order and types
//!
//! Edges are grouped by receiver, receivers in ascending index order, and
//! within one receiver the senders are in ascending index order (also with a
//! `max_neighbors` cap). Indices are `u32` by default ([`radius_graph`]) or
//! any [`EdgeIndex`] type, e.g. `i64` ([`radius_graph_as`]); inputs of more
//! than `u32::MAX` particles are rejected. The number of edges can grow as
//! `N^2` when the radius covers the whole cloud.
//!
//! # Algorithm
//!
//! A uniform cell grid with cell size `>= r` spans the bounding box of the
//! data (particles may be anywhere); if that grid would have more than about
//! `4 N` cells (an outlier far away), the cell size is grown. Particles are
//! counting-sorted into the cells (CSR). Each receiver scans the `3^D`
//! surrounding cells (those farther than `r` from it are skipped; the cells of
//! a row along axis 0 are contiguous), tests the candidates in vectorisable
//! blocks and sorts the accepted senders. Phase 1 ([`Neighbors::search`])
//! finds the sorted neighbour lists; phase 2 ([`Neighbors::write`]) writes
//! the per-edge arrays in parallel, straight into caller-provided or freshly
//! allocated memory.
//!
//! # Determinism
//!
//! The work is split over receivers in fixed-size chunks with rayon; every
//! receiver's edges depend only on the input, so the output is bitwise
//! identical for any number of threads.
//!
//! The crate is safe Rust only and knows nothing of Python.

#![forbid(unsafe_code)]

use rayon::prelude::*;
use thiserror::Error;

/// Errors of the radius graph. Every invalid input yields an error, never a panic.
#[derive(Debug, Clone, PartialEq, Error)]
pub enum GraphError {
    /// An argument is malformed or out of range; `field` names it
    /// (`"positions"`, `"radius"`, `"max_neighbors"`, or `"output"` for
    /// [`Neighbors::write`]).
    #[error("{field}: {msg}")]
    InvalidInput {
        /// Name of the offending argument.
        field: &'static str,
        /// Human-readable reason.
        msg: String,
    },
}

impl GraphError {
    fn invalid(field: &'static str, msg: impl Into<String>) -> Self {
        GraphError::InvalidInput {
            field,
            msg: msg.into(),
        }
    }

    /// Name of the offending argument.
    pub fn field(&self) -> &'static str {
        match self {
            GraphError::InvalidInput { field, .. } => field,
        }
    }
}

/// Parameters of [`radius_graph`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct GraphParams {
    /// Connectivity radius `r` (same length unit as the positions), finite and `> 0`.
    /// Default `0.015` (the GNS WaterDrop / Water-2D value).
    pub radius: f32,
    /// Whether every particle gets the self-edge `(i, i)` (displacement 0,
    /// distance 0). Default `true`.
    pub self_edges: bool,
    /// Optional cap `k >= 1` on the number of incoming edges per receiver: each
    /// receiver keeps its `k` nearest senders (by the reported `f32` distance,
    /// ties broken by the lower sender index; a self-edge counts as a neighbour
    /// at distance 0). The number of removed edges is reported in
    /// [`Graph::dropped`]. Default `None` (no cap).
    pub max_neighbors: Option<usize>,
}

impl Default for GraphParams {
    fn default() -> Self {
        GraphParams {
            radius: 0.015,
            self_edges: true,
            max_neighbors: None,
        }
    }
}

impl GraphParams {
    /// Checks `radius` (finite, `> 0`) and `max_neighbors` (`>= 1` when set).
    pub fn validate(&self) -> Result<(), GraphError> {
        if !self.radius.is_finite() {
            return Err(GraphError::invalid(
                "radius",
                format!("must be finite, got {}", self.radius),
            ));
        }
        if self.radius <= 0.0 {
            return Err(GraphError::invalid(
                "radius",
                format!("must be > 0, got {}", self.radius),
            ));
        }
        if self.max_neighbors == Some(0) {
            return Err(GraphError::invalid(
                "max_neighbors",
                "must be >= 1 when given, got 0",
            ));
        }
        Ok(())
    }
}

/// Integer type of the edge index arrays of a [`Graph`]: `u32` (the default,
/// compact), or `u64` / `i64` / `usize` (e.g. `i64` to hand the arrays to
/// numpy as `int64` without a conversion pass). Indices always fit: inputs of
/// more than `u32::MAX` particles are rejected.
pub trait EdgeIndex: Copy + Send + Sync + Default + 'static {
    /// Converts a particle index (`< 2^32`) losslessly.
    fn from_u32(i: u32) -> Self;
}

impl EdgeIndex for u32 {
    #[inline(always)]
    fn from_u32(i: u32) -> Self {
        i
    }
}

impl EdgeIndex for u64 {
    #[inline(always)]
    fn from_u32(i: u32) -> Self {
        i as u64
    }
}

impl EdgeIndex for i64 {
    #[inline(always)]
    fn from_u32(i: u32) -> Self {
        i as i64
    }
}

impl EdgeIndex for usize {
    #[inline(always)]
    fn from_u32(i: u32) -> Self {
        i as usize
    }
}

/// Directed radius graph, edges grouped and sorted by receiver, then sender.
///
/// All per-edge vectors have the same length `E` (the number of edges).
/// `I` is the index type (see [`EdgeIndex`]; `u32` unless asked otherwise
/// with [`radius_graph_as`]).
#[derive(Debug, Clone, PartialEq, Default)]
pub struct Graph<const D: usize, I = u32> {
    /// Sender (source) particle index of each edge.
    pub senders: Vec<I>,
    /// Receiver (destination) particle index of each edge, ascending.
    pub receivers: Vec<I>,
    /// `p[senders[e]] - p[receivers[e]]` in `f32` (the GNS edge feature
    /// `p_i - p_j` with `i` = sender, `j` = receiver), in position units.
    pub displacement: Vec<[f32; D]>,
    /// Euclidean norm of `displacement[e]`: `sqrt(d·d)` in `f32`, with `d·d`
    /// computed exactly as in the edge criterion.
    pub distance: Vec<f32>,
    /// Number of edges within the radius removed by `max_neighbors`
    /// (0 without a cap).
    pub dropped: usize,
}

impl<const D: usize, I> Graph<D, I> {
    /// Number of edges `E`.
    pub fn num_edges(&self) -> usize {
        self.senders.len()
    }

    /// Whether the graph has no edge.
    pub fn is_empty(&self) -> bool {
        self.senders.is_empty()
    }
}

/// Receivers handled by one rayon task. Fixed, so the work split does not
/// depend on the thread count (the output does not depend on it anyway).
const CHUNK: usize = 512;

/// Most cells per particle before the cell size is grown (outlier guard).
const CELLS_PER_PARTICLE: f64 = 4.0;

/// Candidates tested per block of the vectorised distance test.
const BLOCK: usize = 64;

#[inline(always)]
fn sub<const D: usize>(a: &[f32; D], b: &[f32; D]) -> [f32; D] {
    let mut d = [0.0f32; D];
    for k in 0..D {
        d[k] = a[k] - b[k];
    }
    d
}

#[inline(always)]
fn dot<const D: usize>(d: &[f32; D]) -> f32 {
    // Left-to-right sum, the order documented in the crate docs.
    let mut s = d[0] * d[0];
    for x in &d[1..] {
        s += x * x;
    }
    s
}

/// Uniform grid over the bounding box of the data (cell size `h >= reach`),
/// particles counting-sorted into cells (CSR layout). Cells are numbered with
/// axis 0 fastest, so the cells of one row along axis 0 are contiguous.
struct CellList<const D: usize> {
    lo: [f64; D],
    inv_h: f64,
    dims: [usize; D],
    /// Squared search reach in cell units, with slack for the f64 rounding of
    /// the cell coordinates (infinite for a single cell of infinite size).
    reach2_cells: f64,
    /// `start[c]..start[c + 1]` is the slice of `sorted_*` in cell `c`.
    start: Vec<u32>,
    /// Coordinate `k` of the particles in cell order (structure of arrays;
    /// ascending original index within a cell).
    sorted: [Vec<f32>; D],
    /// Original index of each sorted particle.
    sorted_idx: Vec<u32>,
}

impl<const D: usize> CellList<D> {
    /// `reach` (> 0): every pair accepted by the `f32` criterion is at most
    /// `reach` apart in exact arithmetic (may be infinite).
    fn build(pos: &[[f32; D]], reach: f64) -> Self {
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
        // cells (an outlier far away from the bulk of the particles).
        // (Cell ids are u32.)
        let cap = (CELLS_PER_PARTICLE * n as f64 + 16.0).min(u32::MAX as f64 - 1.0);
        let count = |h: f64| -> ([f64; D], f64) {
            let mut dims = [1.0f64; D];
            let mut total = 1.0f64;
            for k in 0..D {
                dims[k] = ((hi[k] - lo[k]) / h).floor() + 1.0;
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
        let mut dims = [1usize; D];
        for k in 0..D {
            dims[k] = dims_f[k] as usize;
        }
        let (inv_h, reach2_cells) = if h.is_finite() {
            // Cell coordinates u = (p - lo) / h carry an absolute f64 error of
            // a few 1e-16 * u; 1e-12 * (max dim + 1) bounds it generously.
            let max_dim = dims.iter().copied().max().unwrap_or(1) as f64;
            let rc = reach / h + 1e-12 * (max_dim + 1.0);
            (1.0 / h, rc * rc)
        } else {
            (0.0, f64::INFINITY)
        };
        let mut cl = CellList {
            lo,
            inv_h,
            dims,
            reach2_cells,
            start: Vec::new(),
            sorted: std::array::from_fn(|_| Vec::new()),
            sorted_idx: Vec::new(),
        };
        let ncells = total as usize;

        // Counting sort by cell id (stable: ascending index within a cell).
        let cell_of: Vec<u32> = pos
            .par_iter()
            .with_min_len(4096)
            .map(|p| cl.linear(&cl.coords(p).0) as u32)
            .collect();
        let mut start = vec![0u32; ncells + 1];
        for &c in &cell_of {
            start[c as usize + 1] += 1;
        }
        for c in 0..ncells {
            start[c + 1] += start[c];
        }
        let mut fill = start.clone();
        let mut sorted_idx = vec![0u32; n];
        for (i, &c) in cell_of.iter().enumerate() {
            let s = fill[c as usize] as usize;
            fill[c as usize] += 1;
            sorted_idx[s] = i as u32;
        }
        cl.sorted =
            std::array::from_fn(|k| sorted_idx.iter().map(|&i| pos[i as usize][k]).collect());
        cl.start = start;
        cl.sorted_idx = sorted_idx;
        cl
    }

    /// Cell coordinates of `p` and its fractional position in the cell (in
    /// cell units). The one function that maps positions to cells.
    #[inline(always)]
    fn coords(&self, p: &[f32; D]) -> ([usize; D], [f64; D]) {
        let mut c = [0usize; D];
        let mut t = [0.0f64; D];
        for k in 0..D {
            // u >= 0 (p >= lo, rounding is monotonic), so truncation is
            // floor; `as` saturates and the clamp guards the top edge.
            let u = (p[k] as f64 - self.lo[k]) * self.inv_h;
            c[k] = (u as usize).min(self.dims[k] - 1);
            t[k] = u - c[k] as f64;
        }
        (c, t)
    }

    #[inline(always)]
    fn linear(&self, c: &[usize; D]) -> usize {
        let mut id = 0;
        for k in (0..D).rev() {
            id = id * self.dims[k] + c[k];
        }
        id
    }

    /// Slices of `sorted_*` (as index ranges) that may hold particles within
    /// `reach` of `p`: the 3^D cells around `p`, minus those whose box is
    /// farther than `reach` from `p`, one contiguous range per row of cells
    /// along axis 0.
    fn ranges(&self, p: &[f32; D], out: &mut Vec<(usize, usize)>) {
        out.clear();
        let (c, t) = self.coords(p);
        // Squared gap from p to the neighbour cell at offset o-1 along k;
        // None where that cell is outside the grid.
        let gap2 = |k: usize, o: usize| -> Option<f64> {
            match o {
                0 => (c[k] > 0).then(|| t[k] * t[k]),
                1 => Some(0.0),
                _ => (c[k] + 1 < self.dims[k]).then(|| {
                    let g = (1.0 - t[k]).max(0.0);
                    g * g
                }),
            }
        };
        let r2 = self.reach2_cells;
        let nrows = 3usize.pow(D as u32 - 1);
        'rows: for r in 0..nrows {
            let mut rc = c;
            let mut code = r;
            let mut s2 = 0.0f64;
            for k in 1..D {
                let o = code % 3;
                code /= 3;
                match gap2(k, o) {
                    Some(g) => s2 += g,
                    None => continue 'rows,
                }
                rc[k] = c[k] + o - 1;
            }
            if s2 > r2 {
                continue;
            }
            let near = |o: usize| gap2(0, o).is_some_and(|g| s2 + g <= r2);
            rc[0] = if near(0) { c[0] - 1 } else { c[0] };
            let a = self.start[self.linear(&rc)] as usize;
            rc[0] = if near(2) { c[0] + 1 } else { c[0] };
            let b = self.start[self.linear(&rc) + 1] as usize;
            if a < b {
                out.push((a, b));
            }
        }
    }

    /// Writes to `out[len..]` the original index of every particle of
    /// `sorted[a..b]` with `d·d <= rr` (`d = q - p`) and returns the new
    /// `len`. `out` must have room for `b - a` more entries.
    ///
    /// The squared distances are computed over blocks of [`BLOCK`] candidates
    /// (vectorisable), then compacted branch-free.
    #[inline(always)]
    fn gather(
        &self,
        p: &[f32; D],
        rr: f32,
        (a, b): (usize, usize),
        out: &mut [u32],
        mut len: usize,
        tmp: &mut Block,
    ) -> usize {
        let dd = &mut tmp.dd;
        let mut s = a;
        while s < b {
            let n = (b - s).min(BLOCK);
            let idx = &self.sorted_idx[s..s + n];
            {
                let cols: [&[f32]; D] = std::array::from_fn(|k| &self.sorted[k][s..s + n]);
                let dd = &mut dd[..n];
                for (t, x) in dd.iter_mut().enumerate() {
                    let d = cols[0][t] - p[0];
                    let mut acc = d * d;
                    for k in 1..D {
                        let d = cols[k][t] - p[k];
                        acc += d * d;
                    }
                    *x = acc;
                }
                // Branch-free compaction (the accept pattern is unpredictable).
                for (&j, &x) in idx.iter().zip(dd.iter()) {
                    out[len] = j;
                    len += (x <= rr) as usize;
                }
            }
            s += n;
        }
        len
    }
}

/// Per-block temporaries of [`CellList::gather`].
struct Block {
    dd: [f32; BLOCK],
}

/// Per-thread scratch buffers.
#[derive(Default)]
struct Scratch {
    ranges: Vec<(usize, usize)>,
    buf: Vec<u32>,
    keyed: Vec<u64>,
    bits: BitSorter,
}

/// Words of the two-level bitmap of [`sort_distinct`] (spans below
/// `64 * BITMAP_WORDS`).
const BITMAP_WORDS: usize = 4096;

/// Bitmaps of [`sort_distinct`]: `words` (one bit per index) and `summary`
/// (one bit per word, two-level variant) are all zero between uses.
struct BitSorter {
    words: Vec<u64>,
    summary: [u64; BITMAP_WORDS / 64],
}

impl Default for BitSorter {
    fn default() -> Self {
        BitSorter {
            words: Vec::new(),
            summary: [0; BITMAP_WORDS / 64],
        }
    }
}

/// Sorts distinct indices ascending. A comparison sort costs ~7 ns per
/// element for the 30-130 neighbours of a 3D receiver; a bitmap over the
/// index span is cheaper where it fits (thresholds from measurements on
/// lattice-ordered and randomly ordered clouds): a single-level bitmap for
/// spans of at most 8 words, or for lists of 32 or more when it is dense
/// (<= 2 words per element + 8); a two-level one (only touched words are
/// visited) for other lists of 32 or more with spans below 2^18; else
/// `sort_unstable`.
fn sort_distinct(v: &mut [u32], bs: &mut BitSorter) {
    let n = v.len();
    if n < 8 {
        v.sort_unstable();
        return;
    }
    let (mut lo, mut hi) = (u32::MAX, 0u32);
    for &x in v.iter() {
        lo = lo.min(x);
        hi = hi.max(x);
    }
    let span = (hi - lo) as usize;
    let words = (span >> 6) + 1;
    let mut k = 0;
    if words <= 8 || (n >= 32 && words <= 2 * n + 8) {
        // Dense enough for a single-level bitmap over the span (typical of
        // spatially coherent indices).
        bs.words.clear();
        bs.words.resize(words, 0);
        for &x in v.iter() {
            let o = (x - lo) as usize;
            bs.words[o >> 6] |= 1u64 << (o & 63);
        }
        for (w, &word) in bs.words.iter().enumerate() {
            let mut m = word;
            let base = lo as usize + 64 * w;
            while m != 0 {
                v[k] = (base + m.trailing_zeros() as usize) as u32;
                k += 1;
                m &= m - 1;
            }
        }
        bs.words.clear();
    } else if n >= 32 && words <= BITMAP_WORDS {
        // Sparse: two-level bitmap, only touched words are visited.
        if bs.words.len() < BITMAP_WORDS {
            bs.words.resize(BITMAP_WORDS, 0);
        }
        for &x in v.iter() {
            let o = (x - lo) as usize;
            let w = o >> 6;
            bs.words[w] |= 1u64 << (o & 63);
            bs.summary[w >> 6] |= 1u64 << (w & 63);
        }
        for si in 0..=(span >> 12) {
            let mut sm = std::mem::take(&mut bs.summary[si]);
            while sm != 0 {
                let w = si * 64 + sm.trailing_zeros() as usize;
                sm &= sm - 1;
                let mut m = std::mem::take(&mut bs.words[w]);
                let base = lo as usize + 64 * w;
                while m != 0 {
                    v[k] = (base + m.trailing_zeros() as usize) as u32;
                    k += 1;
                    m &= m - 1;
                }
            }
        }
    } else {
        v.sort_unstable();
        k = n;
    }
    debug_assert_eq!(k, n, "indices must be distinct");
}

/// Phase-1 result of one chunk of receivers: their sorted sender lists.
struct Found {
    senders: Vec<u32>,
    counts: Vec<u32>,
    dropped: usize,
}

/// Splits `v` into consecutive pieces of the given lengths (sum <= len).
fn split_by<'a, T>(mut v: &'a mut [T], lens: &[usize]) -> Vec<&'a mut [T]> {
    let mut out = Vec::with_capacity(lens.len());
    for &l in lens {
        let (head, tail) = v.split_at_mut(l);
        out.push(head);
        v = tail;
    }
    out
}

/// Output slices of one chunk of receivers.
struct OutChunk<'a, const D: usize, I> {
    first: usize,
    found: &'a Found,
    s: &'a mut [I],
    r: &'a mut [I],
    dp: &'a mut [[f32; D]],
    ds: &'a mut [f32],
}

impl<const D: usize, I: EdgeIndex> OutChunk<'_, D, I> {
    fn fill(self, positions: &[[f32; D]]) {
        let senders = &self.found.senders;
        for (j, dst) in senders.iter().zip(self.s.iter_mut()) {
            *dst = I::from_u32(*j);
        }
        let mut e = 0;
        for (i, &cnt) in (self.first..).zip(&self.found.counts) {
            let end = e + cnt as usize;
            self.r[e..end].fill(I::from_u32(i as u32));
            let pi = &positions[i];
            for ((&j, dp), ds) in senders[e..end]
                .iter()
                .zip(&mut self.dp[e..end])
                .zip(&mut self.ds[e..end])
            {
                let d = sub(&positions[j as usize], pi);
                *dp = d;
                *ds = dot(&d);
            }
            e = end;
        }
        // Squared distances -> distances, in one vectorisable pass.
        for x in self.ds.iter_mut() {
            *x = x.sqrt();
        }
    }
}

/// The neighbour lists of a radius graph, found but not yet written out as
/// per-edge arrays: phase 1 of [`radius_graph`].
///
/// Lets a caller allocate the output arrays itself (e.g. as numpy arrays)
/// once the number of edges is known, then fill them with
/// [`Neighbors::write`]. [`Neighbors::into_graph`] does both in one step.
pub struct Neighbors<'a, const D: usize> {
    positions: &'a [[f32; D]],
    found: Vec<Found>,
    num_edges: usize,
    dropped: usize,
}

impl<'a, const D: usize> Neighbors<'a, D> {
    /// Finds the sorted neighbour list of every receiver (see
    /// [`radius_graph`] for the criterion, order and cap).
    ///
    /// # Errors
    /// As [`radius_graph`].
    pub fn search(positions: &'a [[f32; D]], params: &GraphParams) -> Result<Self, GraphError> {
        if D == 0 {
            return Err(GraphError::invalid("positions", "dimension must be >= 1"));
        }
        params.validate()?;
        let n = positions.len();
        if n > u32::MAX as usize {
            return Err(GraphError::invalid(
                "positions",
                format!("at most {} particles are supported, got {n}", u32::MAX),
            ));
        }
        if let Some(i) = positions
            .iter()
            .position(|p| p.iter().any(|x| !x.is_finite()))
        {
            return Err(GraphError::invalid(
                "positions",
                format!("must be finite; positions[{i}] = {:?}", positions[i]),
            ));
        }
        let mut out = Neighbors {
            positions,
            found: Vec::new(),
            num_edges: 0,
            dropped: 0,
        };
        if n == 0 {
            return Ok(out);
        }

        let rr = params.radius * params.radius;
        // Largest exact separation that can pass `dd <= rr` in f32: `d` and
        // `dd` carry a relative rounding error of a few 2^-24 (margin 1e-4),
        // and underflow of `d[k]*d[k]` lets separations below ~5e-23 pass
        // (1e-22).
        let reach = if rr.is_finite() {
            (rr as f64).sqrt() * (1.0 + 1e-4) + 1e-22
        } else {
            f64::INFINITY
        };
        let cells = CellList::build(positions, reach);
        let cap = params.max_neighbors;
        let self_edges = params.self_edges;

        let find = |scratch: &mut Scratch, lo: usize, hi: usize| -> Found {
            let mut found = Found {
                senders: Vec::new(),
                counts: Vec::with_capacity(hi - lo),
                dropped: 0,
            };
            let Scratch {
                ranges,
                buf,
                keyed,
                bits,
            } = scratch;
            let mut block = Block { dd: [0.0; BLOCK] };
            for i in lo..hi {
                let pi = &positions[i];
                cells.ranges(pi, ranges);
                let total: usize = ranges.iter().map(|&(a, b)| b - a).sum();
                if buf.len() < total {
                    buf.resize(total, 0);
                }
                let mut len = 0;
                for &range in ranges.iter() {
                    len = cells.gather(pi, rr, range, buf, len, &mut block);
                }
                if !self_edges {
                    // The receiver always finds itself (d = 0); drop it.
                    if let Some(pos) = buf[..len].iter().position(|&j| j == i as u32) {
                        len -= 1;
                        buf.swap(pos, len);
                    }
                }
                let kept = match cap {
                    Some(k) if len > k => {
                        // Rank by (reported distance, index): the distance
                        // is >= 0, so its bits order like its value.
                        keyed.clear();
                        keyed.extend(buf[..len].iter().map(|&j| {
                            let dist = dot(&sub(&positions[j as usize], pi)).sqrt();
                            ((dist.to_bits() as u64) << 32) | j as u64
                        }));
                        keyed.select_nth_unstable(k - 1);
                        for (dst, &key) in buf.iter_mut().zip(&keyed[..k]) {
                            *dst = key as u32;
                        }
                        found.dropped += len - k;
                        &mut buf[..k]
                    }
                    _ => &mut buf[..len],
                };
                sort_distinct(kept, bits);
                found.senders.extend_from_slice(kept);
                found.counts.push(kept.len() as u32);
                if i == lo + 15 {
                    // Size the chunk's list from its first receivers (saves
                    // the reallocation copies; a wrong guess only costs them).
                    let est = found.senders.len() / 16 * (hi - i - 1) * 9 / 8;
                    found.senders.reserve(est);
                }
            }
            found
        };
        let nchunks = n.div_ceil(CHUNK);
        out.found = if nchunks == 1 {
            vec![find(&mut Scratch::default(), 0, n)]
        } else {
            (0..nchunks)
                .into_par_iter()
                .map_init(Scratch::default, |s, c| {
                    find(s, c * CHUNK, ((c + 1) * CHUNK).min(n))
                })
                .collect()
        };
        out.num_edges = out.found.iter().map(|f| f.senders.len()).sum();
        out.dropped = out.found.iter().map(|f| f.dropped).sum();
        Ok(out)
    }

    /// Number of edges `E`.
    pub fn num_edges(&self) -> usize {
        self.num_edges
    }

    /// Number of edges removed by `max_neighbors`.
    pub fn dropped(&self) -> usize {
        self.dropped
    }

    /// Writes the edges (as in [`Graph`]) into caller-provided slices, in
    /// parallel; every element is overwritten, so they may hold anything.
    ///
    /// # Errors
    /// [`GraphError::InvalidInput`] (field `"output"`) if a slice's length is
    /// not [`Neighbors::num_edges`].
    pub fn write<I: EdgeIndex>(
        &self,
        senders: &mut [I],
        receivers: &mut [I],
        displacement: &mut [[f32; D]],
        distance: &mut [f32],
    ) -> Result<(), GraphError> {
        let e = self.num_edges;
        let lens = [
            senders.len(),
            receivers.len(),
            displacement.len(),
            distance.len(),
        ];
        if lens.iter().any(|&l| l != e) {
            return Err(GraphError::invalid(
                "output",
                format!("slices must have length {e} (the number of edges), got {lens:?}"),
            ));
        }
        let lens: Vec<usize> = self.found.iter().map(|f| f.senders.len()).collect();
        let mut s = split_by(senders, &lens).into_iter();
        let mut r = split_by(receivers, &lens).into_iter();
        let mut dp = split_by(displacement, &lens).into_iter();
        let mut ds = split_by(distance, &lens).into_iter();
        let mut parts = Vec::with_capacity(self.found.len());
        for (c, f) in self.found.iter().enumerate() {
            if let (Some(s), Some(r), Some(dp), Some(ds)) =
                (s.next(), r.next(), dp.next(), ds.next())
            {
                parts.push(OutChunk {
                    first: c * CHUNK,
                    found: f,
                    s,
                    r,
                    dp,
                    ds,
                });
            }
        }
        let positions = self.positions;
        if parts.len() <= 1 {
            parts.into_iter().for_each(|o| o.fill(positions));
        } else {
            parts.into_par_iter().for_each(|o| o.fill(positions));
        }
        Ok(())
    }

    /// Allocates the per-edge arrays and writes the edges into them.
    pub fn into_graph<I: EdgeIndex>(self) -> Graph<D, I> {
        let e = self.num_edges;
        let mut g = Graph::<D, I> {
            senders: vec![I::default(); e],
            receivers: vec![I::default(); e],
            displacement: vec![[0.0f32; D]; e],
            distance: vec![0.0f32; e],
            dropped: self.dropped,
        };
        // Lengths match by construction.
        let written = self.write(
            &mut g.senders,
            &mut g.receivers,
            &mut g.displacement,
            &mut g.distance,
        );
        debug_assert!(written.is_ok());
        g
    }
}

/// Radius graph of `positions` (GNS neighbour search), indices as `u32`.
///
/// Returns every directed edge `(sender j, receiver i)` with
/// `|p_j - p_i| <= params.radius`, evaluated in `f32` exactly as
/// `d = p_j - p_i; d·d <= r*r` (see the crate docs), self-edges `(i, i)` iff
/// `params.self_edges`, grouped by receiver ascending and, within a receiver,
/// by sender ascending. `displacement[e] = p[senders[e]] - p[receivers[e]]`
/// and `distance[e] = |displacement[e]|`. With `max_neighbors = Some(k)` each
/// receiver keeps its `k` nearest senders (by the reported `f32` distance,
/// ties: lower sender index), still listed by ascending sender; `dropped`
/// counts the removed edges.
///
/// Works for particles anywhere (the cell grid spans the data's bounding box
/// and is coarsened if an outlier would make it too large). An empty input
/// gives an empty graph.
///
/// # Errors
/// [`GraphError::InvalidInput`] for a non-finite position (`"positions"`),
/// more than `u32::MAX` particles (`"positions"`), a non-finite or
/// non-positive radius (`"radius"`), or `max_neighbors == Some(0)`
/// (`"max_neighbors"`). Parameters are checked first.
pub fn radius_graph<const D: usize>(
    positions: &[[f32; D]],
    params: &GraphParams,
) -> Result<Graph<D>, GraphError> {
    radius_graph_as::<D, u32>(positions, params)
}

/// [`radius_graph`] with the index arrays in another integer type `I`
/// (e.g. `i64`); the edges are identical.
///
/// # Errors
/// As [`radius_graph`].
pub fn radius_graph_as<const D: usize, I: EdgeIndex>(
    positions: &[[f32; D]],
    params: &GraphParams,
) -> Result<Graph<D, I>, GraphError> {
    Ok(Neighbors::search(positions, params)?.into_graph())
}

#[cfg(test)]
mod tests {
    use super::sort_distinct;

    #[test]
    fn sort_distinct_both_paths() {
        let mut bits = super::BitSorter::default();
        let mut s = 1u64;
        let mut next = || {
            s = s
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            (s >> 33) as u32
        };
        for n in [0usize, 1, 7, 8, 9, 30, 31, 32, 33, 64, 200] {
            for span in [
                n as u32 + 1,
                300,
                511,
                512,
                4 * n as u32 + 64,
                5000,
                (1 << 18) - 1,
                1 << 18,
                1 << 20,
                u32::MAX,
            ] {
                let mut set = std::collections::BTreeSet::new();
                while set.len() < n {
                    let base = u32::MAX - span.min(u32::MAX - 1);
                    set.insert(base + next() % span.max(1));
                }
                let want: Vec<u32> = set.into_iter().collect();
                let mut v = want.clone();
                for i in (1..v.len()).rev() {
                    let j = next() as usize % (i + 1);
                    v.swap(i, j);
                }
                sort_distinct(&mut v, &mut bits);
                assert_eq!(v, want, "n {n} span {span}");
            }
        }
    }
}
