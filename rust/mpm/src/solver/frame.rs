//! The substeps of one frame attempt, run by a persistent team of threads
//! ([`super::team`]): the one frame loop of the engine.
//!
//! Per substep, with one barrier between stages:
//!
//! 1. thread 0, serial: finish the previous substep's g2p (the new storage
//!    order), check its health and speed, sort the particles into blocks
//!    (`grid.rs`) and size the buffers;
//! 2. p2g per source block (`p2g.rs`);
//! 3. grid update per output block (`grid_update.rs`);
//! 4. g2p per source block (`g2p.rs`), each block reporting its health and
//!    largest speed.
//!
//! Stages 2–4 are parallel: the team's threads claim blocks from an atomic
//! counter, and each block writes only its own output, so results are
//! bitwise the same for any number of threads.

use std::sync::Mutex;

use super::g2p::G2pOut;
use super::team::{G2P, GRID, KEYS, P2G, RawSlice, SORT_COUNT, SORT_MARK, SORT_SCATTER, Team};
use super::{Health, Solver};
use crate::dim::{Dim, DimOps};
use crate::error::{MpmError, Result};
use crate::isa::{Isa, x86_64_v3};
use crate::kernel::{Cell, cell_of};
use crate::material::sand::SandModel;
use crate::particles::Particle;

