//! The sampled signed-distance collider (`Shape::Sampled`, a scene's mesh
//! obstacle) against analytic shapes: its distance, normal, validation and
//! the flow it makes.

use std::sync::Arc;

use hybridmpm_mpm::collider::MIN_SAMPLED_DEPTH_CELLS;
use hybridmpm_mpm::{BoundaryCondition, Collider, Material, Particle, Shape, Solver, SolverParams};
use nalgebra::{SMatrix, SVector};

/// `shape`'s distance and normal sampled on the nodes `origin + cell·i`.
fn sample_with_normals<const D: usize>(
    shape: &Shape<D>,
    origin: [f32; D],
    cell: f32,
    dims: [usize; D],
) -> Shape<D> {
    let Shape::Sampled { values, .. } = sample(shape, origin, cell, dims) else {
        unreachable!()
    };
    let normals: Vec<f32> = (0..values.len())
        .flat_map(|mut lin| {
            let mut p = SVector::<f32, D>::zeros();
            for d in (0..D).rev() {
                p[d] = origin[d] + cell * (lin % dims[d]) as f32;
                lin /= dims[d];
            }
            shape.normal(&p).iter().copied().collect::<Vec<_>>()
        })
        .collect();
    Shape::Sampled {
        origin: SVector::from_column_slice(&origin),
        cell,
        dims,
        values,
        normals: Some(Arc::from(normals)),
    }
}

/// `shape`'s distance sampled on the nodes `origin + cell·i`, `dims` per axis.
fn sample<const D: usize>(
    shape: &Shape<D>,
    origin: [f32; D],
    cell: f32,
    dims: [usize; D],
) -> Shape<D> {
    let total: usize = dims.iter().product();
    let values: Vec<f32> = (0..total)
        .map(|mut lin| {
            let mut p = SVector::<f32, D>::zeros();
            for d in (0..D).rev() {
                p[d] = origin[d] + cell * (lin % dims[d]) as f32;
                lin /= dims[d];
            }
            shape.sdf(&p)
        })
        .collect();
    Shape::Sampled {
        origin: SVector::from_column_slice(&origin),
        cell,
        dims,
        values: Arc::from(values),
        normals: None,
    }
}

fn lcg(seed: &mut u64) -> f32 {
    *seed = seed
        .wrapping_mul(6364136223846793005)
        .wrapping_add(1442695040888963407);
    (*seed >> 40) as f32 / (1u64 << 24) as f32
}

#[test]
fn sampled_sphere_interpolates_the_analytic_distance_and_normal() {
    let cell = 1.0 / 64.0;
    let sphere = Shape::<3>::Sphere {
        center: SVector::from([0.5, 0.4, 0.5]),
        radius: 0.15,
    };
    let s = sample(&sphere, [0.3125, 0.203125, 0.3125], cell, [27, 27, 27]);
    let mut seed = 7;
    for _ in 0..2000 {
        let p = SVector::<f32, 3>::from_fn(|d, _| {
            0.34 + 0.32 * lcg(&mut seed) - if d == 1 { 0.1 } else { 0.0 }
        });
        let exact = sphere.sdf(&p);
        if exact.abs() < 3.0 * cell {
            assert!((s.sdf(&p) - exact).abs() < 0.05 * cell, "{p:?}");
            assert!(s.normal(&p).dot(&sphere.normal(&p)) > 0.99, "{p:?}");
        }
    }
    // outside the sampled box: positive, never below the true distance
    let far = SVector::<f32, 3>::from([0.05, 0.9, 0.05]);
    assert!(s.sdf(&far) >= sphere.sdf(&far) - 1e-5);
}

