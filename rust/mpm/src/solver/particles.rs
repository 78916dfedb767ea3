//! The solver's particles between frames: replacing, changing, adding
//! and removing them (each validated, the derived stress recomputed), and
//! the clock a checkpoint restores. Any of them ends a projection step that
//! spans frames (`large_step.rs`): the next frame steps the new state.

use super::Solver;
use crate::dim::{Dim, DimOps};
use crate::error::{MpmError, Result};
use crate::material::{MaterialParams, Models};
use crate::particles::Particle;

impl<const D: usize> Solver<D>
where
    Dim<D>: DimOps<D>,
{
    /// Storage in public order (after the particles were replaced).
    fn reset_order(&mut self) {
        self.drift_frames = 0;
        let n = self.particles.len() as u32;
        self.ids = (0..n).collect();
        self.slot_of = (0..n).collect();
    }

    /// Replace all particles (validated; derived stress recomputed).
    pub fn set_particles(&mut self, mut particles: Vec<Particle<D>>) -> Result<()> {
        self.check_particle_budget(particles.len())?;
        let (lo, hi) = self.domain_bounds();
        for (i, p) in particles.iter().enumerate() {
            p.validate(i, lo, hi)?;
            self.check_set(i, p)?;
        }
        for p in particles.iter_mut() {
            self.refresh_stress(p);
        }
        self.particles = particles;
        self.reset_order();
        Ok(())
    }

    /// Replace all particles keeping their stored stress (checkpoint restore).
    pub(crate) fn set_particles_keep_stress(&mut self, particles: Vec<Particle<D>>) -> Result<()> {
        self.check_particle_budget(particles.len())?;
        let (lo, hi) = self.domain_bounds();
        for (i, p) in particles.iter().enumerate() {
            p.validate(i, lo, hi)?;
            self.check_set(i, p)?;
            if !p.tau.iter().all(|a| a.is_finite()) {
                return Err(MpmError::invalid(
                    "stress",
                    format!("particle {i} has a non-finite stress"),
                ));
            }
        }
        self.particles = particles;
        self.reset_order();
        Ok(())
    }

    /// Modify particles in place through `f(id, particle)` (public order),
    /// then validate; `refresh_stress` recomputes τ (needed after changing
    /// `F`, `J` or `C`). On error nothing changes.
    pub fn modify_particles(
        &mut self,
        refresh_stress: bool,
        mut f: impl FnMut(usize, &mut Particle<D>),
    ) -> Result<()> {
        let mut ps = self.particles.clone();
        for (id, &slot) in self.slot_of.iter().enumerate() {
            f(id, &mut ps[slot as usize]);
        }
        let (lo, hi) = self.domain_bounds();
        for (id, &slot) in self.slot_of.iter().enumerate() {
            ps[slot as usize].validate(id, lo, hi)?;
            self.check_set(id, &ps[slot as usize])?;
        }
        if refresh_stress {
            for p in ps.iter_mut() {
                self.refresh_stress(p);
            }
        }
        self.particles = ps;
        self.drift_frames = 0;
        Ok(())
    }

    /// Append particles (validated). Returns the new particle count.
    pub fn add_particles(&mut self, new: Vec<Particle<D>>) -> Result<usize> {
        let (lo, hi) = self.domain_bounds();
        let n0 = self.particles.len();
        self.check_particle_budget(n0.saturating_add(new.len()))?;
        if n0.saturating_add(new.len()) > u32::MAX as usize {
            return Err(MpmError::invalid(
                "positions",
                format!("at most {} particles are supported", u32::MAX),
            ));
        }
        for (i, p) in new.iter().enumerate() {
            p.validate(n0 + i, lo, hi)?;
            self.check_set(n0 + i, p)?;
        }
        for mut p in new {
            self.refresh_stress(&mut p);
            self.ids.push(self.particles.len() as u32);
            self.slot_of.push(self.particles.len() as u32);
            self.particles.push(p);
        }
        self.drift_frames = 0;
        Ok(self.particles.len())
    }

    /// Remove the particles whose `keep[i]` is false (order of the rest kept).
    pub fn retain_particles(&mut self, keep: &[bool]) -> Result<usize> {
        if keep.len() != self.particles.len() {
            return Err(MpmError::invalid(
                "mask",
                format!(
                    "length {} != particle count {}",
                    keep.len(),
                    self.particles.len()
                ),
            ));
        }
        let kept: Vec<Particle<D>> = self
            .particles()
            .into_iter()
            .zip(keep.iter())
            .filter(|(_, k)| **k)
            .map(|(p, _)| p)
            .collect();
        self.particles = kept;
        self.reset_order();
        Ok(self.particles.len())
    }

    /// Set simulated time and frame counter (used by checkpoint restore).
    pub fn set_clock(&mut self, time: f64, frame: u64) {
        self.time = time;
        self.frame = frame;
    }

    /// Recompute the derived stress τ from the particle's state, under the
    /// model of its parameter set (checked first, `check_set`).
    fn refresh_stress(&self, p: &mut Particle<D>) {
        p.tau = self.models.models[p.set as usize].stress(p);
    }

    /// The table of parameter sets particles index (`Particle::set`): the
    /// default set of each material at its code, then `params.sets`.
    pub fn material_table(&self) -> &[MaterialParams] {
        &self.models.params
    }

    /// Appends `set` to the table of parameter sets, in place: the particles,
    /// the clock and every other parameter are kept, and each particle's set
    /// index keeps its meaning. Returns the new set's index in the table
    /// (what `Particle::set` names it by: after the five defaults and the
    /// earlier `params.sets`). Errors (the solver unchanged) name
    /// `sets[k]`'s bad key, or `sets` beyond [`crate::params::MAX_SETS`].
    pub fn add_parameter_set(&mut self, set: MaterialParams) -> Result<u16> {
        let mut params = self.params.clone();
        params.sets.push(set);
        params.validate()?;
        self.models = Models::new::<D>(params.table(), self.isa);
        self.params = params;
        Ok((self.models.params.len() - 1) as u16)
    }

    /// Checks that particle `index`'s parameter set exists and is of its
    /// material (field `material_set`).
    fn check_set(&self, index: usize, p: &Particle<D>) -> Result<()> {
        match self.models.params.get(p.set as usize) {
            Some(set) if set.material() == p.material => Ok(()),
            Some(set) => Err(MpmError::invalid(
                "material_set",
                format!(
                    "particle {index} is {} but its parameter set {} is {}",
                    p.material.name(),
                    p.set,
                    set.material().name()
                ),
            )),
            None => Err(MpmError::invalid(
                "material_set",
                format!(
                    "particle {index}: parameter set {} does not exist (the table has {})",
                    p.set,
                    self.models.params.len()
                ),
            )),
        }
    }
}
