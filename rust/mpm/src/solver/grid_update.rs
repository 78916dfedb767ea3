//! Stage 2 of a substep: the grid update.
//!
//! Per output block, in parallel: gather the overlapping padded p2g buffers
//! of the `2^D` source blocks that reach it, in a fixed order (so sums do not
//! depend on the thread count); turn momentum into velocity,
//! `v_i = (mv)_i / m_i + Δt·g` (explicit symplectic Euler, Hu et al. 2018);
//! then enforce the boundaries on nodes inside them. Only the nodes that the
//! block's present source blocks reach are zeroed, gathered and updated
//! (`Stencil::union_runs`; a block reached only by its neighbours' padding
//! has 8 to 56 of its 64 nodes so, in 3D), and the boundary tests visit only
//! the nodes of a wall band (bit masks, `Stencil::below`) unless a collider
//! is near:
//!
//! - colliders: nodes with `sdf < 0` get the collider's condition with its
//!   outward normal (only colliders near the block are tested); a moving
//!   collider's condition acts on the velocity relative to its own
//!   ([`crate::collider::apply_condition_moving`]);
//! - bodies: nodes inside a body or less than `BODY_REACH_CELLS` outside
//!   it get the `Separate` condition relative to the body's point velocity
//!   after the substep's gravity, `v + ω × r + Δt·g` (Coulomb friction on
//!   the rest), and the node's momentum
//!   change, sign flipped, is summed into the body's impulse and torque
//!   (`crate::body::ImpulseSum`: integer sums, the same bits in any order);
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
use super::grid::{EMPTY, unflatten, unflatten_pow2};
use crate::body::{BODY_REACH_CELLS, BodyPose, Coupled, ImpulseSum};
use crate::boundary::BoundaryCondition;
use crate::collider::{Collider, apply_condition, apply_condition_moving};
use crate::dim::{Dim, DimOps};
use crate::params::WallFace;
use crate::v4::V4;

