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

use rayon::prelude::*;

use super::Solver;
use crate::dim::{Dim, DimOps};
use crate::kernel::{Cell, cell_of};

/// Marks an unused entry of the block lattice maps.
pub(super) const EMPTY: u32 = u32::MAX;

/// Scratch space of the sparse block grid, reused across substeps.
pub(super) struct SparseGrid {
    /// log2 of the block edge `B` (in nodes).
    pub(super) log2_b: u32,
    /// Blocks per dimension of the block lattice.
    pub(super) nb: usize,
    /// Block lattice map: block coordinate → index in `src_blocks` (or EMPTY).
    pub(super) src_map: Vec<u32>,
    /// Block lattice map: block coordinate → index in `out_blocks` (or EMPTY).
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
    pub(super) counts: Vec<u32>,
}

/// Precomputed stencil offsets.
pub(super) struct Stencil<const D: usize> {
    /// Strides of the padded buffer (in nodes), per dimension.
    pub(super) pad_stride: [usize; D],
    /// Strides inside an output block (in nodes), per dimension.
    pub(super) blk_stride: [usize; D],
    /// Strides of the block lattice, per dimension.
    pub(super) lat_stride: [usize; D],
    /// Coordinates of each node of a padded (B+2)^D buffer.
    pub(super) pad_coords: Vec<[usize; D]>,
}

/// The empty sparse grid and the stencil offsets for `n_grid` cells per dimension.
pub(super) fn new_grid<const D: usize>(n_grid: usize) -> (SparseGrid, Stencil<D>)
where
    Dim<D>: DimOps<D>,
{
    let log2_b = <Dim<D> as DimOps<D>>::LOG2_BLOCK;
    let b = 1usize << log2_b;
    // nodes 0..=n+1 may be touched; +1 block for the stencil's reach.
    let nb = (n_grid + 2).div_ceil(b) + 1;
    let lattice = nb.pow(D as u32);
    let p = b + 2;
    let mut pad_stride = [0usize; D];
    let mut blk_stride = [0usize; D];
    let mut lat_stride = [0usize; D];
    for d in 0..D {
        pad_stride[d] = p.pow((D - 1 - d) as u32);
        blk_stride[d] = b.pow((D - 1 - d) as u32);
        lat_stride[d] = nb.pow((D - 1 - d) as u32);
    }
    let pad_nodes = p.pow(D as u32);
    let pad_coords = (0..pad_nodes)
        .map(|q| {
            let mut rem = q;
            let mut c = [0usize; D];
            for d in (0..D).rev() {
                c[d] = rem % p;
                rem /= p;
            }
            c
        })
        .collect();
    let grid = SparseGrid {
        log2_b,
        nb,
        src_map: vec![EMPTY; lattice],
        out_map: vec![EMPTY; lattice],
        src_blocks: Vec::new(),
        src_offsets: Vec::new(),
        sorted: Vec::new(),
        out_blocks: Vec::new(),
        local: Vec::new(),
        out_v: Vec::new(),
        keys: Vec::new(),
        next_keys: Vec::new(),
        counts: Vec::new(),
    };
    (
        grid,
        Stencil {
            pad_stride,
            blk_stride,
            lat_stride,
            pad_coords,
        },
    )
}

impl<const D: usize> Solver<D>
where
    Dim<D>: DimOps<D>,
{
    /// Block key of every particle (from its stencil base node).
    pub(super) fn compute_keys(&mut self) {
        let inv_dx = self.params.n_grid as f32;
        let log2_b = self.grid.log2_b;
        let lat = self.stencil.lat_stride;
        self.grid.keys.resize(self.particles.len(), Cell::default());
        self.particles
            .par_iter()
            .zip(self.grid.keys.par_iter_mut())
            .for_each(|(p, k)| {
                *k = cell_of::<D>(&p.x, inv_dx, log2_b, &lat);
            });
    }

    /// Sort particles into blocks (stable counting sort) and list output blocks.
    pub(super) fn build_blocks(&mut self) {
        let g = &mut self.grid;
        for &b in &g.src_blocks {
            g.src_map[b as usize] = EMPTY;
        }
        for &b in &g.out_blocks {
            g.out_map[b as usize] = EMPTY;
        }
        g.src_blocks.clear();
        g.out_blocks.clear();
        g.counts.clear();
        // Visit particles in id order so that the order inside each block (and
        // so every floating-point sum) depends only on the particle set.
        for &slot_id in &self.slot_of {
            let k = g.keys[slot_id as usize].key;
            let slot = &mut g.src_map[k as usize];
            if *slot == EMPTY {
                *slot = g.src_blocks.len() as u32;
                g.src_blocks.push(k);
                g.counts.push(0);
            }
            g.counts[*slot as usize] += 1;
        }
        g.src_offsets.clear();
        g.src_offsets.push(0);
        let mut acc = 0u32;
        for &c in &g.counts {
            acc += c;
            g.src_offsets.push(acc);
        }
        // reuse counts as cursors
        for (c, &o) in g.counts.iter_mut().zip(g.src_offsets.iter()) {
            *c = o;
        }
        g.sorted.resize(g.keys.len(), 0);
        for &slot_id in &self.slot_of {
            let k = g.keys[slot_id as usize].key;
            let s = g.src_map[k as usize] as usize;
            g.sorted[g.counts[s] as usize] = slot_id;
            g.counts[s] += 1;
        }
        // Output blocks: each source block and its +1 neighbours.
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
                    g.out_map[lin] = g.out_blocks.len() as u32;
                    g.out_blocks.push(lin as u32);
                }
            }
        }
    }
}

/// `acc += s·v` on 4 lanes (compiles to one vector FMA/mul-add).
#[inline(always)]
pub(super) fn fma4(acc: &mut [f32; 4], s: f32, v: &[f32; 4]) {
    for k in 0..4 {
        acc[k] += s * v[k];
    }
}

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
