//! The solids' updates (elastic, snow, viscoplastic) against their
//! definitions, one particle at a time ([`advance`], the reference the lane
//! tests compare g2p's batch with), in f64 where a reference is computed
//! (nalgebra's SVD).

use nalgebra::{DMatrix, SMatrix, SVector};

use super::spectral::{from_lanes, to_lanes};
use super::{ElasticModel, ElasticParams, MaterialParams, SnowParams, ViscoplasticParams};
use super::{Model, State};
use crate::dim::{Dim, DimOps};
use crate::particles::{Material, Particle, det};

/// g2p's update of a solid particle under model `m` with the new velocity
/// gradient `c` over `dt`: its `f` (and `j` = `J_P` for snow) and stress,
/// one particle (g2p's batch does sixteen, with the same bits per lane).
/// Returns `(finite, inverted)`: whether F, J_P and τ are finite, and
/// whether `det F ≤ 0` (or NaN).
pub(super) fn advance<const D: usize>(
    m: &Model,
    p: &mut Particle<D>,
    dt: f32,
    c: &SMatrix<f32, D, D>,
) -> (bool, bool) {
    let mut s = State {
        f: to_lanes(&p.f),
        j: p.j,
        vc: p.vc,
        tau: [0.0; 9],
    };
    m.update_lanes::<f32, D>(&mut s, &to_lanes(c), dt);
    (p.f, p.j, p.tau) = (from_lanes(&s.f), s.j, from_lanes(&s.tau));
    let finite = p.f.iter().chain(p.tau.iter()).all(|a| a.is_finite()) && p.j.is_finite();
    (finite, !(det(&p.f) > 0.0))
}

/// The stress of model `m` at F = `f`, `J` = `j` (the refresh's).
fn stress<const D: usize>(m: &Model, f: &SMatrix<f32, D, D>, j: f32) -> SMatrix<f32, D, D>
where
    Dim<D>: DimOps<D>,
{
    let mut p = Particle::new(SVector::from_element(0.5), Material::Elastic, 1.0, 1.0);
    (p.f, p.j) = (*f, j);
    m.stress(&p)
}

/// `m` in f64, dynamically sized (nalgebra's SVD and determinant need a
/// known size).
fn dyn64<const D: usize>(m: &SMatrix<f32, D, D>) -> DMatrix<f64> {
    DMatrix::from_fn(D, D, |r, c| m[(r, c)] as f64)
}

fn rnd(seed: &mut u64) -> f32 {
    *seed = seed
        .wrapping_mul(6364136223846793005)
        .wrapping_add(1442695040888963407);
    ((*seed >> 33) as f32 / (1u64 << 31) as f32) - 0.5
}

fn model<const D: usize>(m: MaterialParams) -> Model
where
    Dim<D>: DimOps<D>,
{
    Model::new::<D>(&m)
}

fn particle<const D: usize>(material: Material, f: SMatrix<f32, D, D>) -> Particle<D> {
    let mut p = Particle::new(SVector::from_element(0.5), material, 1.0, 1.0);
    p.f = f;
    p
}

/// The crate's SVD (the one the solids use) gives nalgebra's singular values
/// (f64) and, for det F > 0, the rotation of the polar decomposition.
fn svd_matches_nalgebra<const D: usize>()
where
    Dim<D>: DimOps<D>,
{
    let mut seed = 7u64;
    for _ in 0..2000 {
        let f = SMatrix::<f32, D, D>::identity()
            + SMatrix::<f32, D, D>::from_fn(|_, _| 0.8 * rnd(&mut seed));
        if det(&f) <= 1e-3 {
            continue;
        }
        let ours = Dim::<D>::svd(&f);
        let reference = dyn64(&f).svd(true, true);
        let mut want: Vec<f64> = reference.singular_values.iter().copied().collect();
        want.sort_by(|a, b| b.partial_cmp(a).unwrap());
        let mut got: Vec<f64> = ours.sigma.iter().map(|&s| s as f64).collect();
        got.sort_by(|a, b| b.partial_cmp(a).unwrap());
        for (g, w) in got.iter().zip(&want) {
            assert!((g - w).abs() < 2e-5 * (1.0 + w), "σ {got:?} vs {want:?}");
        }
        // polar rotation: R = U Vᵀ against nalgebra's (F = R S, S symmetric positive)
        let r = dyn64(&(ours.u * ours.v.transpose()));
        let (u, vt) = (reference.u.unwrap(), reference.v_t.unwrap());
        let want_r = u * vt;
        assert!((&r - &want_r).norm() < 1e-4, "R {r} vs {want_r}");
    }
}

