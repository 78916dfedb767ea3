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

/// The team or the calling thread alone, whichever is faster here and now.
///
/// On free cores a team of two runs a 4k-particle 2D substep 1.8× faster
/// than one thread, but when the machine has fewer free cores than the team
/// has threads (another process, or other solvers in this one, are busy),
/// its members keep waiting for each other to be scheduled and the same
/// substep became ~5× slower than one thread (measured, `yes` hogging one of
/// two cores). So each mode's cost per particle-substep is tracked, the
/// cheaper one runs, and now and then four frames run the other to keep its
/// estimate current ("probes"). A mode's cost is the median of its last
/// `WINDOW` attempts: single slow frames (another process waking up, a page
/// fault) do not count, but a way of running that is slow in most frames
/// does. (The lowest was tried first: it kept a team whose frames alternated
/// between 1.4 and 9.9 ms, when the thread pool had gone idle between frames
/// and its second core was slow to come back, against 2.4 ms alone; the mean
/// sent a team alone for 50 frames after one 10 ms frame.) The first `SKIP`
/// attempts are not counted (they allocate the buffers and wake the pool,
/// and measured up to 4× slower than the next ones).
///
/// The first probe comes at attempt `FIRST_PROBE`; after a probe that
/// confirms the choice the next one waits twice as long (from `GAP` up to
/// `MAX_GAP` attempts: a probe of the slower mode costs time), after one
/// that changes it, `GAP` or, if the solver has made fewer attempts, that
/// many (on this VM the pool's first team frames after a while alone took
/// 5 ms where the next took 1, long enough to send a new solver's team alone
/// for `GAP` frames; `a_choice_made_while_the_pool_wakes_is_checked_soon`); and when the running mode's cost rises past
/// `DEGRADED` times what it was at the last probe (the machine got busy),
/// the probe comes at once. Results are the same in both modes.
#[derive(Clone, Copy, Debug, Default)]
pub(super) struct ModeChoice {
    /// The last `WINDOW` costs per particle-substep [s] of `[solo, team]`
    /// (0: none yet).
    recent: [[f64; WINDOW]; 2],
    /// Each mode's cost when the last probe ended (0: none yet).
    baseline: [f64; 2],
    attempts: u64,
    /// The attempt at which the next probe starts (0: `FIRST_PROBE`).
    next_probe: u64,
    /// Attempts between the last probe and the next (0: `GAP`).
    gap: u64,
    /// Counted attempts left in the probe under way (0: none), and its mode.
    probe_left: u8,
    /// The warm-up under way (a solver's first attempts, a probe's, or the
    /// team's after attempts alone): its attempts and wall seconds so far
    /// (`None`: none under way).
    warm: Option<(u8, f64)>,
    /// Whether the last attempt ran on the team.
    last_team: bool,
    probed_team: bool,
    /// Attempts run `[alone, by the team]` (probes included; all alone on a
    /// pool of one thread): [`Solver::mode_runs`].
    pub(super) runs: [u64; 2],
    /// Tests: always this mode.
    #[cfg(test)]
    force: Option<bool>,
}

const FIRST_PROBE: u64 = 8;
/// Attempts per probe, of which the first `PROBE_WARMUP` are not counted:
/// after frames alone, the pool's first frames wake it, and on this VM the
/// first two team frames measured 10 and 5 ms where the third took 1.3
/// (the README's hybrid run, after its network steps).
const PROBE_LEN: u8 = 4;
const PROBE_WARMUP: u8 = 2;
/// A warm-up of the team (its first `SKIP` attempts in a solver, the first
/// `PROBE_WARMUP` of a probe, the first `PROBE_WARMUP` after attempts
/// alone) goes on until it has lasted this long [s], up to `WARMUP_MAX`
/// attempts: on this VM the pool's second core, idle for a
/// while, took 10–40 ms to come back (water3d, 4k particles, new solvers:
/// two to seven team frames of 5 ms, then 1.1 ms; alone 1.9 ms).
const WAKE_SECS: f64 = 0.05;
const WARMUP_MAX: u8 = 8;
const GAP: u64 = 50;
const MAX_GAP: u64 = 400;
const SKIP: u64 = 2;
const WINDOW: usize = 8;
const DEGRADED: f64 = 1.5;
/// The thread alone runs only when its cost is below this fraction of the
/// team's (timings are noisy).
const SOLO_MARGIN: f64 = 0.9;

impl ModeChoice {
    /// The estimated cost of a mode (0: unknown).
    fn cost(&self, team: bool) -> f64 {
        let mut v = [0.0f64; WINDOW];
        let mut n = 0;
        for &c in self.recent[team as usize].iter().filter(|&&c| c > 0.0) {
            v[n] = c;
            n += 1;
        }
        let v = &mut v[..n];
        v.sort_by(f64::total_cmp);
        match n {
            0 => 0.0,
            _ if n % 2 == 1 => v[n / 2],
            _ => 0.5 * (v[n / 2 - 1] + v[n / 2]),
        }
    }

