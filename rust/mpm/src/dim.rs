//! The few dimension-specific pieces of the solver, behind one small trait.
//!
//! Everything else is written once for `const D: usize` with nalgebra's
//! `SVector` / `SMatrix`; items that need these pieces carry the bound
//! `where Dim<D>: DimOps<D>`, which holds for `D = 2` and `D = 3`.

use nalgebra::{SMatrix, SVector};

/// Marker type carrying the spatial dimension.
pub struct Dim<const D: usize>;

/// Singular value decomposition `F = U · diag(sigma) · Vᵀ`.
pub struct Svd<const D: usize> {
    pub u: SMatrix<f32, D, D>,
    pub sigma: SVector<f32, D>,
    pub v: SMatrix<f32, D, D>,
}

/// Dimension-specific operations.
pub trait DimOps<const D: usize> {
    /// log2 of the edge length (in cells) of a sparse grid block.
    const LOG2_BLOCK: u32;
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
}

impl DimOps<2> for Dim<2> {
    const LOG2_BLOCK: u32 = 3;

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
