//! The few dimension-specific pieces of the solver, behind one small trait.
//!
//! Everything else is written once for `const D: usize` with nalgebra's
//! `SVector` / `SMatrix`; items that need these pieces carry the bound
//! `where Dim<D>: DimOps<D>`, which holds for `D = 2` and `D = 3`.

use nalgebra::{SMatrix, SVector};

use crate::v4::V4;

/// Marker type carrying the spatial dimension.
pub struct Dim<const D: usize>;

/// Singular value decomposition `F = U · diag(sigma) · Vᵀ`.
pub struct Svd<const D: usize> {
    pub u: SMatrix<f32, D, D>,
    pub sigma: SVector<f32, D>,
    pub v: SMatrix<f32, D, D>,
}

/// `|v|`, nalgebra's `norm()` with the hardware square root. rapier's
/// `enhanced-determinism` (the bodies, `crate::body`) turns on simba's
/// `libm_force` for the whole build, which sends nalgebra's `norm()` and
/// `abs()` through software libm: the same bits, but on `dam_break3d` the
/// grid update took 5.7x as long. The engine's per-node and per-particle
/// code uses [`norm`] and [`abs`] instead.
#[inline(always)]
pub fn norm<const D: usize>(v: &SVector<f32, D>) -> f32 {
    v.norm_squared().sqrt()
}

/// Componentwise `|v|` with `f32::abs` (see [`norm`]).
#[inline(always)]
pub fn abs<const D: usize>(v: &SVector<f32, D>) -> SVector<f32, D> {
    v.map(f32::abs)
}

/// Dimension-specific operations.
pub trait DimOps<const D: usize> {
    /// log2 of the edge length (in cells) of a sparse grid block.
    const LOG2_BLOCK: u32;
    /// The node strides of a block's padded `(B+2)^D` buffer (`B = 2^LOG2_BLOCK`,
    /// the last dimension contiguous), as constants: the transfers' stencil
    /// offsets then fold into their addresses.
    const PAD_STRIDE: [usize; D];
    /// SVD with non-negative singular values (`U`, `V` may contain a reflection
    /// when `det F < 0`, which a physical deformation gradient never has).
    fn svd(f: &SMatrix<f32, D, D>) -> Svd<D>;
    /// Drucker–Prager cone coefficient `α` for friction angle `phi` (radians).
    ///
    /// 3D: the cone inscribed in the Mohr–Coulomb pyramid,
    /// `α = sqrt(2/3)·2 sinφ / (3 − sinφ)` (Klár et al. 2016, Eq. 27).
    /// 2D: the plane-strain Mohr–Coulomb match `α = sinφ / √2`, so that the
    /// limiting principal-stress ratio `(σ1 − σ2)/|σ1 + σ2|` equals `sin φ`
    /// (with the 3D constant a 2D run has a lower effective friction angle,
    /// e.g. 17.1° for φ = 19.8°).
    fn drucker_prager_alpha(phi: f32) -> f32;
    /// Visit the 3^D nodes of a quadratic B-spline stencil: calls
    /// `f(node_offset, weight, o)` with the integer node offset `o ∈ {0,1,2}^D`
    /// (as floats) and `node_offset = Σ o_d·stride_d` (fully unrolled loops).
    fn stencil(w: &[[f32; 3]; D], stride: &[usize; D], f: impl FnMut(usize, f32, [f32; D]));
    /// Visit the 3^(D−1) rows of the stencil along the last dimension:
    /// `f(row_offset, w_outer, o)` with the product of the other dimensions'
    /// weights and their integer offsets (`o[D−1] = 0`). The 3 nodes of a row
    /// are contiguous when the last stride is 1.
    fn stencil_rows(w: &[[f32; 3]; D], stride: &[usize; D], f: impl FnMut(usize, f32, [f32; D]));
    /// g2p's two stencil sums over the node vectors `n` (4 lanes each;
    /// `nodes[0]` the stencil's base node, `stride` the node strides, the
    /// last one 1): `(Σ_o w_o n_o, [Σ_o w_o o_d n_o for d in 0..D])` with
    /// `w_o = Π_d w[d][o_d]` and `o ∈ {0,1,2}^D` the node's integer offset.
    ///
    /// Evaluated one axis at a time (the weights are a tensor product): the
    /// `w` and `k·w` sums of each row along the last axis, then the same on
    /// those sums along the next axis, and so on; in 3D 116 four-lane
    /// operations, where summing every node's `w_o n_o` and `w_o o_d n_o`
    /// takes about 150. A non-finite node reaches the first sum (no weight is
    /// dropped from it).
    fn g2p_sums(nodes: &[[f32; 4]], stride: &[usize; D], w: &[[f32; 3]; D]) -> G2pSums<D>;
}

