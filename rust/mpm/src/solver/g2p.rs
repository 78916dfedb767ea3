//! Stage 3 of a substep: grid-to-particle transfer (g2p) and the particle update.
//!
//! Per particle, from the updated grid velocities `v_i` of its stencil
//! (Hu et al. 2018, MLS-MPM with APIC transfers, Jiang et al. 2015):
//!
//! ```text
//! v_p = Σ_i w_ip v_i,     C_p = (4 / Δx²) Σ_i w_ip v_i (x_i − x_p)ᵀ,
//! x_p ← x_p + Δt·v_p      (clamped to the domain [dx, 1 − dx]^D)
//! ```
//!
//! then, for each collider with [`crate::Collider::project`], a particle
//! that ended more than [`crate::collider::PROJECT_DEPTH_CELLS`] cells inside
//! it goes back onto its surface and loses its inward
//! velocity relative to it ([`crate::Collider::project_particle`]: the grid
//! condition holds nodes, not particles, which end up to about a cell inside
//! without it; a solid's particle goes back only from
//! [`crate::collider::SOLID_PROJECT_DEPTH_CELLS`], above which it only loses
//! its inward velocity); then the material update with the new velocity gradient `C_p`
//! ([`crate::material`]: `J` for water, `F` and the Drucker–Prager return
//! mapping for sand, `F` (and snow's `J_P`) for the solids; each particle
//! with the model of its parameter set, sixteen particles of one set at a
//! time, within one window of the block where the lanes share a route:
//! [`G2P_WINDOW`]) and the new Kirchhoff stress for the next p2g.
//!
//! Blocks are processed in parallel: each source block gathers its padded
//! velocity patch once and its particles read it with fixed strides. A
//! frame attempt's first substep writes them contiguously into the next
//! storage (sorted by block, then id), together with their [`Cell`] for the
//! next substep; the later substeps update them where they are stored (the
//! storage order enters no sum). The per-block results
//! (the state's [`Health`], max speed) are combined with `max`, which is
//! exact in any order.
//!
//! Health: every particle must leave g2p in a state that `Particle::validate`
//! (and so checkpoint restore) accepts: finite `v`, `C`, `F`, `J`, `vc` and
//! stress, `J > 0` for water (and `J_P > 0` for snow) and `det F > 0` for
//! sand and the solids (positions are clamped to the domain). Otherwise the frame is rolled back and retried.

use nalgebra::{SMatrix, SVector};

use super::block_sort::BlockMarks;
use super::grid::{EMPTY, G2P_WINDOW, unflatten};
use super::team::RawSlice;
use super::{Health, Solver};
use crate::collider::{Collider, PROJECT_DEPTH_CELLS, Reach, SOLID_PROJECT_DEPTH_CELLS};
use crate::dim::{Dim, DimOps};
use crate::kernel::{Cell, cell_of, weights};
use crate::material::{Batch, LaneHealth, Models, ParticleSink};
use crate::particles::{Material, Particle};
use crate::v4::V4;