/// What thread 0 publishes for a substep's parallel stages: the sizes of the
/// block lists and the buffers the stages write, chunk by chunk.
struct Stage<const D: usize> {
    key_by_id: RawSlice<u32>,
    src_map: RawSlice<u32>,
    counts: RawSlice<u32>,
    sorted: RawSlice<u32>,
    n_src: usize,
    n_out: usize,
    local: RawSlice<[f32; 4]>,
    out_v: RawSlice<[f32; 4]>,
    next: RawSlice<Particle<D>>,
    ids_next: RawSlice<u32>,
    slot_of: RawSlice<u32>,
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
        let pool = self.pool.clone();
        let pool_threads = pool.current_num_threads().max(1);
        let (team_chosen, probe) = self.mode.choose();
        let use_team = pool_threads > 1 && team_chosen;
        self.mode.runs[use_team as usize] += 1;
        let threads = if use_team { pool_threads } else { 1 };
        let started = std::time::Instant::now();
        let team: Team<Stage<D>> = Team::new(threads);
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
            n_chunks: threads,
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
            n_chunks,
            n_sub,
            dt,
            max_travel,
            retries,
        } = *args;
        // the cells of the frame's first substep, in parallel chunks
        team.barrier_then(|| {
            // SAFETY: serial section
            let s = unsafe { &mut *sp.0 };
            let n = s.particles.len();
            s.grid.keys.resize(n, Cell::default());
            s.grid.key_by_id.resize(n, 0);
            let keys = RawSlice::new(&mut s.grid.keys);
            unsafe { team.publish(s.stage_view(keys)) };
        });
        {
            // SAFETY: parallel section: shared reads, disjoint chunk writes
            let s = unsafe { &*sp.0 };
            let view = unsafe { team.published() };
            let keys = view.cells;
            let n = s.particles.len();
            let inv_dx = s.params.n_grid as f32;
            let (log2_b, lat, pad) = (s.grid.log2_b, s.stencil.lat_stride, s.stencil.pad_stride);
            while let Some(i) = team.claim(KEYS, n.div_ceil(KEYS_CHUNK)) {
                let lo = i * KEYS_CHUNK;
                let hi = (lo + KEYS_CHUNK).min(n);
                // SAFETY: chunk i is this thread's alone
                let out = unsafe { keys.chunk_mut(lo, hi - lo) };
                for ((k, p), &id) in out.iter_mut().zip(&s.particles[lo..hi]).zip(&s.ids[lo..hi]) {
                    *k = cell_of::<D>(&p.x, inv_dx, log2_b, &lat, &pad);
                    // SAFETY: each id is at one slot, and so in one chunk
                    unsafe { view.key_by_id.write(id as usize, k.key) };
                }
            }
        }
        let mut patch = Vec::new();
        let mut cursor = Vec::new();
        let mut acc = Vec::new();
        let mut clock = Profile::new(tid == 0 && unsafe { (*sp.0).profile });
        for sub in 0..=n_sub {
            // serial: finish the previous substep's g2p and check it, then
            // start the block sort
            team.barrier_then(|| {
                // SAFETY: serial section
                let s = unsafe { &mut *sp.0 };
                if sub > 0 {
                    s.g2p_finish();
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
                if !team.stopped() {
                    // the moving colliders where they are at this substep's end
                    s.pose_colliders(sub + 1, n_sub);
                    s.sort_begin();
                    let keys = RawSlice::new(&mut s.grid.next_keys);
                    unsafe { team.publish(s.stage_view(keys)) };
                }
            });
            if sub > 0 {
                clock.lap(Lap::G2p);
                clock.print();
            }
            if team.stopped() {
                break;
            }
            // the block sort's parallel stages (see `grid.rs`)
            {
                // SAFETY: parallel section; `sort_mark`'s conditions hold
                // (chunks are claimed once; src_map is only marked here)
                let s = unsafe { &*sp.0 };
                let view = unsafe { team.published() };
                let mut mine = Vec::new();
                while let Some(c) = team.claim(SORT_MARK, n_chunks) {
                    unsafe { s.sort_mark(c, n_chunks, view.src_map, &mut mine) };
                }
                touched
                    .lock()
                    .expect("no member panicked holding it")
                    .append(&mut mine);
            }
            team.barrier_then(|| {
                // SAFETY: serial section
                let s = unsafe { &mut *sp.0 };
                let mut t = touched.lock().expect("no member panicked holding it");
                s.sort_number(&mut t, n_chunks);
                let keys = RawSlice::new(&mut s.grid.next_keys);
                unsafe { team.publish(s.stage_view(keys)) };
            });
            {
                // SAFETY: parallel section; each chunk's row / places are its own
                let s = unsafe { &*sp.0 };
                let view = unsafe { team.published() };
                while let Some(c) = team.claim(SORT_COUNT, n_chunks) {
                    unsafe { s.sort_count(c, n_chunks, view.counts) };
                }
                team.barrier();
                while let Some(c) = team.claim(SORT_SCATTER, n_chunks) {
                    unsafe { s.sort_scatter(c, n_chunks, view.sorted, &mut cursor) };
                }
            }
            team.barrier_then(|| {
                // SAFETY: serial section
                let s = unsafe { &mut *sp.0 };
                s.sort_end(n_chunks);
                let (n_src, n_out) = (s.grid.src_blocks.len(), s.grid.out_blocks.len());
                let b = 1usize << s.grid.log2_b;
                s.grid.local.resize(n_src * s.stencil.pad_nodes, [0.0; 4]);
                s.grid.out_v.resize(n_out * b.pow(D as u32), [0.0; 4]);
                let n = s.particles.len();
                s.next.resize(n, s.particles[0]);
                s.ids_next.resize(n, 0);
                s.grid.next_keys.resize(n, Cell::default());
                let keys = RawSlice::new(&mut s.grid.next_keys);
                let view = s.stage_view(keys);
                unsafe { team.publish(view) };
            });
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
            while let Some(si) = team.claim(P2G, view.n_src) {
                let buf = unsafe { view.local.chunk_mut(si * st.pad_nodes, st.pad_nodes) };
                s.p2g_block(si, buf, dt);
            }
            team.barrier();
            clock.lap(Lap::P2g);
            while let Some(oi) = team.claim(GRID, view.n_out) {
                let out = unsafe { view.out_v.chunk_mut(oi * blk_nodes, blk_nodes) };
                s.grid_update_block(oi, out, &mut acc, dt);
            }
            team.barrier();
            clock.lap(Lap::Grid);
            let sand = SandModel::new::<D>(&s.params.sand, s.isa);
            let (mut health, mut vmax2) = (Health::Ok, 0.0f32);
            while let Some(si) = team.claim(G2P, view.n_src) {
                let lo = s.grid.src_offsets[si] as usize;
                let len = s.grid.src_offsets[si + 1] as usize - lo;
                // SAFETY: block si's range of the next storage order and its
                // ids are this thread's alone
                let (h, v2) = unsafe {
                    let out = G2pOut {
                        particles: view.next.chunk_mut(lo, len),
                        cells: view.cells.chunk_mut(lo, len),
                        ids: view.ids_next.chunk_mut(lo, len),
                        slot_of: view.slot_of,
                        key_by_id: view.key_by_id,
                    };
                    s.g2p_block(si, &mut patch, out, dt, &sand)
                };
                health = health.max(h);
                vmax2 = vmax2.max(v2);
            }
            team.report(health, vmax2);
        }
    }

    /// The buffers the parallel stages write, sized for this substep.
    fn stage_view(&mut self, cells: RawSlice<Cell>) -> Stage<D> {
        Stage {
            key_by_id: RawSlice::new(&mut self.grid.key_by_id),
            src_map: RawSlice::new(&mut self.grid.src_map),
            counts: RawSlice::new(&mut self.grid.counts),
            sorted: RawSlice::new(&mut self.grid.sorted),
            n_src: self.grid.src_blocks.len(),
            n_out: self.grid.out_blocks.len(),
            local: RawSlice::new(&mut self.grid.local),
            out_v: RawSlice::new(&mut self.grid.out_v),
            next: RawSlice::new(&mut self.next),
            ids_next: RawSlice::new(&mut self.ids_next),
            slot_of: RawSlice::new(&mut self.slot_of),
            cells,
        }
    }
}