/// [`DimOps::g2p_sums`]: `Σ w n` and, per axis `d`, `Σ w o_d n`.
pub type G2pSums<const D: usize> = ([f32; 4], [[f32; 4]; D]);

/// A row of 3 nodes along the last axis with weights `w`:
/// `(Σ_k w_k n_k, Σ_k k·w_k n_k)`.
#[inline(always)]
fn row_sums(row: &[[f32; 4]], w: &[f32; 3]) -> (V4, V4) {
    let n2 = V4::load(&row[2]);
    let t1 = w[1] * V4::load(&row[1]);
    let s = w[0] * V4::load(&row[0]) + t1 + w[2] * n2;
    // 2·w2 is exact: (2·w2)·n2 = 2·(w2·n2) bit for bit
    let k = t1 + (2.0 * w[2]) * n2;
    (s, k)
}

/// Three sums `a_o` combined with weights `w`: `(Σ_o w_o a_o, Σ_o o·w_o a_o)`.
#[inline(always)]
fn axis_sums(a: [V4; 3], w: &[f32; 3]) -> (V4, V4) {
    let t1 = w[1] * a[1];
    let s = w[0] * a[0] + t1 + w[2] * a[2];
    let k = t1 + (2.0 * w[2]) * a[2];
    (s, k)
}

/// `Σ_o w_o a_o`.
#[inline(always)]
fn weighted(a: [V4; 3], w: &[f32; 3]) -> V4 {
    w[0] * a[0] + w[1] * a[1] + w[2] * a[2]
}

impl DimOps<2> for Dim<2> {
    const LOG2_BLOCK: u32 = 3;
    const PAD_STRIDE: [usize; 2] = [(1 << Self::LOG2_BLOCK) + 2, 1];

    #[inline(always)]
    fn svd(f: &SMatrix<f32, 2, 2>) -> Svd<2> {
        svd2(f)
    }

    fn drucker_prager_alpha(phi: f32) -> f32 {
        phi.sin() / std::f32::consts::SQRT_2
    }

    #[inline(always)]
    fn stencil_rows(
        w: &[[f32; 3]; 2],
        stride: &[usize; 2],
        mut f: impl FnMut(usize, f32, [f32; 2]),
    ) {
        for i in 0..3 {
            f(i * stride[0], w[0][i], [i as f32, 0.0]);
        }
    }

    #[inline(always)]
    fn g2p_sums(nodes: &[[f32; 4]], stride: &[usize; 2], w: &[[f32; 3]; 2]) -> G2pSums<2> {
        // rows i along the last axis: (S_i, K_i); then along the first axis
        // (one bounds check for the whole stencil)
        let nodes = &nodes[..2 * stride[0] + 3];
        let (s0, k0) = row_sums(&nodes[..3], &w[1]);
        let (s1, k1) = row_sums(&nodes[stride[0]..stride[0] + 3], &w[1]);
        let (s2, k2) = row_sums(&nodes[2 * stride[0]..2 * stride[0] + 3], &w[1]);
        let (v, b0) = axis_sums([s0, s1, s2], &w[0]);
        let b1 = weighted([k0, k1, k2], &w[0]);
        (v.to_array(), [b0.to_array(), b1.to_array()])
    }

