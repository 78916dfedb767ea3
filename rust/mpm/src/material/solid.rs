//! The solid materials' g2p update, one particle at a time: the elastic
//! solid (fixed-corotated, Stomakhin et al. 2012, or neo-Hookean), snow
//! (Stomakhin et al. 2013) and the viscoplastic solid (von Mises on the
//! Hencky strain with viscous relaxation); and [`Models`], the per-set
//! constants of every material that g2p, the stress refresh and the CFL
//! condition read.
//!
//! Each update takes the trial `F* = (I + Δt·C)·F` and its singular value
//! decomposition `F* = U·diag(σ)·Vᵀ` from the crate's one SVD
//! ([`DimOps::svd`], tested against nalgebra's); with `R = U·Vᵀ`:
//!
//! - fixed-corotated: `τ = 2μ(F − R)Fᵀ + λJ(J − 1)I = U·diag(2μ(σ − 1)σ + λJ(J − 1))·Uᵀ`;
//! - neo-Hookean: `τ = μ(FFᵀ − I) + λ ln J · I` (no SVD);
//! - snow: `σ` clamped to `[1 − θc, 1 + θs]`, `J_P ← J_P·Πσ / Πσ_clamped`
//!   (the rest of the deformation goes to `F_P`), `F_E = U·diag(σ_clamped)·Vᵀ`,
//!   the fixed-corotated stress with μ, λ scaled by `e^{ξ(1 − J_P)}`;
//! - viscoplastic: `ε = ln σ`, `s = 2μ·dev ε`; where `‖s‖ > √2 τ_y`
//!   (`√J₂ > τ_y`) the deviatoric strain is scaled so that
//!   `‖s‖ = √2 τ_y + (‖s*‖ − √2 τ_y)·η/(η + μΔt)`; `F = U·diag(e^ε)·Vᵀ`,
//!   `τ = U·diag(2μ ε + λ tr ε)·Uᵀ` (the Hencky stress, as sand's).

use nalgebra::{SMatrix, SVector};

use super::sand::{SandModel, kirchhoff_stress};
use crate::dim::{Dim, DimOps};
use crate::isa::Isa;
use crate::params::{ElasticModel, MaterialParams, SnowParams, SolverParams, WaterParams};

const JP_LO: f32 = SnowParams::JP_RANGE.0;
const JP_HI: f32 = SnowParams::JP_RANGE.1;
use crate::particles::{Material, Particle, det};

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
        for m in &mut self.models {
            if let Model::Sand(s) = m {
                s.isa = isa;
            }
        }
    }
}

/// `U·diag(d)·Uᵀ`.
#[inline(always)]
fn spectral<const D: usize>(u: &SMatrix<f32, D, D>, d: &SVector<f32, D>) -> SMatrix<f32, D, D> {
    u * SMatrix::<f32, D, D>::from_diagonal(d) * u.transpose()
}

/// Fixed-corotated Kirchhoff stress from the singular values `sigma` and
/// left singular vectors `u` of F.
#[inline(always)]
fn corotated<const D: usize>(
    u: &SMatrix<f32, D, D>,
    sigma: &SVector<f32, D>,
    mu: f32,
    la: f32,
) -> SMatrix<f32, D, D> {
    let j = sigma.product();
    let vol = la * j * (j - 1.0);
    spectral(u, &sigma.map(|s| 2.0 * mu * (s - 1.0) * s + vol))
}

/// 2D fixed-corotated stress `2μ(F − R)Fᵀ + λJ(J − 1)I` with the polar
/// rotation in closed form, `R = [c −s; s c]` with `(c, s) ∝ (F00 + F11,
/// F10 − F01)` (the first step of `svd2`), without the symmetric
/// eigenproblem: one square root and one division where the SVD's chain has
/// three and two (elastic2d's frame 1.9× sand's with the SVD, 1.35× with this).
#[inline(always)]
fn corotated_2d<const D: usize>(f: &SMatrix<f32, D, D>, mu: f32, la: f32) -> SMatrix<f32, D, D> {
    let (x, y) = (f[(0, 0)] + f[(1, 1)], f[(1, 0)] - f[(0, 1)]);
    let r2 = x * x + y * y;
    let (co, si) = if r2 > 1e-30 {
        let inv = 1.0 / r2.sqrt();
        (x * inv, y * inv)
    } else {
        (1.0, 0.0)
    };
    let mut r = SMatrix::<f32, D, D>::identity();
    (r[(0, 0)], r[(0, 1)], r[(1, 0)], r[(1, 1)]) = (co, -si, si, co);
    let jf = det(f);
    (f - r) * f.transpose() * (2.0 * mu) + SMatrix::<f32, D, D>::identity() * (la * jf * (jf - 1.0))
}

