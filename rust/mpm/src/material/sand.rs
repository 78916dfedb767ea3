//! Sand: Drucker–Prager elastoplasticity in Hencky (log) strain with an SVD
//! return mapping (Klár et al. 2016, "Drucker–Prager elastoplasticity for
//! sand animation", Sec. 7) and the volume correction of Tampubolon et al.
//! 2017 ("Multi-species simulation of porous sand and water mixtures",
//! Eq. 26–27).
//!
//! The particle carries the elastic deformation gradient `F` and the
//! accumulated log-volume correction `vc`. Per g2p: trial `F* = (I + Δt·C)·F`,
//! `F* = U·diag(σ)·Vᵀ`, project the principal log strains `ε = ln σ` onto the
//! yield cone ([`drucker_prager_project`]), `F = U·diag(exp ε)·Vᵀ`; the
//! Kirchhoff stress of the St. Venant–Kirchhoff model in Hencky strain is
//! `τ = U·diag(2μ·ε + λ·tr ε)·Uᵀ`.
//!
//! That is the model; g2p computes it without singular vectors, as isotropic
//! functions of `B = F*·F*ᵀ` ([`advance_2d`], [`advance_3d`]), which is faster
//! and closer to an f64 SVD reference than the f32 SVD route
//! ([`advance_svd`], kept as the tests' comparison).

use nalgebra::{SMatrix, SVector};

use crate::dim::{Dim, DimOps};
use crate::params::SandParams;

/// The constants of the sand model derived from [`SandParams`] once per substep.
#[derive(Clone, Copy, Debug)]
pub(crate) struct SandModel {
    /// Lamé parameters μ, λ [Pa].
    pub(crate) mu: f32,
    pub(crate) la: f32,
    /// Drucker–Prager cone coefficient α (see [`DimOps::drucker_prager_alpha`]).
    pub(crate) alpha: f32,
    /// Trace of the log strain at the cone apex (0 without cohesion).
    pub(crate) tr_apex: f32,
}

impl SandModel {
    pub(crate) fn new<const D: usize>(sand: &SandParams) -> Self
    where
        Dim<D>: DimOps<D>,
    {
        let (mu, la) = sand.lame();
        let alpha = Dim::<D>::drucker_prager_alpha(sand.friction_angle_deg.to_radians());
        let tan_phi = sand.friction_angle_deg.to_radians().tan();
        let tr_apex = if sand.cohesion > 0.0 {
            D as f32 * sand.cohesion / (tan_phi * (D as f32 * la + 2.0 * mu))
        } else {
            0.0
        };
        SandModel {
            mu,
            la,
            alpha,
            tr_apex,
        }
    }
}

/// Kirchhoff stress `τ = U·diag(2μ·ε + λ·tr ε)·Uᵀ` [Pa] from the left singular
/// vectors `u` and the principal log strains `eps`.
#[inline(always)]
pub(crate) fn kirchhoff_stress<const D: usize>(
    u: &SMatrix<f32, D, D>,
    eps: &SVector<f32, D>,
    mu: f32,
    la: f32,
) -> SMatrix<f32, D, D> {
    let tr = eps.sum();
    let diag = eps.map(|e| 2.0 * mu * e + la * tr);
    u * SMatrix::<f32, D, D>::from_diagonal(&diag) * u.transpose()
}

/// Kirchhoff stress of the elastic deformation gradient `f` (no plasticity).
#[inline(always)]
pub(crate) fn stress_of<const D: usize>(
    f: &SMatrix<f32, D, D>,
    mu: f32,
    la: f32,
) -> SMatrix<f32, D, D>
where
    Dim<D>: DimOps<D>,
{
    let svd = Dim::<D>::svd(f);
    let eps = svd.sigma.map(|s| s.max(1e-6).ln());
    kirchhoff_stress(&svd.u, &eps, mu, la)
}

