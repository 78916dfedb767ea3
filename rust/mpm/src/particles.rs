//! Particle state (array of structs: MPM touches all fields of a particle
//! together). [`Material`], a particle's material code, is made from the
//! registry's list of the constitutive models (`material/codes.rs`).

use nalgebra::{SMatrix, SVector};

use crate::error::{MpmError, Result};

pub use crate::material::codes::Material;

impl Material {
    /// The material of `code` (`None` for an unknown one).
    pub fn from_code(code: i64) -> Option<Material> {
        usize::try_from(code)
            .ok()
            .and_then(|c| Material::ALL.get(c).copied())
    }
}

/// One material point. Units: SI on the unit domain.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Particle<const D: usize> {
    /// Position x [m].
    pub x: SVector<f32, D>,
    /// Velocity v [m/s].
    pub v: SVector<f32, D>,
    /// APIC affine velocity matrix C [1/s].
    pub c: SMatrix<f32, D, D>,
    /// Deformation gradient F [-]: the elastic part for sand, snow (`F_E`)
    /// and the viscoplastic solid, the whole F for the elastic solid;
    /// identity for water.
    pub f: SMatrix<f32, D, D>,
    /// Volume ratio J = V/V0 [-] for water; the plastic volume ratio
    /// `J_P = det F_P` for snow (so `J_P · det F_E = det F`); 1 otherwise.
    pub j: f32,
    /// Log-volume correction of Tampubolon et al. 2017 (sand) [-]; 0 otherwise.
    pub vc: f32,
    /// Mass [kg] (per unit depth in 2D).
    pub mass: f32,
    /// Rest volume V0 [m^D].
    pub volume: f32,
    /// External acceleration added to gravity [m/s²].
    pub ext: SVector<f32, D>,
    pub material: Material,
    /// The particle's parameter set: an index into the solver's table
    /// (`SolverParams::table`: the default set of each material at its code,
    /// then `SolverParams::sets`), whose material must be `material`.
    pub set: u16,
    /// Kirchhoff stress τ [Pa], derived from the state above (kept in sync by the solver).
    pub(crate) tau: SMatrix<f32, D, D>,
}

impl<const D: usize> Particle<D> {
    /// A particle at rest at `x` with the given material, mass and volume.
    pub fn new(x: SVector<f32, D>, material: Material, mass: f32, volume: f32) -> Self {
        Particle {
            x,
            v: SVector::zeros(),
            c: SMatrix::zeros(),
            f: SMatrix::identity(),
            j: 1.0,
            vc: 0.0,
            mass,
            volume,
            ext: SVector::zeros(),
            material,
            set: material as u16,
            tau: SMatrix::zeros(),
        }
    }

    /// Kirchhoff stress of this particle (derived; read-only).
    pub fn stress(&self) -> SMatrix<f32, D, D> {
        self.tau
    }

    /// Checks that every field is finite and physical; `index` names the
    /// particle. The volume is checked before the mass (a default mass is
    /// density × volume, so a bad volume is named as such).
    pub fn validate(&self, index: usize, lo: f32, hi: f32) -> Result<()> {
        let fin = |field: &str, ok: bool| {
            if ok {
                Ok(())
            } else {
                Err(MpmError::invalid(
                    field,
                    format!("particle {index} has a non-finite value"),
                ))
            }
        };
        fin("positions", self.x.iter().all(|a| a.is_finite()))?;
        fin("velocities", self.v.iter().all(|a| a.is_finite()))?;
        fin("affine", self.c.iter().all(|a| a.is_finite()))?;
        fin("deformation_gradient", self.f.iter().all(|a| a.is_finite()))?;
        fin("volume_ratio", self.j.is_finite())?;
        fin(
            "external_acceleration",
            self.ext.iter().all(|a| a.is_finite()),
        )?;
        fin("volume_correction", self.vc.is_finite())?;
        if self.x.iter().any(|&a| a < lo || a > hi) {
            return Err(MpmError::invalid(
                "positions",
                format!(
                    "particle {index} at {:?} is outside the simulation domain [{lo}, {hi}]^{D}",
                    self.x.as_slice()
                ),
            ));
        }
        if !(self.volume.is_finite() && self.volume > 0.0) {
            return Err(MpmError::invalid(
                "volumes",
                format!(
                    "particle {index}: volume must be finite and > 0, got {}",
                    self.volume
                ),
            ));
        }
        if !(self.mass.is_finite() && self.mass > 0.0) {
            return Err(MpmError::invalid(
                "masses",
                format!(
                    "particle {index}: mass must be finite and > 0, got {}",
                    self.mass
                ),
            ));
        }
        if !(self.j > 0.0) {
            return Err(MpmError::invalid(
                "volume_ratio",
                format!("particle {index}: J must be > 0, got {}", self.j),
            ));
        }
        if !(det(&self.f) > 0.0) {
            return Err(MpmError::invalid(
                "deformation_gradient",
                format!("particle {index}: det F must be > 0"),
            ));
        }
        Ok(())
    }
}

/// Determinant of a 2×2 or 3×3 matrix.
pub fn det<const D: usize>(m: &SMatrix<f32, D, D>) -> f32 {
    match D {
        1 => m[(0, 0)],
        2 => m[(0, 0)] * m[(1, 1)] - m[(0, 1)] * m[(1, 0)],
        3 => {
            m[(0, 0)] * (m[(1, 1)] * m[(2, 2)] - m[(1, 2)] * m[(2, 1)])
                - m[(0, 1)] * (m[(1, 0)] * m[(2, 2)] - m[(1, 2)] * m[(2, 0)])
                + m[(0, 2)] * (m[(1, 0)] * m[(2, 1)] - m[(1, 1)] * m[(2, 0)])
        }
        _ => f32::NAN,
    }
}

/// Particles at rest on a cubic lattice: `side^D` points at
/// `origin + (i + 1/2)·spacing`, each with volume `spacing^D` and mass
/// `density·spacing^D` (used by benches, examples and tests).
pub fn lattice<const D: usize>(
    origin: [f32; D],
    side: usize,
    spacing: f32,
    material: Material,
    density: f32,
) -> Vec<Particle<D>> {
    lattice_box(origin, [side; D], spacing, material, density)
}

/// Particles at rest on a box lattice: `counts[d]` points along axis `d` at
/// `origin + (i + 1/2)·spacing` (the last axis fastest), each with volume
/// `spacing^D` and mass `density·spacing^D`.
pub fn lattice_box<const D: usize>(
    origin: [f32; D],
    counts: [usize; D],
    spacing: f32,
    material: Material,
    density: f32,
) -> Vec<Particle<D>> {
    let vol = spacing.powi(D as i32);
    (0..counts.iter().product::<usize>())
        .map(|mut i| {
            let mut x = SVector::<f32, D>::zeros();
            for d in (0..D).rev() {
                x[d] = origin[d] + ((i % counts[d]) as f32 + 0.5) * spacing;
                i /= counts[d];
            }
            Particle::new(x, material, density * vol, vol)
        })
        .collect()
}