impl<const D: usize> Solver<D>
where
    Dim<D>: DimOps<D>,
{
    /// g2p of the particles of source block `si` at places `places` of the
    /// sorted order (the whole block, or a piece of it:
    /// [`super::grid::G2pItem`]), from the block's padded velocity patch
    /// (`patch`: `(B+2)^D` nodes, filled by [`Self::g2p_patch`]): updates the
    /// particles and their [`Cell`] for the next substep, writes each
    /// one's new block key to `key_by_id` at its id and marks its block
    /// (`marks`, the block sort's first stage). Returns the health and
    /// largest speed squared of these particles.
    ///
    /// `REORDER`: the particles, their cells and their ids go to the same
    /// places of the next storage order (sorted by block, then id), and each
    /// one's new slot to `slot_of`; otherwise each particle is updated where
    /// it is stored (its slot and id stay). The storage order changes no
    /// result (every sum runs in the sorted order, by block then id), so the
    /// frame loop reorders once per frame attempt, in its first substep
    /// (which leaves the frame's start in `next` for a rollback), and
    /// updates in place otherwise: no copy of every particle into another
    /// buffer per substep.
    ///
    /// # Safety
    /// The views of `out` are the solver's buffers (`G2pOut`); nothing else
    /// may access the places of this item's slots (in place) or of this
    /// item's range of the next order (reordering) meanwhile, nor `slot_of`
    /// and `key_by_id` at its ids (each id is in the one block that holds it).
    // inlined into each compiled copy of the frame loop (`crate::isa`)
    #[inline(always)]
    #[allow(clippy::too_many_arguments)] // the item and its patch, the buffers, the step, the worker's scratch
    pub(super) unsafe fn g2p_block<const REORDER: bool>(
        &self,
        places: std::ops::Range<usize>,
        patch: &[[f32; 4]],
        out: G2pOut<D>,
        dt: f32,
        models: &Models,
        marks: &mut BlockMarks<'_>,
        batches: &mut Batches,
    ) -> (Health, f32) {
        let G2pOut {
            particles,
            cells,
            next,
            next_cells,
            ids_next,
            slot_of,
            key_by_id,
        } = out;
        let first = places.start;
        // where the updated particles and cells go
        let (dst, dst_cells) = if REORDER {
            (next, next_cells)
        } else {
            (particles, cells)
        };
        let dx = self.params.dx();
        let inv_dx = 1.0 / dx;
        let c_scale = V4::splat(4.0 * inv_dx);
        let (lo, hi) = self.domain_bounds();
        let st = &self.stencil;
        let lat = st.lat_stride;
        let sorted = &self.grid.sorted[places];
        let mut nan_probe = 0.0f32;
        let mut nonpositive_j = false;
        let mut lane_health = LaneHealth::OK;
        let mut vmax2 = 0.0f32;
        // the particles' material updates wait in `batches` and run sixteen
        // at a time (SIMD across particles, see `Batch`)
        let mut sink = Sink(dst);
        // the colliders that project particles (`Collider::project`), each
        // with the region where it can act (`Collider::reach`) and its
        // velocity in this frame (None: at rest), at their poses at this
        // substep's end
        let depth = PROJECT_DEPTH_CELLS * dx;
        let solid_depth = SOLID_PROJECT_DEPTH_CELLS * dx;
        let projecting: Vec<_> = self
            .colliders
            .iter()
            .zip(&self.collider_velocity)
            .zip(&self.shallow)
            .filter(|((col, _), _)| col.project)
            .map(|((col, u), shallow)| (col, col.reach(depth, shallow.as_ref()), u.as_ref()))
            .collect();
        for (j, &slot) in sorted.iter().enumerate() {
            // a window of the block starts here (this item starts one):
            // the batches whose lanes share a route end
            if j > 0 && j % G2P_WINDOW == 0 && batches.0.iter().any(|b| b.len() > 0) {
                end_window(batches, &mut sink, models, dt, &mut lane_health);
            }
            let slot = slot as usize;
            let id = self.ids[slot];
            // its place in the storage this substep leaves
            let at = if REORDER { first + j } else { slot };
            // the particle, updated where it goes: in place, only the fields
            // that change are written (no copy of the whole particle in and
            // out); reordering, a copy at its new place
            // SAFETY: the slot and the place `at` are this item's alone
            // (caller); `p` is the only reference to it until the next
            // particle (its batch writes it after the loop's body)
            let (p, cell) = unsafe {
                let p = if REORDER {
                    dst.write(at, particles.read(slot));
                    dst.get_mut(at)
                } else {
                    particles.get_mut(slot)
                };
                (p, cells.read(slot))
            };
            let (fx, w) = weights::<D>(&cell);
            let base_idx = cell.pad_off as usize;
            let (acc_v, acc_b) = Dim::<D>::g2p_sums(&patch[base_idx..], &Dim::<D>::PAD_STRIDE, &w);
            // B = Σ w v (o − fx)ᵀ·dx; C = 4/dx² · B = 4/dx · (Σ w v oᵀ − v fxᵀ)
            let new_v = SVector::<f32, D>::from_fn(|r, _| acc_v[r]);
            // column c in 4 lanes (rows r < D; the others unused), each the
            // f32 expression per entry
            let v4 = V4::load(&acc_v);
            let cols: [[f32; 4]; D] =
                std::array::from_fn(|c| ((V4::load(&acc_b[c]) - fx[c] * v4) * c_scale).to_array());
            let new_c = SMatrix::<f32, D, D>::from_fn(|r, c| cols[c][r]);
            p.v = new_v;
            p.c = new_c;
            p.x += new_v * dt;
            for d in 0..D {
                p.x[d] = p.x[d].max(lo).min(hi);
            }
            if !projecting.is_empty()
                && project(
                    &projecting,
                    &mut p.x,
                    &mut p.v,
                    p.material.is_solid().then_some(solid_depth),
                )
            {
                for d in 0..D {
                    p.x[d] = p.x[d].max(lo).min(hi);
                }
            }
            // the particle's update waits in its material's batch, one
            // parameter set per batch: a particle of another set flushes it
            let slot = p.material as usize;
            let batch = &mut batches.0[slot];
            if p.set != batch.set {
                if batch.len() > 0 {
                    flush(batch, &mut sink, models, dt, &mut lane_health);
                }
                batch.set = p.set;
            }
            let full = batch.push(at as u32, (&p.f, p.j, p.vc), &new_c);
            let ko = cell_of::<D>(
                &p.x,
                inv_dx,
                Dim::<D>::LOG2_BLOCK,
                &lat,
                &Dim::<D>::PAD_STRIDE,
            );
            // SAFETY: the place `at` and the id are this item's alone (caller)
            unsafe {
                dst_cells.write(at, ko);
                if REORDER {
                    ids_next.write(at, id);
                    slot_of.write(id as usize, at as u32);
                }
                key_by_id.write(id as usize, ko.key);
            }
            marks.mark(ko.key);
            // NaN/inf propagate through the sum; J ≤ 0 is a blow-up too
            // (the new J, F and τ are checked in the batch, `LaneHealth`)
            nan_probe += p.v.sum() + p.c.sum() + p.tau.sum() + p.j;
            nonpositive_j |= p.j <= 0.0;
            vmax2 = vmax2.max(p.v.norm_squared());
            if full {
                flush(
                    &mut batches.0[slot],
                    &mut sink,
                    models,
                    dt,
                    &mut lane_health,
                );
            }
        }
        for batch in &mut batches.0 {
            if batch.len() > 0 {
                flush(batch, &mut sink, models, dt, &mut lane_health);
            }
        }
        let LaneHealth { finite, inverted } = lane_health;
        // positions are clamped (NaN maps to the bound), so test the rest
        let health = if !(nan_probe.is_finite() && vmax2.is_finite() && finite) || nonpositive_j {
            Health::NonFinite
        } else if inverted {
            Health::Inverted
        } else {
            Health::Ok
        };
        (health, vmax2)
    }

    /// The padded velocity patch of source block `si` (`patch`: `(B+2)^D`
    /// nodes, c·B + q for q ∈ [0, B+2)^D), copied by runs from the 2^D
    /// output blocks c + s it overlaps (the same node pairs the grid update
    /// gathers; every node lies in an output block, so all are overwritten).
    // inlined into each compiled copy of the frame loop (`crate::isa`)
    #[inline(always)]
    pub(super) fn g2p_patch(&self, si: usize, patch: &mut [[f32; 4]]) {
        let g = &self.grid;
        let st = &self.stencil;
        let lat = st.lat_stride;
        let blk_nodes = 1usize << (g.log2_b as usize * D);
        let c = unflatten::<D>(g.src_blocks[si] as usize, &lat);
        for (s, runs) in st.gather_runs.iter().enumerate() {
            let mut lin = 0usize;
            for d in 0..D {
                lin += (c[d] + ((s >> d) & 1)) * lat[d];
            }
            let ob = g.out_map.get(lin).copied().unwrap_or(EMPTY);
            if ob == EMPTY {
                continue;
            }
            let blk = &g.out_v[(ob - 1) as usize * blk_nodes..ob as usize * blk_nodes];
            for &(l, q, len) in runs {
                let (l, q, len) = (l as usize, q as usize, len as usize);
                patch[q..q + len].copy_from_slice(&blk[l..l + len]);
            }
        }
    }

    /// After every block's g2p: if it reordered (`reordered`), the next
    /// storage order becomes the current one (particles, their cells and
    /// ids; g2p wrote `slot_of`), and `next` holds the particles g2p read;
    /// in place there is nothing to do.
    pub(super) fn g2p_finish(&mut self, reordered: bool) {
        if reordered {
            std::mem::swap(&mut self.particles, &mut self.next);
            std::mem::swap(&mut self.grid.keys, &mut self.grid.next_keys);
            std::mem::swap(&mut self.ids, &mut self.ids_next);
            self.start_in_next = true;
        }
    }
}