/// g2p update of one sand particle: elastic predictor `(I + Δt·c)·f`, return
/// mapping onto the Drucker–Prager cone (updates `vc`), new `f`. Returns the
/// new Kirchhoff stress.
#[inline(always)]
pub(crate) fn advance<const D: usize>(
    f: &mut SMatrix<f32, D, D>,
    vc: &mut f32,
    c: &SMatrix<f32, D, D>,
    dt: f32,
    m: &SandModel,
) -> SMatrix<f32, D, D>
where
    Dim<D>: DimOps<D>,
{
    let f_trial = (SMatrix::<f32, D, D>::identity() + c * dt) * *f;
    if D == 2 {
        advance_2d(f, vc, &f_trial, m)
    } else {
        advance_3d(f, vc, &f_trial, m)
    }
}

/// [`advance`] through the SVD of the trial `F`: the reference route, which
/// [`advance_2d`] and [`advance_3d`] replace (the tests compare them).
#[cfg_attr(not(test), allow(dead_code))]
#[inline(always)]
fn advance_svd<const D: usize>(
    f: &mut SMatrix<f32, D, D>,
    vc: &mut f32,
    f_trial: &SMatrix<f32, D, D>,
    m: &SandModel,
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
fn project_with_scale<const D: usize>(
    e0: &SVector<f32, D>,
    vc: &mut f32,
    alpha: f32,
    mu: f32,
    la: f32,
    tr_apex: f32,
) -> (SVector<f32, D>, f32) {
    let dd = D as f32;
    let shift = tr_apex / dd;
    let e = e0.map(|x| x + *vc / dd - shift);
    let tr = e.sum();
    let ehat = e.map(|x| x - tr / dd);
    let ehat_norm = ehat.norm();
    let (e_new, scale) = if tr >= 0.0 {
        // expansion: project to the cone tip
        (SVector::<f32, D>::from_element(shift), 0.0)
    } else {
        let dgamma = ehat_norm + (dd * la + 2.0 * mu) / (2.0 * mu) * tr * alpha;
        if dgamma <= 0.0 {
            // inside the cone: elastic, no volume correction applied
            (*e0, 1.0)
        } else {
            let k = dgamma / ehat_norm;
            ((e - ehat * k).map(|x| x + shift), 1.0 - k)
        }
    };
    *vc += e0.sum() - e_new.sum();
    (e_new, scale)
}

/// The 2D sand update of [`advance`] without singular vectors: every
/// quantity it needs is an isotropic function of the trial `F`, and in 2D
/// such a function of `B = F·Fᵀ` (eigenvalues `λ1 ≥ λ2`, `σ_i = √λ_i`) is
/// `g(B) = g(λ2)·I + (g(λ1) − g(λ2))/(λ1 − λ2)·(B − λ2·I)`. So with the
/// principal log strains `ε0_i = ½ ln λ_i` and their projection `ε_i`
/// ([`project_with_scale`]):
///
/// - Kirchhoff stress `τ = U·diag(2μ·ε_i + λ·tr ε)·Uᵀ` is that function with
///   `g(λ_i) = 2μ·ε_i + λ·tr ε`;
/// - the new elastic `F = U·diag(e^{ε_i})·Vᵀ = G·F_trial` with
///   `G = U·diag(e^{ε_i − ε0_i})·Uᵀ` (`F = F_trial` inside the cone).
///
/// The same model as the SVD route (Klár et al. 2016; [`Svd`] in `dim.rs`),
/// which it replaces in 2D because the SVD's three dependent
/// square-root-and-divide chains were about 37% of a sand2d frame. When
/// `λ1 − λ2` is below `1e-6·λ2` the divided difference is replaced by its
/// limit (the derivative at `λ2`); the rounding of either form is of the
/// order of `μ` times f32's epsilon in τ.
///
/// [`Svd`]: crate::dim::Svd
#[inline(always)]
fn advance_2d<const D: usize>(
    f: &mut SMatrix<f32, D, D>,
    vc: &mut f32,
    f_trial: &SMatrix<f32, D, D>,
    m: &SandModel,
) -> SMatrix<f32, D, D> {
    let (a, b, c, d) = (
        f_trial[(0, 0)],
        f_trial[(0, 1)],
        f_trial[(1, 0)],
        f_trial[(1, 1)],
    );
    let (b11, b12, b22) = (a * a + b * b, a * c + b * d, c * c + d * d);
    let det = a * d - b * c;
    let half = 0.5 * (b11 - b22);
    let rad = (half * half + b12 * b12).sqrt();
    // σ clamped to 1e-6 as in the SVD route (λ = σ² to 1e-12)
    let l1 = (0.5 * (b11 + b22) + rad).max(1e-12);
    // λ2 = det(B)/λ1 = det(F)²/λ1: no cancellation when F is nearly singular
    let l2 = (det * det / l1).max(1e-12);
    let e0 = SVector::<f32, D>::from_fn(|i, _| 0.5 * if i == 0 { l1 } else { l2 }.ln());
    let (e_new, scale) = project_with_scale::<D>(&e0, vc, m.alpha, m.mu, m.la, m.tr_apex);
    let dl = l1 - l2;
    // (ε0_1 − ε0_2)/(λ1 − λ2), or its limit 1/(2 λ2)
    let near = dl <= 1e-6 * l2;
    let de0_dl = if near { 0.5 / l2 } else { (e0[0] - e0[1]) / dl };
    // B − λ2·I
    let (m11, m12, m22) = (b11 - l2, b12, b22 - l2);
    if scale != 1.0 {
        // plastic: F = G·F_trial, G = g2·I + β'·(B − λ2 I), g_i = e^{ε_i − ε0_i}
        let (d1, d2) = (e_new[0] - e0[0], e_new[1] - e0[1]);
        let g2 = d2.exp();
        // (g1 − g2)/(λ1 − λ2) with g1 − g2 = g2·(e^{d1 − d2} − 1), d1 − d2 = (s − 1)(ε0_1 − ε0_2)
        let beta = if near {
            g2 * (scale - 1.0) * de0_dl
        } else {
            (d1.exp() - g2) / dl
        };
        let (g11, g12, g22) = (g2 + beta * m11, beta * m12, g2 + beta * m22);
        f[(0, 0)] = g11 * a + g12 * c;
        f[(0, 1)] = g11 * b + g12 * d;
        f[(1, 0)] = g12 * a + g22 * c;
        f[(1, 1)] = g12 * b + g22 * d;
    } else {
        *f = *f_trial;
    }
    // τ = h2·I + β·(B − λ2 I), h_i = 2μ ε_i + λ tr ε, h1 − h2 = 2μ·s·(ε0_1 − ε0_2)
    let h2 = 2.0 * m.mu * e_new[1] + m.la * e_new.sum();
    let beta = 2.0 * m.mu * scale * de0_dl;
    let mut tau = SMatrix::<f32, D, D>::zeros();
    tau[(0, 0)] = h2 + beta * m11;
    tau[(0, 1)] = beta * m12;
    tau[(1, 0)] = beta * m12;
    tau[(1, 1)] = h2 + beta * m22;
    tau
}

/// Eigenvalues `λ1 ≥ λ2 ≥ λ3` (each at least `1e-12`) of the symmetric 3×3
/// matrix `[[b00, b01, b02], [b01, b11, b12], [b02, b12, b22]]` in closed form
/// (the trigonometric solution of the characteristic cubic, Smith 1961):
/// `q = tr B / 3`, `p² = ‖B − qI‖²_F / 6`, `r = det(B − qI) / (2p³)`,
/// `φ = acos(r) / 3`, `λ1 = q + 2p cos φ`, `λ3 = q + 2p cos(φ + 2π/3)`,
/// `λ2 = 3q − λ1 − λ3`. Near a double eigenvalue (`r → ±1`) the pair comes out
/// with an error of about `p·√ε`; [`advance_3d`] only interpolates at these
/// nodes, which makes that error second order (see there).
#[inline(always)]
fn sym3_eigenvalues(b00: f32, b01: f32, b02: f32, b11: f32, b12: f32, b22: f32) -> (f32, f32, f32) {
    let q = (b00 + b11 + b22) / 3.0;
    let (d0, d1, d2) = (b00 - q, b11 - q, b22 - q);
    let p2 = (d0 * d0 + d1 * d1 + d2 * d2 + 2.0 * (b01 * b01 + b02 * b02 + b12 * b12)) / 6.0;
    if p2 <= 1e-14 * q * q {
        // isotropic to f32 rounding (and p³ below would underflow)
        let l = q.max(1e-12);
        return (l, l, l);
    }
    let p = p2.sqrt();
    let det =
        d0 * (d1 * d2 - b12 * b12) - b01 * (b01 * d2 - b12 * b02) + b02 * (b01 * b12 - d1 * b02);
    let r = (det / (2.0 * p2 * p)).clamp(-1.0, 1.0);
    let phi = r.acos() / 3.0;
    let l1 = q + 2.0 * p * phi.cos();
    let l3 = q + 2.0 * p * (phi + 2.0 * std::f32::consts::FRAC_PI_3).cos();
    let l2 = (3.0 * q - l1 - l3).min(l1).max(l3); // not clamp: no panic on NaN (a blow-up the frame reports)
    (l1.max(1e-12), l2.max(1e-12), l3.max(1e-12))
}

/// The 3D sand update of [`advance`] without singular vectors, as
/// [`advance_2d`] does in 2D: every quantity it needs is an isotropic function
/// of `B = F·Fᵀ` (eigenvalues `λ1 ≥ λ2 ≥ λ3` from [`sym3_eigenvalues`],
/// `σ_i = √λ_i`), and for a symmetric 3×3 `B` such a function is its Newton
/// interpolation at the eigenvalues,
/// `g(B) = g[λ3]·I + g[λ3,λ2]·M3 + g[λ3,λ2,λ1]·M3·M2`, `M_i = B − λ_i·I`,
/// with divided differences `g[·]`. With `ε0_i = ½ ln λ_i` and its
/// projection `ε_i = s·ε0_i + c` ([`project_with_scale`]; `c` common):
///
/// - Kirchhoff stress `τ = U·diag(2μ·ε_i + λ·tr ε)·Uᵀ`: `h(λ) = μ·s·ln λ + const`,
///   so `τ = h_3·I + μ·s·(ln[λ3,λ2]·M3 + ln[λ3,λ2,λ1]·M3·M2)`;
/// - new elastic `F = U·diag(e^{ε_i})·Vᵀ = G·F_trial`, `G` the function
///   `g(λ) = e^{ε_i − ε0_i} = e^c·λ^{(s − 1)/2}` (`F = F_trial` inside the cone).
///
/// The first divided differences are formed without cancellation
/// (`ln[a,b] = ln1p(t)/(a − b)`, `g[a,b] = g(b)·expm1(p·ln1p(t))/(a − b)`,
/// `t = (a − b)/b`); the second ones as their difference over `λ1 − λ3`, or
/// as `g''(λ2)/2` when `λ1 − λ3 ≤ 1e-4·λ3`. An error `δ` in a node moves the
/// result by about `δ` times the gaps to the other nodes (interpolation at
/// nearby nodes), so the closed-form eigenvalues' error near a double root
/// does not show. Same model as the SVD route (Klár et al. 2016), which it
/// replaces in 3D because the Jacobi SVD's chain of dependent divisions and
/// square roots was over half of a flowing sand3d frame; the tests compare
/// both against an f64 SVD.
#[inline(always)]
fn advance_3d<const D: usize>(
    f: &mut SMatrix<f32, D, D>,
    vc: &mut f32,
    f_trial: &SMatrix<f32, D, D>,
    m: &SandModel,
) -> SMatrix<f32, D, D> {
    let row = |i: usize| [f_trial[(i, 0)], f_trial[(i, 1)], f_trial[(i, 2)]];
    let (r0, r1, r2) = (row(0), row(1), row(2));
    let dot = |a: [f32; 3], b: [f32; 3]| a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
    let (b00, b01, b02) = (dot(r0, r0), dot(r0, r1), dot(r0, r2));
    let (b11, b12, b22) = (dot(r1, r1), dot(r1, r2), dot(r2, r2));
    let (l1, l2, l3) = sym3_eigenvalues(b00, b01, b02, b11, b12, b22);
    let e0 = SVector::<f32, D>::from_fn(|i, _| 0.5 * [l1, l2, l3][i].ln());
    let (e_new, scale) = project_with_scale::<D>(&e0, vc, m.alpha, m.mu, m.la, m.tr_apex);
    // divided differences of ln at λ3, λ2, λ1
    let (g32, g21) = (l2 - l3, l1 - l2);
    let (lp32, lp21) = ((g32 / l3).ln_1p(), (g21 / l2).ln_1p());
    let ln32 = if g32 > 0.0 { lp32 / g32 } else { 1.0 / l3 };
    let ln21 = if g21 > 0.0 { lp21 / g21 } else { 1.0 / l2 };
    let near = l1 - l3 <= 1e-4 * l3;
    let ln321 = if near {
        -0.5 / (l2 * l2)
    } else {
        (ln21 - ln32) / (l1 - l3)
    };
    // M3 = B − λ3 I and P = M3·M2 (symmetric: both are polynomials in B)
    let m3 = [
        [b00 - l3, b01, b02],
        [b01, b11 - l3, b12],
        [b02, b12, b22 - l3],
    ];
    let m2 = [
        [b00 - l2, b01, b02],
        [b01, b11 - l2, b12],
        [b02, b12, b22 - l2],
    ];
    let pm = |i: usize, j: usize| m3[i][0] * m2[0][j] + m3[i][1] * m2[1][j] + m3[i][2] * m2[2][j];
    let pr = [
        [pm(0, 0), pm(0, 1), pm(0, 2)],
        [pm(0, 1), pm(1, 1), pm(1, 2)],
        [pm(0, 2), pm(1, 2), pm(2, 2)],
    ];
    let func = |g0: f32, g1: f32, g2: f32| {
        SMatrix::<f32, D, D>::from_fn(|i, j| {
            let id = if i == j { g0 } else { 0.0 };
            id + g1 * m3[i][j] + g2 * pr[i][j]
        })
    };
    if scale != 1.0 {
        // plastic: G = g(B), g(λ) = e^{ε_i − ε0_i} = e^c·λ^pw
        let pw = 0.5 * (scale - 1.0);
        let (g2, g3) = ((e_new[1] - e0[1]).exp(), (e_new[2] - e0[2]).exp());
        let d32 = if g32 > 0.0 {
            g3 * (pw * lp32).exp_m1() / g32
        } else {
            pw * g3 / l3
        };
        let d21 = if g21 > 0.0 {
            g2 * (pw * lp21).exp_m1() / g21
        } else {
            pw * g2 / l2
        };
        let d321 = if near {
            0.5 * pw * (pw - 1.0) * g2 / (l2 * l2)
        } else {
            (d21 - d32) / (l1 - l3)
        };
        *f = func(g3, d32, d321) * f_trial;
    } else {
        *f = *f_trial;
    }
    let h3 = 2.0 * m.mu * e_new[2] + m.la * e_new.sum();
    let ms = m.mu * scale;
    func(h3, ms * ln32, ms * ln321)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::params::SandParams;
    use nalgebra::{DMatrix, DVector, Matrix2, Matrix3, UnitQuaternion, Vector3};

    /// The reference: the same model in f64 through nalgebra's SVD (any D):
    /// `(τ, new F, new vc)`.
    fn reference<const D: usize>(
        ft: &SMatrix<f32, D, D>,
        vc: f32,
        m: &SandModel,
    ) -> (DMatrix<f64>, DMatrix<f64>, f64) {
        let (u, sigma, vt) = svd_f64(ft);
        let (mu, la, alpha, dd) = (m.mu as f64, m.la as f64, m.alpha as f64, D as f64);
        let shift = m.tr_apex as f64 / dd;
        let e0 = sigma.map(|x| x.max(1e-6).ln());
        let e = e0.map(|x| x + vc as f64 / dd - shift);
        let tr = e.sum();
        let ehat = e.map(|x| x - tr / dd);
        let dgamma = ehat.norm() + (dd * la + 2.0 * mu) / (2.0 * mu) * tr * alpha;
        let e_new: DVector<f64> = if tr >= 0.0 {
            e.map(|_| shift)
        } else if dgamma <= 0.0 {
            e0.clone()
        } else {
            (&e - &ehat * (dgamma / ehat.norm())).map(|x| x + shift)
        };
        let vc_new = vc as f64 + e0.sum() - e_new.sum();
        let h = e_new.map(|x| 2.0 * mu * x + la * e_new.sum());
        let tau = &u * DMatrix::from_diagonal(&h) * u.transpose();
        let f = &u * DMatrix::from_diagonal(&e_new.map(f64::exp)) * vt;
        (tau, f, vc_new)
    }

    /// nalgebra's f64 SVD `(U, σ, Vᵀ)` of `ft`, through the fixed-size
    /// matrices: the dynamic-size one (`DMatrix::svd`) returned singular
    /// values off by 1e-5 relative on 3×3 matrices with a near-double one
    /// (0.9755552 for 0.9755457, against the fixed-size 0.9755457 and both
    /// f32 routes here).
    fn svd_f64<const D: usize>(
        ft: &SMatrix<f32, D, D>,
    ) -> (DMatrix<f64>, DVector<f64>, DMatrix<f64>) {
        let dynamic = |u: &[f64], s: &[f64], vt: &[f64]| {
            (
                DMatrix::from_column_slice(D, D, u),
                DVector::from_column_slice(s),
                DMatrix::from_column_slice(D, D, vt),
            )
        };
        let f = |r: usize, c: usize| ft[(r, c)] as f64;
        match D {
            2 => {
                let svd = Matrix2::from_fn(f).svd(true, true);
                dynamic(
                    svd.u.unwrap().as_slice(),
                    svd.singular_values.as_slice(),
                    svd.v_t.unwrap().as_slice(),
                )
            }
            3 => {
                let svd = Matrix3::from_fn(f).svd(true, true);
                dynamic(
                    svd.u.unwrap().as_slice(),
                    svd.singular_values.as_slice(),
                    svd.v_t.unwrap().as_slice(),
                )
            }
            _ => unreachable!("2D and 3D only"),
        }
    }

    /// A deterministic uniform stream on [−1, 1).
    fn stream(mut seed: u64) -> impl FnMut() -> f32 {
        move || {
            seed = seed
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            ((seed >> 40) as f32 / (1u64 << 24) as f32) * 2.0 - 1.0
        }
    }

    type Update<const D: usize> = fn(
        &mut SMatrix<f32, D, D>,
        &mut f32,
        &SMatrix<f32, D, D>,
        &SandModel,
    ) -> SMatrix<f32, D, D>;

    /// Run the closed form `update` and the f32 SVD route on the trial F that
    /// `trial(i, rnd)` makes (20 000 per cohesion, 0 and 200 Pa) against
    /// [`reference`]: stress within 2e-6·μ + 1e-5·|τ| or 1.5× the SVD route's
    /// error, F within 2e-6, vc within 1e-6; every case (inside the cone,
    /// at its tip, on its surface) at least 1000 times. Returns the largest
    /// stress errors over μ (closed form, SVD route) and the largest F error.
    fn check_against_reference<const D: usize>(
        update: Update<D>,
        mut trial: impl FnMut(usize, &mut dyn FnMut() -> f32) -> SMatrix<f32, D, D>,
    ) -> (f64, f64, f64)
    where
        Dim<D>: DimOps<D>,
    {
        let mut rnd = stream(12345 + D as u64);
        let mut cases = [0usize; 3];
        let (mut worst, mut worst_svd, mut worst_f) = (0.0f64, 0.0f64, 0.0f64);
        for cohesion in [0.0, 200.0] {
            let m = SandModel::new::<D>(&SandParams {
                cohesion,
                ..Default::default()
            });
            for i in 0..20_000 {
                let ft = trial(i, &mut rnd);
                let vc0 = 0.01 * rnd();
                let (tau_r, f_r, vc_r) = reference(&ft, vc0, &m);
                let (mut f_a, mut vc_a) = (SMatrix::<f32, D, D>::zeros(), vc0);
                let tau_a = update(&mut f_a, &mut vc_a, &ft, &m);
                let (mut f_b, mut vc_b) = (SMatrix::<f32, D, D>::zeros(), vc0);
                let tau_b = advance_svd(&mut f_b, &mut vc_b, &ft, &m);
                let e0 = Dim::<D>::svd(&ft).sigma.map(|x| x.ln());
                let (_, s) =
                    project_with_scale(&e0, &mut vc_b.clone(), m.alpha, m.mu, m.la, m.tr_apex);
                cases[if s == 1.0 {
                    0
                } else if s == 0.0 {
                    1
                } else {
                    2
                }] += 1;
                let err = |a: &SMatrix<f32, D, D>, r: &DMatrix<f64>| {
                    (0..D * D)
                        .map(|k| (a[k] as f64 - r[k]).abs())
                        .fold(0.0, f64::max)
                };
                let (ea, eb, ef) = (err(&tau_a, &tau_r), err(&tau_b, &tau_r), err(&f_a, &f_r));
                let tol = 2e-6 * m.mu as f64 + 1e-5 * tau_r.abs().max();
                assert!(
                    ea <= tol.max(1.5 * eb),
                    "{ft:?} vc {vc0} s {s}: τ {tau_a:?}, reference {tau_r:?}, SVD route {tau_b:?}"
                );
                assert!(ef <= 2e-6, "{ft:?} s {s}: F {f_a:?} vs {f_r:?}");
                assert!(
                    (vc_a as f64 - vc_r).abs() <= 1e-6,
                    "{ft:?}: vc {vc_a} vs {vc_r}"
                );
                worst = worst.max(ea / m.mu as f64);
                worst_svd = worst_svd.max(eb / m.mu as f64);
                worst_f = worst_f.max(ef);
            }
        }
        assert!(cases.iter().all(|&c| c > 1000), "{cases:?}");
        (worst, worst_svd, worst_f)
    }

    /// Amplitudes from 1e-7 (isotropic to rounding) to 0.3, by case number.
    fn amplitude(i: usize) -> f32 {
        10f32.powf(-7.0 + 6.5 * (i % 100) as f32 / 100.0)
    }

    /// The 2D update without singular vectors against the f64 reference:
    /// stress, new F and volume correction, for trial F inside the cone, on
    /// its surface and beyond its tip, near-isotropic (to rounding) and
    /// sheared, compressed and stretched, with and without cohesion. It is at
    /// least as close to the reference as the f32 SVD route.
    #[test]
    fn advance_2d_matches_an_f64_svd_reference() {
        let (w, w_svd, w_f) = check_against_reference::<2>(advance_2d::<2>, |i, rnd| {
            let (amp, iso) = (amplitude(i), 1.0 + 0.05 * rnd());
            Matrix2::new(
                iso + amp * rnd(),
                amp * rnd(),
                amp * rnd(),
                iso + amp * rnd(),
            )
        });
        eprintln!(
            "2D: largest |τ error| / μ: closed form {w:.2e}, SVD route {w_svd:.2e}; largest |F error| {w_f:.2e}"
        );
    }

    /// The 3D update without singular vectors against the f64 reference, as
    /// the 2D test does, on general trial F (isotropic plus noise of
    /// amplitude 1e-7..0.3), on diagonal F (with equal entries too) and on
    /// rotated F with a double singular value split by 0..1e-3 (uniaxial
    /// states, where the closed-form eigenvalues are least accurate); inside
    /// the cone, on its surface, beyond the tip.
    #[test]
    fn advance_3d_matches_an_f64_svd_reference() {
        let (w, w_svd, w_f) = check_against_reference::<3>(advance_3d::<3>, |i, rnd| {
            let (amp, iso) = (amplitude(i), 1.0 + 0.05 * rnd());
            match i % 3 {
                0 => {
                    Matrix3::from_fn(|r, c| if r == c { iso } else { 0.0 })
                        + Matrix3::from_fn(|_, _| amp * rnd())
                }
                1 => {
                    // diagonal (a sand column at rest), entries equal when the amplitude is tiny
                    let mut d = || iso * (1.0 + if rnd() > 0.0 { amp * rnd() } else { 0.0 });
                    Matrix3::from_diagonal(&Vector3::new(d(), d(), d()))
                }
                _ => {
                    let mut rot = || {
                        let q = nalgebra::Quaternion::new(rnd(), rnd(), rnd(), rnd() + 1e-3);
                        UnitQuaternion::from_quaternion(q)
                            .to_rotation_matrix()
                            .into_inner()
                    };
                    let (ra, rb) = (rot(), rot());
                    let split = 1e-3 * rnd() * if i % 4 == 1 { 1e-4 } else { 1.0 };
                    let (s1, s2) = (iso * (1.0 + amp * rnd()), iso);
                    ra * Matrix3::from_diagonal(&Vector3::new(s1, s2, s2 * (1.0 + split))) * rb
                }
            }
        });
        eprintln!(
            "3D: largest |τ error| / μ: closed form {w:.2e}, SVD route {w_svd:.2e}; largest |F error| {w_f:.2e}"
        );
    }
}
