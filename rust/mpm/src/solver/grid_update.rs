//! Stage 2 of a substep: the grid update.
//!
//! Per output block, in parallel: gather the overlapping padded p2g buffers
//! of the `2^D` source blocks that reach it, in a fixed order (so sums do not
//! depend on the thread count); turn momentum into velocity,
//! `v_i = (mv)_i / m_i + Δt·g` (explicit symplectic Euler, Hu et al. 2018);
//! then enforce the boundaries on nodes inside them:
//!
//! - colliders: nodes with `sdf < 0` get the collider's condition with its
//!   outward normal (only colliders near the block are tested); a moving
//!   collider's condition acts on the velocity relative to its own
//!   ([`crate::collider::apply_condition_moving`]);
//! - domain walls: nodes within `walls.cells` of a face of the unit domain
//!   get that face's condition and friction (`WallParams::face`: the
//!   per-face override or the all-walls default) with the face's inward
//!   normal; a corner node gets the faces' conditions one axis after the
//!   other (x, then y, then z).
//!
//! Conditions (see [`crate::collider::apply_condition`]): `Sticky` zeroes
//! the velocity, `Slip` removes its normal component, `Separate` removes
//! only an inward normal component and applies Coulomb friction.

use nalgebra::SVector;

use super::Solver;
use super::grid::{EMPTY, add4, unflatten, unflatten_pow2};
use crate::collider::{Collider, apply_condition, apply_condition_moving};
use crate::dim::{Dim, DimOps};
use crate::params::WallFace;

impl<const D: usize> Solver<D>
where
    Dim<D>: DimOps<D>,
{
    /// Grid update of output block `oi` into `out` (`B^D` nodes of
    /// `[v, 0]`, overwritten); `acc` is scratch of `B^D` nodes.
    // inlined into each compiled copy of the frame loop (`crate::isa`)
    #[inline(always)]
    pub(super) fn grid_update_block(
        &self,
        oi: usize,
        out: &mut [[f32; 4]],
        acc: &mut [[f32; 4]],
        dt: f32,
    ) {
        let b = 1usize << self.grid.log2_b;
        let blk_nodes = b.pow(D as u32);
        let p = b + 2;
        let pad_nodes = p.pow(D as u32);
        let n = self.params.n_grid;
        let dx = self.params.dx();
        let gravity = SVector::<f32, D>::from_column_slice(&self.params.gravity);
        let walls = &self.params.walls;
        // condition and friction of each wall face, [axis][side] (side 0: the lower face)
        let faces: [[WallFace; 2]; D] =
            std::array::from_fn(|d| [walls.face(d, 0), walls.face(d, 1)]);
        let colliders = &self.colliders;
        let st = &self.stencil;
        let g = &self.grid;
        let (out_blocks, src_map, local, lat, log2_b) =
            (&g.out_blocks, &g.src_map, &g.local, st.lat_stride, g.log2_b);
        let wall_lo = walls.cells;
        let wall_hi = n.saturating_sub(walls.cells);
        let c = unflatten::<D>(out_blocks[oi] as usize, &lat);
        acc.fill([0.0; 4]);
        // Gather from source blocks c - s, s ∈ {0,1}^D, in a fixed order.
        for s in 0..(1usize << D) {
            let mut lin = 0usize;
            let mut ok = true;
            for d in 0..D {
                let sd = (s >> d) & 1;
                if c[d] < sd {
                    ok = false;
                    break;
                }
                lin += (c[d] - sd) * lat[d];
            }
            if !ok {
                continue;
            }
            if src_map[lin] == EMPTY {
                continue;
            }
            let sid = src_map[lin] - 1;
            let src = &local[sid as usize * pad_nodes..(sid as usize + 1) * pad_nodes];
            for &(l, q, len) in &st.gather_runs[s] {
                let (l, q, len) = (l as usize, q as usize, len as usize);
                for (a, sv) in acc[l..l + len].iter_mut().zip(&src[q..q + len]) {
                    add4(a, sv);
                }
            }
        }
        // Block-level test: is any collider near this block?
        // each with its velocity in this frame (None: static)
        let near: Vec<(&Collider<D>, Option<SVector<f32, D>>)> = if colliders.is_empty() {
            Vec::new()
        } else {
            let mut centre = SVector::<f32, D>::zeros();
            for d in 0..D {
                centre[d] = ((c[d] << log2_b) as f32 + 0.5 * (b as f32 - 1.0)) * dx;
            }
            let half_diag = 0.5 * (b as f32) * dx * (D as f32).sqrt() + dx;
            colliders
                .iter()
                .zip(&self.collider_velocity)
                .filter(|(col, _)| col.shape.sdf(&centre) < half_diag)
                .map(|(col, v)| (col, *v))
                .collect()
        };
        let g_dt = gravity * dt;
        // a block whose nodes all lie between the wall bands, with no
        // collider near: each node's update is its velocity and gravity only
        // (the same arithmetic as below, without the per-node tests)
        let clear_of_walls = (0..D).all(|d| {
            let first = c[d] << log2_b;
            first >= wall_lo && first + b - 1 <= wall_hi
        });
        if clear_of_walls && near.is_empty() {
            for (o, a) in out[..blk_nodes].iter_mut().zip(&acc[..blk_nodes]) {
                let m = a[0];
                if m <= 0.0 {
                    *o = [0.0; 4];
                    continue;
                }
                for d in 0..D {
                    o[d] = a[1 + d] / m + g_dt[d];
                }
            }
            return;
        }
        for l in 0..blk_nodes {
            let a = &acc[l];
            let m = a[0];
            let o = &mut out[l];
            if m <= 0.0 {
                *o = [0.0; 4];
                continue;
            }
            let mut v = SVector::<f32, D>::zeros();
            for d in 0..D {
                v[d] = a[1 + d] / m;
            }
            v += g_dt;
            let lc = unflatten_pow2::<D>(l, log2_b);
            let mut gi = [0usize; D];
            for d in 0..D {
                gi[d] = (c[d] << log2_b) + lc[d];
            }
            for (col, v_obs) in &near {
                let mut xp = SVector::<f32, D>::zeros();
                for d in 0..D {
                    xp[d] = gi[d] as f32 * dx;
                }
                if col.shape.sdf(&xp) < 0.0 {
                    let nrm = col.shape.normal(&xp);
                    match v_obs {
                        None => apply_condition(&mut v, &nrm, col.condition, col.friction),
                        Some(u) => {
                            apply_condition_moving(&mut v, &nrm, col.condition, col.friction, u)
                        }
                    }
                }
            }
            for d in 0..D {
                if gi[d] < wall_lo {
                    let mut nrm = SVector::<f32, D>::zeros();
                    nrm[d] = 1.0;
                    let f = &faces[d][0];
                    apply_condition(&mut v, &nrm, f.condition, f.friction);
                } else if gi[d] > wall_hi {
                    let mut nrm = SVector::<f32, D>::zeros();
                    nrm[d] = -1.0;
                    let f = &faces[d][1];
                    apply_condition(&mut v, &nrm, f.condition, f.friction);
                }
            }
            o[..D].copy_from_slice(v.as_slice());
        }
    }
}