    /// The cheaper mode as measured (the team while either is unknown).
    fn best_is_team(&self) -> bool {
        let (solo, team) = (self.cost(false), self.cost(true));
        !(solo > 0.0 && team > 0.0 && solo < SOLO_MARGIN * team)
    }

    fn next_probe(&self) -> u64 {
        if self.next_probe == 0 {
            FIRST_PROBE
        } else {
            self.next_probe
        }
    }

    /// Whether the next attempt uses the team, and whether it is a probe.
    fn choose(&self) -> (bool, bool) {
        #[cfg(test)]
        if let Some(team) = self.force {
            return (team, false);
        }
        let best = self.best_is_team();
        if self.probe_left > 0 {
            (self.probed_team, true)
        } else if self.attempts >= self.next_probe() {
            (!best, true)
        } else {
            (best, false)
        }
    }

    /// Record an attempt's cost per particle-substep [s] and its wall time
    /// [s] (the mode and probe flag that `choose` gave it).
    fn record(&mut self, team: bool, probe: bool, seconds_per_item: f64, seconds: f64) {
        let m = team as usize;
        if self.attempts == 0 {
            self.warm = Some((0, 0.0));
        }
        let starts = probe && self.probe_left == 0;
        if starts {
            // a probe starts its mode's window afresh (older samples are stale)
            self.recent[m] = [0.0; WINDOW];
            self.probe_left = PROBE_LEN - PROBE_WARMUP;
            self.probed_team = team;
        }
        if starts || (team && !self.last_team && self.attempts > 0) {
            // the pool has been idle if the thread ran alone: wake it first
            self.warm = Some((0, 0.0));
        }
        self.last_team = team;
        let least = if self.attempts < SKIP {
            SKIP as u8
        } else {
            PROBE_WARMUP
        };
        // (only the team's warm-up waits for the pool: the thread alone is
        // the caller's, already running)
        let warmup = match self.warm {
            Some((n, secs)) => n < least || (team && secs < WAKE_SECS && n < WARMUP_MAX),
            None => false,
        };
        self.warm = match self.warm {
            Some((n, secs)) if warmup => Some((n + 1, secs + seconds)),
            _ => None,
        };
        if !warmup {
            let w = &mut self.recent[m];
            w.rotate_right(1);
            w[0] = seconds_per_item;
        }
        let probe_ends = probe && !warmup && {
            self.probe_left -= 1;
            self.probe_left == 0
        };
        self.attempts += 1;
        let gap = if self.gap == 0 { GAP } else { self.gap };
        if probe_ends {
            // the probe lost: wait longer for the next one; it won: soon,
            // and sooner in a solver's first frames (a choice made while the
            // pool was waking up is checked again after as many attempts as
            // it was made after)
            self.gap = if self.best_is_team() != team {
                (2 * gap).min(MAX_GAP)
            } else {
                GAP.min(self.attempts)
            };
            self.next_probe = self.attempts + self.gap;
            self.baseline = [self.cost(false), self.cost(true)];
        } else if !probe
            && self.baseline[m] > 0.0
            && self.cost(team) > DEGRADED * self.baseline[m]
            && self.best_is_team() == team
        {
            // the running mode got slower (and still looks the cheaper):
            // measure the other one now
            self.next_probe = self.next_probe().min(self.attempts);
        }
    }
}

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
            pool.broadcast(|ctx| member(ctx.index()));
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
                // the mode choice's view of each attempt (`HMPM_PROFILE`,
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
                    s.sort_begin();
                    let keys = RawSlice::new(&mut s.grid.next_keys);
                    unsafe { team.publish(s.stage_view(keys)) };
                }
            });
            if sub > 0 {
                clock.lap(Lap::G2p);
                clock.print(unsafe { &*sp.0 });
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

/// Stages timed by thread 0 when `HMPM_PROFILE` is set.
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
}

impl Profile {
    fn new(on: bool) -> Self {
        Profile {
            on,
            last: std::time::Instant::now(),
            laps: Default::default(),
        }
    }

    fn lap(&mut self, lap: Lap) {
        if self.on {
            let now = std::time::Instant::now();
            self.laps[lap as usize] = now - self.last;
            self.last = now;
        }
    }