#[test]
fn a_thin_sampled_slab_points_to_its_nearer_face() {
    // slabs 2.6 cells thick, level and tilted, with sampled normals (a
    // mesh's nearest-surface directions): at the nodes inside, the box's
    let cell = 1.0 / 32.0;
    for deg in [0.0f32, -20.0, 35.0] {
        let (s, c) = deg.to_radians().sin_cos();
        let slab = Shape::<2>::Box {
            center: SVector::from([0.5, 0.5]),
            half_extents: SVector::from([0.25, 1.3 * cell]),
            rotation: SMatrix::<f32, 2, 2>::new(c, -s, s, c),
        };
        let sampled = sample_with_normals(&slab, [0.125, 0.125], cell, [25, 25]);

        let mut checked = 0;
        for i in 0..32 {
            for j in 0..32 {
                let p = SVector::<f32, 2>::from([i as f32 * cell, j as f32 * cell]);
                // inside, away from the ends, and not on the mid-plane (no nearer face there)
                let local =
                    SMatrix::<f32, 2, 2>::new(c, s, -s, c) * (p - SVector::from([0.5, 0.5]));
                if slab.sdf(&p) < -0.1 * cell
                    && local[0].abs() < 0.15
                    && local[1].abs() > 0.05 * cell
                {
                    assert!(sampled.sdf(&p) < 0.0);
                    let dot = sampled.normal(&p).dot(&slab.normal(&p));
                    assert!(
                        dot > 0.999,
                        "{deg}° {p:?}: {:?} vs {:?}",
                        sampled.normal(&p),
                        slab.normal(&p)
                    );
                    checked += 1;
                }
            }
        }
        assert!(checked > 10, "{deg}°: {checked}");
    }
}

#[test]
fn validation_names_the_field() {
    let c = |values: Vec<f32>, dims: [usize; 2]| Collider {
        shape: Shape::<2>::Sampled {
            origin: SVector::from([0.4, 0.4]),
            cell: 1.0 / 32.0,
            dims,
            values: Arc::from(values),
            normals: None,
        },
        condition: BoundaryCondition::Separate,
        friction: 0.0,
        project: true,
    };
    let e = c(vec![0.0; 5], [2, 3])
        .validate("colliders[0]")
        .unwrap_err()
        .to_string();
    assert!(e.starts_with("colliders[0].values"), "{e}");
    let e = c(vec![0.0; 3], [1, 3])
        .validate("colliders[0]")
        .unwrap_err()
        .to_string();
    assert!(e.starts_with("colliders[0].dims"), "{e}");
    let e = c(vec![f32::NAN; 4], [2, 2])
        .validate("colliders[0]")
        .unwrap_err()
        .to_string();
    assert!(e.starts_with("colliders[0].values"), "{e}");
    let e = c(vec![1e9; 4], [1 << 13, 1 << 13])
        .validate("colliders[0]")
        .unwrap_err()
        .to_string();
    assert!(e.contains("colliders[0]."), "{e}");
    let dx = 1.0 / 32.0;
    let shallow = c(
        vec![0.1, -0.9 * MIN_SAMPLED_DEPTH_CELLS * dx, 0.1, 0.1],
        [2, 2],
    );
    assert!(shallow.validate("colliders[0]").is_ok());
    let e = shallow
        .validate_resolution("colliders[0]", dx)
        .unwrap_err()
        .to_string();
    assert!(e.starts_with("colliders[0].values"), "{e}");
    let deep = c(
        vec![0.1, -1.1 * MIN_SAMPLED_DEPTH_CELLS * dx, 0.1, 0.1],
        [2, 2],
    );
    assert!(deep.validate_resolution("colliders[0]", dx).is_ok());
}

/// Water dropped on a disc: the sampled disc holds it as the analytic one does.
#[test]
fn water_on_a_sampled_disc_follows_the_analytic_disc() {
    let params = SolverParams::<2> {
        n_grid: 64,
        ..Default::default()
    };
    let disc = Shape::<2>::Sphere {
        center: SVector::from([0.5, 0.35]),
        radius: 0.12,
    };
    let sampled = sample_with_normals(&disc, [0.34375, 0.1875], 1.0 / 64.0, [21, 21]);
    let run = |shape: Shape<2>| {
        let col = Collider {
            shape,
            condition: BoundaryCondition::Separate,
            friction: 0.0,
            project: true,
        };
        let mut s = Solver::new(params.clone(), vec![col]).unwrap();
        let sp = 0.5 / 64.0;
        let vol = sp * sp;
        let ps: Vec<Particle<2>> = (0..30 * 20)
            .map(|i| {
                let x = SVector::from([0.42 + (i % 30) as f32 * sp, 0.6 + (i / 30) as f32 * sp]);
                Particle::new(x, Material::Water, 1000.0 * vol, vol)
            })
            .collect();
        s.add_particles(ps).unwrap();
        for _ in 0..60 {
            s.step_frame(1.0 / 60.0).unwrap();
        }
        s.particles().iter().map(|p| p.x).collect::<Vec<_>>()
    };
    let a = run(disc.clone());
    let b = run(sampled);
    let depth =
        |xs: &[SVector<f32, 2>]| xs.iter().map(|x| -disc.sdf(x)).fold(f32::MIN, f32::max) * 64.0;
    let mean_y = |xs: &[SVector<f32, 2>]| xs.iter().map(|x| x[1]).sum::<f32>() / xs.len() as f32;
    assert!(
        depth(&b) < depth(&a).max(0.5) + 0.1,
        "{} vs {}",
        depth(&b),
        depth(&a)
    );
    assert!(
        (mean_y(&a) - mean_y(&b)).abs() < 0.01,
        "{} vs {}",
        mean_y(&a),
        mean_y(&b)
    );
}

