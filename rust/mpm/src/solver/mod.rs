//! The MLS-MPM solver (Hu et al. 2018, "A moving least squares material
//! point method with displacement discontinuity and two-way rigid body
//! coupling"; APIC transfers, Jiang et al. 2015; quadratic B-splines).
//!
//! One substep, one file per stage:
//!
//! 1. `block_sort.rs`: sort the particles into sparse blocks (a stable
//!    counting sort, each block's count taken by the previous g2p) and
//!    schedule the team's work (`grid.rs`: the sparse grid's buffers);
//! 2. `p2g.rs`: per sparse block, into a private padded buffer (no atomics,
//!    no shared writes);
//! 3. `grid_update.rs`: per output block, gather the overlapping padded
//!    buffers in a fixed order, add gravity, apply walls and colliders;
//! 4. `g2p.rs`: per particle, new `v`, `C`, position, the material update
//!    (`crate::material`: each particle under the model of its parameter
//!    set, sixteen of one set at a time) and the stress, and the
//!    particle's block key for the next substep.
//!
//! `frame.rs` runs a frame's substeps on a persistent team of threads
//! (`team.rs`: one entry into the pool per frame, a barrier between stages,
//! each member's own blocks claimed first from atomic counters), or on the calling thread alone when
//! that is faster (a busy machine): `mode.rs` measures both and chooses.
//!
//! `cfl.rs` chooses the substep size and drives the frame, with rollback
//! and retry. The B-spline weights live in `kernel.rs`. `particles.rs`
//! changes the particles between frames; `bodies.rs` the rigid bodies.
//! `large_step.rs` drives the frame of the other integrator,
//! `integrator = "projection"` (`crate::projection`: incompressible water
//! that steps at the flow's pace).
//!
//! Grid work touches only blocks that contain particles and their `+1`
//! neighbours (the B-spline stencil reaches 2 nodes ahead), so the cost follows
//! the particle count, not the domain volume. Every reduction happens in a
//! fixed order that does not depend on the thread count: results are bitwise
//! identical for any number of threads.

mod block_sort;
mod bodies;
mod cfl;
mod frame;
mod g2p;
mod grid;
mod grid_update;
mod large_step;
mod mode;
mod p2g;
mod particles;
mod team;

pub use crate::material::sand::drucker_prager_project;

use nalgebra::SVector;

use crate::body::Bodies;
use crate::collider::{Collider, PROJECT_DEPTH_CELLS, ShallowCells};
use crate::dim::{Dim, DimOps};
use crate::error::{MpmError, Result, check_budget};
use crate::isa::Isa;
use crate::material::Models;
use crate::params::SolverParams;
use crate::particles::Particle;
use grid::{SparseGrid, Stencil};

/// A pending move of a collider over the next frame
/// ([`Solver::move_collider`]): its anchor ([`crate::Shape::anchor`]) goes
/// from `start` to `end` linearly in time, substep by substep.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ColliderMove<const D: usize> {
    /// Anchor at the frame's start [m] (where the collider was when the move was set).
    pub start: SVector<f32, D>,
    /// Anchor at the frame's end [m].
    pub end: SVector<f32, D>,
    /// The collider's velocity in its boundary condition [m/s]; `None`:
    /// `(end − start) / dt_frame`, computed in f64.
    pub velocity: Option<SVector<f32, D>>,
}

impl<const D: usize> ColliderMove<D> {
    /// The velocity the boundary condition uses over a frame of `dt_frame` seconds.
    pub fn velocity_over(&self, dt_frame: f32) -> SVector<f32, D> {
        self.velocity.unwrap_or_else(|| {
            SVector::from_fn(|d, _| {
                ((self.end[d] as f64 - self.start[d] as f64) / dt_frame as f64) as f32
            })
        })
    }

    /// The anchor after substep `k` of `n` (`k = n`: `end` exactly).
    fn anchor_after(&self, k: usize, n: usize) -> SVector<f32, D> {
        if k >= n {
            return self.end;
        }
        let f = k as f64 / n as f64;
        SVector::from_fn(|d, _| {
            let (a, b) = (self.start[d] as f64, self.end[d] as f64);
            (a + (b - a) * f) as f32
        })
    }
}

/// Largest |coordinate| of a collider's anchor [m]: far beyond the unit
/// domain, small enough that `(end − start) / dt_frame` stays finite.
pub const MAX_ANCHOR_COORD: f32 = 1.0e3;