#[test]
fn the_svd_matches_nalgebras() {
    svd_matches_nalgebra::<2>();
    svd_matches_nalgebra::<3>();
}

/// Fixed-corotated stress against `2μ(F − R)Fᵀ + λJ(J − 1)I` in f64 with
/// nalgebra's polar rotation; neo-Hookean against its formula; rest state
/// stress-free; a rotation stress-free.
fn elastic_stress<const D: usize>()
where
    Dim<D>: DimOps<D>,
{
    let e = ElasticParams {
        youngs_modulus: 1.0e5,
        poisson_ratio: 0.3,
        ..Default::default()
    };
    let (mu, la) = e.lame();
    let m = model::<D>(MaterialParams::Elastic(e.clone()));
    let neo = model::<D>(MaterialParams::Elastic(ElasticParams {
        model: ElasticModel::Neohookean,
        ..e
    }));
    let mut seed = 3u64;
    let i64m = DMatrix::<f64>::identity(D, D);
    for _ in 0..500 {
        let f = SMatrix::<f32, D, D>::identity()
            + SMatrix::<f32, D, D>::from_fn(|_, _| 0.4 * rnd(&mut seed));
        if det(&f) <= 0.1 {
            continue;
        }
        let f64m = dyn64(&f);
        let svd = f64m.clone().svd(true, true);
        let r = svd.u.unwrap() * svd.v_t.unwrap();
        let j = f64m.determinant();
        let (mu64, la64) = (mu as f64, la as f64);
        let want = (&f64m - r) * f64m.transpose() * (2.0 * mu64) + &i64m * (la64 * j * (j - 1.0));
        let got = dyn64(&stress::<D>(&m, &f, 1.0));
        assert!(
            (&got - &want).norm() < 1e-4 * (mu64 + want.norm()),
            "{got} vs {want}"
        );
        let want_neo = (&f64m * f64m.transpose() - &i64m) * mu64 + &i64m * (la64 * j.ln());
        let got_neo = dyn64(&stress::<D>(&neo, &f, 1.0));
        assert!((&got_neo - &want_neo).norm() < 1e-4 * (mu64 + want_neo.norm()));
    }
    let rest = SMatrix::<f32, D, D>::identity();
    assert!(stress::<D>(&m, &rest, 1.0).norm() < 1e-3);
    assert!(stress::<D>(&neo, &rest, 1.0).norm() < 1e-3);
    let mut rot = SMatrix::<f32, D, D>::identity();
    let (s, c) = 0.7f32.sin_cos();
    rot[(0, 0)] = c;
    rot[(0, 1)] = -s;
    rot[(1, 0)] = s;
    rot[(1, 1)] = c;
    assert!(stress::<D>(&m, &rot, 1.0).norm() < 1e-2 * mu);
}

#[test]
fn elastic_stress_matches_its_definition() {
    elastic_stress::<2>();
    elastic_stress::<3>();
}