/// The particle projection's distance and normal (`Shape::surface_step`) of
/// a sampled plate 2.6 cells thick, rotated by 20°: its box's own inside, where the
/// multilinear interpolant of the distance reads shallower near the plate's
/// mid-plane (the corners' nearest faces differ); a sampled disc's within five
/// hundredths of a cell.
#[test]
fn the_projection_step_of_a_sampled_shape_follows_the_analytic_one() {
    let cell = 1.0 / 32.0;
    let (sin, cos) = (-20.0f32).to_radians().sin_cos();
    let plate = Shape::<2>::Box {
        center: SVector::from([0.5, 0.5]),
        half_extents: SVector::from([0.2, 1.3 * cell]),
        rotation: SMatrix::<f32, 2, 2>::new(cos, -sin, sin, cos),
    };
    let disc = Shape::<2>::Sphere {
        center: SVector::from([0.5, 0.5]),
        radius: 0.15,
    };
    let origin = [0.5 - 10.0 * cell, 0.5 - 10.0 * cell];
    let mut worst_interp = 0.0f32;
    for (shape, tol) in [(plate, 1e-4), (disc, 5e-2)] {
        let sampled = sample_with_normals(&shape, origin, cell, [21, 21]);
        for i in 0..200 {
            for j in 0..200 {
                let p = SVector::from([
                    0.5 - 5.0 * cell + i as f32 * 0.05 * cell,
                    0.5 - 5.0 * cell + j as f32 * 0.05 * cell,
                ]);
                let want = shape.sdf(&p);
                if !(-cell..0.0).contains(&want) {
                    continue;
                }
                let (phi, n) = sampled.surface_step(&p);
                assert!(
                    (phi - want).abs() <= tol * cell,
                    "{shape:?} at {p}: {phi} vs {want}"
                );
                assert!(n.dot(&shape.normal(&p)) > 0.95, "{shape:?} at {p}: n {n}");
                if tol < 1e-3 {
                    worst_interp = worst_interp.max((sampled.sdf(&p) - want).abs() / cell);
                }
            }
        }
    }
    // what the step does better than the interpolated distance
    assert!(
        worst_interp > 0.2,
        "worst interpolated error {worst_interp} cells"
    );
}

/// `f32` neighbours of `x`, `k` units in the last place away (k may be < 0).
fn ulps(x: f32, k: i32) -> f32 {
    if x == 0.0 {
        return f32::from_bits(k.unsigned_abs()) * k.signum() as f32;
    }
    let b = x.to_bits() as i64 + if x > 0.0 { k as i64 } else { -(k as i64) };
    f32::from_bits(b as u32)
}