/// The particle projection of each collider of `projecting` (with its
/// reach and velocity, [`crate::Collider::project_particle`]) in turn, at
/// `x` with velocity `v` (`keep_above`: a solid's depth, as there); returns
/// whether any changed the particle. Kept out of
/// the particle loop (one call per particle where a collider projects), whose
/// code it would otherwise crowd for every scene.
#[inline(never)]
fn project<const D: usize>(
    projecting: &[(&Collider<D>, Reach<'_, D>, Option<&SVector<f32, D>>)],
    x: &mut SVector<f32, D>,
    v: &mut SVector<f32, D>,
    keep_above: Option<f32>,
) -> bool {
    let mut moved = false;
    for (col, reach, u) in projecting {
        moved |= col.project_particle(reach, x, v, *u, keep_above);
    }
    moved
}

/// One open [`Batch`] per material code (`Particle::material`), so that
/// particles of other materials between them do not cut a batch: a batch
/// holds the particles of one parameter set, consecutive in the item's
/// order among those of its material (and of one window, [`G2P_WINDOW`],
/// where its lanes share a route). One per worker, reused.
pub(super) struct Batches([Batch; Material::ALL.len()]);

impl Batches {
    pub(super) fn new() -> Self {
        Batches(std::array::from_fn(|m| Batch::new(m as u16)))
    }
}

/// At a window's end ([`G2P_WINDOW`]): [`flush`]es each batch of
/// `batches` that holds particles and whose lanes share a route. Not
/// inlined (the particle loop keeps one inlined copy of a batch's run and
/// write-back), and called only where some batch holds particles: in a
/// block of one set none does at a window's end (sixteen particles filled
/// the batch and it ran).
#[inline(never)]
fn end_window<const D: usize>(
    batches: &mut Batches,
    outp: &mut impl ParticleSink<D>,
    models: &Models,
    dt: f32,
    health: &mut LaneHealth,
) where
    Dim<D>: DimOps<D>,
{
    for batch in &mut batches.0 {
        if batch.len() > 0 && models.models[batch.set as usize].shares_route::<D>() {
            flush(batch, outp, models, dt, health);
        }
    }
}

/// Runs `batch` under its set's model with time step `dt`, writes its
/// lanes into `outp` (at the indices pushed with them), adds its health to
/// `health` and empties it.
// inlined into each compiled copy of the frame loop (`crate::isa`)
#[inline(always)]
fn flush<const D: usize>(
    batch: &mut Batch,
    outp: &mut impl ParticleSink<D>,
    models: &Models,
    dt: f32,
    health: &mut LaneHealth,
) where
    Dim<D>: DimOps<D>,
{
    let m = &models.models[batch.set as usize];
    health.and(m.run::<D>(batch, models.isa, dt));
    batch.write_lanes::<D>(outp, m.has_f());
    batch.clear();
}

/// The buffers g2p reads and writes (see [`Solver::g2p_block`]), whole.
pub(super) struct G2pOut<const D: usize> {
    /// The current storage: the particles and their cells (read at their
    /// slots; written there when g2p updates in place).
    pub(super) particles: RawSlice<Particle<D>>,
    pub(super) cells: RawSlice<Cell>,
    /// The next storage order when g2p reorders: particles, cells and ids.
    pub(super) next: RawSlice<Particle<D>>,
    pub(super) next_cells: RawSlice<Cell>,
    pub(super) ids_next: RawSlice<u32>,
    /// Written at the ids: the new slots (when reordering) and block keys.
    pub(super) slot_of: RawSlice<u32>,
    pub(super) key_by_id: RawSlice<u32>,
}

/// g2p's view of the storage it writes, for the batches' write-back.
struct Sink<const D: usize>(RawSlice<Particle<D>>);

impl<const D: usize> ParticleSink<D> for Sink<D> {
    #[inline(always)]
    fn at(&mut self, i: usize) -> &mut Particle<D> {
        // SAFETY: the lanes' places are those of the calling item's
        // particles, its alone (`Solver::g2p_block`'s caller)
        unsafe { self.0.get_mut(i) }
    }
}

#[cfg(test)]
mod tests {
    use nalgebra::{SMatrix, SVector};

    use crate::boundary::BoundaryCondition;
    use crate::collider::{Collider, Shape};
    use crate::params::SolverParams;
    use crate::particles::{Material, lattice};
    use crate::solver::Solver;

    /// Water and sand falling onto a rotated box, a sphere and a moving box,
    /// all projecting particles or none (`project`), stepped `frames` frames with `threads` threads,
    /// the team forced on or off.
    fn run(threads: usize, team: bool, frames: usize, project: bool) -> Vec<u8> {
        let params = SolverParams::<2> {
            n_grid: 48,
            num_threads: threads,
            ..Default::default()
        };
        let dx = params.dx();
        let (s, c) = 0.3f32.sin_cos();
        let col = |shape, condition| Collider {
            shape,
            condition,
            friction: 0.2,
            project,
        };
        let colliders = vec![
            col(
                Shape::Box {
                    center: SVector::from([0.3, 0.3]),
                    half_extents: SVector::from([0.12, 0.04]),
                    rotation: SMatrix::<f32, 2, 2>::new(c, -s, s, c),
                },
                BoundaryCondition::Separate,
            ),
            col(
                Shape::Sphere {
                    center: SVector::from([0.65, 0.3]),
                    radius: 0.08,
                },
                BoundaryCondition::Slip,
            ),
            col(
                Shape::Box {
                    center: SVector::from([0.5, 0.15]),
                    half_extents: SVector::from([0.04, 0.06]),
                    rotation: SMatrix::<f32, 2, 2>::identity(),
                },
                BoundaryCondition::Sticky,
            ),
        ];
        let mut s = Solver::new(params, colliders).unwrap();
        let mut ps = lattice([0.2, 0.4], 30, dx / 2.0, Material::Water, 1000.0);
        ps.extend(lattice([0.55, 0.4], 24, dx / 2.0, Material::Sand, 1000.0));
        for p in &mut ps {
            p.v = SVector::from([0.0, -2.0]);
        }
        s.set_particles(ps).unwrap();
        s.mode.force = Some(team);
        for f in 0..frames {
            let x = 0.5 + 0.1 * (f as f32 * 0.3).sin();
            s.move_collider(2, SVector::from([x, 0.15]), None).unwrap();
            s.step_frame(2.5e-3).unwrap();
        }
        s.checkpoint()
    }

    /// The projection is per particle, so a team gives the bits of one
    /// thread (and it acts here: off, the bits differ).
    #[test]
    fn projection_is_bitwise_identical_on_a_team() {
        let one = run(1, false, 16, true);
        assert_eq!(one, run(2, true, 16, true));
        assert_eq!(one, run(3, true, 16, true));
        assert_ne!(one, run(1, false, 16, false));
    }
}