/// Snow: after an update the singular values of F_E lie in
/// [1 − θc, 1 + θs] and `J_P · det F_E = det(I + ΔtC) · J_P⁰ · det F_E⁰`;
/// compression past θc lowers J_P, and the hardened stress grows.
fn snow_invariants<const D: usize>()
where
    Dim<D>: DimOps<D>,
{
    let sp = SnowParams::default();
    let m = model::<D>(MaterialParams::Snow(sp.clone()));
    let mut seed = 11u64;
    for _ in 0..500 {
        let mut p = particle::<D>(Material::Snow, SMatrix::identity());
        for _ in 0..20 {
            let c = SMatrix::<f32, D, D>::from_fn(|_, _| 40.0 * rnd(&mut seed));
            let dt = 1e-3;
            let before = p.j as f64 * det(&p.f) as f64;
            let step = dyn64(&(SMatrix::<f32, D, D>::identity() + c * dt)).determinant();
            let (finite, inverted) = advance(&m, &mut p, dt, &c);
            assert!(finite && !inverted);
            let sig = Dim::<D>::svd(&p.f).sigma;
            for &s in sig.iter() {
                assert!(
                    s >= (1.0 - sp.theta_c) * (1.0 - 1e-5)
                        && s <= (1.0 + sp.theta_s) * (1.0 + 1e-5),
                    "σ {sig}"
                );
            }
            let after = p.j as f64 * det(&p.f) as f64;
            assert!(
                (after - before * step).abs() < 1e-5 * after.abs(),
                "J_P det F_E {after} vs {}",
                before * step
            );
        }
    }
    // uniform compression by 10 %: J_P drops below 1, and the stress of the
    // same F_E is larger in magnitude than unhardened
    let mut p = particle::<D>(Material::Snow, SMatrix::identity());
    let c = SMatrix::<f32, D, D>::identity() * (-100.0);
    let (_, _) = advance(&m, &mut p, 1e-3, &c);
    assert!(p.j < 0.95, "J_P = {}", p.j);
    let hardened = stress::<D>(&m, &p.f, p.j).norm();
    let soft = stress::<D>(&m, &p.f, 1.0).norm();
    assert!(hardened > 1.5 * soft, "{hardened} vs {soft}");
}

#[test]
fn snow_keeps_its_invariants() {
    snow_invariants::<2>();
    snow_invariants::<3>();
}

/// Viscoplastic: simple shear at rate γ̇ held for many steps settles at the
/// Bingham stress τ_y + η·γ̇ (√J₂ of the deviatoric Kirchhoff stress), and
/// at τ_y with η = 0; below yield it is elastic.
fn bingham_shear<const D: usize>()
where
    Dim<D>: DimOps<D>,
{
    for (eta, rate) in [(0.0f32, 2.0f32), (5.0, 2.0), (5.0, 10.0)] {
        let vp = ViscoplasticParams {
            youngs_modulus: 1.0e6,
            poisson_ratio: 0.3,
            yield_stress: 100.0,
            viscosity: eta,
            ..Default::default()
        };
        let m = model::<D>(MaterialParams::Viscoplastic(vp));
        let mut p = particle::<D>(Material::Viscoplastic, SMatrix::identity());
        let mut c = SMatrix::<f32, D, D>::zeros();
        c[(0, 1)] = rate;
        let dt = 1e-5;
        for _ in 0..20000 {
            // the flow rotates the material; hold the velocity gradient fixed
            advance(&m, &mut p, dt, &c);
        }
        let tau = p.tau;
        let dev = tau - SMatrix::<f32, D, D>::identity() * (tau.trace() / D as f32);
        let sqrt_j2 = (0.5 * dev.norm_squared()).sqrt();
        let want = 100.0 + eta * rate;
        assert!(
            (sqrt_j2 - want).abs() < 0.03 * want,
            "η {eta}, γ̇ {rate}: √J₂ = {sqrt_j2}, want {want}"
        );
    }
}

#[test]
fn viscoplastic_shear_settles_at_the_bingham_stress() {
    bingham_shear::<2>();
    bingham_shear::<3>();
}

