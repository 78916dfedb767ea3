//! The sparse block grid (scratch reused across substeps) and the block sort
//! that starts every substep.
//!
//! The domain's node lattice is tiled into blocks of `B^D` nodes (`B = 8` in
//! 2D, `4` in 3D). Only *source* blocks (those holding particles' stencil
//! base nodes) and their `+1` neighbours (*output* blocks, reached by the
//! 3-node stencil) exist in a substep, so the cost follows the particle
//! count, not the domain volume. Particles are sorted into source blocks by a
//! stable counting sort that visits them in id order, so the order inside a
//! block — and with it every floating-point sum — depends only on the
//! particle set, never on the thread count.

use std::sync::atomic::{AtomicU32, Ordering};

use super::Solver;
use super::team::RawSlice;
use crate::dim::{Dim, DimOps};
use crate::error::{MpmError, Result, human_bytes};
use crate::kernel::Cell;
use crate::particles::Particle;

/// Marks an unused entry of the block lattice maps, which store `index + 1`
/// otherwise (`src_map`, while the block sort counts: the block's particles): zero, so that the maps are allocated zeroed (`calloc`) and a
/// large grid's pages are only touched where particles are.
pub(super) const EMPTY: u32 = 0;

/// Scratch space of the sparse block grid, reused across substeps.
pub(super) struct SparseGrid {
    /// log2 of the block edge `B` (in nodes).
    pub(super) log2_b: u32,
    /// Blocks per dimension of the block lattice.
    pub(super) nb: usize,
    /// Block lattice map: block coordinate → 1 + index in `src_blocks` (or EMPTY).
    pub(super) src_map: Vec<u32>,
    /// Block lattice map: block coordinate → 1 + index in `out_blocks` (or EMPTY).
    pub(super) out_map: Vec<u32>,
    pub(super) src_blocks: Vec<u32>,
    pub(super) src_offsets: Vec<u32>,
    pub(super) sorted: Vec<u32>,
    pub(super) out_blocks: Vec<u32>,
    /// Padded p2g buffers, one per source block: (B+2)^D nodes of [mass, momentum (D), pad].
    pub(super) local: Vec<[f32; 4]>,
    /// Grid velocities per output block: B^D nodes (padded to 4 lanes).
    pub(super) out_v: Vec<[f32; 4]>,
    /// Stencil base cell, fraction and block key of each particle (storage order).
    pub(super) keys: Vec<Cell>,
    pub(super) next_keys: Vec<Cell>,
    /// Per-chunk block counts of the block sort (more than two chunks only).
    pub(super) counts: Vec<u32>,
    /// Block key of each particle in id order (scratch of the block sort).
    pub(super) key_by_id: Vec<u32>,
    /// The order in which a substep's members claim p2g's source blocks and
    /// g2p's items ([`Solver::schedule`]) ...
    pub(super) p2g_order: Vec<u32>,
    pub(super) g2p_items: Vec<G2pItem>,
    /// ... and each member's range of them and of the output blocks
    /// (`bounds[m] .. bounds[m + 1]`, [`super::team::Team::claim_own`]).
    pub(super) p2g_bounds: Vec<u32>,
    pub(super) g2p_bounds: Vec<u32>,
    pub(super) grid_bounds: Vec<u32>,
}

/// A piece of a source block's particles that g2p hands to one member: the
/// block, and the places `first .. first + len` of the sorted order.
#[derive(Clone, Copy, Debug)]
pub(super) struct G2pItem {
    pub(super) block: u32,
    pub(super) first: u32,
    pub(super) len: u32,
}

/// One member's marks of the blocks that hold particles, set where the
/// particles' keys are computed for the next substep (the block sort's
/// first stage, fused into g2p and into a frame's first stage: no pass of
/// its own over the keys): each block's `src_map` entry counts its
/// particles (atomically: members count concurrently; `EMPTY` is a count of
/// zero), one addition per run of particles with the same key (the
/// particles come by block), and the member that finds a block empty keeps
/// its key in `touched`.
pub(super) struct BlockMarks<'a> {
    map: &'a [AtomicU32],
    last: u32,
    run: u32,
    pub(super) touched: Vec<u32>,
}

