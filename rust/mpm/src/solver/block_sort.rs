//! The block sort that starts every substep, and the order in which a
//! team's members claim the substep's work.
//!
//! Particles are sorted into source blocks by a stable counting sort that
//! visits them in id order, so the order inside a block — and with it every
//! floating-point sum — depends only on the particle set, never on the
//! thread count.

use std::sync::Mutex;
use std::sync::atomic::{AtomicU32, Ordering};

use super::Solver;
use super::grid::{EMPTY, G2P_WINDOW, G2pItem, unflatten};
use super::team::RawSlice;
use crate::dim::{Dim, DimOps};

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
    touched: Vec<u32>,
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

    /// After this member's last [`Self::mark`]: the blocks it found empty
    /// join every member's (`all`, which the block sort numbers).
    pub(super) fn finish_into(mut self, all: &Mutex<Vec<u32>>) {
        self.flush();
        all.lock()
            .expect("no member panicked holding it")
            .append(&mut self.touched);
    }
}

/// g2p items per member a team aims at (finer items balance the members'
/// loads better, each costs a claim and, for a piece of a block, a gather
/// of the block's velocity patch) ...
const ITEMS_PER_MEMBER: usize = 8;
/// ... and the fewest particles a piece of a block holds (a multiple of
/// g2p's window, [`G2P_WINDOW`]).
const MIN_ITEM: usize = 32;
const _: () = assert!(MIN_ITEM.is_multiple_of(G2P_WINDOW));

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
    /// particles (at least `MIN_ITEM`), only where one of g2p's windows
    /// starts ([`G2P_WINDOW`]): a small frame has few blocks, and
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
            .next_multiple_of(G2P_WINDOW) as u32;
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
                // near-equal pieces, each whole windows of g2p but the last
                // (a piece so starts at a window: `G2P_WINDOW`)
                let step = total.div_ceil(pieces).next_multiple_of(G2P_WINDOW as u32);
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