    #[inline(always)]
    fn stencil(w: &[[f32; 3]; 2], stride: &[usize; 2], mut f: impl FnMut(usize, f32, [f32; 2])) {
        for i in 0..3 {
            for j in 0..3 {
                f(
                    i * stride[0] + j * stride[1],
                    w[0][i] * w[1][j],
                    [i as f32, j as f32],
                );
            }
        }
    }
}

impl DimOps<3> for Dim<3> {
    const LOG2_BLOCK: u32 = 2;
    const PAD_STRIDE: [usize; 3] = [
        ((1 << Self::LOG2_BLOCK) + 2) * ((1 << Self::LOG2_BLOCK) + 2),
        (1 << Self::LOG2_BLOCK) + 2,
        1,
    ];

    fn svd(f: &SMatrix<f32, 3, 3>) -> Svd<3> {
        svd3(f)
    }

    fn drucker_prager_alpha(phi: f32) -> f32 {
        let s = phi.sin();
        (2.0f32 / 3.0).sqrt() * 2.0 * s / (3.0 - s)
    }

    #[inline(always)]
    fn stencil_rows(
        w: &[[f32; 3]; 3],
        stride: &[usize; 3],
        mut f: impl FnMut(usize, f32, [f32; 3]),
    ) {
        for i in 0..3 {
            for j in 0..3 {
                f(
                    i * stride[0] + j * stride[1],
                    w[0][i] * w[1][j],
                    [i as f32, j as f32, 0.0],
                );
            }
        }
    }

    #[inline(always)]
    fn g2p_sums(nodes: &[[f32; 4]], stride: &[usize; 3], w: &[[f32; 3]; 3]) -> G2pSums<3> {
        // rows (i, j) along the last axis: (S_ij, K_ij); along the middle
        // axis, per i: (P_i, Q_i) = Σ_j (w_j, j·w_j) S_ij, R_i = Σ_j w_j K_ij;
        // along the first: v = Σ_i w_i P_i, b = (Σ_i i·w_i P_i, Σ_i w_i Q_i, Σ_i w_i R_i)
        // (one bounds check for the whole stencil)
        let nodes = &nodes[..2 * stride[0] + 2 * stride[1] + 3];
        let plane = |i: usize| {
            let row = |j: usize| {
                let off = i * stride[0] + j * stride[1];
                row_sums(&nodes[off..off + 3], &w[2])
            };
            let (r0, r1, r2) = (row(0), row(1), row(2));
            let (p, q) = axis_sums([r0.0, r1.0, r2.0], &w[1]);
            (p, q, weighted([r0.1, r1.1, r2.1], &w[1]))
        };
        let (pl0, pl1, pl2) = (plane(0), plane(1), plane(2));
        let (v, b0) = axis_sums([pl0.0, pl1.0, pl2.0], &w[0]);
        let b1 = weighted([pl0.1, pl1.1, pl2.1], &w[0]);
        let b2 = weighted([pl0.2, pl1.2, pl2.2], &w[0]);
        (v.to_array(), [b0.to_array(), b1.to_array(), b2.to_array()])
    }

    #[inline(always)]
    fn stencil(w: &[[f32; 3]; 3], stride: &[usize; 3], mut f: impl FnMut(usize, f32, [f32; 3])) {
        for i in 0..3 {
            for j in 0..3 {
                let wij = w[0][i] * w[1][j];
                for k in 0..3 {
                    f(
                        i * stride[0] + j * stride[1] + k * stride[2],
                        wij * w[2][k],
                        [i as f32, j as f32, k as f32],
                    );
                }
            }
        }
    }
}

