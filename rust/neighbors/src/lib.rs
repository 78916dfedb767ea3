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
//! `N^2` when the radius covers the whole cloud: [`GraphParams::max_edges`]
//! bounds it (see "Edge budget").
//!
//! # Edge budget
//!
//! With `max_edges = Some(m)`, a graph of more than `m` edges is refused with
//! [`GraphError::InvalidInput`] naming `"radius"`, before the per-edge arrays
//! exist and without holding more than about `m` sender indices: first an
//! upper bound from the cell list (each receiver's candidates, capped by
//! `max_neighbors`); if it exceeds `m`, the search counts edges as it goes and
//! stops as soon as the count passes `m`. The decision is exact (refused iff
//! the graph has more than `m` edges) and does not depend on the thread count;
//! below the bound the search is the usual one.
//!
//! # Algorithm
//!
//! A uniform cell grid with cell size `>= r` spans the bounding box of the
//! data (particles may be anywhere), with one empty layer of cells around
//! it; if that grid would have more than about `16 N` cells (a cloud spread
//! thin, or an outlier far away), the cell size is grown. Particles are
//! counting-sorted into the cells (CSR), their coordinates copied in cell
//! order (SoA). Receivers are processed cell by cell; the candidates of a
//! cell are the particles of its `3^D` neighbourhood, one contiguous range
//! per row of cells along axis 0. In a cell of few receivers, each tests
//! its rows directly (vectorisable blocks, branch-free compaction) and sorts
//! the accepted senders; in a cell of more, the candidates are gathered and
//! sorted by index once (bitmap or comparison sort), and each receiver
//! tests that list, its accepted senders coming out in ascending order.
//! Phase 1 ([`Neighbors::search`]) finds these lists; phase 2
//! ([`Neighbors::write`]) writes the per-edge arrays in receiver order, in
//! parallel, straight into caller-provided or freshly allocated memory.
//!
//! Phase 1 keeps the sender lists as `u32` (4 bytes per edge) until phase 2;
//! those buffers are recycled through a small process-wide pool (at most
//! 64 MiB kept between calls) to avoid first-touch page faults. Small inputs
//! (below 8192 particles; [`uses_rayon`]) run on the calling thread, as
//! does the edge writing below 2^18 edges.
//!
//! # Determinism
//!
//! The work is split over receivers in fixed-size chunks with rayon; every
//! receiver's edges depend only on the input, so the output is bitwise
//! identical for any number of threads.
//!
//! The crate is safe Rust but for one module, `avx512` (the distance test
//! and compaction of the search sixteen candidates at a time: masked loads
//! and stores within lengths asserted before the call, run only on a CPU
//! that has the instructions), and knows nothing of Python.

#![deny(unsafe_code)]

use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};

mod relax;
pub use relax::{
    MAX_MOVE, RelaxParams, RelaxStats, RelaxedGraph, kernel_density, relax_density,
    relax_then_graph,
};

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
    /// Optional edge budget: a graph of more than this many edges (after
    /// `max_neighbors`) is refused with an error naming `"radius"` before its
    /// edges are stored (see the crate docs, "Edge budget"). Default `None`
    /// (no budget).
    pub max_edges: Option<usize>,
}

