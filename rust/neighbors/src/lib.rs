//! Cell-list radius graph for 2D and 3D particles: the neighbour search of
//! Graph Network-based Simulators (GNS; Sanchez-Gonzalez et al., "Learning to
//! Simulate Complex Physics with Graph Networks", ICML 2020, App. A).
//!
//! [`radius_graph`] connects every pair of particles closer than a radius and
//! returns the directed edges (`senders[e] -> receivers[e]`) together with the
//! relative displacement and distance of each edge, computed in the same pass.
//!
//! # Edge criterion (exact, in `f32`)
//!
//! The pair (sender `j`, receiver `i`) is an edge iff, in `f32` arithmetic and
//! in exactly this order (no fused multiply-add),
//!
//! ```text
//! d  = p_j - p_i                         (component-wise)
//! dd = d[0]*d[0] + d[1]*d[1] (+ d[2]*d[2])   (summed left to right)
//! dd <= r*r                              (r*r rounded to f32)
//! ```
//!
//! i.e. `|p_i - p_j| <= r` with `<=` like `scipy.spatial.cKDTree.query_ball_point`.
//! Because `a - b == -(b - a)` exactly in IEEE arithmetic, the relation is
//! symmetric: (j, i) is an edge iff (i, j) is.
//!
//! # Output order
//!
//! Edges are grouped by receiver, receivers in ascending index order, and
//! within one receiver the senders are in ascending index order. Indices are
//! `u32` (inputs of more than `u32::MAX` particles are rejected).
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
    /// (`"positions"`, `"radius"` or `"max_neighbors"`).
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

/// Directed radius graph, edges grouped and sorted by receiver, then sender.
///
/// All per-edge vectors have the same length `E` (the number of edges).
#[derive(Debug, Clone, PartialEq, Default)]
pub struct Graph<const D: usize> {
    /// Sender (source) particle index of each edge.
    pub senders: Vec<u32>,
    /// Receiver (destination) particle index of each edge, ascending.
    pub receivers: Vec<u32>,
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

impl<const D: usize> Graph<D> {
    /// Number of edges `E`.
    pub fn num_edges(&self) -> usize {
        self.senders.len()
    }

    /// Whether the graph has no edge.
    pub fn is_empty(&self) -> bool {
        self.senders.is_empty()
    }
}

/// Receivers handled by one rayon task. Fixed, so the work split (and thus the
/// output) does not depend on the thread count.
const CHUNK: usize = 256;

/// Most cells per particle before the cell size is grown (outlier guard).
const CELLS_PER_PARTICLE: f64 = 4.0;

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

/// Uniform grid over the bounding box of the data (cell size `>= radius`),
/// particles counting-sorted into cells (CSR layout).
struct CellList<const D: usize> {
    lo: [f64; D],
    inv_h: f64,
    dims: [usize; D],
    /// `start[c]..start[c + 1]` is the slice of `sorted_*` in cell `c`.
    start: Vec<u32>,
    /// Positions in cell order (ascending original index within a cell).
    sorted_pos: Vec<[f32; D]>,
    /// Original index of each entry of `sorted_pos`.
    sorted_idx: Vec<u32>,
}

impl<const D: usize> CellList<D> {
    /// `reach`: every pair accepted by the `f32` criterion is at most `reach`
    /// apart in exact arithmetic (may be infinite).
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
        // Cell size h >= reach, grown while the grid would be too large (an
        // outlier far away from the bulk of the particles).
        let cap = CELLS_PER_PARTICLE * n as f64 + 16.0;
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
        let inv_h = if h.is_finite() { 1.0 / h } else { 0.0 };
        let mut cl = CellList {
            lo,
            inv_h,
            dims,
            start: Vec::new(),
            sorted_pos: Vec::new(),
            sorted_idx: Vec::new(),
        };
        let ncells = total as usize;

