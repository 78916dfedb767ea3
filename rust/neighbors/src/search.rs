//! Phase 1 of the radius graph: [`Neighbors::search`] finds every
//! receiver's sorted sender list, chunk by chunk, into buffers recycled
//! through a process-wide pool.

use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};

use rayon::prelude::*;

use crate::cell_list::{CellList, Union, reach};
#[cfg(target_arch = "x86_64")]
use crate::compact::avx512;
use crate::compact::{dot, sub};
use crate::sort::BitSorter;
use crate::{CHUNK, GraphError, GraphParams, uses_rayon};

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

/// Phase-1 result of one chunk of receivers (a range of cell-order slots):
/// their sorted sender lists, concatenated in slot order.
pub(crate) struct Found {
    pub(crate) senders: Vec<u32>,
    pub(crate) dropped: usize,
}

/// Where the sender list of one receiver is: `found[chunk].senders[start..][..len]`.
#[derive(Clone, Copy, Default)]
pub(crate) struct Loc {
    pub(crate) chunk: u32,
    pub(crate) len: u32,
    pub(crate) start: usize,
}

/// The neighbour lists of a radius graph, found but not yet written out as
/// per-edge arrays: phase 1 of [`radius_graph`].
///
/// Lets a caller allocate the output arrays itself (e.g. as numpy arrays)
/// once the number of edges is known, then fill them with
/// [`Neighbors::write`]. [`Neighbors::into_graph`] does both in one step.
///
/// [`radius_graph`]: crate::radius_graph
pub struct Neighbors<'a, const D: usize> {
    pub(crate) positions: &'a [[f32; D]],
    pub(crate) found: Vec<Found>,
    /// Per receiver (original index): its sender list.
    pub(crate) loc: Vec<Loc>,
    pub(crate) num_edges: usize,
    pub(crate) dropped: usize,
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
    ///
    /// [`radius_graph`]: crate::radius_graph
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
}

#[cfg(test)]
mod tests {
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
}
