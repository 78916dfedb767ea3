//! The 2D sand update of g2p without singular vectors ([`advance_2d`]).

use super::Sand;
use super::return_map::project_lanes;
use crate::material::lanes::Real;
use crate::material::spectral::{eig_2d, k};
use crate::material::vmath;

/// The 2D sand update of g2p ([`Sand`]'s lanes) without singular vectors, on
/// lanes of `R` (one particle or sixteen): trial F row-major (the first four
/// entries) and `vc` in, new F, `vc` and Kirchhoff stress out. Every
/// quantity it needs is an isotropic function of the trial `F`, and in 2D
/// such a function of `B = F·Fᵀ` (eigenvalues `λ1 ≥ λ2`, `σ_i = √λ_i`) is
/// `g(B) = g(λ2)·I + (g(λ1) − g(λ2))/(λ1 − λ2)·(B − λ2·I)`. So with the
/// principal log strains `ε0_i = ½ ln λ_i` and their projection `ε_i`
/// ([`project_lanes`]):
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
pub(crate) fn advance_2d<R: Real>(ft: &[R; 9], vc: R, m: &Sand) -> ([R; 4], R, [R; 4]) {
    let [a, b, c, d] = [ft[0], ft[1], ft[2], ft[3]];
    // B = F·Fᵀ and its eigenvalues: σ clamped to 1e-6 as in the SVD route
    // (λ = σ² to 1e-12); λ2 = det(F)²/λ1, no cancellation when F is nearly
    // singular
    let ([b11, b12, b22], l1, l2, _) = eig_2d(ft);
    let e0 = [k::<R>(0.5) * vmath::ln(l1), k::<R>(0.5) * vmath::ln(l2)];
    let (e_new, scale, vc) = project_lanes(&e0, vc, m.alpha, m.mu, m.la, m.tr_apex);
    let dl = l1 - l2;
    // (ε0_1 − ε0_2)/(λ1 − λ2), or its limit 1/(2 λ2)
    let near = dl.le(k::<R>(1e-6) * l2);
    let de0_dl = R::select_div(near, k(0.5), l2, e0[0] - e0[1], dl);
    // B − λ2·I
    let (m11, m12, m22) = (b11 - l2, b12, b22 - l2);
    // plastic (s ≠ 1): F = G·F_trial, G = g2·I + β'·(B − λ2 I),
    // g_i = e^{ε_i − ε0_i}; inside the cone F = F_trial
    // (skipped if no lane is plastic)
    let plastic = scale.ne(k(1.0));
    let mut f = [a, b, c, d];
    if R::any(plastic) {
        let (d1, d2) = (e_new[0] - e0[0], e_new[1] - e0[1]);
        let g2 = vmath::exp(d2);
        // (g1 − g2)/(λ1 − λ2) with g1 − g2 = g2·(e^{d1 − d2} − 1), d1 − d2 = (s − 1)(ε0_1 − ε0_2)
        let beta = R::select(
            near,
            g2 * (scale - k(1.0)) * de0_dl,
            (vmath::exp(d1) - g2) / dl,
        );
        let (g11, g12, g22) = (g2 + beta * m11, beta * m12, g2 + beta * m22);
        f = [
            R::select(plastic, g11 * a + g12 * c, a),
            R::select(plastic, g11 * b + g12 * d, b),
            R::select(plastic, g12 * a + g22 * c, c),
            R::select(plastic, g12 * b + g22 * d, d),
        ];
    }
    // τ = h2·I + β·(B − λ2 I), h_i = 2μ ε_i + λ tr ε, h1 − h2 = 2μ·s·(ε0_1 − ε0_2)
    let h2 = k::<R>(2.0 * m.mu) * e_new[1] + k::<R>(m.la) * (e_new[0] + e_new[1]);
    let beta = k::<R>(2.0 * m.mu) * scale * de0_dl;
    let tau = [h2 + beta * m11, beta * m12, beta * m12, h2 + beta * m22];
    (f, vc, tau)
}