    fn print<const D: usize>(&mut self, s: &Solver<D>)
    where
        Dim<D>: DimOps<D>,
    {
        if self.on {
            let l = &self.laps;
            eprintln!(
                "blocks {:?} p2g {:?} grid {:?} g2p {:?} nsrc {} nout {}",
                l[Lap::Sort as usize],
                l[Lap::P2g as usize],
                l[Lap::Grid as usize],
                l[Lap::G2p as usize],
                s.grid.src_blocks.len(),
                s.grid.out_blocks.len()
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

    /// Run `n` attempts at the given costs per mode; returns how many were
    /// probes.
    fn attempts(m: &mut ModeChoice, n: usize, solo: f64, team: f64) -> usize {
        let mut probes = 0;
        for _ in 0..n {
            let (t, probe) = m.choose();
            probes += probe as usize;
            let c = if t { team } else { solo };
            m.record(t, probe, c, c);
        }
        probes
    }

    #[test]
    fn the_frames_of_a_waking_pool_are_not_counted() {
        // the team's first five frames take 5 ms (the pool's second core
        // comes back), and its first two after frames alone, then 1.1 ms;
        // alone 1.9 ms: the thread alone runs only in probes
        let mut m = ModeChoice::default();
        let (mut team_frames, mut since_alone, mut alone) = (0, 0, 0);
        for _ in 0..200 {
            let (t, probe) = m.choose();
            let c = if t {
                team_frames += 1;
                since_alone += 1;
                if team_frames <= 5 || since_alone <= 2 {
                    0.005
                } else {
                    0.0011
                }
            } else {
                alone += !probe as usize;
                since_alone = 0;
                0.0019
            };
            m.record(t, probe, c, c);
        }
        assert_eq!(m.choose(), (true, false));
        assert_eq!(alone, 0, "attempts alone outside probes");
    }

    #[test]
    fn a_choice_made_while_the_pool_wakes_is_checked_soon() {
        // the team's first frames are slow (the pool wakes), then it is
        // twice as fast as the thread alone: the thread alone wins the first
        // probe, and the team is back within about as many attempts again
        let mut m = ModeChoice::default();
        attempts(&mut m, FIRST_PROBE as usize, 2.0, 5.0);
        attempts(&mut m, PROBE_LEN as usize, 2.0, 1.0);
        assert_eq!(m.choose(), (false, false));
        let n = (FIRST_PROBE as usize + PROBE_LEN as usize) + PROBE_LEN as usize;
        attempts(&mut m, n, 2.0, 1.0);
        assert_eq!(m.choose(), (true, false));
        assert!(m.attempts < GAP, "{}", m.attempts);
    }

    #[test]
    fn the_cheaper_mode_runs_and_the_other_is_probed() {
        let mut m = ModeChoice::default();
        // nothing measured: the team; the first attempts are not counted
        for _ in 0..SKIP {
            assert_eq!(m.choose(), (true, false));
            m.record(true, false, 100.0, 100.0);
        }
        assert_eq!((m.cost(false), m.cost(true)), (0.0, 0.0));
        // the team's cost: the median of its recent attempts (one slow
        // frame does not count)
        for cost in [1.5, 0.5, 9.0, 0.9, 1.0, 1.0] {
            assert_eq!(m.choose(), (true, false));
            m.record(true, false, cost, cost);
        }
        assert_eq!(m.cost(true), 1.0);
        // four attempts probe the thread alone (the first two, which wake
        // the pool in a team's probe, do not count); only slightly cheaper,
        // it does not win
        for cost in [50.0, 20.0, 0.9, 1.0] {
            assert_eq!(m.choose(), (false, true));
            m.record(false, true, cost, cost);
        }
        assert_eq!(m.cost(false), 0.95);
        assert_eq!(m.choose(), (true, false));
        // probes that confirm the choice come ever less often: each waits
        // twice the last gap (from 2·GAP after the first) up to MAX_GAP
        let mut starts = Vec::new();
        for _ in 0..1500 {
            let (t, probe) = m.choose();
            if probe && m.probe_left == 0 {
                starts.push(m.attempts);
            }
            let c = if t { 1.0 } else { 2.0 };
            m.record(t, probe, c, c);
        }
        let len = PROBE_LEN as u64;
        assert_eq!(starts[0], FIRST_PROBE + len + 2 * GAP);
        let gaps: Vec<u64> = starts.windows(2).map(|w| w[1] - w[0] - len).collect();
        assert_eq!(gaps, [4 * GAP, MAX_GAP, MAX_GAP]);
        // the machine gets busy (the team's cost rises past DEGRADED × its
        // baseline, a probe follows): within a window and a probe of
        // attempts the thread alone runs
        attempts(&mut m, WINDOW + 2, 1.5, 5.0);
        assert_eq!(m.choose(), (false, false));
        // the team is cheaper again: within MAX_GAP and a probe it runs
        attempts(&mut m, MAX_GAP as usize + PROBE_LEN as usize, 1.5, 0.5);
        assert_eq!(m.choose(), (true, false));
        // and a solver whose team was never cheaper stays alone
        let mut m = ModeChoice::default();
        let len = PROBE_LEN as usize;
        assert!(attempts(&mut m, 1000, 1.0, 5.0) <= len + len * 1000 / (2 * GAP as usize));
        assert_eq!(m.choose(), (false, false));
    }
}
