//! A frame of the projection integrator (`integrator = "projection"`,
//! [`crate::projection`]): incompressible APIC water that steps at the
//! flow's pace (docs/large-step.md).
//!
//! What it steps: water particles in the box walls. Colliders, rigid
//! bodies, sand and the solids need the explicit substeps; a solver that
//! holds any of them refuses a projection frame with an `InvalidInput`
//! naming the field (`integrator`, or `walls.condition` for walls that are
//! not free slip), and its state is unchanged.
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

use super::{FrameStats, Solver};
use crate::boundary::BoundaryCondition;
use crate::dim::{Dim, DimOps};
use crate::error::{MpmError, Result};
use crate::params::{MaterialParams, WallParams};
use crate::particles::Material;
use crate::projection::{ADVECTIVE_CFL, Projection};

/// The most cells a particle may cross in one projection step before the
/// frame is retried with smaller steps (the step is chosen for one).
pub const MAX_TRAVEL_CELLS: f32 = 2.0;

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
        if !self.colliders.is_empty() {
            return refuse(format!(
                "this scene has {} collider(s)",
                self.colliders.len()
            ));
        }
        if !self.bodies.is_empty() {
            return refuse(format!(
                "this scene has {} rigid body(ies)",
                self.bodies.len()
            ));
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

    /// One frame of `n_sub` projection steps ([`Solver::step_frame`] with
    /// `integrator = "projection"`), with rollback and retry.
    pub(super) fn step_frame_projection(
        &mut self,
        dt_frame: f32,
        n_sub: usize,
    ) -> Result<FrameStats> {
        let rho = self.projection_density()?;
        let gravity = SVector::<f32, D>::from_fn(|d, _| self.params.gravity[d]);
        let mut projection = self.large_step.take().unwrap_or_else(|| {
            Box::new(Projection::new(self.params.n_grid, self.params.walls.cells))
        });
        self.rollback.2.clone_from(&self.particles);
        let dx = self.params.dx();
        let (mut n_sub, mut retries) = (n_sub, 0);
        let result =
            loop {
                let dt = dt_frame / n_sub as f32;
                let mut failed = None;
                for k in 0..n_sub {
                    let particles = &mut self.particles;
                    self.pool
                        .install(|| projection.step(particles, dt, &gravity, rho));
                    let vmax = self.particles.iter().map(|p| crate::dim::norm(&p.v)).fold(
                        0.0f32,
                        |a, b| if b.is_nan() { f32::INFINITY } else { a.max(b) },
                    );
                    if !vmax.is_finite()
                        || self
                            .particles
                            .iter()
                            .any(|p| !p.x.iter().all(|x| x.is_finite()))
                    {
                        failed = Some(MpmError::NonFinite {
                            substep: k + 1,
                            substeps: n_sub,
                            retries,
                        });
                        break;
                    }
                    if vmax * dt > MAX_TRAVEL_CELLS * dx {
                        failed = Some(MpmError::CflViolation {
                            substep: k + 1,
                            substeps: n_sub,
                            max_speed: vmax,
                            retries,
                        });
                        break;
                    }
                }
                match failed {
                    None => {
                        let max_speed = self
                            .particles
                            .iter()
                            .map(|p| crate::dim::norm(&p.v))
                            .fold(0.0f32, f32::max);
                        break Ok(FrameStats {
                            substeps: n_sub,
                            dt,
                            max_speed,
                            active_blocks: 0,
                            retries,
                        });
                    }
                    Some(e) => {
                        self.particles.clone_from(&self.rollback.2);
                        if 2 * n_sub > self.params.max_substeps {
                            break Err(e);
                        }
                        n_sub *= 2;
                        retries += 1;
                    }
                }
            };
        self.large_step = Some(projection);
        if result.is_ok() {
            self.time += dt_frame as f64;
            self.frame += 1;
        }
        result
    }
}