impl BlockMarks<'_> {
    /// Counts in `src_map` (a view of `grid.src_map`).
    ///
    /// # Safety
    /// While the result lives, every access to `grid.src_map` goes through
    /// a `BlockMarks` (or another atomic view), and the buffer is not
    /// reallocated.
    pub(super) unsafe fn new(src_map: RawSlice<u32>) -> Self {
        BlockMarks {
            // SAFETY: the caller's conditions
            map: unsafe { src_map.as_atomic() },
            last: 0,
            run: 0,
            touched: Vec::new(),
        }
    }

    /// One particle lies in block `key`.
    #[inline(always)]
    pub(super) fn mark(&mut self, key: u32) {
        if key == self.last {
            self.run += 1;
        } else {
            self.flush();
            self.last = key;
            self.run = 1;
        }
    }

    /// Adds the current run to its block's count.
    #[inline(always)]
    fn flush(&mut self) {
        if self.run > 0
            && self.map[self.last as usize].fetch_add(self.run, Ordering::Relaxed) == EMPTY
        {
            self.touched.push(self.last);
        }
    }

    /// The blocks this member found empty (after its last [`Self::mark`]).
    pub(super) fn finish(mut self) -> Vec<u32> {
        self.flush();
        self.touched
    }
}

/// g2p items per member a team aims at (finer items balance the members'
/// loads better, each costs a claim and, for a piece of a block, a gather
/// of the block's velocity patch) ...
const ITEMS_PER_MEMBER: usize = 8;
/// ... and the fewest particles a piece of a block holds (a multiple of the
/// sand lanes' batch, [`crate::material::sand::SandBatch`]).
const MIN_ITEM: usize = 32;

/// Precomputed stencil offsets.
pub(super) struct Stencil<const D: usize> {
    /// Strides of the block lattice, per dimension.
    pub(super) lat_stride: [usize; D],
    /// Nodes of a padded (B+2)^D buffer.
    pub(super) pad_nodes: usize,
    /// What an output block gathers from the padded buffer of its source
    /// block `c − s` (`s ∈ {0,1}^D`, bit `d` of the index): runs of nodes
    /// contiguous along the last dimension in both, as
    /// `(first node in the output block, first node in the padded buffer, length)`.
    pub(super) gather_runs: Vec<Vec<(u16, u16, u16)>>,
}

/// Blocks per dimension of the block lattice for `n_grid` cells per dimension.
fn blocks_per_side<const D: usize>(n_grid: usize) -> usize
where
    Dim<D>: DimOps<D>,
{
    let b = 1usize << <Dim<D> as DimOps<D>>::LOG2_BLOCK;
    // nodes 0..=n+1 may be touched; +1 block for the stencil's reach.
    n_grid.saturating_add(2).div_ceil(b).saturating_add(1)
}

/// Bytes of the two block-lattice maps (`src_map`, `out_map`: one `u32` per
/// block each) for `n_grid` cells per dimension; `None` beyond `u128`.
pub(super) fn lattice_bytes<const D: usize>(n_grid: usize) -> Option<u128>
where
    Dim<D>: DimOps<D>,
{
    let nb = blocks_per_side::<D>(n_grid) as u128;
    nb.checked_pow(D as u32)?.checked_mul(2 * 4)
}

/// Estimated bytes per particle (see [`Solver::bytes_per_particle`]).
pub(super) fn bytes_per_particle<const D: usize>() -> usize
where
    Dim<D>: DimOps<D>,
{
    let b = 1usize << <Dim<D> as DimOps<D>>::LOG2_BLOCK;
    let node = std::mem::size_of::<[f32; 4]>();
    // per source block: its padded p2g buffer and up to 2^D output blocks of
    // velocities; at one particle per cell a block holds b^D particles
    let per_block = (b + 2).pow(D as u32) * node + (1 << D) * b.pow(D as u32) * node;
    let per_cell = per_block.div_ceil(b.pow(D as u32));
    // state, g2p double buffer, frame rollback copy, one copy to read/write a field
    4 * std::mem::size_of::<Particle<D>>()
        // keys and next keys
        + 2 * std::mem::size_of::<Cell>()
        // ids and their g2p double buffer, slot_of, sorted, the block sort's
        // keys by id, and the rollback copies of ids and slot_of
        + 7 * std::mem::size_of::<u32>()
        + per_cell
}

