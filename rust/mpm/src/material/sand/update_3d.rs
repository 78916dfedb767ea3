//! The 3D sand update of g2p without singular vectors ([`advance_3d`]): a
//! matrix-series route for small deviatoric strain
//! ([`advance_3d_series`]), an eigenvalue route otherwise
//! ([`advance_3d_eigen`], on the spectral tools of `material/spectral.rs`).

use super::Sand;
use super::return_map::project_lanes;
use crate::material::lanes::Real;
use crate::material::spectral::{LnDiffs, Spectral3, gram_3, k, plastic_f};
use crate::material::vmath;

/// The 3D sand update of g2p ([`Sand`]'s lanes) without singular vectors, on
/// lanes of `R` (one particle or sixteen): trial F row-major and `vc` in, new
/// F, `vc` and Kirchhoff stress out. With `B = F·Fᵀ = q·(I + X)`
/// ([`strain_3d`]) it takes the series route ([`advance_3d_series`]) when
/// `‖X‖_F ≤` [`SERIES_MAX_X`] in every lane, else the eigenvalue route
/// ([`advance_3d_eigen`]): the same model, both within about 1e-6·μ of an
/// f64 SVD (tests). So in a batch a particle's bits depend on its batch
/// mates through that choice ([`Sand`]'s `shares_route` in 3D). g2p's
/// batches of one set are the same for any thread count: consecutive
/// particles of that set, in the sorted order (by block, then id), within
/// one window of sixteen places of their source block (`solver/grid.rs`,
/// `G2P_WINDOW`; a team cuts a block only at a window), and the frame stays
/// deterministic. Where particles of other materials or sets share a
/// window, the batch holds fewer particles, and its route is chosen by
/// those alone (the unused lanes repeat the first).
#[inline(always)]
pub(crate) fn advance_3d<R: Real>(ft: &[R; 9], vc: R, m: &Sand) -> ([R; 9], R, [R; 9]) {
    let (b, q, x, small) = strain_3d(ft);
    if R::all(small) {
        advance_3d_series(ft, vc, m, q, &x)
    } else {
        advance_3d_eigen(ft, vc, m, &b)
    }
}

/// `(B, q, X, small)` of a trial F: `B = F·Fᵀ = q·(I + X)` (upper triangles
/// `[00, 01, 02, 11, 12, 22]`), `q = tr B / 3`, and whether `‖X‖_F ≤`
/// [`SERIES_MAX_X`] (false for NaN and for `q = 0`), per lane.
#[inline(always)]
pub(super) fn strain_3d<R: Real>(ft: &[R; 9]) -> ([R; 6], R, [R; 6], R::Mask) {
    let b = gram_3(ft);
    let q = (b[0] + b[3] + b[5]) * k(1.0 / 3.0);
    let inv_q = k::<R>(1.0) / q;
    let mut x = [k::<R>(0.0); 6];
    for i in 0..6 {
        x[i] = b[i] * inv_q;
    }
    for i in [0, 3, 5] {
        x[i] = x[i] - k(1.0);
    }
    let off = x[1] * x[1] + x[2] * x[2] + x[4] * x[4];
    let x2 = x[0] * x[0] + x[3] * x[3] + x[5] * x[5] + k::<R>(2.0) * off;
    // q ≥ 2e-12 keeps every eigenvalue above the eigenvalue route's clamp
    // (σ ≥ 1e-6, λ ≥ 1e-12), which the series does not apply
    // (folded into the one comparison: a second mask and `and` made LLVM
    // compile the batch 17% slower on sand3d)
    (b, q, x, x2.le(k(SERIES_MAX_X * SERIES_MAX_X)))
}

/// `‖X‖_F` (with `B = F·Fᵀ = q·(I + X)`, `q = tr B / 3`) up to which
/// [`advance_3d`] takes the series route ([`advance_3d_series`]): there the
/// dropped terms of `ln(I + X)` (from `X⁵/5`) are below `5e-9`, and those of
/// `exp(Y)` (from `Y⁴/24`, `‖Y‖ ≤ ‖X‖/2`) below `3e-9`. A sand particle's
/// elastic shear strain is small (friction caps it), so nearly every batch
/// qualifies (98% of sand3d's batches of eight had ‖X‖ ≤ 0.03 in every
/// lane). (0.05 with one more term of each series: 2% slower on sand3d.)
const SERIES_MAX_X: f32 = 0.03;