/// 2D: whether the singular values of `f` all lie in `[lo, hi]`, from the
/// eigenvalues of `B = F·Fᵀ` (`σ² = λ`, `λ2 = det(F)²/λ1`), without singular
/// vectors.
#[inline(always)]
fn inside_2d<const D: usize>(f: &SMatrix<f32, D, D>, lo: f32, hi: f32) -> bool {
    let (a, b, c, d) = (f[(0, 0)], f[(0, 1)], f[(1, 0)], f[(1, 1)]);
    let (b11, b12, b22) = (a * a + b * b, a * c + b * d, c * c + d * d);
    let half = 0.5 * (b11 - b22);
    let l1 = 0.5 * (b11 + b22) + (half * half + b12 * b12).sqrt();
    let jf = a * d - b * c;
    jf > 0.0 && l1 <= hi * hi && jf * jf >= lo * lo * l1
}

/// 2D viscoplastic update without singular vectors (sand's `advance_2d`
/// does the same for its cone): every quantity is an isotropic function of
/// `B = F*·F*ᵀ` (eigenvalues `λ1 ≥ λ2`, `ε0_i = ½ ln λ_i`), and in 2D such a
/// function is `g(B) = g(λ2)·I + (g(λ1) − g(λ2))/(λ1 − λ2)·(B − λ2·I)`.
/// The return scales the deviatoric log strain by `scale` (1 inside the
/// yield surface); then `τ = g(B)` with `g(λ_i) = 2μ ε_i + λ tr ε`, and
/// `F = G·F*` with `G = g(B)`, `g(λ_i) = e^{ε_i − ε0_i}`. Divided differences
/// become their limits when `λ1 − λ2 ≤ 1e-6·λ2`. `keep = η/(η + μΔt)`.
/// Returns the new F and τ; `None` for `f` = F* itself (inside the surface).
#[inline(always)]
fn viscoplastic_2d<const D: usize>(
    ft: &SMatrix<f32, D, D>,
    mu: f32,
    la: f32,
    radius: f32,
    keep: f32,
) -> (Option<SMatrix<f32, D, D>>, SMatrix<f32, D, D>) {
    let (a, b, c, d) = (ft[(0, 0)], ft[(0, 1)], ft[(1, 0)], ft[(1, 1)]);
    let (b11, b12, b22) = (a * a + b * b, a * c + b * d, c * c + d * d);
    let half = 0.5 * (b11 - b22);
    let l1 = (0.5 * (b11 + b22) + (half * half + b12 * b12).sqrt()).max(1e-12);
    let jf = a * d - b * c;
    let l2 = (jf * jf / l1).max(1e-12);
    let (e1, e2) = (0.5 * l1.ln(), 0.5 * l2.ln());
    let mean = 0.5 * (e1 + e2);
    // ‖s‖ = 2μ‖dev ε‖ = √2·μ·(ε1 − ε2)
    let s_norm = std::f32::consts::SQRT_2 * mu * (e1 - e2);
    let scale = if s_norm > radius {
        (radius + (s_norm - radius) * keep) / s_norm
    } else {
        1.0
    };
    let dl = l1 - l2;
    let near = dl <= 1e-6 * l2;
    // g(B) from g(λ2) and the divided difference
    let iso = |g2: f32, slope: f32| {
        let mut m = SMatrix::<f32, D, D>::zeros();
        m[(0, 0)] = g2 + slope * (b11 - l2);
        m[(1, 1)] = g2 + slope * (b22 - l2);
        m[(0, 1)] = slope * b12;
        m[(1, 0)] = slope * b12;
        m
    };
    // ε_i = mean ± scale·(ε1 − ε2)/2
    let tau_slope = if near {
        mu * scale / l2
    } else {
        2.0 * mu * scale * (e1 - e2) / dl
    };
    let e2_new = mean - 0.5 * scale * (e1 - e2);
    let tau = iso(2.0 * mu * e2_new + la * 2.0 * mean, tau_slope);
    if scale == 1.0 {
        return (None, tau);
    }
    // g_i = e^{(scale − 1)(ε_i − mean)}: g2 = e^{−x}, g1 − g2 = g2·(e^{2x} − 1)
    let x = 0.5 * (scale - 1.0) * (e1 - e2);
    let g2 = (-x).exp();
    let g_slope = if near {
        g2 * (scale - 1.0) / (2.0 * l2)
    } else {
        g2 * (2.0 * x).exp_m1() / dl
    };
    (Some(iso(g2, g_slope) * ft), tau)
}