/// The particle projection's quick test (`Reach::may_act` with a sampled
/// shape's `ShallowCells`) leaves a particle alone only where the
/// projection without it (the full step, `Shape::step_below`, within the
/// shape's bounding ball) does: at random points in and around the grid, on
/// the cells' sides and a few units in the last place from them, with the
/// grid at its origin and moved; for shapes whose border samples are all
/// ≥ 0 and ones cut by the grid's side (whose outside then goes to the full
/// step). And it settles many points (else it would cost, not save).
#[test]
fn the_projections_quick_test_leaves_alone_only_what_the_full_step_does() {
    // a power of two (1/cell exact: the product is the quotient) and not
    for n in [64.0f32, 60.0] {
        let cell = 1.0 / n;
        let (sin, cos) = (-20.0f32).to_radians().sin_cos();
        let sphere = Shape::<3>::Sphere {
            center: SVector::from([0.5, 0.4, 0.5]),
            radius: 0.15,
        };
        let plate = Shape::<3>::Box {
            center: SVector::from([0.5, 0.45, 0.5]),
            half_extents: SVector::from([0.25, 1.3 * cell, 0.2]),
            rotation: SMatrix::<f32, 3, 3>::new(cos, -sin, 0.0, sin, cos, 0.0, 0.0, 0.0, 1.0),
        };
        // the sphere's nodes on the grid's lattice (i·cell) with a margin of
        // samples around it; the plate's off the lattice, its ends beyond
        // the grid's sides
        let lattice = |x: f32| (x / cell).floor() * cell;
        let sphere_origin = [lattice(0.3), lattice(0.2), lattice(0.3)];
        let plate_origin = [0.3013, 0.3507, 0.3491];
        let sphere = sample_with_normals(&sphere, sphere_origin, cell, [27, 27, 27]);
        let plate = sample_with_normals(&plate, plate_origin, cell, [26, 12, 20]);
        quick_test_agrees("sphere", &sphere, cell, 1);
        sphere_threshold_on_cell_sides(&sphere, cell);
        quick_test_agrees("plate", &plate, cell, 2);
        // in 2D: a disc, and a rotated plate cut by the grid
        let disc = Shape::<2>::Sphere {
            center: SVector::from([0.5, 0.5]),
            radius: 0.15,
        };
        let plate2 = Shape::<2>::Box {
            center: SVector::from([0.5, 0.5]),
            half_extents: SVector::from([0.3, 1.3 * cell]),
            rotation: SMatrix::<f32, 2, 2>::new(cos, -sin, sin, cos),
        };
        let origin = [0.5 - 12.0 * cell + 1e-3, 0.5 - 12.0 * cell - 2e-3];
        let disc = sample_with_normals(&disc, origin, cell, [25, 25]);
        quick_test_agrees("disc", &disc, cell, 3);
        let plate2 = sample_with_normals(&plate2, origin, cell, [25, 25]);
        quick_test_agrees("2D plate", &plate2, cell, 4);
        // outside the grid the quick test settles points where the border
        // samples are ≥ 0; where the plate leaves the grid (its +x side), a
        // point half a cell beyond the side, in the plate, goes to the step,
        // which moves it
        let depth = hybridmpm_mpm::collider::PROJECT_DEPTH_CELLS * cell;
        let x = plate_origin[0] + 25.5 * cell;
        for (shape, point, clear) in [
            (
                &sphere,
                SVector::from([sphere_origin[0] - 0.5 * cell, 0.4, 0.5]),
                true,
            ),
            (
                &plate,
                SVector::from([x, 0.45 + (x - 0.5) * sin / cos, 0.5]),
                false,
            ),
        ] {
            let shallow = hybridmpm_mpm::collider::ShallowCells::new(shape, depth).unwrap();
            let col = Collider {
                shape: shape.clone(),
                condition: BoundaryCondition::Separate,
                friction: 0.0,
                project: true,
            };
            let reach = col.reach(depth, Some(&shallow));
            assert_eq!(reach.may_act(&point), !clear);
            assert_eq!(shape.step_below(&point, depth).is_some(), !clear);
        }
    }
}

