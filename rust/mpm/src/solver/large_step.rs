//! A frame of the projection integrator (`integrator = "projection"`,
//! [`crate::projection`]): incompressible APIC water that steps at the
//! flow's pace (docs/large-step.md).
//!
//! What it steps: water particles in the box walls, around colliders, at
//! rest or moving, as solid boundaries with their own velocity
//! (`crate::projection`'s `obstacles.rs`), and around rigid bodies coupled
//! both ways in the pressure solve (its `bodies.rs`): each step applies the
//! pressure impulse to the bodies' rigid world, steps it by the step's `dt`
//! (gravity, contacts) and puts the particles that ended deeper than
//! [`PROJECT_DEPTH_CELLS`] inside a body back onto its surface. A frame
//! with bodies steps within itself (no step spans frames). Sand and the
//! solids need the explicit substeps; a solver that holds any of them, or
//! walls or colliders that are not free slip, refuses a projection frame
//! with an `InvalidInput` naming the field (`integrator`, `walls.condition`
//! or `colliders`), and its state is unchanged.
//!
//! A frame in which a collider moves takes at most one frame a step, and
//! each step sees the colliders at their poses at its end (as each
//! explicit substep does); setting a move ends a step that spans frames.
//!
//! A step may span up to [`MAX_FRAMES_PER_STEP`] frames where the flow
//! allows it (two cells a step: `dt = 2·dx/(|v|max + √(|g|·dx))`): the step
//! takes the velocity over all of them (gravity and the pressure for `k`
//! frames) and moves the particles one frame's worth; each following frame
//! of the step moves them on at that velocity (`Projection::drift`, no
//! grid), so the frames show the step's motion evenly, and the particles
//! are where one step of `k` frames puts them. The frames left in the step
//! are the solver's state: a checkpoint keeps them, and any change to the
//! particles between frames ends the step (the next frame steps the new
//! state).
//!
//! Its promises are the explicit frame's: the same bits on any number of
//! threads (the step runs on the solver's pool, its p2g in two parts fixed
//! by the particle count and summed in one order), a
//! checkpoint that restores bitwise (a step reads nothing but the
//! particles: its pressure solve starts from zero), and rollback: a step
//! that leaves a non-finite particle, or one that crossed more than
//! [`MAX_TRAVEL_CELLS`] cells, rolls the frame back to its start and
//! retries it with twice the steps, up to `max_substeps`.

use nalgebra::SVector;
use rayon::prelude::*;

use super::{FrameStats, Solver};
use crate::boundary::BoundaryCondition;
use crate::collider::PROJECT_DEPTH_CELLS;
use crate::dim::{Dim, DimOps};
use crate::error::{MpmError, Result};
use crate::material::MaterialParams;
use crate::params::WallParams;
use crate::particles::Material;
use crate::projection::{ADVECTIVE_CFL, Projection, StepBody, StepColliders, push_out_of_bodies};

/// Particles a task copies when the rollback copy goes to the pool.
const ROLLBACK_CHUNK: usize = 8192;

/// The most cells a particle may cross in one projection step before the
/// frame is retried with smaller steps (the step is chosen for
/// [`ADVECTIVE_CFL`], half of it).
pub const MAX_TRAVEL_CELLS: f32 = 2.0 * ADVECTIVE_CFL;

/// The most frames one projection step spans. Six or eight (a slow flow's
/// step at two cells spans more) keep the dam break and the column at rest,
/// but let the first sloshing mode of a tank grow, by 1.5–1.7 times its
/// amplitude over 6,000 frames, where four keep it (0.97; docs/large-step.md).
pub const MAX_FRAMES_PER_STEP: u32 = 4;