/// Product of two commuting symmetric 3×3 matrices (upper triangles
/// `[00, 01, 02, 11, 12, 22]`), which is symmetric.
#[inline(always)]
fn sym_mul<R: Real>(a: &[R; 6], b: &[R; 6]) -> [R; 6] {
    [
        a[0] * b[0] + a[1] * b[1] + a[2] * b[2],
        a[0] * b[1] + a[1] * b[3] + a[2] * b[4],
        a[0] * b[2] + a[1] * b[4] + a[2] * b[5],
        a[1] * b[1] + a[3] * b[3] + a[4] * b[4],
        a[1] * b[2] + a[3] * b[4] + a[4] * b[5],
        a[2] * b[2] + a[4] * b[4] + a[5] * b[5],
    ]
}

/// `s·A + d·I` for a symmetric `A` (upper triangle).
#[inline(always)]
fn sym_axpi<R: Real>(a: &[R; 6], s: R, d: R) -> [R; 6] {
    [
        a[0] * s + d,
        a[1] * s,
        a[2] * s,
        a[3] * s + d,
        a[4] * s,
        a[5] * s + d,
    ]
}

/// The 3D sand update of [`advance_3d`] for small deviatoric strain, as
/// matrix series instead of eigenvalues: with `B = q·(I + X)` (`X` from
/// [`advance_3d`]), the Hencky strain is `L = ½ ln B = ½ (ln q·I + ln(I + X))`,
/// `ln(I + X) = X − X²/2 + X³/3 − X⁴/4 + X⁵/5` (Horner in `X`: four products
/// of commuting symmetric matrices). The return mapping acts on `L`'s trace
/// and deviator `dev L` (whose norm is that of the principal deviatoric
/// strains): new `L' = a·dev L + c·I` with `(a, c)` = `(0, shift)` beyond the
/// tip, `(1, tr L/3)` inside the cone, `(1 − Δγ/‖dev L‖, tr L/3 + vc/3)` on
/// its surface (the same cases as [`project_lanes`]); `τ = 2μ·L' + λ·tr L'·I`
/// and, when plastic, `F = exp(L' − L)·F_trial` with
/// `exp(L' − L) = e^{c − tr L/3}·exp((a − 1)·dev L)` (series to the 4th
/// power). Same model as [`advance_3d_eigen`] (Klár et al. 2016, Sec. 7),
/// without its chain of square roots, divisions, logarithms and
/// exponentials; the tests compare both with an f64 SVD.
#[inline(always)]
pub(super) fn advance_3d_series<R: Real>(
    ft: &[R; 9],
    vc: R,
    m: &Sand,
    q: R,
    x: &[R; 6],
) -> ([R; 9], R, [R; 9]) {
    let one = k::<R>(1.0);
    // ln(I + X) = X(I + X(−½I + X(⅓I − X/4)))
    let mut p = sym_axpi(x, k(-1.0 / 4.0), k(1.0 / 3.0));
    for c in [-1.0 / 2.0, 1.0] {
        p = sym_axpi(&sym_mul(x, &p), one, k(c));
    }
    let ln_x = sym_mul(x, &p);
    // L = ½ (ln q·I + ln(I + X))
    let half = k::<R>(0.5);
    // ln q clamped as the singular values are (σ ≥ 1e-6, λ ≥ 1e-12: the
    // eigenvalue route and the reference): exact for an isotropic F
    // compressed below it, within ‖X‖/2 of the reference otherwise (a
    // blow-up's state; a mask for it in `strain_3d` cost 17% of sand3d)
    let l = sym_axpi(&ln_x, half, half * vmath::ln(q.max(k(1e-12))));
    let tr = l[0] + l[3] + l[5];
    let mean = tr * k(1.0 / 3.0);
    let dev = sym_axpi(&l, one, -mean);
    let dev_off = dev[1] * dev[1] + dev[2] * dev[2] + dev[4] * dev[4];
    let dev_norm =
        (dev[0] * dev[0] + dev[3] * dev[3] + dev[5] * dev[5] + k::<R>(2.0) * dev_off).sqrt();
    // the projection of `project_lanes` on (tr, dev)
    let (mu, la) = (m.mu, m.la);
    let shift = k::<R>(m.tr_apex / 3.0);
    let vcd = vc * k(1.0 / 3.0);
    let tr_e = tr + k::<R>(3.0) * (vcd - shift);
    let dgamma = dev_norm + k::<R>((3.0 * la + 2.0 * mu) / (2.0 * mu)) * tr_e * k(m.alpha);
    let tip = tr_e.ge(k(0.0));
    let inside = R::and(R::not(tip), dgamma.le(k(0.0)));
    let kk = dgamma / dev_norm;
    let a = R::select(tip, k(0.0), R::select(inside, one, one - kk));
    let c = R::select(tip, shift, R::select(inside, mean, mean + vcd));
    let l_new = sym_axpi(&dev, a, c);
    let tr_new = k::<R>(3.0) * c;
    let vc_new = R::select(inside, vc, vc + (tr - tr_new));
    let tau6 = sym_axpi(&l_new, k(2.0 * mu), k::<R>(la) * tr_new);
    let full = |s: &[R; 6]| [s[0], s[1], s[2], s[1], s[3], s[4], s[2], s[4], s[5]];
    // plastic (a ≠ 1): G = e^{c − tr L/3}·exp(Y), Y = (a − 1)·dev L,
    // exp(Y) = I + Y(I + Y(½I + Y/6))
    let plastic = a.ne(one);
    let mut f = *ft;
    if R::any(plastic) {
        let y = sym_axpi(&dev, a - one, k(0.0));
        let mut e = sym_axpi(&y, k(1.0 / 6.0), k(0.5));
        for cc in [1.0, 1.0] {
            e = sym_axpi(&sym_mul(&y, &e), one, k(cc));
        }
        let g = full(&sym_axpi(&e, vmath::exp(c - mean), k(0.0)));
        f = plastic_f(&g, ft, plastic);
    }
    (f, vc_new, full(&tau6))
}

