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
//! # Density relaxation
//!
//! The crate also holds a density relaxation ([`relax_density`],
//! [`relax_then_graph`], [`kernel_density`]): a position-based correction
//! that pushes apart particles packed denser than a rest density, run
//! between two network steps. It lives here because it reuses the neighbour
//! lists of the search: it iterates on the lists [`Neighbors::csr`] gives,
//! and [`relax_then_graph`] builds the radius graph of its result from those
//! lists and the cell list where few particles moved, searching again only
//! the ones that did.
//!
//! # Layout
//!
//! `cell_list` (the grid and a cell's shared candidates), `compact` (the
//! distance test, with the `avx512` module), `sort` (index sorts), `search`
//! (phase 1, [`Neighbors`], the buffer pool), `write` (phase 2 and
//! [`write_edges`]) and `relax` (the density relaxation).
//!
//! The crate is safe Rust but for one module, `compact::avx512` (the
//! distance test and compaction of the search sixteen candidates at a time,
//! and the rank sort of short lists: masked loads and stores within lengths
//! asserted before the call, run only on a CPU that has the instructions),
//! and knows nothing of Python.

#![deny(unsafe_code)]

mod cell_list;
mod compact;
mod relax;
mod search;
mod sort;
mod write;

pub use relax::{
    MAX_MOVE, RelaxParams, RelaxStats, RelaxedGraph, kernel_density, relax_density,
    relax_then_graph,
};
pub use search::Neighbors;
pub use write::write_edges;

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

/// The connectivity radius R (in the positions' length unit, metres in
/// hybridmpm) of the GNS WaterDrop / Water-2D datasets: [`GraphParams`]'s
/// default radius. Defined here once; the binding gives it to Python, whose
/// `hybridmpm.conventions.CONNECTIVITY_RADIUS` reads it.
pub const CONNECTIVITY_RADIUS: f32 = 0.015;

/// Parameters of [`radius_graph`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct GraphParams {
    /// Connectivity radius `r` (same length unit as the positions), finite and `> 0`.
    /// Default [`CONNECTIVITY_RADIUS`].
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
            radius: CONNECTIVITY_RADIUS,
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
pub(crate) const CHUNK: usize = 512;

/// Below these sizes a phase runs on the calling thread: handing ~1 ms of
/// work to the rayon pool (waking workers, waiting for them) cost more than
/// it saved on the 2-core reference machine (4096 particles in 2D: 0.9 ms
/// serial vs 1.3 ms through the pool). The output is the same either way.
pub const SERIAL_PARTICLES: usize = 8192;
pub(crate) const SERIAL_EDGES: usize = 1 << 18;

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