/// Closed-form 2×2 SVD without trigonometry: polar decomposition
/// `F = R·S` (R a rotation), then the symmetric eigenproblem of `S = V Σ Vᵀ`,
/// so `U = R·V`.
#[inline(always)]
fn svd2(m: &SMatrix<f32, 2, 2>) -> Svd<2> {
    let (a, b, c, d) = (m[(0, 0)], m[(0, 1)], m[(1, 0)], m[(1, 1)]);
    let (x, y) = (a + d, c - b);
    let r2 = x * x + y * y;
    let (co, si) = if r2 > 1e-30 {
        let inv = 1.0 / r2.sqrt();
        (x * inv, y * inv)
    } else {
        (1.0, 0.0)
    };
    let rot = SMatrix::<f32, 2, 2>::new(co, -si, si, co);
    // S = Rᵀ F (symmetric up to rounding)
    let s11 = co * a + si * c;
    let s12 = 0.5 * ((co * b + si * d) + (-si * a + co * c));
    let s22 = -si * b + co * d;
    let mean = 0.5 * (s11 + s22);
    let half = 0.5 * (s11 - s22);
    let rad = (half * half + s12 * s12).sqrt();
    let (l1, mut l2) = (mean + rad, mean - rad);
    // eigenvector of l1: (cos t, sin t) with tan 2t = 2 s12 / (s11 − s22)
    let (v1x, v1y) = if rad > 1e-30 {
        // robust half-angle form: (half + rad, s12) or (s12, rad − half)
        let (ex, ey) = if half >= 0.0 {
            (half + rad, s12)
        } else {
            (s12, rad - half)
        };
        let inv = 1.0 / (ex * ex + ey * ey).sqrt();
        (ex * inv, ey * inv)
    } else {
        (1.0, 0.0)
    };
    let v = SMatrix::<f32, 2, 2>::new(v1x, -v1y, v1y, v1x);
    if l2 < 0.0 {
        // S = l1·v1v1ᵀ + |l2|·(−v2)v2ᵀ: flip U's second column
        l2 = -l2;
        let u = rot * SMatrix::<f32, 2, 2>::new(v1x, v1y, v1y, -v1x);
        return Svd {
            u,
            sigma: SVector::<f32, 2>::new(l1, l2),
            v,
        };
    }
    Svd {
        u: rot * v,
        sigma: SVector::<f32, 2>::new(l1, l2),
        v,
    }
}

#[inline]
fn svd3(m: &SMatrix<f32, 3, 3>) -> Svd<3> {
    // Jacobi eigen-decomposition of the symmetric FᵀF gives V and σ²;
    // U = F V Σ⁻¹, completed to an orthonormal basis where σ is tiny.
    let f = [
        [m[(0, 0)], m[(0, 1)], m[(0, 2)]],
        [m[(1, 0)], m[(1, 1)], m[(1, 2)]],
        [m[(2, 0)], m[(2, 1)], m[(2, 2)]],
    ];
    let mut a = [[0.0f32; 3]; 3];
    for i in 0..3 {
        for j in 0..3 {
            a[i][j] = f[0][i] * f[0][j] + f[1][i] * f[1][j] + f[2][i] * f[2][j];
        }
    }
    let (evals, v) = jacobi_eigen3(a);
    let mut sigma = [0.0f32; 3];
    for i in 0..3 {
        sigma[i] = evals[i].max(0.0).sqrt();
    }
    // U columns: F v_i / σ_i
    let mut u = [[0.0f32; 3]; 3]; // u[col][row]
    for c in 0..3 {
        for r in 0..3 {
            u[c][r] = f[r][0] * v[0][c] + f[r][1] * v[1][c] + f[r][2] * v[2][c];
        }
    }
    let norm = |x: &[f32; 3]| (x[0] * x[0] + x[1] * x[1] + x[2] * x[2]).sqrt();
    for c in 0..2 {
        let n = norm(&u[c]);
        if n > 1e-20 {
            for r in 0..3 {
                u[c][r] /= n;
            }
        }
    }
    // third column from the first two (right-handed); flip σ3 if F has det < 0
    let cross = [
        u[0][1] * u[1][2] - u[0][2] * u[1][1],
        u[0][2] * u[1][0] - u[0][0] * u[1][2],
        u[0][0] * u[1][1] - u[0][1] * u[1][0],
    ];
    let dot = cross[0] * u[2][0] + cross[1] * u[2][1] + cross[2] * u[2][2];
    let cn = norm(&cross);
    if cn > 1e-20 {
        let sgn = if dot < 0.0 { -1.0 } else { 1.0 };
        for r in 0..3 {
            u[2][r] = sgn * cross[r] / cn;
        }
    }
    let um = SMatrix::<f32, 3, 3>::from_fn(|r, c| u[c][r]);
    let vm = SMatrix::<f32, 3, 3>::from_fn(|r, c| v[r][c]);
    Svd {
        u: um,
        sigma: SVector::<f32, 3>::new(sigma[0], sigma[1], sigma[2]),
        v: vm,
    }
}

