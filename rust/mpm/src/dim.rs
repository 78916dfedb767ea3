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
    /// `f(node_offset, weight, o − fx)` with `node_offset = Σ o_d·stride_d`
    /// (fully unrolled nested loops).
    fn stencil(w: &[[f32; 3]; D], fx: &SVector<f32, D>, stride: &[usize; D], f: impl FnMut(usize, f32, SVector<f32, D>));
}

impl DimOps<2> for Dim<2> {
    const LOG2_BLOCK: u32 = 3;

    fn svd(f: &SMatrix<f32, 2, 2>) -> Svd<2> {
        svd2(f)
    }

    fn drucker_prager_alpha(phi: f32) -> f32 {
        phi.sin() / std::f32::consts::SQRT_2
    }

    #[inline(always)]
    fn stencil(w: &[[f32; 3]; 2], fx: &SVector<f32, 2>, stride: &[usize; 2], mut f: impl FnMut(usize, f32, SVector<f32, 2>)) {
        for i in 0..3 {
            let di = i as f32 - fx[0];
            for j in 0..3 {
                f(i * stride[0] + j * stride[1], w[0][i] * w[1][j], SVector::<f32, 2>::new(di, j as f32 - fx[1]));
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
    fn stencil(w: &[[f32; 3]; 3], fx: &SVector<f32, 3>, stride: &[usize; 3], mut f: impl FnMut(usize, f32, SVector<f32, 3>)) {
        for i in 0..3 {
            let di = i as f32 - fx[0];
            for j in 0..3 {
                let dj = j as f32 - fx[1];
                let wij = w[0][i] * w[1][j];
                for k in 0..3 {
                    f(
                        i * stride[0] + j * stride[1] + k * stride[2],
                        wij * w[2][k],
                        SVector::<f32, 3>::new(di, dj, k as f32 - fx[2]),
                    );
                }
            }
        }
    }
}

/// Closed-form 2×2 SVD (polar angles of the symmetric / antisymmetric parts).
fn svd2(m: &SMatrix<f32, 2, 2>) -> Svd<2> {
    let (a, b, c, d) = (m[(0, 0)], m[(0, 1)], m[(1, 0)], m[(1, 1)]);
    let e = 0.5 * (a + d);
    let f = 0.5 * (a - d);
    let g = 0.5 * (c + b);
    let h = 0.5 * (c - b);
    let q = (e * e + h * h).sqrt();
    let r = (f * f + g * g).sqrt();
    let s1 = q + r;
    let mut s2 = q - r;
    let a1 = g.atan2(f);
    let a2 = h.atan2(e);
    let theta = 0.5 * (a2 - a1);
    let phi = 0.5 * (a2 + a1);
    let (sp, cp) = phi.sin_cos();
    let (st, ct) = theta.sin_cos();
    let u = SMatrix::<f32, 2, 2>::new(cp, -sp, sp, cp);
    // Vᵀ = R(θ) ⇒ V = R(θ)ᵀ
    let mut v = SMatrix::<f32, 2, 2>::new(ct, st, -st, ct);
    if s2 < 0.0 {
        s2 = -s2;
        v[(0, 1)] = -v[(0, 1)];
        v[(1, 1)] = -v[(1, 1)];
    }
    Svd { u, sigma: SVector::<f32, 2>::new(s1, s2), v }
}

fn svd3(m: &SMatrix<f32, 3, 3>) -> Svd<3> {
    // Jacobi eigen-decomposition of the symmetric FᵀF in f64 gives V and σ²;
    // U = F V Σ⁻¹, re-orthonormalised for tiny σ.
    let md: SMatrix<f64, 3, 3> = m.cast::<f64>();
    let ata = md.transpose() * md;
    let (evals, v) = jacobi_eigen3(ata);
    let mut sigma = SVector::<f64, 3>::zeros();
    for i in 0..3 {
        sigma[i] = evals[i].max(0.0).sqrt();
    }
    let mut u = md * v;
    for i in 0..3 {
        let n = u.column(i).norm();
        if n > 1e-12 {
            let col = u.column(i) / n;
            u.set_column(i, &col);
        }
    }
    // Fix degenerate columns by completing an orthonormal basis.
    let c0 = u.column(0).into_owned();
    let c1 = u.column(1).into_owned();
    if sigma[2] < 1e-9 * sigma[0].max(1e-30) || (u.column(2).norm() - 1.0).abs() > 1e-6 {
        let c2 = c0.cross(&c1);
        let n = c2.norm();
        if n > 1e-12 {
            u.set_column(2, &(c2 / n));
        }
    }
    Svd { u: u.cast::<f32>(), sigma: sigma.cast::<f32>(), v: v.cast::<f32>() }
}

/// Cyclic Jacobi eigen-decomposition of a symmetric 3×3 matrix; eigenvalues
/// sorted in decreasing order, eigenvectors as the columns of the returned matrix.
fn jacobi_eigen3(mut a: SMatrix<f64, 3, 3>) -> (SVector<f64, 3>, SMatrix<f64, 3, 3>) {
    let mut v = SMatrix::<f64, 3, 3>::identity();
    for _sweep in 0..12 {
        let off = a[(0, 1)].powi(2) + a[(0, 2)].powi(2) + a[(1, 2)].powi(2);
        let scale = a[(0, 0)].powi(2) + a[(1, 1)].powi(2) + a[(2, 2)].powi(2);
        if off <= 1e-30 * scale.max(1e-300) {
            break;
        }
        for (p, q) in [(0usize, 1usize), (0, 2), (1, 2)] {
            let apq = a[(p, q)];
            if apq.abs() < 1e-300 {
                continue;
            }
            let theta = (a[(q, q)] - a[(p, p)]) / (2.0 * apq);
            let t = theta.signum() / (theta.abs() + (theta * theta + 1.0).sqrt());
            let t = if theta == 0.0 { 1.0 } else { t };
            let c = 1.0 / (t * t + 1.0).sqrt();
            let s = t * c;
            // A ← Jᵀ A J with the rotation J in the (p, q) plane.
            for k in 0..3 {
                let akp = a[(k, p)];
                let akq = a[(k, q)];
                a[(k, p)] = c * akp - s * akq;
                a[(k, q)] = s * akp + c * akq;
            }
            for k in 0..3 {
                let apk = a[(p, k)];
                let aqk = a[(q, k)];
                a[(p, k)] = c * apk - s * aqk;
                a[(q, k)] = s * apk + c * aqk;
            }
            for k in 0..3 {
                let vkp = v[(k, p)];
                let vkq = v[(k, q)];
                v[(k, p)] = c * vkp - s * vkq;
                v[(k, q)] = s * vkp + c * vkq;
            }
        }
    }
    let mut idx = [0usize, 1, 2];
    let d = [a[(0, 0)], a[(1, 1)], a[(2, 2)]];
    idx.sort_by(|&i, &j| d[j].partial_cmp(&d[i]).unwrap_or(std::cmp::Ordering::Equal));
    let mut evals = SVector::<f64, 3>::zeros();
    let mut vs = SMatrix::<f64, 3, 3>::zeros();
    for (k, &i) in idx.iter().enumerate() {
        evals[k] = d[i];
        vs.set_column(k, &v.column(i));
    }
    (evals, vs)
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
        assert!((rec - f).norm() < 1e-4 * (1.0 + f.norm()), "reconstruction {rec} vs {f}");
        let i = SMatrix::<f32, D, D>::identity();
        assert!((s.u.transpose() * s.u - i).norm() < 1e-4);
        assert!((s.v.transpose() * s.v - i).norm() < 1e-4);
        assert!(s.sigma.iter().all(|&x| x >= 0.0));
    }

    #[test]
    fn svd_reconstructs() {
        let mut seed = 12345u64;
        let mut rnd = || {
            seed = seed.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
            ((seed >> 33) as f32 / (1u64 << 31) as f32) - 0.5
        };
        for _ in 0..500 {
            let f2 = SMatrix::<f32, 2, 2>::identity() + SMatrix::<f32, 2, 2>::from_fn(|_, _| rnd());
            check(f2);
            let f3 = SMatrix::<f32, 3, 3>::identity() + SMatrix::<f32, 3, 3>::from_fn(|_, _| rnd());
            check(f3);
        }
        check(SMatrix::<f32, 2, 2>::identity());
        check(SMatrix::<f32, 3, 3>::identity());
        check(SMatrix::<f32, 3, 3>::from_diagonal(&SVector::<f32, 3>::new(1.0, 1.0, 0.9)));
    }
}
