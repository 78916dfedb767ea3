//! The solid materials' g2p update, one particle at a time: the elastic
//! solid (fixed-corotated, Stomakhin et al. 2012, or neo-Hookean), snow
//! (Stomakhin et al. 2013) and the viscoplastic solid (von Mises on the
//! Hencky strain with viscous relaxation); and [`Models`], the per-set
//! constants of every material that g2p, the stress refresh and the CFL
//! condition read.
//!
//! Each update takes the trial `F* = (I + Δt·C)·F`; the models
//! (`material/solid/update.rs`, without singular vectors, on one particle
//! or sixteen SIMD lanes, [`SolidBatch`]):
//!
//! - fixed-corotated: `τ = 2μ(F − R)Fᵀ + λJ(J − 1)I = 2μ(B − √B) + λJ(J − 1)I`;
//! - neo-Hookean: `τ = μ(FFᵀ − I) + λ ln J · I`;
//! - snow: `σ` clamped to `[1 − θc, 1 + θs]`, `J_P ← J_P·Πσ / Πσ_clamped`
//!   (the rest of the deformation goes to `F_P`), `F_E = U·diag(σ_clamped)·Vᵀ`,
//!   the fixed-corotated stress with μ, λ scaled by `e^{ξ(1 − J_P)}`;
//! - viscoplastic: `ε = ln σ`, `s = 2μ·dev ε`; where `‖s‖ > √2 τ_y`
//!   (`√J₂ > τ_y`) the deviatoric strain is scaled so that
//!   `‖s‖ = √2 τ_y + (‖s*‖ − √2 τ_y)·η/(η + μΔt)`; `F = U·diag(e^ε)·Vᵀ`,
//!   `τ = U·diag(2μ ε + λ tr ε)·Uᵀ` (the Hencky stress, as sand's).

mod batch;
mod update;

pub(crate) use batch::SolidBatch;

use nalgebra::SMatrix;

use super::lanes::Real;
use super::sand::SandModel;
use crate::dim::{Dim, DimOps};
use crate::isa::Isa;
use crate::params::{ElasticModel, MaterialParams, SnowParams, SolverParams, WaterParams};

const JP_LO: f32 = SnowParams::JP_RANGE.0;
const JP_HI: f32 = SnowParams::JP_RANGE.1;
use crate::particles::Material;
// the one-particle reference's (test builds only)
#[cfg(test)]
use crate::particles::{Particle, det};

/// The constants of one parameter set, derived once per solver.
#[derive(Clone, Debug)]
pub(crate) enum Model {
    Water(WaterParams),
    Sand(SandModel),
    Elastic {
        mu: f32,
        la: f32,
        neo: bool,
    },
    Snow {
        mu: f32,
        la: f32,
        lo: f32,
        hi: f32,
        xi: f32,
    },
    Viscoplastic {
        mu: f32,
        la: f32,
        /// √2 τ_y: the yield radius of ‖s‖ [Pa].
        radius: f32,
        /// η / μ [s].
        relax: f32,
    },
}

/// The table of parameter sets (`SolverParams::table`) and each set's
/// [`Model`], indexed by `Particle::set`.
#[derive(Clone, Debug)]
pub(crate) struct Models {
    pub(crate) params: Vec<MaterialParams>,
    pub(crate) models: Vec<Model>,
    /// The compiled copy of the lanes' updates to run (`crate::isa`).
    pub(crate) isa: Isa,
}

impl Models {
    /// The table of `params` (validated), sand's constants for `isa`.
    pub(crate) fn new<const D: usize>(params: &SolverParams<D>, isa: Isa) -> Self
    where
        Dim<D>: DimOps<D>,
    {
        let table = params.table();
        let models = table
            .iter()
            .map(|p| match p {
                MaterialParams::Water(w) => Model::Water(w.clone()),
                MaterialParams::Sand(s) => Model::Sand(SandModel::new::<D>(s, isa)),
                MaterialParams::Elastic(e) => {
                    let (mu, la) = e.lame();
                    Model::Elastic {
                        mu,
                        la,
                        neo: e.model == ElasticModel::Neohookean,
                    }
                }
                MaterialParams::Snow(s) => {
                    let (mu, la) = s.lame();
                    Model::Snow {
                        mu,
                        la,
                        lo: 1.0 - s.theta_c,
                        hi: 1.0 + s.theta_s,
                        xi: s.hardening,
                    }
                }
                MaterialParams::Viscoplastic(v) => {
                    let (mu, la) = v.lame();
                    Model::Viscoplastic {
                        mu,
                        la,
                        radius: std::f32::consts::SQRT_2 * v.yield_stress,
                        relax: v.viscosity / mu,
                    }
                }
            })
            .collect();
        Models {
            params: table,
            models,
            isa,
        }
    }