/// The check of `the_projections_quick_test_leaves_alone_only_what_the_full_step_does`
/// for one sampled shape (with normals) on a grid of spacing `cell`.
fn quick_test_agrees<const D: usize>(name: &str, sampled: &Shape<D>, cell: f32, seed: u64)
where
    hybridmpm_mpm::Dim<D>: hybridmpm_mpm::DimOps<D>,
{
    let Shape::Sampled { dims, .. } = sampled else {
        unreachable!()
    };
    let depth = hybridmpm_mpm::collider::PROJECT_DEPTH_CELLS * cell;
    let shallow = hybridmpm_mpm::collider::ShallowCells::new(sampled, depth).unwrap();
    let mut seed = seed;
    let mut shift = SVector::<f32, D>::zeros();
    shift[0] = 0.0123;
    shift[1] = -0.0071;
    for shift in [SVector::zeros(), shift] {
        let mut col = Collider {
            shape: sampled.clone(),
            condition: BoundaryCondition::Separate,
            friction: 0.0,
            project: true,
        };
        let anchor = col.shape.anchor() + shift;
        col.shape.set_anchor(anchor);
        let reach = col.reach(depth, Some(&shallow));
        // the projection without the quick test: the step where the
        // shape's bounding ball holds the point
        let r = col.shape.bounding_radius() * 1.001 + 1e-6;
        let (centre, r2) = (col.shape.center(), r * r);
        let (mut tried, mut settled) = (0usize, 0usize);
        let mut check = |x: SVector<f32, D>| {
            tried += 1;
            if !reach.may_act(&x) {
                settled += 1;
                assert!(
                    (x - centre).norm_squared() >= r2 || col.shape.step_below(&x, depth).is_none(),
                    "{name}, cell {cell}, grid at {anchor:?}: the quick test leaves alone {x:?}, which the step moves"
                );
            }
        };
        // random points in the grid's box and two cells around it
        for _ in 0..200_000 {
            check(SVector::from_fn(|d, _| {
                anchor[d] + (lcg(&mut seed) * (dims[d] + 3) as f32 - 2.0) * cell
            }));
        }
        // on cells' sides (and the grid's), and a few ulps off them
        for _ in 0..20_000 {
            let mut x = SVector::<f32, D>::from_fn(|d, _| {
                anchor[d] + lcg(&mut seed) * (dims[d] - 1) as f32 * cell
            });
            let d = (lcg(&mut seed) * D as f32) as usize % D;
            let k = (lcg(&mut seed) * dims[d] as f32) as usize;
            x[d] = anchor[d] + k as f32 * cell;
            for off in [-3, -1, 0, 1, 3] {
                let mut y = x;
                y[d] = ulps(x[d], off);
                check(y);
            }
        }
        assert!(
            settled * 4 > tried,
            "{name}, cell {cell}: settled {settled} of {tried} points"
        );
    }
}

/// The quick test at the sampled sphere's projection threshold (about
/// `depth` inside) on cells' sides, where the product and the quotient can
/// name different cells: points on a side, at `R − depth ± 0.05` cells from
/// the centre, and a few ulps off the side.
fn sphere_threshold_on_cell_sides(sampled: &Shape<3>, cell: f32) {
    let (centre, radius) = (SVector::<f32, 3>::from([0.5, 0.4, 0.5]), 0.15f32);
    let depth = hybridmpm_mpm::collider::PROJECT_DEPTH_CELLS * cell;
    let shallow = hybridmpm_mpm::collider::ShallowCells::new(sampled, depth).unwrap();
    let col = Collider {
        shape: sampled.clone(),
        condition: BoundaryCondition::Separate,
        friction: 0.0,
        project: true,
    };
    let reach = col.reach(depth, Some(&shallow));
    let anchor = col.shape.anchor();
    let mut seed = 11u64;
    let (mut tried, mut near) = (0usize, 0usize);
    for _ in 0..50_000 {
        // a side of the cells along axis d through a point of the sphere
        let d = (lcg(&mut seed) * 3.0) as usize % 3;
        let (e, f) = ((d + 1) % 3, (d + 2) % 3);
        let r = radius - depth + (lcg(&mut seed) - 0.5) * 0.1 * cell;
        let k = ((centre[d] - anchor[d] + (lcg(&mut seed) - 0.5) * 1.6 * r) / cell).round();
        let mut x = centre;
        x[d] = anchor[d] + k * cell;
        // on the circle of radius r in the plane of the side
        let rho2 = r * r - (x[d] - centre[d]).powi(2);
        if rho2 <= 0.0 {
            continue;
        }
        let a = lcg(&mut seed) * std::f32::consts::TAU;
        x[e] = centre[e] + rho2.sqrt() * a.cos();
        x[f] = centre[f] + rho2.sqrt() * a.sin();
        for off in -4..=4 {
            let mut y = x;
            y[d] = ulps(x[d], off);
            tried += 1;
            let moves = col.shape.step_below(&y, depth).is_some();
            near += moves as usize;
            assert!(
                reach.may_act(&y) || !moves,
                "cell {cell}: the quick test leaves alone {y:?}, which the step moves"
            );
        }
    }
    // the points straddle the threshold
    assert!(
        near * 10 > tried && near * 10 < 9 * tried,
        "{near} of {tried} moved"
    );
}