/// The 2D viscoplastic update (an isotropic function of `B`, no singular
/// vectors) against the SVD route in f64: new F and τ, yielding or not.
#[test]
fn viscoplastic_2d_matches_the_svd_route() {
    let vp = ViscoplasticParams {
        youngs_modulus: 1.0e5,
        poisson_ratio: 0.3,
        yield_stress: 200.0,
        viscosity: 0.5,
        ..Default::default()
    };
    let (mu, la) = vp.lame();
    let radius = std::f64::consts::SQRT_2 * vp.yield_stress as f64;
    let m = model::<2>(MaterialParams::Viscoplastic(vp.clone()));
    let dt = 1e-4f32;
    let keep = (vp.viscosity as f64 / mu as f64) / (vp.viscosity as f64 / mu as f64 + dt as f64);
    let mut seed = 5u64;
    let mut yielded = 0;
    for _ in 0..2000 {
        let f0 = SMatrix::<f32, 2, 2>::identity() + SMatrix::from_fn(|_, _| 0.02 * rnd(&mut seed));
        let c = SMatrix::<f32, 2, 2>::from_fn(|_, _| 50.0 * rnd(&mut seed));
        let mut p = particle::<2>(Material::Viscoplastic, f0);
        let ft = (SMatrix::<f32, 2, 2>::identity() + c * dt) * f0;
        advance(&m, &mut p, dt, &c);
        // reference: SVD in f64
        let svd = dyn64(&ft).svd(true, true);
        let (u, vt, s) = (svd.u.unwrap(), svd.v_t.unwrap(), svd.singular_values);
        let mut eps: Vec<f64> = s.iter().map(|x| x.ln()).collect();
        let mean = (eps[0] + eps[1]) / 2.0;
        let dev = [eps[0] - mean, eps[1] - mean];
        let s_norm = 2.0 * mu as f64 * (dev[0] * dev[0] + dev[1] * dev[1]).sqrt();
        if s_norm > radius {
            yielded += 1;
            let target = radius + (s_norm - radius) * keep;
            eps = dev.iter().map(|d| d * target / s_norm + mean).collect();
        }
        let tr = eps[0] + eps[1];
        let diag = |g: &dyn Fn(f64) -> f64| {
            DMatrix::from_diagonal(&nalgebra::DVector::from_iterator(
                2,
                eps.iter().map(|&e| g(e)),
            ))
        };
        let want_f = &u * diag(&|e| e.exp()) * &vt;
        let want_tau = &u * diag(&|e| 2.0 * mu as f64 * e + la as f64 * tr) * u.transpose();
        assert!(
            (dyn64(&p.f) - &want_f).norm() < 2e-5,
            "F {} vs {want_f}",
            p.f
        );
        assert!(
            (dyn64(&p.tau) - &want_tau).norm() < 1e-3 * (mu as f64 * 1e-3 + want_tau.norm()),
            "τ {} vs {want_tau}",
            p.tau
        );
    }
    assert!(yielded > 200 && yielded < 1800, "{yielded} of 2000 yielded");
}

/// A substep that would invert a solid particle (`det(I + Δt·C) < 0`: one
/// axis compressed past zero) keeps its F, `J_P` and their stress, bit for
/// bit, and reports no inversion; a substep that does not invert it is
/// applied as before.
fn inversion_kept_out<const D: usize>()
where
    Dim<D>: DimOps<D>,
{
    let vp = ViscoplasticParams {
        youngs_modulus: 1.0e5,
        poisson_ratio: 0.3,
        yield_stress: 200.0,
        viscosity: 0.5,
        ..Default::default()
    };
    let models = [
        (
            Material::Elastic,
            MaterialParams::Elastic(ElasticParams::default()),
        ),
        (Material::Snow, MaterialParams::Snow(SnowParams::default())),
        (Material::Viscoplastic, MaterialParams::Viscoplastic(vp)),
    ];
    let dt = 1e-4f32;
    for (material, params) in models {
        let m = model::<D>(params);
        let mut f = SMatrix::<f32, D, D>::identity() * 0.9;
        f[(0, 1)] = 0.05;
        let mut p = particle::<D>(material, f);
        p.j = 0.97;
        // past zero along x in one substep: I + Δt·C = diag(−0.5, 1, …)
        let mut c = SMatrix::<f32, D, D>::zeros();
        c[(0, 0)] = -1.5 / dt;
        let (f0, j0) = (p.f, p.j);
        let (finite, inverted) = advance(&m, &mut p, dt, &c);
        assert!(finite && !inverted, "{material:?}");
        assert_eq!((p.f, p.j), (f0, j0), "{material:?}: F and J_P kept");
        assert_eq!(
            p.tau,
            stress::<D>(&m, &f0, j0),
            "{material:?}: their stress"
        );
        assert!(det(&p.f) > 0.0);
        // a compression that does not invert it is applied
        c[(0, 0)] = -0.2 / dt;
        let (finite, inverted) = advance(&m, &mut p, dt, &c);
        assert!(finite && !inverted && p.f != f0, "{material:?}");
    }
}

#[test]
fn a_substep_that_would_invert_a_solid_keeps_its_deformation() {
    inversion_kept_out::<2>();
    inversion_kept_out::<3>();
}