/// The empty sparse grid and the stencil offsets for `n_grid` cells per
/// dimension. Errors (field `n_grid`) if the block lattice cannot be allocated.
pub(super) fn new_grid<const D: usize>(n_grid: usize) -> Result<(SparseGrid, Stencil<D>)>
where
    Dim<D>: DimOps<D>,
{
    let log2_b = <Dim<D> as DimOps<D>>::LOG2_BLOCK;
    let b = 1usize << log2_b;
    let nb = blocks_per_side::<D>(n_grid);
    let lattice = nb
        .checked_pow(D as u32)
        .filter(|&l| l < u32::MAX as usize)
        .ok_or_else(|| {
            MpmError::invalid(
                "n_grid",
                format!("{n_grid} cells per side is too large a grid"),
            )
        })?;
    let map = || -> Result<Vec<u32>> {
        // Zeroed memory (EMPTY = 0) without touching it: the allocator hands
        // out untouched zero pages (calloc); `try_reserve` turns a failed
        // allocation into an error instead of an abort.
        let mut v: Vec<u32> = Vec::new();
        v.try_reserve_exact(lattice).map_err(|_| {
            MpmError::invalid(
                "n_grid",
                format!(
                    "cannot allocate the block index of n_grid = {n_grid} ({}): out of memory",
                    human_bytes(lattice as f64 * 4.0)
                ),
            )
        })?;
        drop(v);
        Ok(vec![EMPTY; lattice])
    };
    let p = b + 2;
    // the padded buffer's strides: one definition, the constant the transfers use
    let pad_stride = <Dim<D> as DimOps<D>>::PAD_STRIDE;
    let mut blk_stride = [0usize; D];
    let mut lat_stride = [0usize; D];
    for d in 0..D {
        blk_stride[d] = b.pow((D - 1 - d) as u32);
        lat_stride[d] = nb.pow((D - 1 - d) as u32);
    }
    let pad_nodes = p.pow(D as u32);
    let gather_runs = (0..(1usize << D))
        .map(|s| gather_runs_for::<D>(s, b, &pad_stride, &blk_stride))
        .collect();
    let grid = SparseGrid {
        log2_b,
        nb,
        src_map: map()?,
        out_map: map()?,
        src_blocks: Vec::new(),
        src_offsets: Vec::new(),
        sorted: Vec::new(),
        out_blocks: Vec::new(),
        local: Vec::new(),
        out_v: Vec::new(),
        keys: Vec::new(),
        next_keys: Vec::new(),
        counts: Vec::new(),
        key_by_id: Vec::new(),
        p2g_order: Vec::new(),
        g2p_items: Vec::new(),
        p2g_bounds: Vec::new(),
        g2p_bounds: Vec::new(),
        grid_bounds: Vec::new(),
    };
    Ok((
        grid,
        Stencil {
            lat_stride,
            pad_nodes,
            gather_runs,
        },
    ))
}

/// The runs an output block gathers from the padded buffer of source block
/// `c − s`: output node `l` (block coordinates `lc`) reads padded node
/// `q = s·B + lc` where every `q_d < B + 2`, i.e. all `B` nodes along an
/// axis with `s_d = 0` and the first 2 along one with `s_d = 1`.
fn gather_runs_for<const D: usize>(
    s: usize,
    b: usize,
    pad_stride: &[usize; D],
    blk_stride: &[usize; D],
) -> Vec<(u16, u16, u16)> {
    let extent = |d: usize| if (s >> d) & 1 == 1 { 2 } else { b };
    // rows: every combination of the first D − 1 block coordinates
    let rows: usize = (0..D - 1).map(extent).product();
    let mut runs = Vec::with_capacity(rows);
    for r in 0..rows {
        let mut rem = r;
        let (mut l, mut q) = (0usize, 0usize);
        for d in (0..D - 1).rev() {
            let lc = rem % extent(d);
            rem /= extent(d);
            l += lc * blk_stride[d];
            q += (((s >> d) & 1) * b + lc) * pad_stride[d];
        }
        q += ((s >> (D - 1)) & 1) * b * pad_stride[D - 1];
        runs.push((l as u16, q as u16, extent(D - 1) as u16));
    }
    runs
}