/// Statistics of one `step_frame` call.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct FrameStats {
    /// Substeps taken.
    pub substeps: usize,
    /// Substep size [s].
    pub dt: f32,
    /// Largest particle speed at the end of the frame [m/s].
    pub max_speed: f32,
    /// Sparse blocks holding particles during the last substep.
    pub active_blocks: usize,
    /// Times the frame was restarted with the substep halved (after a
    /// non-finite state or a CFL violation).
    pub retries: usize,
    /// Projection steps whose solved velocity would have carried water
    /// farther than a step may, stopped before the particles moved: the
    /// rest of the frame takes shorter steps, and nothing rolls back
    /// (`solver/large_step.rs`; 0 on the explicit step).
    pub replans: usize,
}

/// What a substep left behind (checked in g2p, particle by particle).
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord)]
pub(crate) enum Health {
    /// Every particle is finite and physical (what `Particle::validate` and
    /// so `restore` accept).
    Ok,
    /// A sand or solid particle's `det F ≤ 0`.
    Inverted,
    /// A non-finite value, or a water particle's `J ≤ 0` (a snow particle's `J_P ≤ 0`).
    NonFinite,
}

/// MLS-MPM solver for `D` = 2 or 3.
pub struct Solver<const D: usize>
where
    Dim<D>: DimOps<D>,
{
    params: SolverParams<D>,
    colliders: Vec<Collider<D>>,
    /// Each collider's pending move for the next frame (`move_collider`).
    moves: Vec<Option<ColliderMove<D>>>,
    /// Each collider's velocity [m/s] in the frame under way: `Some` only
    /// for a collider that moves with a velocity other than zero (the others
    /// take the static boundary condition, bit for bit).
    collider_velocity: Vec<Option<SVector<f32, D>>>,
    /// Each projecting sampled collider's [`ShallowCells`], made once (a
    /// collider only translates): where its particle projection can act
    /// ([`Collider::reach`]).
    shallow: Vec<Option<ShallowCells>>,
    /// The rigid bodies (`solver/bodies.rs`, `crate::body`).
    bodies: Bodies<D>,
    /// Particles in storage order: sorted by sparse block, then by id.
    particles: Vec<Particle<D>>,
    /// `ids[slot]`: the public index of the particle stored at `slot`.
    ids: Vec<u32>,
    /// Scratch for the next substep's `ids` (g2p writes here).
    ids_next: Vec<u32>,
    /// `slot_of[id]`: where particle `id` is stored.
    slot_of: Vec<u32>,
    /// Scratch for the next substep's storage (g2p writes here in block order).
    next: Vec<Particle<D>>,
    /// `ids` and `slot_of` at the start of the frame under way, and its
    /// particles when a team runs it (`start_copied`), to roll back to
    /// (`step_frame`).
    rollback: (Vec<u32>, Vec<u32>, Vec<Particle<D>>),
    /// Whether `rollback.2` holds the particles at the start of the frame
    /// attempt under way (a team runs it: its g2p reorders every substep).
    start_copied: bool,
    /// Whether `next` holds the particles at the start of the frame attempt
    /// under way: its first substep's g2p reorders the particles into the
    /// other buffer, the later ones update them in place
    /// (`Solver::g2p_block`), so `next` keeps the frame's start, what a
    /// rollback restores (`step_frame`).
    start_in_next: bool,
    time: f64,
    frame: u64,
    grid: SparseGrid,
    stencil: Stencil<D>,
    /// The process's pool of `num_threads` threads, shared with the other
    /// solvers that ask for as many ([`crate::pool::shared_pool`]), and the
    /// process id it was taken in (a forked child takes a new one).
    pool: std::sync::Arc<rayon::ThreadPool>,
    pool_pid: u32,
    /// Whether frames run on the team or the calling thread alone (`mode.rs`).
    mode: mode::ModeChoice,
    /// A team sorts in one serial section below this many particles per
    /// member, in chunks above (`frame.rs`; tests set it to try both).
    serial_sort_below: usize,
    /// Print per-stage substep timings and each frame attempt's mode choice to
    /// stderr (env `HYBRIDMPM_PROFILE` set at construction).
    profile: bool,
    /// The compiled copy of the frame loop that runs ([`crate::isa`]).
    isa: Isa,
    /// The table of parameter sets and each set's constants, indexed by
    /// `Particle::set`.
    models: Models,
    /// Memory budget [bytes] for what the inputs make the solver allocate
    /// (`None`: unlimited); see [`Solver::with_memory_budget`].
    memory_budget: Option<u64>,
    /// The projection integrator's grids (`large_step.rs`), made by its first
    /// frame, and the frames its last step still spans (checkpointed).
    large_step: Option<Box<crate::projection::Projection<D>>>,
    drift_frames: u32,
}