/// Cyclic Jacobi eigen-decomposition of a symmetric 3×3 matrix (f32): returns
/// eigenvalues in decreasing order and eigenvectors as columns (`v[row][col]`).
#[inline]
fn jacobi_eigen3(mut a: [[f32; 3]; 3]) -> ([f32; 3], [[f32; 3]; 3]) {
    let mut v = [[1.0f32, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]];
    for _sweep in 0..8 {
        let off = a[0][1] * a[0][1] + a[0][2] * a[0][2] + a[1][2] * a[1][2];
        let diag = a[0][0] * a[0][0] + a[1][1] * a[1][1] + a[2][2] * a[2][2];
        if off <= 1e-14 * diag || off == 0.0 {
            break;
        }
        for (p, q) in [(0usize, 1usize), (0, 2), (1, 2)] {
            let apq = a[p][q];
            if apq == 0.0 {
                continue;
            }
            let theta = (a[q][q] - a[p][p]) / (2.0 * apq);
            let t = if theta.abs() > 1e18 {
                0.5 / theta
            } else {
                theta.signum() / (theta.abs() + (theta * theta + 1.0).sqrt())
            };
            let t = if theta == 0.0 { 1.0 } else { t };
            let c = 1.0 / (t * t + 1.0).sqrt();
            let s = t * c;
            for k in 0..3 {
                let (akp, akq) = (a[k][p], a[k][q]);
                a[k][p] = c * akp - s * akq;
                a[k][q] = s * akp + c * akq;
            }
            for k in 0..3 {
                let (apk, aqk) = (a[p][k], a[q][k]);
                a[p][k] = c * apk - s * aqk;
                a[q][k] = s * apk + c * aqk;
            }
            for k in 0..3 {
                let (vkp, vkq) = (v[k][p], v[k][q]);
                v[k][p] = c * vkp - s * vkq;
                v[k][q] = s * vkp + c * vkq;
            }
        }
    }
    let d = [a[0][0], a[1][1], a[2][2]];
    let mut idx = [0usize, 1, 2];
    if d[idx[0]] < d[idx[1]] {
        idx.swap(0, 1);
    }
    if d[idx[1]] < d[idx[2]] {
        idx.swap(1, 2);
    }
    if d[idx[0]] < d[idx[1]] {
        idx.swap(0, 1);
    }
    let mut vs = [[0.0f32; 3]; 3];
    for (k, &i) in idx.iter().enumerate() {
        for r in 0..3 {
            vs[r][k] = v[r][i];
        }
    }
    ([d[idx[0]], d[idx[1]], d[idx[2]]], vs)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// `g2p_sums` against every node's term summed in f64, on a padded
    /// buffer with strides as the solver's, and a non-finite node reaching
    /// the velocity sum.
    fn g2p_sums_brute_force<const D: usize>()
    where
        Dim<D>: DimOps<D>,
    {
        let side = 6usize;
        let mut stride = [1usize; D];
        for d in (0..D - 1).rev() {
            stride[d] = stride[d + 1] * side;
        }
        let mut seed = 12345u32;
        let mut rnd = move || {
            seed = seed.wrapping_mul(1_664_525).wrapping_add(1_013_904_223);
            (seed >> 8) as f32 / (1u32 << 24) as f32
        };
        for _ in 0..50 {
            let mut nodes = vec![[0.0f32; 4]; side.pow(D as u32)];
            for n in nodes.iter_mut() {
                *n = [0; 4].map(|_| 20.0 * rnd() - 10.0);
            }
            let mut w = [[0.0f32; 3]; D];
            for wd in w.iter_mut() {
                *wd = crate::kernel::quadratic_weights(0.5 + rnd());
            }
            let base = (0..D)
                .map(|d| (rnd() * 3.0) as usize * stride[d])
                .sum::<usize>();
            let (v, b) = Dim::<D>::g2p_sums(&nodes[base..], &stride, &w);
            let (mut v64, mut b64) = ([0.0f64; 4], [[0.0f64; 4]; D]);
            for lin in 0..3usize.pow(D as u32) {
                let mut o = [0usize; D];
                let (mut rest, mut off, mut wo) = (lin, 0usize, 1.0f64);
                for d in (0..D).rev() {
                    o[d] = rest % 3;
                    rest /= 3;
                    off += o[d] * stride[d];
                    wo *= w[d][o[d]] as f64;
                }
                for l in 0..4 {
                    let t = wo * nodes[base + off][l] as f64;
                    v64[l] += t;
                    for d in 0..D {
                        b64[d][l] += o[d] as f64 * t;
                    }
                }
            }
            for l in 0..4 {
                assert!((v[l] as f64 - v64[l]).abs() < 1e-5, "v {v:?} vs {v64:?}");
                for d in 0..D {
                    assert!(
                        (b[d][l] as f64 - b64[d][l]).abs() < 2e-5,
                        "b {b:?} vs {b64:?}"
                    );
                }
            }
            // any node of the stencil, non-finite, makes the velocity sum so
            let corner = (0..D).map(|d| 2 * stride[d]).sum::<usize>();
            let mut bad = nodes.clone();
            bad[base + corner][1] = f32::INFINITY;
            let (v, _) = Dim::<D>::g2p_sums(&bad[base..], &stride, &w);
            assert!(!v[1].is_finite());
        }
    }

    #[test]
    fn g2p_sums_match_a_brute_force_sum() {
        g2p_sums_brute_force::<2>();
        g2p_sums_brute_force::<3>();
    }

    fn check<const D: usize>(f: SMatrix<f32, D, D>)
    where
        Dim<D>: DimOps<D>,
    {
        let s = Dim::<D>::svd(&f);
        let rec = s.u * SMatrix::<f32, D, D>::from_diagonal(&s.sigma) * s.v.transpose();
        assert!(
            (rec - f).norm() < 1e-4 * (1.0 + f.norm()),
            "reconstruction {rec} vs {f}"
        );
        let i = SMatrix::<f32, D, D>::identity();
        assert!((s.u.transpose() * s.u - i).norm() < 1e-4);
        assert!((s.v.transpose() * s.v - i).norm() < 1e-4);
        assert!(s.sigma.iter().all(|&x| x >= 0.0));
    }

    #[test]
    fn svd_reconstructs() {
        let mut seed = 12345u64;
        let mut rnd = || {
            seed = seed
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            ((seed >> 33) as f32 / (1u64 << 31) as f32) - 0.5
        };
        for _ in 0..500 {
            let f2 = SMatrix::<f32, 2, 2>::identity() + SMatrix::<f32, 2, 2>::from_fn(|_, _| rnd());
            check(f2);
            let f3 = SMatrix::<f32, 3, 3>::identity() + SMatrix::<f32, 3, 3>::from_fn(|_, _| rnd());
            check(f3);
        }
        check(SMatrix::<f32, 2, 2>::identity());
        check(SMatrix::<f32, 2, 2>::new(1.0, 0.0, 0.0, -1.0));
        check(SMatrix::<f32, 2, 2>::new(0.3, 2.0, 1.0, 0.5));
        check(SMatrix::<f32, 2, 2>::new(2.0, 0.0, 0.0, 2.0));
        check(SMatrix::<f32, 2, 2>::new(0.0, 0.0, 0.0, 0.0));
        check(SMatrix::<f32, 3, 3>::identity());
        check(SMatrix::<f32, 3, 3>::from_diagonal(
            &SVector::<f32, 3>::new(1.0, 1.0, 0.9),
        ));
    }
}
