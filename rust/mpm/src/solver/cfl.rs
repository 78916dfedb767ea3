//! Substep size and the frame loop: the CFL condition, rollback and retry.
//!
//! A frame of `dt_frame` seconds is cut into `n` equal substeps with
//! `Δt = dt_frame / n ≤ cfl·Δx / (c + |v|max)`, `c` the largest wave speed
//! of the parameter sets present (water: `sqrt(K/ρ)`; sand and the solids:
//! the P-wave speed `sqrt((λ + 2μ)/ρ)`, snow's with its hardening) — the explicit-integration stability limit. If a
//! substep still produces a non-finite state or moves a particle more than
//! one cell, the frame is rolled back to its start and retried with the
//! substep halved, as long as `max_substeps` allows.

use rayon::prelude::*;

use super::{FrameStats, Solver};
use crate::dim::{Dim, DimOps};
use crate::error::{MpmError, Result};
use crate::pool::shared_pool;

impl<const D: usize> Solver<D>
where
    Dim<D>: DimOps<D>,
{
    /// Whether a pass over every particle goes to the pool: past [`SERIAL_SPEED_SCAN`] particles, with
    /// more than one thread, and not in a forked child (where the pool's threads do not exist). With
    /// fewer particles a scan on this thread takes less time than waking the pool; a pool of one thread
    /// is shared (`crate::pool`: the scan would wait for other solvers' scans).
    pub(super) fn scan_in_parallel(&self) -> bool {
        self.pool_pid == std::process::id()
            && self.particles.len() > SERIAL_SPEED_SCAN
            && self.pool.current_num_threads() > 1
    }

    /// The largest `f(particle)` (0 without particles; a NaN is passed over), on the pool where
    /// [`Self::scan_in_parallel`]: a maximum, the same in any order.
    pub(super) fn max_over_particles(
        &self,
        f: impl Fn(&crate::particles::Particle<D>) -> f32 + Sync + Send,
    ) -> f32 {
        if self.scan_in_parallel() {
            self.pool
                .install(|| self.particles.par_iter().map(&f).reduce(|| 0.0, f32::max))
        } else {
            self.particles.iter().map(&f).fold(0.0, f32::max)
        }
    }

    /// Largest wave speed among the parameter sets present [m/s]: water
    /// `sqrt(K/ρ)` (or, if larger, its viscous limit as a speed,
    /// [`crate::material::WaterParams::viscous_speed`]), the others their P-wave speed `sqrt((λ + 2μ)/ρ)`, snow's
    /// hardened by `e^{ξ(1 − J_P)}` at its smallest `J_P` present.
    pub(super) fn wave_speed(&self) -> f32 {
        self.wave_speed_of().0
    }

    /// [`Self::wave_speed`] and the parameter set that has it (`None`
    /// without particles).
    fn wave_speed_of(&self) -> (f32, Option<usize>) {
        let models = &self.models.models;
        let n = models.len();
        let mut has = vec![false; n];
        let mut jp_min = vec![f32::INFINITY; n];
        let reads_j: Vec<bool> = models.iter().map(|m| m.wave_reads_j()).collect();
        let any_reads_j = reads_j.iter().any(|&r| r);
        let mut found = 0;
        for p in &self.particles {
            let s = p.set as usize;
            if !has[s] {
                has[s] = true;
                found += 1;
            }
            if any_reads_j {
                if reads_j[s] {
                    jp_min[s] = jp_min[s].min(p.j);
                }
            } else if found == n {
                break;
            }
        }
        let mut c = 0.0f32;
        let mut of = None;
        let (cfl, dx) = (self.params.cfl, self.params.dx());
        for (s, m) in models.iter().enumerate() {
            if !has[s] {
                continue;
            }
            let cs = m.wave_speed::<D>(cfl, dx, jp_min[s]);
            // a NaN or larger speed names its set
            if of.is_none() || !(cs <= c) {
                c = if cs.is_nan() {
                    f32::INFINITY
                } else {
                    cs.max(c)
                };
                of = Some(s);
            }
        }
        (c, of)
    }

    /// Substep count the CFL condition asks for over a frame of `dt_frame`
    /// seconds: `ceil(dt_frame / dt_max)` (at least 1) with
    /// `dt_max = cfl·dx / (c + |v|max)`, or `params.substeps` if set.
    ///
    /// Errors: `InvalidInput` (field `dt_frame`) unless `dt_frame` is in
    /// (0, 1] s; [`MpmError::TooManySubsteps`] (naming the particles' max
    /// speed) when more than `max_substeps` would be needed: the count is
    /// never saturated or capped, a frame that cannot be stepped is an error
    /// here as in [`Solver::step_frame`].
    pub fn substeps_for(&self, dt_frame: f32) -> Result<usize> {
        check_dt_frame(dt_frame)?;
        if self.drift_frames > 0 && self.bodies.is_empty() {
            return Ok(0); // a frame inside the projection's last step (`large_step.rs`)
        }
        if let Some(s) = self.params.substeps {
            return Ok(s);
        }
        let vmax = self.max_over_particles(|p| crate::dim::norm(&p.v));
        // a moving collider gives the fluid its speed: it counts as a particle's
        let vmax = match self.move_speed(dt_frame) {
            Some(u) => vmax.max(u),
            None => vmax,
        };
        // and so does a body's fastest point
        let vmax = vmax.max(self.bodies.max_speed());
        let (cfl, c) = self.step_bound();
        let dt_max = cfl * self.params.dx() / (c + vmax).max(1e-6);
        let needed = (dt_frame / dt_max).ceil();
        // `needed` may be inf (dt_max = 0) or far beyond usize: compare before converting
        if !(needed as f64 <= self.params.max_substeps as f64) {
            // the same in f64, where speeds up to f32::MAX do not overflow,
            // naming what moves fastest and whose wave speed it is
            let particles = self
                .particles
                .iter()
                .map(|p| {
                    p.v.iter()
                        .map(|&x| (x as f64) * (x as f64))
                        .sum::<f64>()
                        .sqrt()
                })
                .fold(0.0f64, f64::max);
            let mut speed_of = "particles".to_string();
            let mut vmax64 = particles;
            if let Some(u) = self.move_speed(dt_frame)
                && (u as f64) > vmax64
            {
                vmax64 = u as f64;
                speed_of = "a moving obstacle".to_string();
            }
            for (i, u) in self.bodies.point_speeds().into_iter().enumerate() {
                if u > vmax64 {
                    vmax64 = u;
                    speed_of = format!("body {i}'s fastest point (|v| + |ω|·R)");
                }
            }
            let (c, set) = self.wave_speed_of();
            let wave_of = match set {
                _ if !self.params.integrator.is_explicit() => "the projection (√(|g|·dx))".into(),
                Some(s) => format!(
                    "parameter set {s} ({})",
                    self.models.params[s].material().name()
                ),
                None => "no material".to_string(),
            };
            let c = if self.params.integrator.is_explicit() {
                c
            } else {
                self.step_bound().1
            };
            let dt_max64 = cfl as f64 * self.params.dx() as f64 / (c as f64 + vmax64).max(1e-6);
            return Err(MpmError::TooManySubsteps {
                needed: (dt_frame as f64 / dt_max64).ceil(),
                max_substeps: self.params.max_substeps,
                max_speed: vmax64,
                wave_speed: c,
                dt_max: dt_max64,
                dt_frame,
                speed_of,
                wave_of,
            });
        }
        Ok((needed as usize).max(1))
    }

    /// Advance one frame of `dt_frame` seconds (default 2.5e-3) in as many
    /// substeps as the CFL condition requires (`cfl·dx / (c + |v|max)`), or
    /// `params.substeps` if set.
    ///
    /// Stability: when a substep leaves a non-finite state, inverts a sand
    /// particle (`det F ≤ 0`) or violates the CFL condition (a particle would
    /// travel more than one cell `dx` in a substep), the frame is rolled back
    /// to its start and retried with the substep halved, up to
    /// `max_substeps` (`FrameStats::retries` counts the restarts). A frame
    /// that returns leaves a state that [`Solver::checkpoint`] /
    /// [`Solver::restore`] accept.
    ///
    /// Errors: `InvalidInput` for a bad `dt_frame`; `TooManySubsteps` when
    /// more than `max_substeps` would be needed (state unchanged);
    /// `NonFinite` / `Inverted` / `CflViolation` when even `max_substeps`
    /// substeps fail, in which case the state is restored to the start of
    /// the frame.
    pub fn step_frame(&mut self, dt_frame: f32) -> Result<FrameStats> {
        check_dt_frame(dt_frame)?;
        if self.pool_pid != std::process::id() {
            // We are in a forked child: the parent's worker threads do not exist here.
            self.pool = shared_pool(self.params.num_threads)?;
            self.pool_pid = std::process::id();
        }
        let n_sub = self.substeps_for(dt_frame)?;
        if !self.params.integrator.is_explicit() {
            return self.step_frame_projection(dt_frame, n_sub);
        }
        self.begin_moves(dt_frame);
        if self.particles.is_empty() {
            self.end_moves(true);
            self.time += dt_frame as f64;
            self.frame += 1;
            let dt = dt_frame / n_sub as f32;
            return Ok(FrameStats {
                substeps: n_sub,
                dt,
                max_speed: 0.0,
                active_blocks: 0,
                retries: 0,
                replans: 0,
            });
        }
        // the frame's start, to roll back to (buffers kept across frames:
        // allocating them afresh cost 10–30 µs a frame at 789 particles);
        // the particles stay in `next` (`start_in_next`) or are copied when
        // a team runs the attempt (`start_copied`, `run_substeps`)
        self.rollback.0.clone_from(&self.ids);
        self.rollback.1.clone_from(&self.slot_of);
        let max_travel = self.params.dx(); // a particle may not cross more than one cell per substep
        let mut n_sub = n_sub;
        let mut retries = 0;
        loop {
            let dt = dt_frame / n_sub as f32;
            self.begin_bodies();
            let result = self.run_substeps(n_sub, dt, max_travel, retries);
            self.bodies.end(result.is_ok(), dt_frame);
            match result {
                Ok(vmax) => {
                    self.end_moves(true);
                    self.time += dt_frame as f64;
                    self.frame += 1;
                    let active_blocks = self.grid.src_blocks.len();
                    return Ok(FrameStats {
                        substeps: n_sub,
                        dt,
                        max_speed: vmax,
                        active_blocks,
                        retries,
                        replans: 0,
                    });
                }
                Err(e) => {
                    // Roll back to the frame's start; retry with the substep halved
                    // while the substep budget allows it.
                    if self.start_copied {
                        self.particles.clone_from(&self.rollback.2);
                    } else if self.start_in_next {
                        std::mem::swap(&mut self.particles, &mut self.next);
                        self.start_in_next = false;
                    }
                    self.ids.clone_from(&self.rollback.0);
                    self.slot_of.clone_from(&self.rollback.1);
                    if 2 * n_sub > self.params.max_substeps {
                        self.end_moves(false);
                        return Err(e);
                    }
                    n_sub *= 2;
                    retries += 1;
                }
            }
        }
    }
}

/// Particles up to which a pass over them ([`Solver::scan_in_parallel`]: the
/// step count's and the large step's speed scans, its rollback copy) runs on
/// the calling thread: about 1 ns each, where handing the scan to the pool
/// (`install`) cost 20–27 µs per frame on a 2-core VM, asleep between
/// frames (sand2d on a 64² grid, 789 particles: 4% of its frame).
const SERIAL_SPEED_SCAN: usize = 1 << 15;

/// `dt_frame` must be in (0, 1] s.
fn check_dt_frame(dt_frame: f32) -> Result<()> {
    if dt_frame.is_finite() && dt_frame > 0.0 && dt_frame <= 1.0 {
        Ok(())
    } else {
        Err(MpmError::invalid(
            "dt_frame",
            format!("must be in (0, 1] s, got {dt_frame}"),
        ))
    }
}