/// What the members of a frame's team share (`Solver::run_substeps`): the
/// solver, the team, the sort's touched blocks, the frame's result slot, the
/// number of sort chunks (the team's size), and the frame's substeps.
struct MemberArgs<'a, const D: usize>
where
    Dim<D>: DimOps<D>,
{
    sp: &'a SolverPtr<D>,
    team: &'a Team<Stage<D>>,
    touched: &'a Mutex<Vec<u32>>,
    result: &'a Mutex<Option<Result<f32>>>,
    n_chunks: usize,
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
mod tests {
    use super::*;
    use crate::params::SolverParams;
    use crate::particles::{Material, lattice};

    /// A water and a sand block falling and colliding, stepped `frames`
    /// frames with `threads` threads, the team forced on or off.
    fn run<const D: usize>(threads: usize, team: bool, frames: usize) -> Vec<u8>
    where
        Dim<D>: DimOps<D>,
    {
        run_with::<D>(Isa::Baseline, threads, team, frames)
    }

    /// [`run`] with the frame loop's copy for `isa`.
    fn run_with<const D: usize>(isa: Isa, threads: usize, team: bool, frames: usize) -> Vec<u8>
    where
        Dim<D>: DimOps<D>,
    {
        let params = SolverParams::<D> {
            n_grid: 48,
            num_threads: threads,
            ..Default::default()
        };
        let dx = params.dx();
        let mut s = Solver::new(params, vec![]).unwrap();
        let mut ps = lattice([0.1; D], 20, dx / 2.0, Material::Water, 1000.0);
        ps.extend(lattice([0.45; D], 14, dx / 2.0, Material::Sand, 1000.0));
        s.set_particles(ps).unwrap();
        s.mode.force = Some(team);
        s.set_isa(isa).unwrap();
        for _ in 0..frames {
            s.step_frame(2.5e-3).unwrap();
        }
        s.checkpoint()
    }

    /// The team's chunked block sort and claimed blocks give bitwise the
    /// result of one thread, for teams of 2 and 3 (more threads than this
    /// machine's cores: members are descheduled mid-stage), 2D and 3D.
    #[test]
    fn team_is_bitwise_identical_to_one_thread() {
        let one = run::<2>(1, false, 12);
        assert_eq!(one, run::<2>(2, true, 12));
        assert_eq!(one, run::<2>(3, true, 12));
        assert_eq!(one, run::<2>(2, false, 12));
        let one = run::<3>(1, false, 6);
        assert_eq!(one, run::<3>(2, true, 6));
        assert_eq!(one, run::<3>(3, true, 6));
    }

    /// Every compiled copy of the frame loop this CPU runs (`crate::isa`)
    /// gives the bits of the portable one, alone and on a team, 2D and 3D,
    /// water and sand (the blocks collide, so sand yields). On a CPU without
    /// x86-64-v3 only the portable copy is compared with itself; the
    /// machines this project is tested on have it.
    #[test]
    fn every_isa_gives_the_bits_of_the_portable_copy() {
        let base2 = run::<2>(1, false, 12);
        let base3 = run::<3>(1, false, 6);
        for isa in Isa::ALL.into_iter().filter(|i| i.available()) {
            assert_eq!(base2, run_with::<2>(isa, 1, false, 12), "{isa:?} 2D");
            assert_eq!(base2, run_with::<2>(isa, 2, true, 12), "{isa:?} 2D team");
            assert_eq!(base3, run_with::<3>(isa, 1, false, 6), "{isa:?} 3D");
            assert_eq!(base3, run_with::<3>(isa, 2, true, 6), "{isa:?} 3D team");
        }
        let mut s = Solver::<2>::new(SolverParams::default(), vec![]).unwrap();
        assert!(s.isa().available());
        for isa in Isa::ALL {
            assert_eq!(s.set_isa(isa).is_ok(), isa.available(), "{isa:?}");
        }
    }

    /// `mode_runs` counts each frame attempt under the way it ran: the team
    /// (forced on, 2 threads), the thread alone (forced off, or a pool of one
    /// thread, where "the team" is the calling thread).
    #[test]
    fn mode_runs_count_the_way_each_frame_ran() {
        for (threads, team, alone_expected) in [(2, true, false), (2, false, true), (1, true, true)]
        {
            let params = SolverParams::<2> {
                n_grid: 32,
                num_threads: threads,
                ..Default::default()
            };
            let dx = params.dx();
            let mut s = Solver::new(params, vec![]).unwrap();
            s.set_particles(lattice([0.2; 2], 10, dx / 2.0, Material::Water, 1000.0))
                .unwrap();
            s.mode.force = Some(team);
            assert_eq!(s.mode_runs(), (0, 0));
            for _ in 0..5 {
                s.step_frame(2.5e-3).unwrap();
            }
            let (alone, on_team) = s.mode_runs();
            assert!(
                alone + on_team >= 5,
                "{threads} {team}: {alone} + {on_team}"
            );
            assert_eq!(
                (alone > 0, on_team > 0),
                (alone_expected, !alone_expected),
                "{threads} {team}"
            );
        }
    }
}
