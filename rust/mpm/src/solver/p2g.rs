//! Stage 1 of a substep: particle-to-grid transfer (p2g).
//!
//! MLS-MPM's fused transfer (Hu et al. 2018, the "88-line" form of the
//! MLS-MPM update): each particle scatters mass and momentum to its 3^D
//! stencil nodes `i` with the quadratic B-spline weights `w_ip` (see
//! [`crate::kernel`]),
//!
//! ```text
//! m_i   += w_ip · m_p
//! (mv)_i += w_ip · [ m_p (v_p + Δt·a_ext) + A_p (x_i − x_p) ],
//! A_p    = m_p C_p − (4 Δt / Δx²) V_p τ_p
//! ```
//!
//! the APIC affine momentum `m_p C_p` (Jiang et al. 2015) and the stress
//! force of the MLS gradient approximation combined into one matrix `A_p`
//! (τ: Kirchhoff stress from [`crate::material`]; `V_p`: rest volume;
//! `a_ext`: the particle's external acceleration).
//!
//! Parallel and deterministic without atomics: each source block writes into
//! its own padded `(B+2)^D` buffer (the stencil reaches 2 nodes past the
//! block), its particles in a fixed order; `grid_update` sums the buffers.
//! The frame loop (`frame.rs`) hands the blocks to the team's threads.

use super::Solver;
use crate::dim::{Dim, DimOps};
use crate::kernel::weights;
use crate::v4::V4;

impl<const D: usize> Solver<D>
where
    Dim<D>: DimOps<D>,
{
    /// p2g of source block `si` into its padded buffer `buf` (`(B+2)^D`
    /// nodes of `[mass, momentum]`, overwritten).
    // inlined into each compiled copy of the frame loop (`crate::isa`)
    #[inline(always)]
    pub(super) fn p2g_block(&self, si: usize, buf: &mut [[f32; 4]], dt: f32) {
        let dx = self.params.dx();
        let inv_dx = 1.0 / dx;
        let stress_scale = -dt * 4.0 * inv_dx * inv_dx;
        let g = &self.grid;
        let particles = &self.particles;
        let (src_offsets, sorted, cells) = (&g.src_offsets, &g.sorted, &g.keys);
        buf.fill([0.0; 4]);
        let lo = src_offsets[si] as usize;
        let hi = src_offsets[si + 1] as usize;
        for &pi in &sorted[lo..hi] {
            let p = &particles[pi as usize];
            let cell = &cells[pi as usize];
            let (fx, w) = weights::<D>(cell);
            let base_idx = cell.pad_off as usize;
            // [mass, momentum + affine·dpos] with dpos = (o − fx)·dx, written
            // as base + Σ_c o_c·col_c (o integer offsets): 4-wide vector work
            let a_mat = (p.tau * (stress_scale * p.volume) + p.c * p.mass) * dx;
            let mom = (p.v + p.ext * dt) * p.mass;
            let q = mom - a_mat * fx;
            let mut base4 = [p.mass, 0.0, 0.0, 0.0];
            let mut cols = [[0.0f32; 4]; D];
            for r in 0..D {
                base4[1 + r] = q[r];
                for c in 0..D {
                    cols[c][1 + r] = a_mat[(r, c)];
                }
            }
            // 4-lane values (`V4`): as `[f32; 4]` loops the optimiser tracks
            // the lanes known to be zero and splits the updates below into
            // shuffles and scalar operations (same results, more instructions)
            let base4 = V4::load(&base4);
            let cols = cols.map(|c| V4::load(&c));
            // the stencil's nodes (one bounds check for all of them)
            let span = Dim::<D>::PAD_STRIDE.iter().map(|s| 2 * s).sum::<usize>() + 1;
            let nodes = &mut buf[base_idx..base_idx + span];
            let w_last = w[D - 1];
            let last = cols[D - 1];
            Dim::<D>::stencil_rows(
                &w,
                &Dim::<D>::PAD_STRIDE,
                #[inline(always)]
                |off, w_outer, o| {
                    let mut contrib = base4;
                    for c in 0..D - 1 {
                        // a zero offset's term (a constant once the loops are
                        // unrolled) is left out: adding 0·v to a finite sum
                        // changes at most a zero's sign, lost when the sum
                        // reaches a node (which starts at +0); a non-finite
                        // column makes `base4` non-finite too, in the same lane
                        if o[c] != 0.0 {
                            contrib = contrib + o[c] * cols[c];
                        }
                    }
                    // the row's 3 nodes are contiguous (last stride 1)
                    let row = &mut nodes[off..off + 3];
                    for k in 0..3 {
                        row[k] = (V4::load(&row[k]) + (w_outer * w_last[k]) * contrib).to_array();
                        contrib = contrib + last;
                    }
                },
            );
        }
    }
}
