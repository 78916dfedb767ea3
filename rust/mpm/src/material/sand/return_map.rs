//! The Drucker–Prager return mapping on the principal log strains
//! ([`drucker_prager_project`]; [`project_lanes`] on SIMD lanes) and the
//! update through the SVD of the trial F that applies it ([`advance_svd`],
//! the tests' reference, compiled for them only).

use nalgebra::SVector;

use super::sum;
use crate::material::lanes::Real;
use crate::material::spectral::k;
// the reference route's (test builds only)
#[cfg(test)]
use super::{Sand, kirchhoff_stress};
#[cfg(test)]
use crate::dim::{Dim, DimOps};
#[cfg(test)]
use nalgebra::SMatrix;

/// The sand update through the SVD of the trial `F`: the reference route, which
/// [`advance_2d`](super::update_2d::advance_2d) and
/// [`advance_3d`](super::update_3d::advance_3d) replace (the tests compare
/// them).
#[cfg(test)]
#[inline(always)]
pub(super) fn advance_svd<const D: usize>(
    f: &mut SMatrix<f32, D, D>,
    vc: &mut f32,
    f_trial: &SMatrix<f32, D, D>,
    m: &Sand,
) -> SMatrix<f32, D, D>
where
    Dim<D>: DimOps<D>,
{
    let svd = Dim::<D>::svd(f_trial);
    let e0 = svd.sigma.map(|s| s.max(1e-6).ln());
    let e_new = drucker_prager_project::<D>(&e0, vc, m.alpha, m.mu, m.la, m.tr_apex);
    if e_new == e0 {
        // inside the cone: elastic, F is the trial F
        *f = *f_trial;
    } else {
        *f = svd.u * SMatrix::<f32, D, D>::from_diagonal(&e_new.map(f32::exp)) * svd.v.transpose();
    }
    kirchhoff_stress(&svd.u, &e_new, m.mu, m.la)
}

/// Drucker–Prager return mapping in Hencky strain (Klár et al. 2016, Sec. 7.3,
/// with the volume correction of Tampubolon et al. 2017, Eq. 26–27).
///
/// `e0`: principal log strains of the trial elastic F; `vc`: accumulated log
/// volume correction (updated); `alpha`: cone coefficient; `mu`, `la`: Lamé
/// parameters; `tr_apex`: trace of the strain at the cone apex (cohesion).
/// Returns the projected principal log strains.
pub fn drucker_prager_project<const D: usize>(
    e0: &SVector<f32, D>,
    vc: &mut f32,
    alpha: f32,
    mu: f32,
    la: f32,
    tr_apex: f32,
) -> SVector<f32, D> {
    project_with_scale(e0, vc, alpha, mu, la, tr_apex).0
}

/// [`drucker_prager_project`], also returning the factor `s` by which the
/// projection scales the strains' differences: `e_new_i − e_new_j =
/// s·(e0_i − e0_j)` (1 inside the cone, 0 at the tip, `1 − Δγ/‖ê‖` on the
/// cone's surface).
#[inline(always)]
pub(super) fn project_with_scale<const D: usize>(
    e0: &SVector<f32, D>,
    vc: &mut f32,
    alpha: f32,
    mu: f32,
    la: f32,
    tr_apex: f32,
) -> (SVector<f32, D>, f32) {
    let mut e0a = [0.0f32; D];
    for i in 0..D {
        e0a[i] = e0[i];
    }
    let (e_new, scale, vc_new) = project_lanes(&e0a, *vc, alpha, mu, la, tr_apex);
    *vc = vc_new;
    (SVector::<f32, D>::from_fn(|i, _| e_new[i]), scale)
}

/// [`project_with_scale`] on lanes of `R` (one particle or sixteen):
/// `(ε_new, s, vc_new)`. The three cases (beyond the tip, inside the cone, on
/// its surface) are selects, not branches.
#[inline(always)]
pub(super) fn project_lanes<R: Real, const D: usize>(
    e0: &[R; D],
    vc: R,
    alpha: f32,
    mu: f32,
    la: f32,
    tr_apex: f32,
) -> ([R; D], R, R) {
    let dd = D as f32;
    let shift = k::<R>(tr_apex / dd);
    let vcd = vc / k(dd);
    let mut e = [k::<R>(0.0); D];
    for i in 0..D {
        e[i] = e0[i] + vcd - shift;
    }
    let tr = sum(&e);
    let mean = tr / k(dd);
    let mut ehat = e;
    let mut norm2 = k::<R>(0.0);
    for i in 0..D {
        ehat[i] = e[i] - mean;
        norm2 = norm2 + ehat[i] * ehat[i];
    }
    let ehat_norm = norm2.sqrt();
    let dgamma = ehat_norm + k::<R>((dd * la + 2.0 * mu) / (2.0 * mu)) * tr * k(alpha);
    // expansion (tr ≥ 0): the cone tip; tr < 0 and Δγ ≤ 0: inside the cone,
    // elastic, no volume correction; otherwise onto the cone's surface
    // (there Δγ > 0 needs ‖ê‖ > 0)
    let tip = tr.ge(k(0.0));
    let inside = R::and(R::not(tip), dgamma.le(k(0.0)));
    let kk = dgamma / ehat_norm;
    let mut e_new = e;
    for i in 0..D {
        let on_surface = e[i] - ehat[i] * kk + shift;
        e_new[i] = R::select(tip, shift, R::select(inside, e0[i], on_surface));
    }
    let scale = R::select(tip, k(0.0), R::select(inside, k(1.0), k::<R>(1.0) - kk));
    let vc_new = vc + (sum(e0) - sum(&e_new));
    (e_new, scale, vc_new)
}