impl<const D: usize> Solver<D>
where
    Dim<D>: DimOps<D>,
{
    /// A solver with no particles and no memory budget. Errors name the bad
    /// parameter.
    pub fn new(params: SolverParams<D>, colliders: Vec<Collider<D>>) -> Result<Self> {
        Self::with_memory_budget(params, colliders, None)
    }

    /// A solver with no particles whose allocations that scale with an input
    /// are estimated first and refused beyond `memory_budget` bytes
    /// ([`MpmError::OverBudget`]; `None`: no budget): the block lattice,
    /// [`Solver::grid_bytes`] (field `n_grid`, checked here), and the
    /// particles, [`Solver::bytes_per_particle`] each (field `positions`,
    /// checked when particles are added or restored).
    ///
    /// Errors name the bad parameter: `colliders[i].half_extents` /
    /// `colliders[i].radius` also for a collider too thin for the grid
    /// ([`Collider::validate_resolution`]).
    pub fn with_memory_budget(
        params: SolverParams<D>,
        colliders: Vec<Collider<D>>,
        memory_budget: Option<u64>,
    ) -> Result<Self> {
        if !(D == 2 || D == 3) {
            return Err(MpmError::invalid("dim", format!("must be 2 or 3, got {D}")));
        }
        params.validate()?;
        for (i, c) in colliders.iter().enumerate() {
            let field = format!("colliders[{i}]");
            c.validate(&field)?;
            c.validate_resolution(&field, params.dx())?;
        }
        check_budget(
            "n_grid",
            &format!(
                "the block index of a {D}D grid of n_grid = {} cells per side",
                params.n_grid
            ),
            Self::grid_bytes(params.n_grid),
            memory_budget,
        )?;
        let (grid, stencil) = grid::new_grid::<D>(params.n_grid)?;
        let pool = crate::pool::shared_pool(params.num_threads)?;
        let nc = colliders.len();
        let depth = PROJECT_DEPTH_CELLS * params.dx();
        let shallow = colliders
            .iter()
            .map(|c| {
                c.project
                    .then(|| ShallowCells::new(&c.shape, depth))
                    .flatten()
            })
            .collect();
        let isa = Isa::detect();
        let models = Models::new::<D>(params.table(), isa);
        Ok(Solver {
            models,
            params,
            colliders,
            shallow,
            moves: vec![None; nc],
            collider_velocity: vec![None; nc],
            bodies: Bodies::default(),
            particles: Vec::new(),
            ids: Vec::new(),
            ids_next: Vec::new(),
            slot_of: Vec::new(),
            next: Vec::new(),
            rollback: Default::default(),
            start_in_next: false,
            start_copied: false,
            time: 0.0,
            frame: 0,
            grid,
            stencil,
            pool,
            pool_pid: std::process::id(),
            mode: Default::default(),
            serial_sort_below: frame::SERIAL_SORT_BELOW,
            profile: std::env::var_os("HYBRIDMPM_PROFILE").is_some(),
            isa,
            memory_budget,
            large_step: None,
            drift_frames: 0,
        })
    }

    /// The instruction set the frame loop runs with ([`crate::isa`]): the
    /// fastest this CPU has, unless `HYBRIDMPM_ISA` said otherwise when the
    /// solver was made. Results are the same bits on every variant.
    pub fn isa(&self) -> Isa {
        self.isa
    }

    /// Runs the frame loop with `isa` from the next frame on. Errors (field
    /// `isa`) when this CPU lacks it.
    pub fn set_isa(&mut self, isa: Isa) -> Result<()> {
        if !isa.available() {
            return Err(MpmError::invalid(
                "isa",
                format!("this CPU cannot run the {} frame loop", isa.name()),
            ));
        }
        self.isa = isa;
        self.models.set_isa(isa);
        Ok(())
    }

    /// Bytes the solver allocates for a grid of `n_grid` cells per side
    /// whatever the particles: the two block-lattice index maps, 8 bytes per
    /// block of `B^D` nodes (`None`: beyond `u128`). 3D `n_grid = 4096`
    /// needs 8.1 GiB.
    pub fn grid_bytes(n_grid: usize) -> Option<u128> {
        grid::lattice_bytes::<D>(n_grid)
    }

    /// Bytes per particle the solver allocates (estimate): the state, the
    /// g2p double buffer, the frame's rollback copy and one copy for reading
    /// or writing a field (4 × the particle struct), the block keys and
    /// index arrays, and the sparse-grid buffers at one particle per cell.
    /// 2D: 525 bytes, 3D: 906 bytes.
    pub fn bytes_per_particle() -> usize {
        grid::bytes_per_particle::<D>()
    }

    /// The memory budget [bytes] (`None`: unlimited).
    pub fn memory_budget(&self) -> Option<u64> {
        self.memory_budget
    }

    /// Sets the memory budget for later calls (`None`: unlimited).
    pub fn set_memory_budget(&mut self, memory_budget: Option<u64>) {
        self.memory_budget = memory_budget;
    }

    /// Refuses `n` particles beyond the memory budget (field `positions`).
    pub fn check_particle_budget(&self, n: usize) -> Result<()> {
        check_budget(
            "positions",
            &format!("{n} particles ({} bytes each)", Self::bytes_per_particle()),
            (n as u128).checked_mul(Self::bytes_per_particle() as u128),
            self.memory_budget,
        )
    }

    pub fn params(&self) -> &SolverParams<D> {
        &self.params
    }

    /// The colliders at their current poses.
    pub fn colliders(&self) -> &[Collider<D>] {
        &self.colliders
    }

    fn check_collider(&self, index: usize) -> Result<()> {
        if index >= self.colliders.len() {
            return Err(MpmError::invalid(
                "index",
                format!(
                    "no collider {index}: the solver has {}",
                    self.colliders.len()
                ),
            ));
        }
        Ok(())
    }

    fn check_vector(field: &str, v: &SVector<f32, D>, bound: f32) -> Result<()> {
        if !v.iter().all(|x| x.is_finite() && x.abs() <= bound) {
            return Err(MpmError::invalid(
                field,
                format!(
                    "must be {D} finite numbers of magnitude <= {bound}, got {:?}",
                    v.as_slice()
                ),
            ));
        }
        Ok(())
    }

    /// Where collider `index` is: its anchor ([`crate::Shape::anchor`]) [m].
    /// Errors (field `index`) for no such collider.
    pub fn collider_anchor(&self, index: usize) -> Result<SVector<f32, D>> {
        self.check_collider(index)?;
        Ok(self.colliders[index].shape.anchor())
    }

    /// Puts collider `index` at `anchor` now, without motion (its velocity
    /// is zero in the boundary condition; a checkpoint restore, a reset), and
    /// drops its pending move. Errors name `index` or `position` (not
    /// finite, or a coordinate beyond [`MAX_ANCHOR_COORD`]).
    pub fn place_collider(&mut self, index: usize, anchor: SVector<f32, D>) -> Result<()> {
        self.check_collider(index)?;
        Self::check_vector("position", &anchor, MAX_ANCHOR_COORD)?;
        self.colliders[index].shape.set_anchor(anchor);
        self.moves[index] = None;
        Ok(())
    }

    /// Moves collider `index` over the next frame: its anchor goes linearly
    /// in time from where it is to `end` [m], reached exactly at the frame's
    /// end (substep `k` of `n` puts it at `start + (end − start)·k/n`, in
    /// f64, before its grid update), and its boundary condition acts on the
    /// grid velocity relative to `velocity` [m/s] (`None`: `(end − start) /
    /// dt_frame`). The move is used once: after the frame the collider rests
    /// at `end` unless moved again. A velocity of exactly zero takes the
    /// static boundary condition, bit for bit. The substep count accounts
    /// for the collider's speed as for a particle's. Replaces an earlier
    /// pending move. Errors name `index`, `position` or `velocity` (not
    /// finite, or beyond [`MAX_ANCHOR_COORD`]).
    pub fn move_collider(
        &mut self,
        index: usize,
        end: SVector<f32, D>,
        velocity: Option<SVector<f32, D>>,
    ) -> Result<()> {
        self.check_collider(index)?;
        Self::check_vector("position", &end, MAX_ANCHOR_COORD)?;
        if let Some(v) = &velocity {
            Self::check_vector("velocity", v, f32::MAX)?;
        }
        let start = self.colliders[index].shape.anchor();
        self.drift_frames = 0; // a projection step spanning frames ends: the next frame steps the move
        self.moves[index] = Some(ColliderMove {
            start,
            end,
            velocity,
        });
        Ok(())
    }

    /// The pending move of collider `index` for the next frame, if any.
    pub fn collider_move(&self, index: usize) -> Option<ColliderMove<D>> {
        self.moves.get(index).copied().flatten()
    }

    /// The fastest pending move's speed [m/s] over a frame of `dt_frame`
    /// seconds (`None`: nothing moves).
    fn move_speed(&self, dt_frame: f32) -> Option<f32> {
        self.moves
            .iter()
            .flatten()
            .map(|m| crate::dim::norm(&m.velocity_over(dt_frame)))
            .reduce(f32::max)
    }

    /// Start of a frame: the velocity each moving collider has in it.
    fn begin_moves(&mut self, dt_frame: f32) {
        for (v, m) in self.collider_velocity.iter_mut().zip(&self.moves) {
            *v = m
                .map(|m| m.velocity_over(dt_frame))
                .filter(|u| u.iter().any(|&x| x != 0.0));
        }
    }

    /// Before substep `k` (1-based: the pose at that substep's end) of `n`:
    /// the moving colliders' poses.
    pub(super) fn pose_colliders(&mut self, k: usize, n: usize) {
        for (c, m) in self.colliders.iter_mut().zip(&self.moves) {
            if let Some(m) = m {
                c.shape.set_anchor(m.anchor_after(k, n));
            }
        }
        // the bodies' rigid world moves them there too (docs/bodies.md)
        if !self.bodies.is_empty() {
            let at = self.colliders.iter().zip(&self.moves).map(|(c, m)| {
                m.map(|_| {
                    let a = c.shape.anchor();
                    std::array::from_fn(|d| if d < D { a[d] } else { 0.0 })
                })
            });
            self.bodies.move_obstacles(at);
        }
    }

    /// End of a frame: done, each moved collider rests where its move ended
    /// and the moves are used; not done (the frame failed and the state is
    /// its start), each is back at its start and its move still pending.
    fn end_moves(&mut self, done: bool) {
        for (c, m) in self.colliders.iter_mut().zip(self.moves.iter_mut()) {
            if let Some(mv) = m {
                c.shape.set_anchor(if done { mv.end } else { mv.start });
                if done {
                    *m = None;
                }
            }
        }
        self.collider_velocity.iter_mut().for_each(|v| *v = None);
    }

    /// The particles in their public order (index = the order they were given in).
    pub fn particles(&self) -> Vec<Particle<D>> {
        self.slot_of
            .iter()
            .map(|&s| self.particles[s as usize])
            .collect()
    }

    /// Visit the particles in their public order.
    pub fn for_each_particle(&self, mut f: impl FnMut(usize, &Particle<D>)) {
        for (i, &s) in self.slot_of.iter().enumerate() {
            f(i, &self.particles[s as usize]);
        }
    }

    pub fn num_particles(&self) -> usize {
        self.particles.len()
    }

    /// Simulated time [s].
    pub fn time(&self) -> f64 {
        self.time
    }

    /// How the frame attempts so far ran: `(alone, team)`, the calling
    /// thread alone or the pool's team (probes of the other way included;
    /// every attempt alone on a pool of one thread). Which one runs is the
    /// solver's choice by measured cost (`ModeChoice`, docs/engine.md); a
    /// benchmark reads it to tell a slow team from a frame run alone.
    pub fn mode_runs(&self) -> (u64, u64) {
        (self.mode.runs[0], self.mode.runs[1])
    }

    /// Frames advanced so far.
    pub fn frame(&self) -> u64 {
        self.frame
    }

    /// Lower and upper bound of valid particle coordinates: one cell inside the domain.
    pub fn domain_bounds(&self) -> (f32, f32) {
        let dx = self.params.dx();
        (dx, 1.0 - dx)
    }
}