impl Default for GraphParams {
    fn default() -> Self {
        GraphParams {
            radius: 0.015,
            self_edges: true,
            max_neighbors: None,
            max_edges: None,
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

/// Below these sizes a phase runs on the calling thread: handing ~1 ms of
/// work to the rayon pool (waking workers, waiting for them) cost more than
/// it saved on the 2-core reference machine (4096 particles in 2D: 0.9 ms
/// serial vs 1.3 ms through the pool). The output is the same either way.
pub const SERIAL_PARTICLES: usize = 8192;
const SERIAL_EDGES: usize = 1 << 18;

/// Whether the crate's functions ([`radius_graph`], [`Neighbors`],
/// [`relax_density`], [`kernel_density`]) on `particles` particles hand
/// work to rayon; below [`SERIAL_PARTICLES`] they run on the calling thread
/// and never touch a rayon pool, whatever the edge count. A caller that runs
/// them inside a pool of its own can skip entering it when this is false:
/// entering one wakes a worker, about 15-35 µs on the 2-core machine, as
/// much as a 500-particle radius graph takes (0.03 ms).
pub fn uses_rayon(particles: usize) -> bool {
    particles >= SERIAL_PARTICLES
}

/// Most cells per particle before the cell size is grown (outlier guard),
/// beyond [`MIN_CELLS`]. At 4 (until 2026-11-24), sand run out over a 3D
/// floor (1 900 particles, a bounding box of 86 000 cells of size `R`) got
/// cells 2.3 `R` wide and 6 times the candidates per receiver; at 16 they
/// are 1.4 `R` (2.2 times). More cells cost more than they save: the grid's
/// counting sort and first touch are per cell (64 per particle: 226 µs
/// against 154 for that cloud's graph).
const CELLS_PER_PARTICLE: f64 = 16.0;

/// Cells a grid may always have, whatever the number of particles.
const MIN_CELLS: f64 = 4096.0;

/// Candidates of a row tested at a time ([`CellList::accept`]).
const LANES: usize = 8;

/// Receivers in a cell from which their candidates are gathered and sorted
/// once for all ([`Union`]); below, each receiver tests its rows directly
/// ([`CellList::accept`]). Sorting a union costs about 40 instructions per
/// candidate, so it pays only when shared: radius graphs of network states
/// (one thread, µs; thresholds 0 / 4 / never) sand3d run out, 1.4 particles
/// per occupied cell: 307 / 171 / 159; sand3d and water3d at rest: 322 /
/// 289 / 390 and 314 / 292 / 367; dam break 2D: 222 / 218 / 327.
const UNION_RECEIVERS: usize = 4;

/// [`UNION_RECEIVERS`] where the direct tests run on the portable code;
/// with the AVX-512 compaction and rank sort the direct tests win in every
/// cell (`relax_then_graph` on network states, µs, threshold 4 / 8 /
/// never: dam break 697–703 / 666–687 / 663–666 and 1 281–1 300 / 1 212–1 223
/// / 1 217; sand3d run out 749 / 704–710 / 713–717, at rest 276–279 / 262–267
/// / 264–268; water3d 1 537–1 576 / 1 498–1 548 / 1 461–1 508), so the union
/// is not built there.
fn union_receivers() -> usize {
    #[cfg(target_arch = "x86_64")]
    if avx512::available() {
        return usize::MAX;
    }
    UNION_RECEIVERS
}

/// Sorts a short list of distinct indices ascending (a receiver's accepted
/// senders, a few dozen): up to 64 by rank with AVX-512 where the CPU has it
/// (no data-dependent branches: the insertion sort's comparisons mispredict,
/// a quarter of a 3D search's time by `perf annotate`), else by insertion;
/// longer ones by `sort_unstable`.
fn insertion_sort(v: &mut [u32]) {
    if v.len() > 64 {
        v.sort_unstable();
        return;
    }
    #[cfg(target_arch = "x86_64")]
    if v.len() > 1 && avx512::available() {
        // SAFETY: the CPU has AVX-512F (checked); at most 64 entries.
        #[allow(unsafe_code)]
        unsafe {
            avx512::rank_sort(v)
        };
        return;
    }
    insertion_sort_portable(v);
}

/// The insertion sort of [`insertion_sort`] (any length).
fn insertion_sort_portable(v: &mut [u32]) {
    for i in 1..v.len() {
        let x = v[i];
        let mut k = i;
        while k > 0 && v[k - 1] > x {
            v[k] = v[k - 1];
            k -= 1;
        }
        v[k] = x;
    }
}

/// Appends to `out[len..]`, in order, the `idx[t]` (`t < n`) whose squared
/// distance to `p`, `Σ_k (cols[k][t] - p[k])²` summed left to right without
/// fused multiply-adds (the crate's criterion), is at most `rr`; returns the
/// new length. `cols[k]` and `idx` hold at least `n` entries, `out` at least
/// `len + n`. Sixteen candidates at a time with AVX-512 (a compare mask and
/// a compress) where the CPU has it, else [`LANES`] at a time, compacted
/// branch-free: the same candidates either way (same operations, same order).
#[inline(always)]
fn compact<const D: usize>(
    cols: [&[f32]; D],
    idx: &[u32],
    n: usize,
    p: &[f32; D],
    rr: f32,
    out: &mut [u32],
    len: usize,
) -> usize {
    assert!(idx.len() >= n && cols.iter().all(|c| c.len() >= n) && out.len() >= len + n);
    #[cfg(target_arch = "x86_64")]
    if avx512::available() {
        // SAFETY: the CPU has AVX-512F/VL (checked); lengths asserted above.
        #[allow(unsafe_code)]
        return unsafe { avx512::compact(cols, idx, n, p, rr, out, len) };
    }
    compact_portable(cols, idx, n, p, rr, out, len)
}

/// [`compact`] without SIMD intrinsics (the reference of the AVX-512 copy).
#[inline(always)]
fn compact_portable<const D: usize>(
    cols: [&[f32]; D],
    idx: &[u32],
    n: usize,
    p: &[f32; D],
    rr: f32,
    out: &mut [u32],
    mut len: usize,
) -> usize {
    let mut t = 0;
    while t < n {
        let m = (n - t).min(LANES);
        let mut dd = [0.0f32; LANES];
        for (l, x) in dd.iter_mut().enumerate().take(m) {
            let d = cols[0][t + l] - p[0];
            let mut acc = d * d;
            for k in 1..D {
                let d = cols[k][t + l] - p[k];
                acc += d * d;
            }
            *x = acc;
        }
        // branch-free compaction (the accept pattern is unpredictable)
        for (&j, &x) in idx[t..t + m].iter().zip(&dd) {
            out[len] = j;
            len += (x <= rr) as usize;
        }
        t += LANES;
    }
    len
}

#[cfg(target_arch = "x86_64")]
#[allow(unsafe_code)]
mod avx512 {
    use std::arch::x86_64::*;
    use std::sync::OnceLock;

    /// Whether the CPU has AVX-512F and VL, and `HYBRIDMPM_ISA` allows
    /// x86-64-v4 (`hybridmpm-isa`'s vocabulary, shared with the MPM frame
    /// loop and the network kernels; `baseline` and `x86-64-v3`/`avx2` keep
    /// the portable code). Read once per process.
    pub(super) fn available() -> bool {
        static ON: OnceLock<bool> = OnceLock::new();
        *ON.get_or_init(|| {
            hybridmpm_isa::Level::X86_64V4.allows() && hybridmpm_isa::cpu::avx512f_vl()
        })
    }

    /// [`super::compact`], sixteen candidates at a time.
    ///
    /// # Safety
    /// The CPU must have AVX-512F and VL; `cols[k]` and `idx` hold at least
    /// `n` entries, `out` at least `len + n`.
    #[target_feature(enable = "avx512f,avx512vl,popcnt")]
    pub(super) unsafe fn compact<const D: usize>(
        cols: [&[f32]; D],
        idx: &[u32],
        n: usize,
        p: &[f32; D],
        rr: f32,
        out: &mut [u32],
        mut len: usize,
    ) -> usize {
        let limit = _mm512_set1_ps(rr);
        let mut t = 0;
        while t < n {
            let m = (n - t).min(16);
            let live: __mmask16 = if m == 16 { u16::MAX } else { (1u16 << m) - 1 };
            // SAFETY (all loads and the store): masked to the `m` entries left,
            // which the slices hold (caller); masked-off lanes are not accessed.
            unsafe {
                let x = _mm512_maskz_loadu_ps(live, cols[0].as_ptr().add(t));
                let d = _mm512_sub_ps(x, _mm512_set1_ps(p[0]));
                let mut acc = _mm512_mul_ps(d, d);
                for k in 1..D {
                    let x = _mm512_maskz_loadu_ps(live, cols[k].as_ptr().add(t));
                    let d = _mm512_sub_ps(x, _mm512_set1_ps(p[k]));
                    acc = _mm512_add_ps(acc, _mm512_mul_ps(d, d));
                }
                let hit = _mm512_mask_cmp_ps_mask::<_CMP_LE_OQ>(live, acc, limit);
                let j = _mm512_maskz_loadu_epi32(live, idx.as_ptr().add(t) as *const i32);
                let kept = _mm512_maskz_compress_epi32(hit, j);
                let count = hit.count_ones() as usize;
                let first: __mmask16 = if count == 16 {
                    u16::MAX
                } else {
                    (1u16 << count) - 1
                };
                _mm512_mask_storeu_epi32(out.as_mut_ptr().add(len) as *mut i32, first, kept);
                len += count;
            }
            t += 16;
        }
        len
    }

    /// Sorts up to 64 distinct values ascending without branches on the
    /// data: each value's rank is the number of values below it (compare
    /// masks against the list held in up to four registers, counted), and
    /// it is stored at its rank.
    ///
    /// # Safety
    /// The CPU must have AVX-512F; `v.len() <= 64` and the values distinct.
    #[target_feature(enable = "avx512f,popcnt")]
    pub(super) unsafe fn rank_sort(v: &mut [u32]) {
        let n = v.len();
        assert!(n <= 64);
        let used = n.div_ceil(16);
        let pad = _mm512_set1_epi32(-1); // u32::MAX: never below a value
        let mut vecs = [pad; 4];
        let mut copy = [0u32; 64];
        for (q, vq) in vecs.iter_mut().enumerate().take(used) {
            let m = (n - 16 * q).min(16);
            let live: __mmask16 = if m == 16 { u16::MAX } else { (1u16 << m) - 1 };
            // SAFETY: masked to the `m` entries of `v` from 16·q; `copy` holds 64.
            unsafe {
                *vq = _mm512_mask_loadu_epi32(pad, live, v.as_ptr().add(16 * q) as *const i32);
                _mm512_storeu_si512(copy.as_mut_ptr().add(16 * q) as *mut __m512i, *vq);
            }
        }
        for &x in &copy[..n] {
            let b = _mm512_set1_epi32(x as i32);
            let mut rank = 0u32;
            for vq in &vecs[..used] {
                rank += _mm512_cmplt_epu32_mask(*vq, b).count_ones();
            }
            v[rank as usize] = x;
        }
        debug_assert!(
            v.windows(2).all(|w| w[0] < w[1]),
            "rank_sort: values must be distinct"
        );
    }
}

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

/// Largest exact separation that can pass `dd <= rr` in f32: `d` and `dd`
/// carry a relative rounding error of a few 2^-24 (margin 1e-4), and
/// underflow of `d[k]*d[k]` lets separations below ~5e-23 pass (1e-22).
fn reach(rr: f32) -> f64 {
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
struct CellList<const D: usize> {
    lo: [f64; D],
    inv_h: f64,
    /// Cells along each axis, the two padding layers included.
    dims: [usize; D],
    /// `start[c]..start[c + 1]` is the slice of `sorted_idx` in cell `c`.
    start: Vec<u32>,
    /// Original particle indices in cell order (ascending within a cell).
    sorted_idx: Vec<u32>,
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
    fn accept(&self, p: &[f32; D], ranges: &[(usize, usize)], rr: f32, out: &mut [u32]) -> usize {
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
    fn edge_bound(&self, cap: Option<usize>, self_edges: bool) -> u64 {
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
    fn coords(&self, p: &[f32; D]) -> [usize; D] {
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
    fn linear(&self, c: &[usize; D]) -> usize {
        let mut id = 0;
        for k in (0..D).rev() {
            id = id * self.dims[k] + c[k];
        }
        id
    }

    /// The cell of the particle at `slot` of `sorted_idx` (looked up: a
    /// binary search of `start` per cell was a fifth of a 2D search's time).
    #[inline(always)]
    fn cell_at(&self, slot: usize) -> usize {
        self.slot_cell[slot] as usize
    }

    /// Index ranges of `sorted_idx` covering the 3^D cells around `cell`
    /// (an occupied cell, so not in the padding), one contiguous range per
    /// row of cells along axis 0.
    #[inline(always)]
    fn neighbourhood(&self, cell: usize, out: &mut Vec<(usize, usize)>) {
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
struct Union<const D: usize> {
    idx: Vec<u32>,
    pos: [Vec<f32>; D],
}

impl<const D: usize> Union<D> {
    fn build(
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
    fn gather(&self, p: &[f32; D], rr: f32, out: &mut [u32]) -> usize {
        let cols: [&[f32]; D] = std::array::from_fn(|k| &self.pos[k][..]);
        compact(cols, &self.idx, self.idx.len(), p, rr, out, 0)
    }
}

/// Per-thread scratch buffers.
struct Scratch<const D: usize> {
    ranges: Vec<(usize, usize)>,
    union: Union<D>,
    buf: Vec<u32>,
    keyed: Vec<u64>,
    bits: BitSorter,
}

impl<const D: usize> Default for Scratch<D> {
    fn default() -> Self {
        Scratch {
            ranges: Vec::new(),
            union: Union {
                idx: Vec::new(),
                pos: std::array::from_fn(|_| Vec::new()),
            },
            buf: Vec::new(),
            keyed: Vec::new(),
            bits: BitSorter::default(),
        }
    }
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

/// Phase-1 result of one chunk of receivers (a range of cell-order slots):
/// their sorted sender lists, concatenated in slot order.
struct Found {
    senders: Vec<u32>,
    dropped: usize,
}

/// Where the sender list of one receiver is: `found[chunk].senders[start..][..len]`.
#[derive(Clone, Copy, Default)]
struct Loc {
    chunk: u32,
    len: u32,
    start: usize,
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

/// Output slices of one chunk of receivers (in index order).
struct OutChunk<'a, const D: usize, I> {
    first: usize,
    s: &'a mut [I],
    r: &'a mut [I],
    dp: &'a mut [[f32; D]],
    ds: &'a mut [f32],
}

impl<const D: usize, I: EdgeIndex> OutChunk<'_, D, I> {
    fn fill(self, positions: &[[f32; D]], found: &[Found], loc: &[Loc]) {
        let mut e = 0;
        for (i, l) in (self.first..).zip(loc) {
            let end = e + l.len as usize;
            let list = &found[l.chunk as usize].senders[l.start..l.start + l.len as usize];
            for (dst, &j) in self.s[e..end].iter_mut().zip(list) {
                *dst = I::from_u32(j);
            }
            self.r[e..end].fill(I::from_u32(i as u32));
            let pi = &positions[i];
            for ((&j, dp), ds) in list
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
    /// Per receiver (original index): its sender list.
    loc: Vec<Loc>,
    num_edges: usize,
    dropped: usize,
}

impl<const D: usize> Drop for Neighbors<'_, D> {
    fn drop(&mut self) {
        pool::give(self.found.drain(..).map(|f| f.senders));
    }
}

/// Process-wide pool of phase-1 sender buffers, reused across calls: fresh
/// memory costs a page fault per 4 KiB on first touch (about 3 ms of a 20 ms
/// search for 2.2 M edges). Retains at most [`pool::MAX_BYTES`] of buffer
/// capacity; contents never outlive a call, so results are unaffected.
mod pool {
    use std::sync::Mutex;

    /// Cap on the capacity held between calls.
    pub const MAX_BYTES: usize = 64 << 20;

    static POOL: Mutex<Vec<Vec<u32>>> = Mutex::new(Vec::new());

    /// An empty buffer, with capacity if one is pooled.
    pub fn take() -> Vec<u32> {
        match POOL.lock() {
            Ok(mut p) => p.pop().unwrap_or_default(),
            Err(_) => Vec::new(),
        }
    }

    /// Returns buffers to the pool while it holds less than `MAX_BYTES`.
    pub fn give(bufs: impl Iterator<Item = Vec<u32>>) {
        if let Ok(mut p) = POOL.lock() {
            let mut held: usize = p.iter().map(|b| b.capacity() * 4).sum();
            for mut b in bufs {
                let bytes = b.capacity() * 4;
                if bytes == 0 || held + bytes > MAX_BYTES {
                    continue;
                }
                held += bytes;
                b.clear();
                p.push(b);
            }
        }
    }
}

impl<'a, const D: usize> Neighbors<'a, D> {
    /// Finds the sorted neighbour list of every receiver (see
    /// [`radius_graph`] for the criterion, order and cap).
    ///
    /// Receivers are processed cell by cell: the candidates of a cell (its
    /// 3^D neighbourhood) are gathered and sorted by index once, so each
    /// receiver's accepted senders come out already in ascending order.
    ///
    /// # Errors
    /// As [`radius_graph`].
    pub fn search(positions: &'a [[f32; D]], params: &GraphParams) -> Result<Self, GraphError> {
        Self::search_with(positions, params, union_receivers())
    }

    /// [`Neighbors::search`] with cells of `union_from` receivers or more
    /// searched through their shared candidate list (tests take both paths).
    fn search_with(
        positions: &'a [[f32; D]],
        params: &GraphParams,
        union_from: usize,
    ) -> Result<Self, GraphError> {
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
            loc: Vec::new(),
            num_edges: 0,
            dropped: 0,
        };
        if n == 0 {
            return Ok(out);
        }

        let rr = params.radius * params.radius;
        let cells = CellList::build(positions, reach(rr));
        let cap = params.max_neighbors;
        let self_edges = params.self_edges;
        // Edge budget: count as we go only if the cell-list bound exceeds it
        // (not even the bound is needed when N · min(N, cap) fits).
        let per_receiver = cap.map_or(n, |k| k.min(n)) as u128;
        let bound = match params.max_edges {
            Some(m) if (n as u128) * per_receiver > m as u128 => cells.edge_bound(cap, self_edges),
            _ => 0,
        };
        let limit = params.max_edges.filter(|&m| bound > m as u64);
        let counted = AtomicUsize::new(0);
        let over = AtomicBool::new(false);

        // Chunk `c` handles the receivers in cell-order slots
        // [c * CHUNK, (c + 1) * CHUNK); a cell cut by a chunk boundary builds
        // its candidate union in both chunks.
        let find = |scratch: &mut Scratch<D>, lo: usize, hi: usize| -> (Found, Vec<u32>) {
            let mut found = Found {
                senders: pool::take(),
                dropped: 0,
            };
            let mut lens = Vec::with_capacity(hi - lo);
            let Scratch {
                ranges,
                union,
                buf,
                keyed,
                bits,
            } = scratch;
            let mut slot = lo;
            'cells: while slot < hi {
                // the cell of the next receiver (empty cells are never visited)
                let cell = cells.cell_at(slot);
                let cell_end = (cells.start[cell + 1] as usize).min(hi);
                // A cell of few receivers tests each one's rows directly and
                // sorts what it accepts; one of more builds their common
                // candidate list once, sorted, so accepted senders come out
                // in order (UNION_RECEIVERS).
                let direct = cell_end - slot < union_from;
                if direct {
                    cells.neighbourhood(cell, ranges);
                    let total: usize = ranges.iter().map(|&(a, b)| b - a).sum();
                    if buf.len() < total {
                        buf.resize(total, 0);
                    }
                } else {
                    union.build(&cells, positions, cell, ranges, bits);
                    if buf.len() < union.idx.len() {
                        buf.resize(union.idx.len(), 0);
                    }
                }
                for &iu in &cells.sorted_idx[slot..cell_end] {
                    let pi = &positions[iu as usize];
                    let mut len = if direct {
                        cells.accept(pi, ranges, rr, buf)
                    } else {
                        union.gather(pi, rr, buf)
                    };
                    if !self_edges {
                        // The receiver always finds itself (d = 0).
                        if let Ok(pos) = buf[..len].binary_search(&iu) {
                            buf.copy_within(pos + 1..len, pos);
                            len -= 1;
                        }
                    }
                    if let Some(k) = cap
                        && len > k
                    {
                        // Keep the k nearest by (reported distance, index):
                        // the distance is >= 0, so its bits order like it.
                        keyed.clear();
                        keyed.extend(buf[..len].iter().map(|&j| {
                            let dist = dot(&sub(&positions[j as usize], pi)).sqrt();
                            ((dist.to_bits() as u64) << 32) | j as u64
                        }));
                        keyed.select_nth_unstable(k - 1);
                        for (dst, &key) in buf.iter_mut().zip(&keyed[..k]) {
                            *dst = key as u32;
                        }
                        buf[..k].sort_unstable();
                        found.dropped += len - k;
                        len = k;
                    }
                    if let Some(m) = limit {
                        // Count the edges; stop once the graph is over budget
                        // (before storing them).
                        if counted
                            .fetch_add(len, Ordering::Relaxed)
                            .saturating_add(len)
                            > m
                            || over.load(Ordering::Relaxed)
                        {
                            over.store(true, Ordering::Relaxed);
                            break 'cells;
                        }
                    }
                    found.senders.extend_from_slice(&buf[..len]);
                    lens.push(len as u32);
                    if lens.len() == 16 {
                        // Size the chunk's list from its first receivers
                        // (saves reallocation copies; a bad guess costs them),
                        // never beyond the edge budget.
                        let mut est = (found.senders.len() / 16)
                            .saturating_mul(hi - lo - 16)
                            .saturating_mul(9)
                            / 8;
                        if let Some(m) = limit {
                            est = est.min(m.saturating_sub(counted.load(Ordering::Relaxed)));
                        }
                        found.senders.reserve(est);
                    }
                }
                slot = cell_end;
            }
            (found, lens)
        };
        let nchunks = n.div_ceil(CHUNK);
        let results: Vec<(Found, Vec<u32>)> = if !uses_rayon(n) {
            vec![find(&mut Scratch::default(), 0, n)]
        } else {
            (0..nchunks)
                .into_par_iter()
                .map_init(Scratch::default, |s, c| {
                    find(s, c * CHUNK, ((c + 1) * CHUNK).min(n))
                })
                .collect()
        };

        if over.load(Ordering::Relaxed) {
            let m = limit.unwrap_or(0);
            pool::give(results.into_iter().map(|(f, _)| f.senders));
            return Err(GraphError::invalid(
                "radius",
                format!(
                    "radius {} gives more than max_edges = {m} edges ({} particles; the cell list bounds the graph at {bound} edges); use a smaller radius, set max_neighbors, or raise max_edges",
                    params.radius, n
                ),
            ));
        }

        // Where each receiver's list is, by original index.
        let mut loc = vec![Loc::default(); n];
        let mut slot = 0;
        for (c, (found, lens)) in results.iter().enumerate() {
            let mut start = 0;
            for &len in lens {
                loc[cells.sorted_idx[slot] as usize] = Loc {
                    chunk: c as u32,
                    len,
                    start,
                };
                start += len as usize;
                slot += 1;
            }
            out.dropped += found.dropped;
            out.num_edges += found.senders.len();
        }
        out.found = results.into_iter().map(|(f, _)| f).collect();
        out.loc = loc;
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

    /// The sender lists as CSR: `senders[offsets[i]..offsets[i + 1]]` are
    /// receiver `i`'s senders, ascending (the edges of [`Neighbors::write`]
    /// in the same order, without their geometry).
    pub fn csr(&self) -> (Vec<usize>, Vec<u32>) {
        let mut offsets = Vec::with_capacity(self.loc.len() + 1);
        let mut senders = Vec::with_capacity(self.num_edges);
        offsets.push(0);
        for l in &self.loc {
            let list = &self.found[l.chunk as usize].senders[l.start..l.start + l.len as usize];
            senders.extend_from_slice(list);
            offsets.push(senders.len());
        }
        (offsets, senders)
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
        check_output(
            e,
            [
                senders.len(),
                receivers.len(),
                displacement.len(),
                distance.len(),
            ],
        )?;
        // Receivers in index order, CHUNK at a time.
        let lens: Vec<usize> = self
            .loc
            .chunks(CHUNK)
            .map(|c| c.iter().map(|l| l.len as usize).sum())
            .collect();
        let mut s = split_by(senders, &lens).into_iter();
        let mut r = split_by(receivers, &lens).into_iter();
        let mut dp = split_by(displacement, &lens).into_iter();
        let mut ds = split_by(distance, &lens).into_iter();
        let mut parts = Vec::with_capacity(lens.len());
        for c in 0..lens.len() {
            if let (Some(s), Some(r), Some(dp), Some(ds)) =
                (s.next(), r.next(), dp.next(), ds.next())
            {
                parts.push((
                    OutChunk {
                        first: c * CHUNK,
                        s,
                        r,
                        dp,
                        ds,
                    },
                    c,
                ));
            }
        }
        let (positions, found) = (self.positions, &self.found[..]);
        let run = |(o, c): (OutChunk<'_, D, I>, usize)| {
            let loc = &self.loc[c * CHUNK..((c + 1) * CHUNK).min(self.loc.len())];
            o.fill(positions, found, loc);
        };
        if !uses_rayon(self.positions.len()) || e < SERIAL_EDGES {
            parts.into_iter().for_each(run);
        } else {
            parts.into_par_iter().for_each(run);
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

/// The output slices' lengths against the number of edges `e`.
fn check_output(e: usize, lens: [usize; 4]) -> Result<(), GraphError> {
    if lens.iter().any(|&l| l != e) {
        return Err(GraphError::invalid(
            "output",
            format!("slices must have length {e} (the number of edges), got {lens:?}"),
        ));
    }
    Ok(())
}

/// Writes the edges of neighbour lists in CSR form (receiver `i`'s senders
/// `senders[offsets[i]..offsets[i + 1]]`, as [`Neighbors::csr`] gives them)
/// as [`Neighbors::write`] does: senders, receivers, `p[sender] -
/// p[receiver]` and its length, in receiver order.
///
/// # Errors
/// [`GraphError::InvalidInput`] (field `"output"`) if a slice's length is
/// not the number of edges or `offsets` does not fit `positions`.
pub fn write_edges<const D: usize, I: EdgeIndex>(
    positions: &[[f32; D]],
    offsets: &[usize],
    senders: &[u32],
    out_senders: &mut [I],
    out_receivers: &mut [I],
    displacement: &mut [[f32; D]],
    distance: &mut [f32],
) -> Result<(), GraphError> {
    let e = senders.len();
    check_output(
        e,
        [
            out_senders.len(),
            out_receivers.len(),
            displacement.len(),
            distance.len(),
        ],
    )?;
    let n = positions.len();
    if offsets.len() != n + 1
        || offsets.first() != Some(&0)
        || offsets.last() != Some(&e)
        || offsets.windows(2).any(|w| w[0] > w[1])
        || senders.iter().any(|&j| j as usize >= n)
    {
        return Err(GraphError::invalid(
            "output",
            format!("offsets must ascend from 0 to {e} over {n} particles and senders be < {n}"),
        ));
    }
    for i in 0..positions.len() {
        let (a, b) = (offsets[i], offsets[i + 1]);
        let pi = &positions[i];
        for e in a..b {
            let j = senders[e];
            out_senders[e] = I::from_u32(j);
            out_receivers[e] = I::from_u32(i as u32);
            let d = sub(&positions[j as usize], pi);
            displacement[e] = d;
            distance[e] = dot(&d);
        }
    }
    for x in distance.iter_mut() {
        *x = x.sqrt();
    }
    Ok(())
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

    /// The sort of a receiver's accepted senders, for every length up to 70
    /// (the AVX-512 rank sort up to 64 where the CPU has it, `sort_unstable`
    /// above), against a plain sort, with values near `u32::MAX` (the rank
    /// sort's padding).
    #[test]
    fn short_sorts_sort() {
        let mut s = 9u64;
        let mut next = || {
            s = s
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            (s >> 33) as u32
        };
        for n in 0..=70usize {
            for top in [false, true] {
                let mut set = std::collections::BTreeSet::new();
                while set.len() < n {
                    let x = next() % 5000;
                    set.insert(if top { u32::MAX - x } else { x });
                }
                let want: Vec<u32> = set.into_iter().collect();
                let mut v = want.clone();
                for i in (1..v.len()).rev() {
                    let j = next() as usize % (i + 1);
                    v.swap(i, j);
                }
                let mut w = v.clone();
                super::insertion_sort(&mut v);
                assert_eq!(v, want, "n {n}");
                super::insertion_sort_portable(&mut w);
                assert_eq!(w, want, "n {n}, portable");
            }
        }
    }

    /// The two ways of searching a cell's receivers (each receiver's rows
    /// tested directly, or the cell's candidates gathered and sorted once)
    /// give the same lists, with and without self-edges and a cap, in 2D
    /// and 3D on clouds from sparse to clumped (the proptests against brute
    /// force in `tests/` cover the way the CPU runs).
    #[test]
    fn direct_and_union_searches_agree() {
        fn check<const D: usize>(seed: u64, n: usize, spread: f32) {
            let mut s = seed;
            let mut next = || {
                s = s
                    .wrapping_mul(6364136223846793005)
                    .wrapping_add(1442695040888963407);
                ((s >> 40) as f32) / (1u64 << 24) as f32
            };
            let pos: Vec<[f32; D]> = (0..n)
                .map(|_| std::array::from_fn(|_| next() * spread))
                .collect();
            for (self_edges, cap) in [(true, None), (false, None), (true, Some(5))] {
                let gp = super::GraphParams {
                    radius: 0.1,
                    self_edges,
                    max_neighbors: cap,
                    ..Default::default()
                };
                let direct = super::Neighbors::search_with(&pos, &gp, usize::MAX)
                    .unwrap()
                    .csr();
                for from in [1, 4] {
                    let union = super::Neighbors::search_with(&pos, &gp, from)
                        .unwrap()
                        .csr();
                    assert_eq!(direct, union, "D {D}, n {n}, spread {spread}, from {from}");
                }
            }
        }
        for seed in 0..4 {
            for (n, spread) in [(50, 2.0), (400, 1.0), (800, 0.3)] {
                check::<2>(seed, n, spread);
                check::<3>(seed + 10, n, spread);
            }
        }
    }

    /// The AVX-512 compaction keeps exactly the candidates of the portable
    /// one, in the same order, for every length (full and partial vectors),
    /// with candidates exactly at the radius and the output appended after
    /// existing entries; the portable one is held to the criterion itself.
    #[test]
    fn compaction_copies_agree_with_the_criterion() {
        fn check<const D: usize>(seed: u64) {
            let mut s = seed;
            let mut next = || {
                s = s
                    .wrapping_mul(6364136223846793005)
                    .wrapping_add(1442695040888963407);
                ((s >> 40) as f32) / (1u64 << 24) as f32
            };
            // on a 1/1024 grid, so that a candidate 0.25 away along an axis is at
            // squared distance 0.0625 = rr exactly (a tie, which is kept)
            let p: [f32; D] = std::array::from_fn(|_| (next() * 1024.0).floor() / 1024.0);
            let rr = 0.0625f32;
            for n in [0usize, 1, 7, 8, 15, 16, 17, 31, 33, 64, 100] {
                let mut cols: [Vec<f32>; D] =
                    std::array::from_fn(|_| (0..n).map(|_| next()).collect());
                // some candidates exactly on the sphere, some at the receiver
                for t in (0..n).step_by(5) {
                    for (k, c) in cols.iter_mut().enumerate() {
                        c[t] = p[k];
                    }
                    cols[0][t] = p[0] + 0.25;
                }
                for t in (2..n).step_by(7) {
                    for (k, c) in cols.iter_mut().enumerate() {
                        c[t] = p[k];
                    }
                }
                let idx: Vec<u32> = (0..n as u32).map(|i| 3 * i + 1).collect();
                let want: Vec<u32> = (0..n)
                    .filter(|&t| {
                        let d = cols[0][t] - p[0];
                        let mut acc = d * d;
                        for k in 1..D {
                            let d = cols[k][t] - p[k];
                            acc += d * d;
                        }
                        acc <= rr
                    })
                    .map(|t| idx[t])
                    .collect();
                let refs: [&[f32]; D] = std::array::from_fn(|k| &cols[k][..]);
                let mut out = vec![7u32; 3 + n];
                let len = super::compact_portable(refs, &idx, n, &p, rr, &mut out, 3);
                assert_eq!(&out[3..len], &want[..], "portable, D {D}, n {n}");
                assert_eq!(&out[..3], &[7, 7, 7]);
                #[cfg(target_arch = "x86_64")]
                if super::avx512::available() {
                    let mut out2 = vec![7u32; 3 + n];
                    #[allow(unsafe_code)]
                    // SAFETY: checked above; lengths as `compact` asserts.
                    let len2 =
                        unsafe { super::avx512::compact(refs, &idx, n, &p, rr, &mut out2, 3) };
                    assert_eq!(&out2[..len2], &out[..len], "AVX-512, D {D}, n {n}");
                    assert!(
                        out2[len2..].iter().all(|&v| v == 7),
                        "wrote past the kept ones"
                    );
                }
            }
        }
        for seed in 0..20 {
            check::<2>(seed);
            check::<3>(seed + 100);
        }
    }
}