impl<const D: usize> Solver<D>
where
    Dim<D>: DimOps<D>,
{
    // The block sort, a stable counting sort of the ids by block, in
    // stages that the frame loop (`frame.rs`) runs between barriers: the
    // blocks that hold particles are marked where their keys are computed
    // (g2p, or a frame's first stage: [`BlockMarks`]), then numbered; the ids
    // are cut into `n_chunks` contiguous ranges, each counted and scattered
    // by one thread. Inside a block the particles end up in id order
    // whatever the chunking, and blocks are numbered in key order, so the
    // result (and every sum that follows) is the same for any number of
    // threads.

    /// Sort stage 1 (serial): forget the previous substep's output blocks
    /// and size the scratch (its source blocks left `src_map` after the grid
    /// update, [`Self::forget_sources`], and the marks of this substep's are
    /// there).
    pub(super) fn sort_begin(&mut self) {
        let g = &mut self.grid;
        for &b in &g.out_blocks {
            g.out_map[b as usize] = EMPTY;
        }
        g.out_blocks.clear();
        // (`key_by_id` is sized at the frame's start and filled by g2p)
        g.sorted.resize(self.particles.len(), 0);
    }

    /// Serial, after the grid update (the last reader of the source blocks'
    /// numbers): the source blocks leave `src_map`, which g2p marks next.
    pub(super) fn forget_sources(&mut self) {
        let g = &mut self.grid;
        for &b in &g.src_blocks {
            g.src_map[b as usize] = EMPTY;
        }
    }

    /// Serial, when a frame attempt ends: the blocks its last stage marked
    /// (`touched`, emptied) leave `src_map`, so that the next frame finds it
    /// empty.
    pub(super) fn forget_marks(&mut self, touched: &mut Vec<u32>) {
        for k in touched.drain(..) {
            self.grid.src_map[k as usize] = EMPTY;
        }
    }

    /// The ids of chunk `c` of `n_chunks`.
    fn chunk_ids(&self, c: usize, n_chunks: usize) -> std::ops::Range<usize> {
        let n = self.particles.len();
        c * n / n_chunks..(c + 1) * n / n_chunks
    }

    /// Sort stage 2 (serial): number the counted blocks in key order
    /// (`touched`: every member's, emptied), their offsets in the sorted
    /// order from their counts, and zero the per-chunk counts (more than two
    /// chunks: [`Self::sort_count`]).
    pub(super) fn sort_number(&mut self, touched: &mut Vec<u32>, n_chunks: usize) {
        let g = &mut self.grid;
        touched.sort_unstable();
        g.src_offsets.clear();
        g.src_offsets.push(0);
        let mut acc = 0u32;
        for (i, &k) in touched.iter().enumerate() {
            acc += g.src_map[k as usize];
            g.src_offsets.push(acc);
            g.src_map[k as usize] = i as u32 + 1;
        }
        debug_assert_eq!(acc as usize, self.particles.len());
        g.src_blocks.clear();
        g.src_blocks.append(touched);
        g.counts.clear();
        if n_chunks > 2 {
            g.counts.resize(n_chunks * g.src_blocks.len(), 0);
        }
    }

    /// Sort stage 3 (parallel, chunk `c`; more than two chunks only): how
    /// many of the chunk's ids each block holds, into row `c` of `counts`
    /// (`n_chunks × blocks`).
    ///
    /// # Safety
    /// `counts` views `grid.counts`; nothing else may access its row `c`.
    // inlined into each compiled copy of the frame loop (`crate::isa`)
    #[inline(always)]
    pub(super) unsafe fn sort_count(&self, c: usize, n_chunks: usize, counts: RawSlice<u32>) {
        let n_src = self.grid.src_blocks.len();
        // SAFETY: row c is ours alone (caller)
        let row = unsafe { counts.chunk_mut(c * n_src, n_src) };
        let map = &self.grid.src_map;
        for &k in &self.grid.key_by_id[self.chunk_ids(c, n_chunks)] {
            row[map[k as usize] as usize - 1] += 1;
        }
    }

    /// Sort stage 4 (parallel, chunk `c`): write the chunk's slots to their
    /// places in `sorted`: block by block, and inside a block after the ids
    /// of the chunks before this one (`cursor`: scratch). With one or two
    /// chunks no counts per chunk are needed: the first fills each block
    /// from its start and the second from its end, its ids in reverse.
    ///
    /// # Safety
    /// `sorted` views `grid.sorted`; the places this chunk writes are its
    /// alone (they are, by construction), and nothing reads `sorted` meanwhile.
    // inlined into each compiled copy of the frame loop (`crate::isa`)
    #[inline(always)]
    pub(super) unsafe fn sort_scatter(
        &self,
        c: usize,
        n_chunks: usize,
        sorted: RawSlice<u32>,
        cursor: &mut Vec<u32>,
    ) {
        let g = &self.grid;
        let n_src = g.src_blocks.len();
        let ids = self.chunk_ids(c, n_chunks);
        let (keys, slots) = (&g.key_by_id[ids.clone()], &self.slot_of[ids]);
        cursor.clear();
        if n_chunks == 2 && c == 1 {
            cursor.extend_from_slice(&g.src_offsets[1..]);
            for (&k, &slot) in keys.iter().zip(slots).rev() {
                let b = g.src_map[k as usize] as usize - 1;
                cursor[b] -= 1;
                // SAFETY: place `cursor[b]` belongs to this chunk (see above)
                unsafe { sorted.write(cursor[b] as usize, slot) };
            }
            return;
        }
        cursor.extend_from_slice(&g.src_offsets[..n_src]);
        if n_chunks > 2 {
            for (b, cur) in cursor.iter_mut().enumerate() {
                for cc in 0..c {
                    *cur += g.counts[cc * n_src + b];
                }
            }
        }
        for (&k, &slot) in keys.iter().zip(slots) {
            let b = g.src_map[k as usize] as usize - 1;
            // SAFETY: place `cursor[b]` belongs to this chunk (see above)
            unsafe { sorted.write(cursor[b] as usize, slot) };
            cursor[b] += 1;
        }
    }

    /// Sort stage 5 (serial): the output blocks (each source block and its
    /// `+1` neighbours).
    pub(super) fn sort_end(&mut self) {
        let g = &mut self.grid;
        let lat = self.stencil.lat_stride;
        let nb = g.nb;
        for &b in &g.src_blocks {
            let c = unflatten::<D>(b as usize, &lat);
            for s in 0..(1usize << D) {
                let mut lin = 0usize;
                let mut ok = true;
                for d in 0..D {
                    let cd = c[d] + ((s >> d) & 1);
                    if cd >= nb {
                        ok = false;
                    }
                    lin += cd * lat[d];
                }
                if ok && g.out_map[lin] == EMPTY {
                    g.out_blocks.push(lin as u32);
                    g.out_map[lin] = g.out_blocks.len() as u32;
                }
            }
        }
    }
}

