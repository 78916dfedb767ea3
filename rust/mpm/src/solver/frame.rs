//! The substeps of one frame attempt, run by a persistent team of threads
//! ([`super::team`]): the one frame loop of the engine.
//!
//! Per substep, with one barrier between stages:
//!
//! 1. thread 0, serial: finish the previous substep's g2p (the new storage
//!    order), check its health and speed, sort the particles into blocks
//!    (`block_sort.rs`: g2p counted the blocks' particles; a large frame scatters
//!    in parallel chunks, after one more barrier, and with more than two
//!    chunks counts per chunk first, after another) and size the buffers;
//! 2. p2g per source block (`p2g.rs`);
//! 3. grid update per output block (`grid_update.rs`), after which the
//!    source blocks leave the block map;
//! 4. g2p per source block (`g2p.rs`), each block reporting its health and
//!    largest speed, and marking the blocks its particles move to.
//!
//! Stages 2–4 are parallel: each member of the team claims the blocks it
//! owns (the same run of blocks in every stage, `Solver::schedule`) from
//! an atomic counter, then helps the others, and each block writes only its
//! own output, so results are bitwise the same for any number of threads.

use std::sync::Mutex;

use super::block_sort::BlockMarks;
use super::g2p::{Batches, G2pOut};
use super::team::{KEYS, OWN_G2P, OWN_GRID, OWN_P2G, RawSlice, SORT_COUNT, SORT_SCATTER, Team};
use super::{Health, Solver};
use crate::body::ImpulseSum;
use crate::dim::{Dim, DimOps};
use crate::error::{MpmError, Result};
use crate::isa::{Isa, x86_64_v3};
use crate::kernel::{Cell, cell_of};
use crate::particles::Particle;

/// What thread 0 publishes for a substep's parallel stages: the sizes of the
/// block lists and the buffers the stages write, chunk by chunk.
struct Stage<const D: usize> {
    key_by_id: RawSlice<u32>,
    src_map: RawSlice<u32>,
    counts: RawSlice<u32>,
    sorted: RawSlice<u32>,
    local: RawSlice<[f32; 4]>,
    out_v: RawSlice<[f32; 4]>,
    particles: RawSlice<Particle<D>>,
    next: RawSlice<Particle<D>>,
    ids_next: RawSlice<u32>,
    slot_of: RawSlice<u32>,
    /// The cells of the current storage order (`grid.keys`).
    keys: RawSlice<Cell>,
    /// The cells this substep writes: `grid.next_keys` in g2p (and
    /// `grid.keys` in the frame's first stage, which computes them afresh).
    cells: RawSlice<Cell>,
}

impl<const D: usize> Clone for Stage<D> {
    fn clone(&self) -> Self {
        *self
    }
}
impl<const D: usize> Copy for Stage<D> {}

/// The solver, shared with the team's threads for one frame attempt.
struct SolverPtr<const D: usize>(*mut Solver<D>)
where
    Dim<D>: DimOps<D>;

// SAFETY: the team's protocol (see `run_substeps`) gives thread 0 exclusive
// access in serial sections and every thread shared access in parallel ones.
unsafe impl<const D: usize> Sync for SolverPtr<D> where Dim<D>: DimOps<D> {}
unsafe impl<const D: usize> Send for SolverPtr<D> where Dim<D>: DimOps<D> {}

/// Particles per claimed item when the cells are computed at the frame's start.
const KEYS_CHUNK: usize = 1024;

/// Below this many particles per member the block sort runs whole in the
/// serial section that starts a substep instead of in chunks after one or
/// two more barriers (two chunks: the scatter; more: the counts too): its
/// work, ~3 ns a particle per chunked stage, is less than the barriers cost
/// a small frame.
pub(super) const SERIAL_SORT_BELOW: usize = 2048;

