//! New particles for `MpmSolver.add_particles`: read from Python before the
//! solver's lock is taken, then made into the core's particles under it
//! (each parameter set's density gives a mass where none is given).

use hybridmpm_mpm as core;
use hybridmpm_mpm::{Particle, Solver};
use nalgebra::SVector;

use crate::material::{Codes, expand_sets};

/// New particles, read from Python before the solver's lock is taken.
pub(crate) struct NewParticles {
    pub(crate) n: usize,
    pub(crate) x: Vec<f32>,
    pub(crate) mats: Codes,
    /// Parameter-set indices (one for all when `sets_scalar`), or `None`:
    /// each material's default set.
    pub(crate) sets: Option<(Vec<u16>, bool)>,
    pub(crate) v: Option<Vec<f32>>,
    pub(crate) m: Option<Vec<f32>>,
    pub(crate) vol: Option<Vec<f32>>,
}

pub(crate) fn add_particles_impl<const D: usize>(
    s: &mut Solver<D>,
    new: &NewParticles,
) -> core::Result<usize>
where
    core::Dim<D>: core::DimOps<D>,
{
    let n = new.n;
    s.check_particle_budget(s.num_particles().saturating_add(n))?;
    let mats = new.mats.expand(n)?;
    let sets = match &new.sets {
        Some((v, scalar)) => Some(expand_sets(v, n, *scalar)?),
        None => None,
    };
    let table = s.material_table();
    let params = s.params();
    // default: 2 particles per cell per dimension
    let default_vol = (0.5 * params.dx()).powi(D as i32);
    let mut ps = Vec::with_capacity(n);
    for i in 0..n {
        let xi = SVector::<f32, D>::from_column_slice(&new.x[i * D..(i + 1) * D]);
        let volume = new.vol.as_ref().map_or(default_vol, |a| a[i]);
        let set = sets.as_ref().map_or(mats[i] as u16, |v| v[i]);
        // a missing set is refused by `add_particles` (field `material_set`)
        let rho = table.get(set as usize).map_or(1.0, |t| t.density());
        let mass = new.m.as_ref().map_or(rho * volume, |a| a[i]);
        let mut p = Particle::new(xi, mats[i], mass, volume);
        p.set = set;
        if let Some(v) = &new.v {
            p.v = SVector::<f32, D>::from_column_slice(&v[i * D..(i + 1) * D]);
        }
        ps.push(p);
    }
    s.add_particles(ps)
}