    /// Water's parameters of set `set` (the default set if it is not water's).
    #[inline(always)]
    pub(crate) fn water(&self, set: u16) -> &WaterParams {
        match self.models.get(set as usize) {
            Some(Model::Water(w)) => w,
            _ => match &self.models[Material::Water as usize] {
                Model::Water(w) => w,
                _ => unreachable!("table entry 0 is water's"),
            },
        }
    }

    /// Sand's constants of set `set` (the default set if it is not sand's).
    #[inline(always)]
    pub(crate) fn sand(&self, set: u16) -> &SandModel {
        match self.models.get(set as usize) {
            Some(Model::Sand(s)) => s,
            _ => match &self.models[Material::Sand as usize] {
                Model::Sand(s) => s,
                _ => unreachable!("table entry 1 is sand's"),
            },
        }
    }

    /// Points the sand sets at the frame loop's copy for `isa`.
    pub(crate) fn set_isa(&mut self, isa: Isa) {
        self.isa = isa;
        for m in &mut self.models {
            if let Model::Sand(s) = m {
                s.isa = isa;
            }
        }
    }
}

/// Row-major `[R; 9]` of a `D × D` matrix (the first `D²` entries).
#[inline(always)]
fn to_lanes<const D: usize>(m: &SMatrix<f32, D, D>) -> [f32; 9] {
    let mut a = [0.0; 9];
    for r in 0..D {
        for c in 0..D {
            a[r * D + c] = m[(r, c)];
        }
    }
    a
}

#[inline(always)]
fn from_lanes<const D: usize>(a: &[f32; 9]) -> SMatrix<f32, D, D> {
    SMatrix::<f32, D, D>::from_fn(|r, c| a[r * D + c])
}

/// The trial `F* = (I + Δt·C)·F` (row-major), summed as sand's lanes do.
#[inline(always)]
pub(crate) fn trial<R: Real, const D: usize>(f: &[R; 9], c: &[R; 9], dt: f32) -> [R; 9] {
    let dtv = R::splat(dt);
    let mut ft = [R::splat(0.0); 9];
    for r in 0..D {
        for k in 0..D {
            let mut acc = R::splat(0.0);
            for j in 0..D {
                let a = c[r * D + j] * dtv;
                let a = if r == j { R::splat(1.0) + a } else { a };
                acc = if j == 0 {
                    a * f[j * D + k]
                } else {
                    acc + a * f[j * D + k]
                };
            }
            ft[r * D + k] = acc;
        }
    }
    ft
}

/// The Kirchhoff stress [Pa] of a solid's state (`f` row-major, and `j` =
/// `J_P` for snow) under model `m`, on lanes of `R`.
#[inline(always)]
pub(crate) fn stress_lanes<R: Real, const D: usize>(m: &Model, f: &[R; 9], j: R) -> [R; 9] {
    let corot = |mu: R, la: R| {
        if D == 2 {
            update::corotated_2d(f, mu, la)
        } else {
            update::corotated_3d(f, mu, la)
        }
    };
    match *m {
        Model::Elastic { mu, la, neo: true } => update::neo_hookean::<R, D>(f, mu, la),
        Model::Elastic { mu, la, neo: false } => corot(R::splat(mu), R::splat(la)),
        Model::Snow { mu, la, xi, .. } => {
            let h = update::hardening(j, xi, JP_LO, JP_HI);
            corot(R::splat(mu) * h, R::splat(la) * h)
        }
        Model::Viscoplastic { mu, la, .. } if D == 2 => {
            update::viscoplastic_2d(f, mu, la, f32::INFINITY, 1.0).1
        }
        Model::Viscoplastic { mu, la, .. } => {
            update::viscoplastic_3d(f, mu, la, f32::INFINITY, 1.0).1
        }
        Model::Water(_) | Model::Sand(_) => [R::splat(0.0); 9],
    }
}