impl<const D: usize> Solver<D>
where
    Dim<D>: DimOps<D>,
{
    /// `n_sub` substeps of `dt` seconds on the solver's pool. Returns the
    /// largest particle speed after the last substep, or the error that ends
    /// the attempt: a non-finite state or inverted sand particle, or a
    /// particle that would travel more than `max_travel` (CFL violation);
    /// `retries` is reported in the error. On error the state is left where
    /// the failing substep put it (the caller rolls back).
    pub(super) fn run_substeps(
        &mut self,
        n_sub: usize,
        dt: f32,
        max_travel: f32,
        retries: usize,
    ) -> Result<f32> {
        self.start_in_next = false;
        let pool = self.pool.clone();
        let pool_threads = pool.current_num_threads().max(1);
        let (team_chosen, probe) = self.mode.choose();
        let use_team = pool_threads > 1 && team_chosen;
        self.mode.runs[use_team as usize] += 1;
        let threads = if use_team { pool_threads } else { 1 };
        let sort_chunks = if self.particles.len() < self.serial_sort_below.saturating_mul(threads) {
            1
        } else {
            threads
        };
        // a small frame's team reorders every substep (`reorders`), so the
        // frame's start is copied for a rollback
        self.start_copied = reorders(1, threads, sort_chunks);
        if self.start_copied {
            self.rollback.2.clone_from(&self.particles);
        }
        let started = std::time::Instant::now();
        let team: Team<Stage<D>> = Team::new(threads);
        // the buffers of the frame's first stage, published before any
        // member starts: the first stage needs no barrier before it, so the
        // calling thread computes cells while the pool's threads wake up
        let n = self.particles.len();
        self.grid.keys.resize(n, Cell::default());
        self.grid.key_by_id.resize(n, 0);
        let keys = RawSlice::new(&mut self.grid.keys);
        // SAFETY: no member runs yet: this thread has the team to itself
        unsafe { team.publish(self.stage_view(keys)) };
        let isa = self.isa;
        let sp = SolverPtr(self as *mut Self);
        let sp = &sp;
        let team = &team;
        let touched = &Mutex::new(Vec::new());
        let result = &Mutex::new(None);
        let args = &MemberArgs {
            sp,
            team,
            touched,
            result,
            members: threads,
            sort_chunks,
            n_sub,
            dt,
            max_travel,
            retries,
        };
        let member = |tid: usize| {
            team.member(|| {
                // SAFETY: every member of the team runs this once, concurrently
                // (below); nothing else touches the solver meanwhile
                unsafe { Self::substeps_member(isa, args, tid) }
            })
        };
        if threads == 1 {
            member(0);
        } else {
            // the calling thread is member 0 and the pool's threads the
            // others: one thread fewer to wake per frame, and none at its
            // end (`broadcast` left the caller asleep until the pool's
            // members were done)
            let member = &member;
            pool.in_place_scope(|scope| {
                for tid in 1..threads {
                    scope.spawn(move |_| member(tid));
                }
                member(0);
            });
        }
        let result = result
            .lock()
            .expect("no member panicked holding it")
            .take()
            .expect("the last substep leaves the frame's result");
        if pool_threads > 1 {
            let items = (n_sub * self.particles.len()).max(1) as f64;
            let seconds = started.elapsed().as_secs_f64();
            self.mode.record(use_team, probe, seconds / items, seconds);
            if self.profile {
                // the mode choice's view of each attempt (`HYBRIDMPM_PROFILE`,
                // read once at construction, not per frame)
                eprintln!(
                    "team {use_team} probe {probe} {:.3} ms {:?}",
                    seconds * 1e3,
                    self.mode
                );
            }
        }
        if self.profile && use_team {
            let (rounds, parks) = team.barrier_stats();
            eprintln!("team: {threads} threads, {rounds} barriers, {parks} parked waits");
        }
        result
    }

    /// One member of the team (`tid`: 0 ..); the frame's result is left in
    /// `result`.
    ///
    /// # Safety
    /// Every thread of the team must call it once, concurrently, with the
    /// same arguments (what `run_substeps` does), and nothing else may touch
    /// the solver meanwhile. `&mut Solver` is taken only in serial sections
    /// (run by the last member to arrive at a barrier while the others
    /// wait); in parallel stages every member takes `&Solver` and writes
    /// only the chunks of the published buffers that belong to the items it
    /// claimed (a buffer being written is never read in the same stage).
    unsafe fn substeps_member(isa: Isa, args: &MemberArgs<'_, D>, tid: usize) {
        // SAFETY: `Solver::set_isa` and `Isa::detect` only choose a variant
        // on a CPU that has its features; the caller's conditions are ours
        #[cfg(target_arch = "x86_64")]
        if isa == Isa::X86_64V3 {
            return unsafe { Self::substeps_member_v3(args, tid) };
        }
        let _ = isa;
        // SAFETY: the caller's conditions
        unsafe { Self::substeps_member_body(args, tid) }
    }

    x86_64_v3! {
        /// [`Self::substeps_member_body`] compiled for x86-64-v3 ([`crate::isa`]).
        ///
        /// # Safety
        /// As `substeps_member`, on a CPU with the x86-64-v3 features.
        unsafe fn substeps_member_v3(args: &MemberArgs<'_, D>, tid: usize) {
            // SAFETY: the caller's conditions
            unsafe { Self::substeps_member_body(args, tid) }
        }
    }

    /// The frame loop of one member (see `substeps_member`); inlined into
    /// each compiled copy.
    ///
    /// # Safety
    /// As `substeps_member`.
    #[inline(always)]
    unsafe fn substeps_member_body(args: &MemberArgs<'_, D>, tid: usize) {
        let MemberArgs {
            sp,
            team,
            touched,
            result,
            members,
            sort_chunks,
            n_sub,
            dt,
            max_travel,
            retries,
        } = *args;
        let serial_sort = sort_chunks == 1;
        // the cells of the frame's first substep, in parallel chunks (the
        // buffers were published before the members started)
        {
            // SAFETY: parallel section: shared reads, disjoint chunk writes
            let s = unsafe { &*sp.0 };
            let view = unsafe { team.published() };
            let keys = view.cells;
            let n = s.particles.len();
            let inv_dx = s.params.n_grid as f32;
            let (log2_b, lat, pad) = (s.grid.log2_b, s.stencil.lat_stride, Dim::<D>::PAD_STRIDE);
            // SAFETY: src_map is only marked in this stage
            let mut marks = unsafe { BlockMarks::new(view.src_map) };
            while let Some(i) = team.claim(KEYS, n.div_ceil(KEYS_CHUNK)) {
                let lo = i * KEYS_CHUNK;
                let hi = (lo + KEYS_CHUNK).min(n);
                // SAFETY: chunk i is this thread's alone
                let out = unsafe { keys.chunk_mut(lo, hi - lo) };
                for ((k, p), &id) in out.iter_mut().zip(&s.particles[lo..hi]).zip(&s.ids[lo..hi]) {
                    *k = cell_of::<D>(&p.x, inv_dx, log2_b, &lat, &pad);
                    // SAFETY: each id is at one slot, and so in one chunk
                    unsafe { view.key_by_id.write(id as usize, k.key) };
                    marks.mark(k.key);
                }
            }
            marks.finish_into(touched);
        }
        let mut patch = Vec::new();
        let mut batches = Batches::new();
        let mut acc = Vec::new();
        // this member's sums of the bodies' impulses in a grid update
        let mut sums = vec![ImpulseSum::default(); unsafe { (*sp.0).bodies.len() }];
        let mut coupled = Vec::new();
        let mut clock = Profile::new(tid == 0 && unsafe { (*sp.0).profile });
        for sub in 0..=n_sub {
            // serial: finish the previous substep's g2p and check it, then
            // start the block sort
            team.barrier_then(|| {
                // SAFETY: serial section
                let s = unsafe { &mut *sp.0 };
                if sub > 0 {
                    s.g2p_finish(reorders(sub - 1, members, sort_chunks));
                    let (health, v) = team.outcome();
                    let err = match health {
                        Health::Ok if v * dt > max_travel => Some(MpmError::CflViolation {
                            substep: sub - 1,
                            substeps: n_sub,
                            max_speed: v,
                            retries,
                        }),
                        Health::Ok => None,
                        Health::NonFinite => Some(MpmError::NonFinite {
                            substep: sub - 1,
                            substeps: n_sub,
                            retries,
                        }),
                        Health::Inverted => Some(MpmError::Inverted {
                            substep: sub - 1,
                            substeps: n_sub,
                            retries,
                        }),
                    };
                    let mut r = result.lock().expect("no member panicked holding it");
                    if let Some(e) = err {
                        *r = Some(Err(e));
                        team.set_stop();
                    } else if sub == n_sub {
                        *r = Some(Ok(v));
                        team.set_stop();
                    }
                }
                let mut t = touched.lock().expect("no member panicked holding it");
                if team.stopped() {
                    s.forget_marks(&mut t);
                } else {
                    // the moving colliders where they are at this substep's end
                    s.pose_colliders(sub + 1, n_sub);
                    s.sort_begin();
                    s.sort_number(&mut t, sort_chunks);
                    let view = if serial_sort {
                        // the whole block sort here: a barrier fewer
                        // (same order: the sort is stable in id order for
                        // any chunking)
                        let keys = RawSlice::new(&mut s.grid.next_keys);
                        let view = s.stage_view(keys);
                        // SAFETY: serial section: nothing else accesses the
                        // sort's buffers
                        unsafe { s.sort_scatter(0, 1, view.sorted, &mut Vec::new()) };
                        s.size_stages(members)
                    } else {
                        let keys = RawSlice::new(&mut s.grid.next_keys);
                        s.stage_view(keys)
                    };
                    unsafe { team.publish(view) };
                }
            });
            if sub > 0 {
                clock.lap(Lap::G2p);
                clock.print();
            }
            if team.stopped() {
                break;
            }
            // the block sort's parallel stages (see `block_sort.rs`)
            if !serial_sort {
                // SAFETY: parallel section; each chunk's row / places are its own
                let s = unsafe { &*sp.0 };
                let view = unsafe { team.published() };
                if sort_chunks > 2 {
                    while let Some(c) = team.claim(SORT_COUNT, sort_chunks) {
                        unsafe { s.sort_count(c, sort_chunks, view.counts) };
                    }
                    team.barrier();
                }
                let mut cur = Vec::new();
                while let Some(c) = team.claim(SORT_SCATTER, sort_chunks) {
                    unsafe { s.sort_scatter(c, sort_chunks, view.sorted, &mut cur) };
                }
                team.barrier_then(|| {
                    // SAFETY: serial section
                    let s = unsafe { &mut *sp.0 };
                    let view = s.size_stages(members);
                    unsafe { team.publish(view) };
                });
            }
            clock.lap(Lap::Sort);
            clock.blocks(unsafe { &*sp.0 });
            // SAFETY: parallel sections from here to the loop's next barrier:
            // shared reads, and writes to the claimed chunks only
            let s = unsafe { &*sp.0 };
            let view = unsafe { team.published() };
            let st = &s.stencil;
            let blk_nodes = 1usize << (s.grid.log2_b as usize * D);
            patch.resize(st.pad_nodes, [0.0f32; 4]);
            acc.resize(blk_nodes, [0.0f32; 4]);
            while let Some(k) = team.claim_own(OWN_P2G, tid, &s.grid.p2g_bounds) {
                let si = s.grid.p2g_order[k] as usize;
                let buf = unsafe { view.local.chunk_mut(si * st.pad_nodes, st.pad_nodes) };
                s.p2g_block(si, buf, dt);
            }
            team.barrier();
            clock.lap(Lap::P2g);
            while let Some(oi) = team.claim_own(OWN_GRID, tid, &s.grid.grid_bounds) {
                let out = unsafe { view.out_v.chunk_mut(oi * blk_nodes, blk_nodes) };
                s.grid_update_block(oi, out, &mut acc, &mut sums, &mut coupled, dt);
            }
            if !sums.is_empty() {
                s.bodies.merge(&sums, &mut coupled);
                sums.fill(ImpulseSum::default());
            }
            team.barrier_then(|| {
                // SAFETY: serial section
                let s = unsafe { &mut *sp.0 };
                s.forget_sources();
                // the bodies take the fluid's impulses and step; the nodes
                // they hold follow their new velocities
                s.bodies.substep(dt, &mut s.grid.out_v);
            });
            clock.lap(Lap::Grid);
            let models = &s.models;
            let (mut health, mut vmax2) = (Health::Ok, 0.0f32);
            // the block whose velocity patch `patch` holds
            let mut patch_of = usize::MAX;
            // SAFETY: src_map is only marked in g2p
            let mut marks = unsafe { BlockMarks::new(view.src_map) };
            while let Some(k) = team.claim_own(OWN_G2P, tid, &s.grid.g2p_bounds) {
                let item = s.grid.g2p_items[k];
                let (si, lo, len) = (item.block as usize, item.first as usize, item.len as usize);
                if si != patch_of {
                    s.g2p_patch(si, &mut patch);
                    patch_of = si;
                }
                // SAFETY: the item's slots, its range of the next storage
                // order and its ids are this thread's alone
                let (h, v2) = unsafe {
                    let out = G2pOut {
                        particles: view.particles,
                        cells: view.keys,
                        next: view.next,
                        next_cells: view.cells,
                        ids_next: view.ids_next,
                        slot_of: view.slot_of,
                        key_by_id: view.key_by_id,
                    };
                    if reorders(sub, members, sort_chunks) {
                        s.g2p_block::<true>(
                            lo..lo + len,
                            &patch,
                            out,
                            dt,
                            models,
                            &mut marks,
                            &mut batches,
                        )
                    } else {
                        s.g2p_block::<false>(
                            lo..lo + len,
                            &patch,
                            out,
                            dt,
                            models,
                            &mut marks,
                            &mut batches,
                        )
                    }
                };
                health = health.max(h);
                vmax2 = vmax2.max(v2);
            }
            team.report(health, vmax2);
            marks.finish_into(touched);
        }
    }

    /// After the block sort: the output blocks
    /// ([`Self::sort_end`]), the claim order of a team of
    /// `members` ([`Self::schedule`]), and the buffers of p2g, the grid
    /// update and g2p sized for this substep; returns their view.
    fn size_stages(&mut self, members: usize) -> Stage<D> {
        self.sort_end();
        self.schedule(members);
        let (n_src, n_out) = (self.grid.src_blocks.len(), self.grid.out_blocks.len());
        let b = 1usize << self.grid.log2_b;
        self.grid
            .local
            .resize(n_src * self.stencil.pad_nodes, [0.0; 4]);
        self.grid.out_v.resize(n_out * b.pow(D as u32), [0.0; 4]);
        let n = self.particles.len();
        self.next.resize(n, self.particles[0]);
        self.ids_next.resize(n, 0);
        self.grid.next_keys.resize(n, Cell::default());
        let keys = RawSlice::new(&mut self.grid.next_keys);
        self.stage_view(keys)
    }

    /// The buffers the parallel stages write, sized for this substep.
    fn stage_view(&mut self, cells: RawSlice<Cell>) -> Stage<D> {
        Stage {
            key_by_id: RawSlice::new(&mut self.grid.key_by_id),
            src_map: RawSlice::new(&mut self.grid.src_map),
            counts: RawSlice::new(&mut self.grid.counts),
            sorted: RawSlice::new(&mut self.grid.sorted),
            local: RawSlice::new(&mut self.grid.local),
            out_v: RawSlice::new(&mut self.grid.out_v),
            particles: RawSlice::new(&mut self.particles),
            next: RawSlice::new(&mut self.next),
            ids_next: RawSlice::new(&mut self.ids_next),
            keys: RawSlice::new(&mut self.grid.keys),
            slot_of: RawSlice::new(&mut self.slot_of),
            cells,
        }
    }
}