impl<const D: usize> Solver<D>
where
    Dim<D>: DimOps<D>,
{
    /// The order in which the `members` of a team claim this substep's work
    /// (after [`Self::sort_end`]), and each member's share of it. Alone,
    /// every source block whole, in key order. On a team, member `m` owns
    /// the source blocks whose particles' middle place lies in the `m`-th
    /// of `members` equal parts of the sorted order (a run of blocks in key
    /// order), g2p's pieces of those blocks and the output blocks they first
    /// reach ([`Self::sort_end`] numbers output blocks in that order): a
    /// member so works on the same particles and grid nodes in every stage
    /// and substep, which stay in its core's cache, and the others take
    /// over its items only once they have run out of their own
    /// ([`super::team::Team::claim_own`]). Inside a member's range p2g's
    /// blocks and g2p's items come largest first (the last items claimed
    /// are the small ones, so the members end close together), g2p's
    /// blocks cut into pieces of about `n / (members · ITEMS_PER_MEMBER)`
    /// particles (at least `MIN_ITEM`): a small frame has few blocks, and
    /// one large block claimed last kept the other member waiting. Which
    /// member runs which item changes no result: each block's p2g writes its
    /// own buffer, each output block its own nodes, and each particle's g2p
    /// reads only the grid and writes only its own place.
    pub(super) fn schedule(&mut self, members: usize) {
        let g = &mut self.grid;
        let n_src = g.src_blocks.len();
        let len = |b: usize| g.src_offsets[b + 1] - g.src_offsets[b];
        g.p2g_order.clear();
        g.p2g_order.extend(0..n_src as u32);
        g.g2p_items.clear();
        for bounds in [&mut g.p2g_bounds, &mut g.g2p_bounds, &mut g.grid_bounds] {
            bounds.clear();
            bounds.push(0);
        }
        if members <= 1 {
            g.g2p_items.extend((0..n_src).map(|b| G2pItem {
                block: b as u32,
                first: g.src_offsets[b],
                len: len(b),
            }));
            g.p2g_bounds.push(n_src as u32);
            g.g2p_bounds.push(n_src as u32);
            g.grid_bounds.push(g.out_blocks.len() as u32);
            return;
        }
        let n = self.particles.len() as u64;
        // the owner of block b (non-decreasing in b)
        let owner = |b: usize| {
            let mid2 = (g.src_offsets[b] + g.src_offsets[b + 1]) as u64;
            ((mid2 * members as u64) / (2 * n.max(1))).min(members as u64 - 1) as usize
        };
        let target = (n as usize / (members * ITEMS_PER_MEMBER))
            .max(MIN_ITEM)
            .next_multiple_of(16) as u32;
        let lat = self.stencil.lat_stride;
        let nb = g.nb;
        // the output blocks numbered so far (`sort_end` numbers them in the
        // order in which the source blocks, in key order, first reach them)
        let mut reached = 0u32;
        let mut b = 0;
        for m in 0..members {
            // member m's blocks, p2g's order and g2p's items
            let first_block = b;
            while b < n_src && owner(b) == m {
                let (first, total) = (g.src_offsets[b], len(b));
                let pieces = total.div_ceil(target).max(1);
                // near-equal pieces, each a multiple of 16 but the last
                let step = total.div_ceil(pieces).next_multiple_of(16);
                let mut at = 0;
                while at < total {
                    let l = step.min(total - at);
                    g.g2p_items.push(G2pItem {
                        block: b as u32,
                        first: first + at,
                        len: l,
                    });
                    at += l;
                }
                let c = unflatten::<D>(g.src_blocks[b] as usize, &lat);
                for s in 0..(1usize << D) {
                    let mut lin = 0usize;
                    let mut ok = true;
                    for d in 0..D {
                        let cd = c[d] + ((s >> d) & 1);
                        ok &= cd < nb;
                        lin += cd * lat[d];
                    }
                    if ok {
                        reached = reached.max(g.out_map[lin]);
                    }
                }
                b += 1;
            }
            // stable: equal blocks stay in key order (neighbours share grid data)
            g.p2g_order[first_block..b].sort_by_key(|&k| std::cmp::Reverse(len(k as usize)));
            let items = *g.g2p_bounds.last().expect("starts with 0") as usize;
            g.g2p_items[items..].sort_by_key(|it| std::cmp::Reverse(it.len));
            g.p2g_bounds.push(b as u32);
            g.g2p_bounds.push(g.g2p_items.len() as u32);
            g.grid_bounds.push(reached);
        }
        debug_assert_eq!(b, n_src);
        debug_assert_eq!(reached as usize, g.out_blocks.len());
    }
}