        // Counting sort by cell id (stable: ascending index within a cell).
        let cell_of: Vec<u32> = pos.par_iter().map(|p| cl.cell_id(p) as u32).collect();
        let mut start = vec![0u32; ncells + 1];
        for &c in &cell_of {
            start[c as usize + 1] += 1;
        }
        for c in 0..ncells {
            start[c + 1] += start[c];
        }
        let mut fill = start.clone();
        let mut sorted_pos = vec![[0.0f32; D]; n];
        let mut sorted_idx = vec![0u32; n];
        for (i, &c) in cell_of.iter().enumerate() {
            let s = fill[c as usize] as usize;
            fill[c as usize] += 1;
            sorted_pos[s] = pos[i];
            sorted_idx[s] = i as u32;
        }
        cl.start = start;
        cl.sorted_pos = sorted_pos;
        cl.sorted_idx = sorted_idx;
        cl
    }

    #[inline(always)]
    fn coords(&self, p: &[f32; D]) -> [usize; D] {
        let mut c = [0usize; D];
        for k in 0..D {
            let x = ((p[k] as f64 - self.lo[k]) * self.inv_h).floor();
            // `as` saturates (NaN -> 0); clamp guards rounding at the top edge.
            c[k] = (x as usize).min(self.dims[k] - 1);
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

    #[inline(always)]
    fn cell_id(&self, p: &[f32; D]) -> usize {
        self.linear(&self.coords(p))
    }

    /// Calls `f(original_index, position)` for every particle in the 3^D cells
    /// around `p`. Cells along axis 0 are contiguous in memory, so each row of
    /// up to 3 cells is one slice.
    #[inline(always)]
    fn for_each_near(&self, p: &[f32; D], mut f: impl FnMut(u32, &[f32; D])) {
        let c = self.coords(p);
        let x_lo = c[0].saturating_sub(1);
        let x_hi = (c[0] + 1).min(self.dims[0] - 1);
        // Iterate the rows: offsets in {-1, 0, 1} along axes 1..D.
        let nrows = 3usize.pow(D as u32 - 1);
        'rows: for r in 0..nrows {
            let mut rc = c;
            let mut code = r;
            for k in 1..D {
                let o = code % 3;
                code /= 3;
                let v = c[k] + o;
                if v == 0 || v > self.dims[k] {
                    continue 'rows;
                }
                rc[k] = v - 1;
            }
            rc[0] = x_lo;
            let a = self.start[self.linear(&rc)] as usize;
            rc[0] = x_hi;
            let b = self.start[self.linear(&rc) + 1] as usize;
            for (q, j) in self.sorted_pos[a..b].iter().zip(&self.sorted_idx[a..b]) {
                f(*j, q);
            }
        }
    }
}

/// Edges of one chunk of receivers.
struct ChunkOut<const D: usize> {
    senders: Vec<u32>,
    receivers: Vec<u32>,
    displacement: Vec<[f32; D]>,
    distance: Vec<f32>,
    dropped: usize,
}

/// Concatenates the parts in order, copying them in parallel.
fn concat<T: Copy + Send + Sync>(parts: &[&[T]], zero: T) -> Vec<T> {
    let total = parts.iter().map(|p| p.len()).sum();
    let mut out = vec![zero; total];
    let mut rest: &mut [T] = &mut out;
    let mut dst = Vec::with_capacity(parts.len());
    for p in parts {
        let (head, tail) = rest.split_at_mut(p.len());
        dst.push(head);
        rest = tail;
    }
    dst.into_par_iter()
        .zip(parts.par_iter())
        .for_each(|(d, s)| d.copy_from_slice(s));
    out
}

/// Radius graph of `positions` (GNS neighbour search).
///
/// Returns every directed edge `(sender j, receiver i)` with
/// `|p_j - p_i| <= params.radius`, evaluated in `f32` exactly as
/// `d = p_j - p_i; d·d <= r*r` (see the crate docs), self-edges `(i, i)` iff
/// `params.self_edges`, grouped by receiver ascending and, within a receiver,
/// by sender ascending. `displacement[e] = p[senders[e]] - p[receivers[e]]`
/// and `distance[e] = |displacement[e]|`. With `max_neighbors = Some(k)` each
/// receiver keeps its `k` nearest senders (ties: lower sender index), still
/// listed by ascending sender; `dropped` counts the removed edges.
///
/// Works for particles anywhere (the cell grid spans the data's bounding box).
/// An empty input gives an empty graph.
///
/// # Errors
/// [`GraphError::InvalidInput`] for a non-finite position (`"positions"`),
/// more than `u32::MAX` particles (`"positions"`), a non-finite or
/// non-positive radius (`"radius"`), or `max_neighbors == Some(0)`.
pub fn radius_graph<const D: usize>(
    positions: &[[f32; D]],
    params: &GraphParams,
) -> Result<Graph<D>, GraphError> {
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
    if n == 0 {
        return Ok(Graph::default());
    }

    let rr = params.radius * params.radius;
    // Largest exact separation that can pass `dd <= rr` in f32: `d` and `dd`
    // carry a relative rounding error of a few 2^-24 (margin 1e-4), and
    // underflow of `d[k]*d[k]` lets separations below ~4e-23 pass (1e-22).
    let reach = if rr.is_finite() {
        (rr as f64).sqrt() * (1.0 + 1e-4) + 1e-22
    } else {
        f64::INFINITY
    };
    let cells = CellList::build(positions, reach);
    let cap = params.max_neighbors;
    let self_edges = params.self_edges;

    let run_chunk = |lo: usize, hi: usize| -> ChunkOut<D> {
        let mut out = ChunkOut {
            senders: Vec::new(),
            receivers: Vec::new(),
            displacement: Vec::new(),
            distance: Vec::new(),
            dropped: 0,
        };
        let mut cand: Vec<u32> = Vec::new();
        let mut keyed: Vec<u64> = Vec::new();
        for i in lo..hi {
            let pi = &positions[i];
            let iu = i as u32;
            cand.clear();
            match cap {
                None => {
                    cells.for_each_near(pi, |j, pj| {
                        if dot(&sub(pj, pi)) <= rr && (self_edges || j != iu) {
                            cand.push(j);
                        }
                    });
                }
                Some(k) => {
                    keyed.clear();
                    cells.for_each_near(pi, |j, pj| {
                        let dd = dot(&sub(pj, pi));
                        if dd <= rr && (self_edges || j != iu) {
                            // Rank by (reported distance, index); the
                            // distance is >= 0 so its bits order like it.
                            let key = ((dd.sqrt().to_bits() as u64) << 32) | j as u64;
                            keyed.push(key);
                        }
                    });
                    if keyed.len() > k {
                        keyed.select_nth_unstable(k - 1);
                        out.dropped += keyed.len() - k;
                        keyed.truncate(k);
                    }
                    cand.extend(keyed.iter().map(|&key| key as u32));
                }
            }
            cand.sort_unstable();
            for &j in &cand {
                let d = sub(&positions[j as usize], pi);
                out.senders.push(j);
                out.receivers.push(iu);
                out.displacement.push(d);
                out.distance.push(dot(&d).sqrt());
            }
        }
        out
    };

    if n <= CHUNK {
        let c = run_chunk(0, n);
        return Ok(Graph {
            senders: c.senders,
            receivers: c.receivers,
            displacement: c.displacement,
            distance: c.distance,
            dropped: c.dropped,
        });
    }
    let chunks: Vec<ChunkOut<D>> = (0..n.div_ceil(CHUNK))
        .into_par_iter()
        .map(|c| run_chunk(c * CHUNK, ((c + 1) * CHUNK).min(n)))
        .collect();
    let s: Vec<&[u32]> = chunks.iter().map(|c| c.senders.as_slice()).collect();
    let r: Vec<&[u32]> = chunks.iter().map(|c| c.receivers.as_slice()).collect();
    let dp: Vec<&[[f32; D]]> = chunks.iter().map(|c| c.displacement.as_slice()).collect();
    let ds: Vec<&[f32]> = chunks.iter().map(|c| c.distance.as_slice()).collect();
    let (senders, receivers) = rayon::join(|| concat(&s, 0), || concat(&r, 0));
    let (displacement, distance) = rayon::join(|| concat(&dp, [0.0; D]), || concat(&ds, 0.0));
    Ok(Graph {
        senders,
        receivers,
        displacement,
        distance,
        dropped: chunks.iter().map(|c| c.dropped).sum(),
    })
}