/// The Kirchhoff stress [Pa] of a solid particle's state (`f`, and `j` =
/// `J_P` for snow) under model `m`.
pub(crate) fn stress<const D: usize>(
    m: &Model,
    f: &SMatrix<f32, D, D>,
    j: f32,
) -> SMatrix<f32, D, D>
where
    Dim<D>: DimOps<D>,
{
    match *m {
        Model::Elastic { mu, la, neo: true } => {
            let jf = det(f);
            SMatrix::<f32, D, D>::identity() * (la * jf.max(1e-6).ln() - mu)
                + f * f.transpose() * mu
        }
        Model::Elastic { mu, la, neo: false } if D == 2 => corotated_2d(f, mu, la),
        Model::Elastic { mu, la, neo: false } => {
            let svd = Dim::<D>::svd(f);
            corotated(&svd.u, &svd.sigma, mu, la)
        }
        Model::Snow { mu, la, xi, .. } if D == 2 => {
            let h = (xi * (1.0 - j.clamp(JP_LO, JP_HI))).exp();
            corotated_2d(f, mu * h, la * h)
        }
        Model::Snow { mu, la, xi, .. } => {
            let h = (xi * (1.0 - j.clamp(JP_LO, JP_HI))).exp();
            let svd = Dim::<D>::svd(f);
            corotated(&svd.u, &svd.sigma, mu * h, la * h)
        }
        Model::Viscoplastic { mu, la, .. } if D == 2 => {
            viscoplastic_2d(f, mu, la, f32::INFINITY, 1.0).1
        }
        Model::Viscoplastic { mu, la, .. } => {
            let svd = Dim::<D>::svd(f);
            let eps = svd.sigma.map(|s| s.max(1e-6).ln());
            kirchhoff_stress(&svd.u, &eps, mu, la)
        }
        Model::Water(_) | Model::Sand(_) => SMatrix::zeros(),
    }
}

/// g2p update of a solid particle (elastic, snow, viscoplastic) with the new
/// velocity gradient `c` over `dt`: its `f` (and `j` = `J_P` for snow) and
/// stress. Returns `(finite, inverted)`: whether F, J_P and τ are finite,
/// and whether `det F ≤ 0` (or NaN).
#[inline(never)]
pub(crate) fn advance<const D: usize>(
    m: &Model,
    p: &mut Particle<D>,
    dt: f32,
    c: &SMatrix<f32, D, D>,
) -> (bool, bool)
where
    Dim<D>: DimOps<D>,
{
    let ft = (SMatrix::<f32, D, D>::identity() + c * dt) * p.f;
    match *m {
        Model::Elastic { .. } => {
            p.f = ft;
            p.tau = stress(m, &ft, 1.0);
        }
        Model::Snow {
            mu, la, lo, hi, xi, ..
        } if D == 2 && inside_2d(&ft, lo, hi) => {
            // no singular value is clamped: F_E = F*, J_P unchanged
            p.f = ft;
            let h = (xi * (1.0 - p.j.clamp(JP_LO, JP_HI))).exp();
            p.tau = corotated_2d(&ft, mu * h, la * h);
        }
        Model::Snow {
            mu, la, lo, hi, xi, ..
        } => {
            let svd = Dim::<D>::svd(&ft);
            let clamped = svd.sigma.map(|s| s.clamp(lo, hi));
            p.j *= svd.sigma.product() / clamped.product();
            p.f = svd.u * SMatrix::<f32, D, D>::from_diagonal(&clamped) * svd.v.transpose();
            let h = (xi * (1.0 - p.j.clamp(JP_LO, JP_HI))).exp();
            p.tau = corotated(&svd.u, &clamped, mu * h, la * h);
        }
        Model::Viscoplastic {
            mu,
            la,
            radius,
            relax,
        } => {
            // η/(η + μΔt) = relax/(relax + Δt); 0 for η = 0
            let keep = relax / (relax + dt);
            if D == 2 {
                let (f, tau) = viscoplastic_2d(&ft, mu, la, radius, keep);
                p.f = f.unwrap_or(ft);
                p.tau = tau;
            } else {
                let svd = Dim::<D>::svd(&ft);
                let mut eps = svd.sigma.map(|s| s.max(1e-6).ln());
                let mean = eps.sum() / D as f32;
                let dev = eps.add_scalar(-mean);
                let s_norm = 2.0 * mu * dev.norm();
                if s_norm > radius {
                    let target = radius + (s_norm - radius) * keep;
                    eps = (dev * (target / s_norm)).add_scalar(mean);
                    p.f = svd.u
                        * SMatrix::<f32, D, D>::from_diagonal(&eps.map(f32::exp))
                        * svd.v.transpose();
                } else {
                    p.f = ft;
                }
                p.tau = kirchhoff_stress(&svd.u, &eps, mu, la);
            }
        }
        Model::Water(_) | Model::Sand(_) => {}
    }
    let finite = p.f.iter().chain(p.tau.iter()).all(|a| a.is_finite()) && p.j.is_finite();
    (finite, !(det(&p.f) > 0.0))
}

#[cfg(test)]
mod tests;
