//! The sparse block grid: scratch reused across substeps, and the tables of
//! which padded nodes an output block gathers (the block sort that fills it
//! is in `block_sort.rs`).
//!
//! The domain's node lattice is tiled into blocks of `B^D` nodes (`B = 8` in
//! 2D, `4` in 3D). Only *source* blocks (those holding particles' stencil
//! base nodes) and their `+1` neighbours (*output* blocks, reached by the
//! 3-node stencil) exist in a substep, so the cost follows the particle
//! count, not the domain volume.

use crate::dim::{Dim, DimOps};
use crate::error::{MpmError, Result, human_bytes};
use crate::kernel::Cell;
use crate::material::LANES;
use crate::particles::Particle;

/// Marks an unused entry of the block lattice maps, which store `index + 1`
/// otherwise (`src_map`, while the block sort counts: the block's
/// particles): zero, so that the maps are allocated zeroed (`calloc`) and a
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

/// The windows of g2p's batches: a source block's places in the sorted
/// order, `G2P_WINDOW` at a time from its first. g2p's items start at a
/// window (`Solver::schedule` cuts a block only there), and a batch whose
/// lanes share a route (sand's in 3D, `Constitutive::shares_route`) ends at
/// every window as well as at the item's end: it so holds particles of one
/// window only, consecutive among those of its set, whichever members run
/// which pieces of the block, and a particle's bits are the same for any
/// thread count. In a block of one set the batches end there anyway
/// (sixteen particles fill one); where other materials or sets come between,
/// the batch runs with fewer lanes in use.
pub(super) const G2P_WINDOW: usize = LANES;

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
    /// The nodes of an output block that any of its present source blocks
    /// reaches, by the mask of those present (bit `s`: source block `c − s`
    /// exists): runs `(first node, length)` of consecutive nodes. Only
    /// these nodes receive mass, and g2p reads only these (its patch takes
    /// from output block `c + s` the runs of `gather_runs[s]`, inside the
    /// union by definition), so the grid update visits no other node.
    pub(super) union_runs: Vec<Vec<(u16, u16)>>,
    /// The same nodes as bits (bit `l`: node `l`; a block has at most 64).
    pub(super) union_masks: Vec<u64>,
    /// The nodes of `union_runs[mask]` that the mask's first source block
    /// (the lowest `s`) does not reach, as runs: the first gathers as
    /// `0 + x` (the sum's start, +0, and its first term), so only these start
    /// from a zero written before.
    pub(super) zero_runs: Vec<Vec<(u16, u16)>>,
    /// `below[d][k]`: the nodes of a block whose coordinate along axis `d`
    /// is below `k` (`k` in `0..=B`), as bits: the wall bands of a block.
    pub(super) below: [Vec<u64>; D],
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
    // a block's nodes fit the bits of a u64 (8² in 2D, 4³ in 3D)
    let blk_nodes = b.pow(D as u32);
    assert!(blk_nodes <= 64, "a block's nodes must fit a u64 mask");
    let bits = |nodes: &mut dyn Iterator<Item = usize>| nodes.fold(0u64, |m, l| m | (1u64 << l));
    // the output nodes that source block c − s reaches: every s_d = 0 or
    // lc_d < 2 (the rule of `gather_runs_for`)
    let region: Vec<u64> = (0..(1usize << D))
        .map(|s| {
            bits(&mut (0..blk_nodes).filter(|&l| {
                let lc = unflatten_pow2::<D>(l, log2_b);
                (0..D).all(|d| (s >> d) & 1 == 0 || lc[d] < 2)
            }))
        })
        .collect();
    let union_masks: Vec<u64> = (0..(1usize << (1usize << D)))
        .map(|mask| {
            (0..(1usize << D))
                .filter(|s| (mask >> s) & 1 == 1)
                .fold(0, |m, s| m | region[s])
        })
        .collect();
    let union_runs = union_masks.iter().map(|&m| runs_of(m)).collect();
    let zero_runs = union_masks
        .iter()
        .enumerate()
        .map(|(mask, &m)| match mask {
            0 => Vec::new(),
            _ => runs_of(m & !region[mask.trailing_zeros() as usize]),
        })
        .collect();
    let below = std::array::from_fn(|d| {
        (0..=b)
            .map(|k| {
                bits(&mut (0..b.pow(D as u32)).filter(|&l| unflatten_pow2::<D>(l, log2_b)[d] < k))
            })
            .collect()
    });
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
            union_runs,
            union_masks,
            zero_runs,
            below,
        },
    ))
}

/// The runs `(first node, length)` of consecutive set bits of `mask`.
fn runs_of(mask: u64) -> Vec<(u16, u16)> {
    let mut runs = Vec::new();
    let mut rest = mask;
    while rest != 0 {
        let first = rest.trailing_zeros();
        let len = (rest >> first).trailing_ones();
        runs.push((first as u16, len as u16));
        let run = if len == 64 {
            u64::MAX
        } else {
            ((1u64 << len) - 1) << first
        };
        rest &= !run;
    }
    runs
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

    /// The union runs of every mask cover exactly the output nodes that the
    /// gather runs of the mask's source blocks write, each node once.
    fn union_runs_are_the_gathered_nodes<const D: usize>()
    where
        Dim<D>: DimOps<D>,
    {
        let (_, st) = new_grid::<D>(64).unwrap();
        assert_eq!(st.union_runs.len(), 1 << (1 << D));
        for (mask, runs) in st.union_runs.iter().enumerate() {
            let mut want: Vec<usize> = (0..(1usize << D))
                .filter(|s| (mask >> s) & 1 == 1)
                .flat_map(|s| st.gather_runs[s].iter())
                .flat_map(|&(l, _, len)| l as usize..(l + len) as usize)
                .collect();
            want.sort();
            want.dedup();
            let got: Vec<usize> = runs
                .iter()
                .flat_map(|&(l, len)| l as usize..(l + len) as usize)
                .collect();
            assert_eq!(got, want, "D = {D}, mask = {mask:#b}");
            let bits: Vec<usize> = (0..64)
                .filter(|l| (st.union_masks[mask] >> l) & 1 == 1)
                .collect();
            assert_eq!(bits, want, "D = {D}, mask = {mask:#b} (bits)");
            // the zero runs: the union less the lowest source's gathered nodes
            let first: Vec<usize> = match mask {
                0 => Vec::new(),
                _ => st.gather_runs[mask.trailing_zeros() as usize]
                    .iter()
                    .flat_map(|&(l, _, len)| l as usize..(l + len) as usize)
                    .collect(),
            };
            let zero: Vec<usize> = st.zero_runs[mask]
                .iter()
                .flat_map(|&(l, len)| l as usize..(l + len) as usize)
                .collect();
            let rest: Vec<usize> = want
                .iter()
                .copied()
                .filter(|l| !first.contains(l))
                .collect();
            assert_eq!(zero, rest, "D = {D}, mask = {mask:#b} (zero runs)");
        }
    }

    #[test]
    fn union_runs_cover_the_gathered_nodes() {
        union_runs_are_the_gathered_nodes::<2>();
        union_runs_are_the_gathered_nodes::<3>();
    }

    #[test]
    fn gather_runs_match_the_node_rule() {
        runs_match_the_node_rule::<2>();
        runs_match_the_node_rule::<3>();
    }
}