impl<const D: usize> Solver<D>
where
    Dim<D>: DimOps<D>,
{
    /// The CFL number and the wave speed [m/s] the step count follows: the
    /// materials' for the explicit substeps; for the projection the
    /// advective CFL with `√(|g|·dx)`, the speed a still surface gains
    /// falling one cell (no sound speed: the water is incompressible).
    pub(super) fn step_bound(&self) -> (f32, f32) {
        if self.params.integrator.is_explicit() {
            (self.params.cfl, self.wave_speed())
        } else {
            let g = self.params.gravity.iter().map(|g| g * g).sum::<f32>();
            (ADVECTIVE_CFL, (g.sqrt() * self.params.dx()).sqrt())
        }
    }

    /// Whether the projection can step this solver: its rest density
    /// [kg/m³], else the error naming the field.
    pub(super) fn projection_density(&self) -> Result<f32> {
        let refuse = |what: String| {
            Err(MpmError::invalid(
                "integrator",
                format!(
                    "the projection integrator steps water in the box walls only, and {what}: \
                     use integrator 'explicit'"
                ),
            ))
        };
        for (i, c) in self.colliders.iter().enumerate() {
            if c.condition == BoundaryCondition::Sticky || c.friction != 0.0 {
                return Err(MpmError::invalid(
                    "colliders",
                    format!(
                        "the projection integrator has free-slip obstacles: collider {i} is {:?} \
                         with friction {} (use 'slip' or 'separate' without friction, or \
                         integrator 'explicit')",
                        c.condition, c.friction
                    ),
                ));
            }
        }
        for axis in 0..D {
            for side in 0..2 {
                let face = self.params.walls.face(axis, side);
                if face.condition == BoundaryCondition::Sticky || face.friction != 0.0 {
                    let name = WallParams::FACE_NAMES[axis][side];
                    return Err(MpmError::invalid(
                        "walls.condition",
                        format!(
                            "the projection integrator has free-slip walls: wall {name} is \
                             {:?} with friction {} (use 'slip' or 'separate' without friction, \
                             or integrator 'explicit')",
                            face.condition, face.friction
                        ),
                    ));
                }
            }
        }
        let mut rho = None;
        for (i, &slot) in self.slot_of.iter().enumerate() {
            let p = &self.particles[slot as usize];
            let density = match (&self.models.params[p.set as usize], p.material) {
                (MaterialParams::Water(w), Material::Water) => w.density,
                _ => {
                    return refuse(format!(
                        "particle {i} is {}",
                        self.models.params[p.set as usize].material().name()
                    ));
                }
            };
            match rho {
                None => rho = Some(density),
                Some(r) if r != density => {
                    return refuse(format!(
                        "particle {i}'s water has density {density} kg/m³, another's {r}"
                    ));
                }
                _ => {}
            }
        }
        Ok(rho.unwrap_or(self.params.water.density))
    }

    /// The frames the current projection step still spans (0: the next frame steps).
    pub fn drift_frames(&self) -> u32 {
        self.drift_frames
    }

    /// Sets what [`Solver::drift_frames`] reads (checkpoint restore): at most
    /// [`MAX_FRAMES_PER_STEP`] − 1, and only for the projection.
    pub(crate) fn set_drift_frames(&mut self, frames: u32) -> Result<()> {
        if frames > 0 && (self.params.integrator.is_explicit() || frames >= MAX_FRAMES_PER_STEP) {
            return Err(MpmError::Checkpoint(format!(
                "{frames} frames left in a projection step, for a solver of integrator '{}' (at most {})",
                self.params.integrator.name(),
                MAX_FRAMES_PER_STEP - 1
            )));
        }
        self.drift_frames = frames;
        Ok(())
    }

    /// One frame of the projection ([`Solver::step_frame`] with
    /// `integrator = "projection"`): a frame inside the last step moves the
    /// particles on; otherwise one step spanning `k` frames where `n_sub`
    /// is 1 and the flow allows `k` > 1, else `n_sub` steps; with rollback
    /// and retry.
    pub(super) fn step_frame_projection(
        &mut self,
        dt_frame: f32,
        n_sub: usize,
    ) -> Result<FrameStats> {
        let mut projection = self.large_step.take().unwrap_or_else(|| {
            Box::new(Projection::new(self.params.n_grid, self.params.walls.cells))
        });
        projection.set_isa(self.isa);
        projection.set_correction_time(dt_frame);
        if !self.bodies.is_empty() {
            // a step spans no frames with bodies (adding one ends a step; a checkpoint's frames left
            // from before it was added are stepped anew: `substeps_for` counts this frame's steps)
            self.drift_frames = 0;
        }
        let result = if self.drift_frames > 0 {
            // a frame inside the last step: the particles are the ones that step checked (any change
            // between frames ends the step, a collider's move too), and their velocities are the step's
            let cols = StepColliders {
                colliders: &self.colliders,
                velocity: &self.collider_velocity,
                shallow: &self.shallow,
                bodies: &[],
            };
            let max_speed = projection.drift(&mut self.particles, dt_frame, &cols);
            self.drift_frames -= 1;
            Ok(FrameStats {
                substeps: 0,
                dt: 0.0,
                max_speed,
                active_blocks: 0,
                retries: 0,
                replans: 0,
            })
        } else {
            match self.projection_density() {
                Ok(rho) => self.projection_steps(&mut projection, dt_frame, n_sub, rho),
                Err(e) => Err(e),
            }
        };
        self.large_step = Some(projection);
        if result.is_ok() {
            self.time += dt_frame as f64;
            self.frame += 1;
        }
        result
    }

    /// The fastest particle's speed [m/s]: infinite where a particle's position or velocity is not
    /// finite (one scan for the step's check and its report).
    fn checked_max_speed(&self) -> f32 {
        self.max_over_particles(|p| {
            let s = crate::dim::norm(&p.v);
            if s.is_nan() || !p.x.iter().all(|x| x.is_finite()) {
                f32::INFINITY
            } else {
                s
            }
        })
    }

    /// The frame's start, to roll back to: a copy of the particles (on the pool past
    /// [`Solver::scan_in_parallel`]'s count, in chunks: 17 MB at 100k particles in 3D).
    fn save_rollback(&mut self) {
        if !self.scan_in_parallel() || self.rollback.2.len() != self.particles.len() {
            self.rollback.2.clone_from(&self.particles);
            return;
        }
        let (dst, src) = (&mut self.rollback.2, &self.particles);
        self.pool.install(|| {
            dst.par_chunks_mut(ROLLBACK_CHUNK)
                .zip(src.par_chunks(ROLLBACK_CHUNK))
                .for_each(|(d, s)| d.copy_from_slice(s))
        });
    }

    /// The bodies as a projection step of `dt` [s] sees them: at their poses now, with the step's
    /// gravity in their velocity, and their inverse masses.
    fn step_bodies(&self, dt: f32) -> Vec<StepBody<D>> {
        (0..self.bodies.len())
            .map(|i| {
                let mut pose = self.bodies.poses[i].clone();
                for d in 0..D {
                    pose.velocity[d] += dt * self.params.gravity[d];
                }
                let (inv_mass, inv_inertia) = self.bodies.inverse_mass(i);
                StepBody {
                    pose,
                    inv_mass,
                    inv_inertia,
                }
            })
            .collect()
    }

    /// The frames one step may span from the state now: `⌊dt / dt_frame⌋` for the step bound's
    /// `dt`, in [1, [`MAX_FRAMES_PER_STEP`]]; 1 with a fixed step count (`params.substeps`).
    fn frames_per_step(&self, dt_frame: f32) -> u32 {
        if self.params.substeps.is_some()
            || self.moves.iter().any(Option::is_some)
            || !self.bodies.is_empty()
        {
            return 1;
        }
        let (cfl, c) = self.step_bound();
        let dt = cfl * self.params.dx() / (self.checked_max_speed() + c);
        ((dt / dt_frame).floor() as u32).clamp(1, MAX_FRAMES_PER_STEP)
    }

    /// The steps of one frame: one spanning `k` frames, or `n_sub` within it; on failure the frame
    /// rolls back and retries with one frame a step and twice the steps.
    fn projection_steps(
        &mut self,
        projection: &mut Projection<D>,
        dt_frame: f32,
        n_sub: usize,
        rho: f32,
    ) -> Result<FrameStats> {
        let gravity = SVector::<f32, D>::from_fn(|d, _| self.params.gravity[d]);
        self.save_rollback();
        self.begin_moves(dt_frame);
        let dx = self.params.dx();
        let mut frames = if n_sub == 1 {
            self.frames_per_step(dt_frame)
        } else {
            1
        };
        let (mut n_sub, mut retries, mut replans) = (n_sub, 0, 0);
        projection.set_travel_limit(MAX_TRAVEL_CELLS * dx);
        loop {
            let mut dt = frames as f32 * dt_frame / n_sub as f32;
            let mut advance = dt / frames as f32;
            let (mut failed, mut vmax) = (None, 0.0f32);
            let (mut k, mut steps, mut spanning, mut taken) = (0, n_sub, false, 0);
            self.begin_bodies();
            while k < steps {
                self.pose_colliders(k + 1, steps);
                let bodies = self.step_bodies(dt);
                let particles = &mut self.particles;
                let cols = StepColliders {
                    colliders: &self.colliders,
                    velocity: &self.collider_velocity,
                    shallow: &self.shallow,
                    bodies: &bodies,
                };
                let stats = self.pool.install(|| {
                    projection.step_advancing(particles, dt, advance, &gravity, rho, &cols)
                });
                if let Some(bound) = stats.stopped {
                    // nothing moved: the rest of the frame in steps short enough for the velocity the
                    // solve gave (a step spanning frames is replanned as one frame a step)
                    replans += 1;
                    if frames > 1 {
                        spanning = true;
                        break;
                    }
                    let m = ((bound * dt / (ADVECTIVE_CFL * dx)).ceil() as usize).max(2);
                    if steps * m > self.params.max_substeps {
                        failed = Some(MpmError::CflViolation {
                            substep: k + 1,
                            substeps: steps,
                            max_speed: bound,
                            retries,
                        });
                        break;
                    }
                    (k, steps) = (k * m, steps * m);
                    dt /= m as f32;
                    advance = dt;
                    continue;
                }
                if !bodies.is_empty() {
                    let body_steps: Vec<_> = projection
                        .body_steps()
                        .iter()
                        .map(|s| (s.impulse, s.delta))
                        .collect();
                    self.bodies.projection_step(&body_steps, dt);
                    let (poses, particles) = (&self.bodies.poses, &mut self.particles);
                    let (depth, bounds) = (PROJECT_DEPTH_CELLS * dx, projection.bounds());
                    self.pool
                        .install(|| push_out_of_bodies(particles, poses, depth, bounds));
                }
                vmax = self.checked_max_speed();
                if !vmax.is_finite() {
                    failed = Some(MpmError::NonFinite {
                        substep: k + 1,
                        substeps: steps,
                        retries,
                    });
                    break;
                }
                if vmax * dt > MAX_TRAVEL_CELLS * dx {
                    failed = Some(MpmError::CflViolation {
                        substep: k + 1,
                        substeps: steps,
                        max_speed: vmax,
                        retries,
                    });
                    break;
                }
                (k, taken) = (k + 1, taken + 1);
            }
            self.bodies.end(failed.is_none() && !spanning, dt_frame);
            if spanning {
                frames = 1; // nothing moved: not a rollback
                continue;
            }
            match failed {
                None => {
                    self.end_moves(true);
                    self.drift_frames = frames - 1;
                    return Ok(FrameStats {
                        substeps: taken,
                        dt,
                        max_speed: vmax,
                        active_blocks: 0,
                        retries,
                        replans,
                    });
                }
                Some(e) => {
                    self.particles.clone_from(&self.rollback.2);
                    if frames > 1 {
                        frames = 1;
                    } else if 2 * n_sub > self.params.max_substeps {
                        self.end_moves(false);
                        return Err(e);
                    } else {
                        n_sub *= 2;
                    }
                    retries += 1;
                }
            }
        }
    }
}