/// `acc += v` on 4 lanes.
#[inline(always)]
pub(super) fn add4(acc: &mut [f32; 4], v: &[f32; 4]) {
    for k in 0..4 {
        acc[k] += v[k];
    }
}

/// Coordinates of the linear index `lin` of a lattice with `strides`.
#[inline(always)]
pub(super) fn unflatten<const D: usize>(mut lin: usize, strides: &[usize; D]) -> [usize; D] {
    let mut c = [0usize; D];
    for d in 0..D {
        c[d] = lin / strides[d];
        lin %= strides[d];
    }
    c
}

/// Coordinates of the linear index `lin` inside a block of `2^log2_b` nodes per side.
#[inline(always)]
pub(super) fn unflatten_pow2<const D: usize>(lin: usize, log2_b: u32) -> [usize; D] {
    let mask = (1usize << log2_b) - 1;
    let mut c = [0usize; D];
    for d in 0..D {
        c[d] = (lin >> (log2_b as usize * (D - 1 - d))) & mask;
    }
    c
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The gather runs list exactly the (output node, padded node) pairs of
    /// the per-node rule `q = s·B + lc`, inside iff every `q_d < B + 2`.
    fn runs_match_the_node_rule<const D: usize>()
    where
        Dim<D>: DimOps<D>,
    {
        let (_, st) = new_grid::<D>(64).unwrap();
        let log2_b = <Dim<D> as DimOps<D>>::LOG2_BLOCK;
        let b = 1usize << log2_b;
        for s in 0..(1usize << D) {
            let mut want = Vec::new();
            for l in 0..b.pow(D as u32) {
                let lc = unflatten_pow2::<D>(l, log2_b);
                let q: Vec<usize> = (0..D).map(|d| ((s >> d) & 1) * b + lc[d]).collect();
                if q.iter().all(|&x| x < b + 2) {
                    want.push((
                        l,
                        (0..D)
                            .map(|d| q[d] * (b + 2).pow((D - 1 - d) as u32))
                            .sum::<usize>(),
                    ));
                }
            }
            let mut got = Vec::new();
            for &(l, q, len) in &st.gather_runs[s] {
                for k in 0..len as usize {
                    got.push((l as usize + k, q as usize + k));
                }
            }
            got.sort();
            assert_eq!(got, want, "D = {D}, s = {s}");
        }
    }

    #[test]
    fn gather_runs_match_the_node_rule() {
        runs_match_the_node_rule::<2>();
        runs_match_the_node_rule::<3>();
    }
}