/// The 3D sand update of [`advance_3d`] through the eigenvalues of `B`
/// (upper triangle `b`), without singular vectors, as
/// [`advance_2d`](super::update_2d::advance_2d) does in 2D: every quantity it needs is an isotropic function
/// of `B = F·Fᵀ` (eigenvalues `λ1 ≥ λ2 ≥ λ3` from
/// [`sym3_eigenvalues`](crate::material::spectral::sym3_eigenvalues),
/// `σ_i = √λ_i`), and for a symmetric 3×3 `B` such a function is its Newton
/// interpolation at the eigenvalues,
/// `g(B) = g[λ3]·I + g[λ3,λ2]·M3 + g[λ3,λ2,λ1]·M3·M2`, `M_i = B − λ_i·I`,
/// with divided differences `g[·]`. With `ε0_i = ½ ln λ_i` and its
/// projection `ε_i = s·ε0_i + c` ([`project_lanes`]; `c` common):
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
pub(super) fn advance_3d_eigen<R: Real>(
    ft: &[R; 9],
    vc: R,
    m: &Sand,
    b: &[R; 6],
) -> ([R; 9], R, [R; 9]) {
    // the eigenvalues of B, M3 = B − λ3 I and P = M3·M2
    let sp = Spectral3::of_b(b);
    let [l1, l2, l3] = sp.l;
    let half = k::<R>(0.5);
    let e0 = [
        half * vmath::ln(l1),
        half * vmath::ln(l2),
        half * vmath::ln(l3),
    ];
    let (e_new, scale, vc) = project_lanes(&e0, vc, m.alpha, m.mu, m.la, m.tr_apex);
    // divided differences of ln at λ3, λ2, λ1
    let dl = LnDiffs::new(sp.l);
    // plastic (s ≠ 1): G = g(B), g(λ) = e^{ε_i − ε0_i} = e^c·λ^pw, F =
    // G·F_trial; inside the cone F = F_trial (skipped if no lane is plastic)
    let plastic = scale.ne(k(1.0));
    let mut f = *ft;
    if R::any(plastic) {
        let pw = half * (scale - k(1.0));
        let (g2, g3) = (vmath::exp(e_new[1] - e0[1]), vmath::exp(e_new[2] - e0[2]));
        let (d32, d321) = dl.power(pw, g2, g3);
        f = plastic_f(&sp.newton(g3, d32, d321), ft, plastic);
    }
    let h3 = k::<R>(2.0 * m.mu) * e_new[2] + k::<R>(m.la) * (e_new[0] + e_new[1] + e_new[2]);
    let ms = k::<R>(m.mu) * scale;
    (f, vc, sp.newton(h3, ms * dl.ln32, ms * dl.ln321))
}