/// The g2p update of a solid under model `m` on lanes of `R`, from the trial
/// `ft` (row-major) and `j` (`J_P` for snow) over `dt`: the new F, `j` and
/// Kirchhoff stress.
#[inline(always)]
pub(crate) fn update_lanes<R: Real, const D: usize>(
    m: &Model,
    ft: &[R; 9],
    j: R,
    dt: f32,
) -> ([R; 9], R, [R; 9]) {
    match *m {
        Model::Elastic { .. } => (*ft, j, stress_lanes::<R, D>(m, ft, j)),
        Model::Snow {
            mu, la, lo, hi, xi, ..
        } => {
            let consts = (mu, la, lo, hi, xi);
            if D == 2 {
                update::snow_2d(ft, j, consts, (JP_LO, JP_HI))
            } else {
                update::snow_3d(ft, j, consts, (JP_LO, JP_HI))
            }
        }
        Model::Viscoplastic {
            mu,
            la,
            radius,
            relax,
        } => {
            // η/(η + μΔt) = relax/(relax + Δt); 0 for η = 0
            let keep = relax / (relax + dt);
            let (f, tau) = if D == 2 {
                update::viscoplastic_2d(ft, mu, la, radius, keep)
            } else {
                update::viscoplastic_3d(ft, mu, la, radius, keep)
            };
            (f, j, tau)
        }
        Model::Water(_) | Model::Sand(_) => (*ft, j, [R::splat(0.0); 9]),
    }
}

/// The Kirchhoff stress [Pa] of a solid particle's state (`f`, and `j` =
/// `J_P` for snow) under model `m`.
pub(crate) fn stress<const D: usize>(
    m: &Model,
    f: &SMatrix<f32, D, D>,
    j: f32,
) -> SMatrix<f32, D, D> {
    from_lanes(&stress_lanes::<f32, D>(m, &to_lanes(f), j))
}

/// A step that would invert a solid particle (`det F ≤ 0` after the
/// update: compression past zero volume in one substep, as when a soft
/// solid is driven into a wall at speed) keeps its `F` and `J_P` of the
/// start of the substep and their stress: the compression beyond inversion
/// is taken as plastic, so `det F > 0` always holds and the particle's
/// stress pushes it back out. Lanes with `det F > 0` (and NaN, which the
/// health check reports) are unchanged: the same bits as without it.
#[inline(always)]
pub(crate) fn keep_uninverted<R: Real, const D: usize>(
    m: &Model,
    (f0, j0): (&[R; 9], R),
    (f, j, tau): ([R; 9], R, [R; 9]),
) -> ([R; 9], R, [R; 9]) {
    let inverted = update::det::<R, D>(&f).le(R::splat(0.0));
    if !R::any(inverted) {
        return (f, j, tau);
    }
    let tau0 = stress_lanes::<R, D>(m, f0, j0);
    (
        std::array::from_fn(|k| R::select(inverted, f0[k], f[k])),
        R::select(inverted, j0, j),
        std::array::from_fn(|k| R::select(inverted, tau0[k], tau[k])),
    )
}

/// g2p update of a solid particle (elastic, snow, viscoplastic) with the new
/// velocity gradient `c` over `dt`: its `f` (and `j` = `J_P` for snow) and
/// stress, one particle ([`SolidBatch`] does sixteen, with the same bits
/// per lane; [`keep_uninverted`]). Returns `(finite, inverted)`: whether F,
/// J_P and τ are finite, and whether `det F ≤ 0` (or NaN). The reference
/// the lane tests compare [`SolidBatch`] with (g2p runs the batch); compiled
/// for the tests only.
#[cfg(test)]
pub(crate) fn advance<const D: usize>(
    m: &Model,
    p: &mut Particle<D>,
    dt: f32,
    c: &SMatrix<f32, D, D>,
) -> (bool, bool) {
    let f0 = to_lanes(&p.f);
    let ft = trial::<f32, D>(&f0, &to_lanes(c), dt);
    let (f, j, tau) =
        keep_uninverted::<f32, D>(m, (&f0, p.j), update_lanes::<f32, D>(m, &ft, p.j, dt));
    (p.f, p.j, p.tau) = (from_lanes(&f), j, from_lanes(&tau));
    let finite = p.f.iter().chain(p.tau.iter()).all(|a| a.is_finite()) && p.j.is_finite();
    (finite, !(det(&p.f) > 0.0))
}

#[cfg(test)]
mod lane_tests;
#[cfg(test)]
mod tests;