/// Whether substep `sub` of a frame attempt on a team of `members`, whose
/// block sort runs in `sort_chunks` chunks, reorders the particle storage in
/// its g2p ([`Solver::g2p_block`]). The first one does, writing the
/// particles in its sorted order into the other buffer, which so keeps the
/// frame's start for a rollback (`Solver::start_in_next`); the others update
/// in place, except on the team of a small frame (one sort chunk, see
/// [`SERIAL_SORT_BELOW`]), which reorders every substep so that each member
/// writes a contiguous range: in place, its members' few-particle items
/// interleave in the storage and their writes share cache lines (the 2D half
/// grids' team frames took up to 1.3× as long).
fn reorders(sub: usize, members: usize, sort_chunks: usize) -> bool {
    sub == 0 || (members > 1 && sort_chunks == 1)
}

/// What the members of a frame's team share (`Solver::run_substeps`): the
/// solver, the team, the sort's touched blocks, the frame's result slot, the
/// team's size and the number of sort chunks, and the frame's substeps.
struct MemberArgs<'a, const D: usize>
where
    Dim<D>: DimOps<D>,
{
    sp: &'a SolverPtr<D>,
    team: &'a Team<Stage<D>>,
    touched: &'a Mutex<Vec<u32>>,
    result: &'a Mutex<Option<Result<f32>>>,
    /// The team's size, and the chunks of the block sort (1: the sort runs
    /// whole in the serial section that starts a substep).
    members: usize,
    sort_chunks: usize,
    n_sub: usize,
    dt: f32,
    max_travel: f32,
    retries: usize,
}