impl<const D: usize> Solver<D>
where
    Dim<D>: DimOps<D>,
{
    /// Grid update of output block `oi` into `out` (`B^D` nodes of
    /// `[v, 0]`); `acc` is scratch of `B^D` nodes. Only the nodes that the
    /// block's present source blocks reach are written
    /// (`Stencil::union_runs`): the others get no mass and g2p never reads
    /// them.
    // inlined into each compiled copy of the frame loop (`crate::isa`)
    #[inline(always)]
    pub(super) fn grid_update_block(
        &self,
        oi: usize,
        out: &mut [[f32; 4]],
        acc: &mut [[f32; 4]],
        sums: &mut [ImpulseSum],
        coupled: &mut Vec<Coupled>,
        dt: f32,
    ) {
        let b = 1usize << self.grid.log2_b;
        let p = b + 2;
        let pad_nodes = p.pow(D as u32);
        let n = self.params.n_grid;
        let dx = self.params.dx();
        let gravity = SVector::<f32, D>::from_column_slice(&self.params.gravity);
        let walls = &self.params.walls;
        let colliders = &self.colliders;
        let st = &self.stencil;
        let g = &self.grid;
        let (out_blocks, src_map, local, lat, log2_b) =
            (&g.out_blocks, &g.src_map, &g.local, st.lat_stride, g.log2_b);
        let wall_lo = walls.cells;
        let wall_hi = n.saturating_sub(walls.cells);
        let c = unflatten::<D>(out_blocks[oi] as usize, &lat);
        // The source blocks c - s, s ∈ {0,1}^D, that exist (bit s of `mask`).
        let mut src_of = [0u32; 8];
        let mut mask = 0usize;
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
            if ok && src_map[lin] != EMPTY {
                src_of[s] = src_map[lin] - 1;
                mask |= 1 << s;
            }
        }
        // Only the nodes these reach get mass, and only these are read
        // (`Stencil::union_runs`): zero, gather and update those alone.
        // Each node's sum starts at +0 and adds the sources in a fixed order
        // of s (the sums do not depend on threads): the first source block
        // writes `0 + x` over its region, and the nodes outside it are zeroed.
        let runs = &st.union_runs[mask];
        for &(l, len) in &st.zero_runs[mask] {
            for a in &mut acc[l as usize..(l + len) as usize] {
                *a = [0.0; 4];
            }
        }
        for s in 0..(1usize << D) {
            if (mask >> s) & 1 == 0 {
                continue;
            }
            let first = s == mask.trailing_zeros() as usize;
            let sid = src_of[s] as usize;
            let src = &local[sid * pad_nodes..(sid + 1) * pad_nodes];
            for &(l, q, len) in &st.gather_runs[s] {
                let (l, q) = (l as usize, q as usize);
                // a run is 2 or B nodes: unrolled at those lengths
                match (len, first) {
                    (2, false) => add_run::<2, false>(&mut acc[l..], &src[q..]),
                    (4, false) => add_run::<4, false>(&mut acc[l..], &src[q..]),
                    (8, false) => add_run::<8, false>(&mut acc[l..], &src[q..]),
                    (2, true) => add_run::<2, true>(&mut acc[l..], &src[q..]),
                    (4, true) => add_run::<4, true>(&mut acc[l..], &src[q..]),
                    (8, true) => add_run::<8, true>(&mut acc[l..], &src[q..]),
                    _ => {
                        let len = len as usize;
                        for (a, sv) in acc[l..l + len].iter_mut().zip(&src[q..q + len]) {
                            let start = if first { V4::splat(0.0) } else { V4::load(a) };
                            *a = (start + V4::load(sv)).to_array();
                        }
                    }
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
        // the bodies near this block (index, pose): their nodes to
        // `BODY_REACH_CELLS` outside the surface are coupled
        let reach = BODY_REACH_CELLS * dx;
        let near_bodies: Vec<(usize, &BodyPose<D>)> = if self.bodies.is_empty() {
            Vec::new()
        } else {
            let mut centre = SVector::<f32, D>::zeros();
            for d in 0..D {
                centre[d] = ((c[d] << log2_b) as f32 + 0.5 * (b as f32 - 1.0)) * dx;
            }
            let half_diag = 0.5 * (b as f32) * dx * (D as f32).sqrt();
            self.bodies
                .poses
                .iter()
                .enumerate()
                .filter(|(_, p)| p.near(&centre, half_diag, reach))
                .collect()
        };
        let g_dt = gravity * dt;
        // gravity's velocity change in the node layout `[v, 0]` (lanes past D zero)
        let g4: [f32; 4] = std::array::from_fn(|k| if k < D { g_dt[k] } else { 0.0 });
        // Every reached node: its velocity and gravity, `v = (mv)/m + Δt·g`,
        // or zero without mass (a NaN mass is not `<= 0`: it gives NaN, as
        // the per-node form did). Lane k < D of the output is lane 1 + k of
        // the sum; the lanes past D stay zero.
        for &(l, len) in runs {
            let (l, len) = (l as usize, len as usize);
            for (o, a) in out[l..l + len].iter_mut().zip(&acc[l..l + len]) {
                let m = a[0];
                let v: [f32; 4] =
                    std::array::from_fn(|k| if k < D { a[1 + k] / m + g4[k] } else { 0.0 });
                *o = if m <= 0.0 { [0.0; 4] } else { v };
            }
        }
        // a block whose nodes all lie between the wall bands, with no
        // collider near, is done
        let clear_of_walls = (0..D).all(|d| {
            let first = c[d] << log2_b;
            first >= wall_lo && first + b - 1 <= wall_hi
        });
        if clear_of_walls && near.is_empty() && near_bodies.is_empty() {
            return;
        }
        // The boundary conditions on the nodes with mass: the colliders
        // near, then the walls, axis by axis.
        // condition and friction of each wall face, [axis][side] (side 0: the lower face)
        let faces: [[WallFace; 2]; D] =
            std::array::from_fn(|d| [walls.face(d, 0), walls.face(d, 1)]);
        // and its inward normal, built once: a normal built per node on the
        // stack (a zeroed vector, then one lane set) was read back before its
        // stores had left, a store-forwarding stall per wall node
        let normals: [[SVector<f32, D>; 2]; D] = std::array::from_fn(|d| {
            let (mut lo, mut hi) = (SVector::<f32, D>::zeros(), SVector::<f32, D>::zeros());
            // (not `-lo`: its other lanes would be −0)
            (lo[d], hi[d]) = (1.0, -1.0);
            [lo, hi]
        });
        // the nodes to visit: every reached one with a collider near, else
        // those in a wall band (node coordinate below `wall_lo` or above
        // `wall_hi` along some axis)
        let mut visit = st.union_masks[mask];
        if near.is_empty() && near_bodies.is_empty() {
            let mut band = 0u64;
            for d in 0..D {
                let first = c[d] << log2_b;
                let lo = wall_lo.saturating_sub(first).min(b);
                let hi = (wall_hi + 1).saturating_sub(first).min(b);
                band |= st.below[d][lo] | !st.below[d][hi];
            }
            visit &= band;
        }
        while visit != 0 {
            let l = visit.trailing_zeros() as usize;
            visit &= visit - 1;
            let m = acc[l][0];
            if m <= 0.0 {
                continue;
            }
            let lc = unflatten_pow2::<D>(l, log2_b);
            let mut gi = [0usize; D];
            for d in 0..D {
                gi[d] = (c[d] << log2_b) + lc[d];
            }
            let o = &mut out[l];
            let mut v = SVector::<f32, D>::from_column_slice(&o[..D]);
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
            for &(bi, pose) in &near_bodies {
                let mut xp = SVector::<f32, D>::zeros();
                for d in 0..D {
                    xp[d] = gi[d] as f32 * dx;
                }
                let (phi, nrm) = pose.sdf_normal(&xp);
                if phi < reach {
                    // the body's point velocity after this substep's gravity
                    // (rapier adds `Δt·g` before it moves the body): held
                    // to the velocity the body had, a resting body would
                    // sink into the water by `g Δt²` every substep
                    let u = pose.point_velocity(&xp) + g_dt;
                    if (v - u).dot(&nrm) < 0.0 {
                        let before = v;
                        apply_condition_moving(
                            &mut v,
                            &nrm,
                            BoundaryCondition::Separate,
                            pose.friction,
                            &u,
                        );
                        // the node's momentum change, returned to the body,
                        // and its mass in the body's coupled mass matrix
                        let r = xp - pose.center;
                        sums[bi].add(&((before - v) * m), &r);
                        sums[bi].add_coupled(m, &nrm, &r);
                        coupled.push(Coupled {
                            node: (oi * b.pow(D as u32) + l) as u32,
                            body: bi as u32,
                            n: std::array::from_fn(|d| if d < D { nrm[d] } else { 0.0 }),
                            r: std::array::from_fn(|d| if d < D { r[d] } else { 0.0 }),
                        });
                    }
                }
            }
            for d in 0..D {
                let side = if gi[d] < wall_lo {
                    0
                } else if gi[d] > wall_hi {
                    1
                } else {
                    continue;
                };
                let f = &faces[d][side];
                apply_condition(&mut v, &normals[d][side], f.condition, f.friction);
            }
            o[..D].copy_from_slice(v.as_slice());
        }
    }
}

/// `acc[..N] += src[..N]` node by node on 4 lanes (`V4`: one SSE add a
/// node, the per-lane `f32` add); with `FIRST`, `acc[..N] = 0 + src[..N]`
/// (the same sum from a zeroed `acc`). Panics if either is shorter than `N`.
#[inline(always)]
fn add_run<const N: usize, const FIRST: bool>(acc: &mut [[f32; 4]], src: &[[f32; 4]]) {
    let a = acc.first_chunk_mut::<N>().expect("a run inside the block");
    let s = src
        .first_chunk::<N>()
        .expect("a run inside the padded buffer");
    for k in 0..N {
        let start = if FIRST {
            V4::splat(0.0)
        } else {
            V4::load(&a[k])
        };
        a[k] = (start + V4::load(&s[k])).to_array();
    }
}