impl<const D: usize> Clone for MemberArgs<'_, D>
where
    Dim<D>: DimOps<D>,
{
    fn clone(&self) -> Self {
        *self
    }
}

impl<const D: usize> Copy for MemberArgs<'_, D> where Dim<D>: DimOps<D> {}

/// Stages timed by thread 0 when `HYBRIDMPM_PROFILE` is set.
#[derive(Clone, Copy)]
enum Lap {
    Sort,
    P2g,
    Grid,
    G2p,
}

/// Per-stage wall times of one substep, seen from thread 0 (each stage ends
/// at the barrier after it, so it includes waiting for the slowest thread).
struct Profile {
    on: bool,
    last: std::time::Instant,
    laps: [std::time::Duration; 4],
    /// The substep's source and output blocks and its largest source block
    /// (particles), noted after the block sort.
    blocks: (usize, usize, usize),
}

impl Profile {
    fn new(on: bool) -> Self {
        Profile {
            on,
            last: std::time::Instant::now(),
            laps: Default::default(),
            blocks: (0, 0, 0),
        }
    }

    fn lap(&mut self, lap: Lap) {
        if self.on {
            let now = std::time::Instant::now();
            self.laps[lap as usize] = now - self.last;
            self.last = now;
        }
    }

    /// Notes the substep's blocks (after the block sort).
    fn blocks<const D: usize>(&mut self, s: &Solver<D>)
    where
        Dim<D>: DimOps<D>,
    {
        if self.on {
            let largest = s.grid.src_offsets.windows(2).map(|w| w[1] - w[0]).max();
            self.blocks = (
                s.grid.src_blocks.len(),
                s.grid.out_blocks.len(),
                largest.unwrap_or(0) as usize,
            );
            // (not part of the next stage)
            self.last = std::time::Instant::now();
        }
    }

    fn print(&mut self) {
        if self.on {
            let l = &self.laps;
            let (n_src, n_out, largest) = self.blocks;
            eprintln!(
                "blocks {:?} p2g {:?} grid {:?} g2p {:?} nsrc {n_src} nout {n_out} largest {largest}",
                l[Lap::Sort as usize],
                l[Lap::P2g as usize],
                l[Lap::Grid as usize],
                l[Lap::G2p as usize],
            );
            // the printing is not part of the next stage
            self.last = std::time::Instant::now();
        }
    }
}

#[cfg(test)]
#[path = "frame_tests.rs"]
mod tests;
