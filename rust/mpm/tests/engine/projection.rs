//! The particle projection of colliders (`Collider::project`): a particle
//! that a substep's g2p leaves more than `PROJECT_DEPTH_CELLS` inside a
//! collider ends on its surface with no
//! velocity into it (relative to the collider's), a particle far from every
//! collider is untouched bit for bit, and a collider with `project: false`
//! leaves the particle where the grid condition put it (inside). A solid's
//! particle keeps its place down to `SOLID_PROJECT_DEPTH_CELLS`, losing only
//! its inward velocity.

use hybridmpm_mpm::collider::{PROJECT_DEPTH_CELLS, SOLID_PROJECT_DEPTH_CELLS};
use hybridmpm_mpm::{BoundaryCondition, Collider, Material, Particle, Shape, Solver, SolverParams};
use nalgebra::{SMatrix, SVector};

type V2 = SVector<f32, 2>;

/// One substep per frame of this length [s].
const DT: f32 = 1e-3;

fn params() -> SolverParams<2> {
    SolverParams::<2> {
        n_grid: 64,
        substeps: Some(1),
        num_threads: 1,
        ..Default::default()
    }
}

fn rotated_box() -> Shape<2> {
    let (s, c) = 0.35f32.sin_cos();
    Shape::Box {
        center: V2::new(0.5, 0.4),
        half_extents: V2::new(0.15, 0.05),
        rotation: SMatrix::<f32, 2, 2>::new(c, -s, s, c),
    }
}

fn sphere() -> Shape<2> {
    Shape::Sphere {
        center: V2::new(0.5, 0.4),
        radius: 0.1,
    }
}

fn water(x: V2, v: V2, p: &SolverParams<2>) -> Particle<2> {
    of(Material::Water, x, v, p)
}

fn of(material: Material, x: V2, v: V2, p: &SolverParams<2>) -> Particle<2> {
    let vol = (0.5 * p.dx()).powi(2);
    let mut q = Particle::new(x, material, p.water.density * vol, vol);
    q.v = v;
    q
}

/// The point `depth` [m] inside `shape` below the surface point above its
/// centre, found by walking down from above.
fn inside(shape: &Shape<2>, depth: f32) -> V2 {
    let c = shape.center();
    let mut y = c[1] + 0.3;
    while shape.sdf(&V2::new(c[0] + 0.02, y)) > -depth {
        y -= 1e-5;
    }
    V2::new(c[0] + 0.02, y)
}

/// Steps one substep with a water particle `0.6` cells inside `shape`
/// moving into it and one far away; returns both.
fn step_one(
    shape: &Shape<2>,
    condition: BoundaryCondition,
    project: bool,
    moving: Option<V2>,
) -> (Particle<2>, Particle<2>, Collider<2>) {
    step_one_of(Material::Water, 0.6, shape, condition, project, moving)
}

/// [`step_one`] with a particle of `material` `cells` cells inside.
fn step_one_of(
    material: Material,
    cells: f32,
    shape: &Shape<2>,
    condition: BoundaryCondition,
    project: bool,
    moving: Option<V2>,
) -> (Particle<2>, Particle<2>, Collider<2>) {
    let p = params();
    let col = Collider {
        shape: shape.clone(),
        condition,
        friction: 0.3,
        project,
    };
    let mut s = Solver::new(p.clone(), vec![col]).unwrap();
    let x = inside(shape, cells * p.dx());
    let near = of(material, x, V2::new(0.4, -1.2), &p);
    let far = water(V2::new(0.15, 0.85), V2::new(0.3, -0.7), &p);
    s.set_particles(vec![near, far]).unwrap();
    if let Some(u) = moving {
        let end = s.collider_anchor(0).unwrap() + u * DT;
        s.move_collider(0, end, Some(u)).unwrap();
    }
    s.step_frame(DT).unwrap();
    let ps = s.particles();
    (ps[0], ps[1], s.colliders()[0].clone())
}

fn bits(p: &Particle<2>) -> Vec<u32> {
    p.x.iter()
        .chain(p.v.iter())
        .chain(p.c.iter())
        .chain(p.f.iter())
        .chain([p.j, p.vc].iter())
        .map(|x| x.to_bits())
        .collect()
}

#[test]
fn a_particle_inside_ends_on_the_surface_without_inward_velocity() {
    let dx = params().dx();
    for shape in [rotated_box(), sphere()] {
        for condition in [
            BoundaryCondition::Sticky,
            BoundaryCondition::Slip,
            BoundaryCondition::Separate,
        ] {
            let what = format!("{shape:?} {condition:?}");
            let (near, far, col) = step_one(&shape, condition, true, None);
            let phi = col.shape.sdf(&near.x);
            assert!(phi.abs() <= 1e-3 * dx, "{what}: {phi} m from the surface");
            let n = col.shape.normal(&near.x);
            match condition {
                BoundaryCondition::Sticky => assert_eq!(near.v, V2::zeros(), "{what}"),
                _ => assert!(near.v.dot(&n) >= -1e-6, "{what}: v {}", near.v),
            }
            // without the projection the same particle stays inside
            let (near_off, far_off, _) = step_one(&shape, condition, false, None);
            assert!(
                col.shape.sdf(&near_off.x) < -0.3 * dx,
                "{what}: {} cells inside without the projection",
                -col.shape.sdf(&near_off.x) / dx
            );
            // the particle far from the collider: the same bits either way
            assert_eq!(bits(&far), bits(&far_off), "{what}");
        }
    }
}

#[test]
fn a_moving_collider_projects_relative_to_its_pose_and_velocity() {
    let dx = params().dx();
    let u = V2::new(0.8, -0.5);
    for shape in [rotated_box(), sphere()] {
        for condition in [BoundaryCondition::Sticky, BoundaryCondition::Separate] {
            let what = format!("{shape:?} {condition:?}");
            let (near, _, col) = step_one(&shape, condition, true, Some(u));
            // the collider where the substep ended: moved by u·dt
            assert_eq!(col.shape.anchor(), shape.anchor() + u * DT, "{what}");
            let phi = col.shape.sdf(&near.x);
            assert!(phi.abs() <= 1e-3 * dx, "{what}: {phi} m from the surface");
            let n = col.shape.normal(&near.x);
            match condition {
                BoundaryCondition::Sticky => assert_eq!(near.v, u, "{what}"),
                _ => assert!((near.v - u).dot(&n) >= -1e-6, "{what}: v {}", near.v),
            }
        }
    }
}

/// Water thrown on a sphere: no particle ever more than
/// `PROJECT_DEPTH_CELLS` inside at a frame's end with the projection,
/// deeper without it; the same bits for 1 and 3 threads.
#[test]
fn water_on_a_sphere_stays_out_of_it() {
    let deepest = |project: bool, threads: usize| {
        let p = SolverParams::<2> {
            n_grid: 64,
            num_threads: threads,
            ..Default::default()
        };
        let dx = p.dx();
        let col = Collider {
            shape: sphere(),
            condition: BoundaryCondition::Separate,
            friction: 0.0,
            project,
        };
        let mut s = Solver::new(p.clone(), vec![col.clone()]).unwrap();
        let sp = 0.5 * dx;
        let ps: Vec<Particle<2>> = (0..24 * 24)
            .map(|i| {
                let x = V2::new(0.44 + (i % 24) as f32 * sp, 0.55 + (i / 24) as f32 * sp);
                water(x, V2::new(0.0, -2.0), &p)
            })
            .collect();
        s.set_particles(ps).unwrap();
        let mut worst = 0.0f32;
        for _ in 0..60 {
            s.step_frame(2.5e-3).unwrap();
            for q in s.particles() {
                worst = worst.max(-col.shape.sdf(&q.x) / dx);
            }
        }
        (worst, s.checkpoint())
    };
    let (on, bits_on) = deepest(true, 1);
    let (off, _) = deepest(false, 1);
    assert!(
        on <= PROJECT_DEPTH_CELLS + 1e-3,
        "{on} cells inside with the projection"
    );
    assert!(off > 0.4, "{off} cells inside without it");
    assert_eq!(bits_on, deepest(true, 3).1);
}

/// An elastic particle 0.4 cells inside keeps its place (its `F` would not
/// see the jump) and loses its inward velocity; one 0.8 cells inside, past
/// `SOLID_PROJECT_DEPTH_CELLS`, goes onto the surface as water's does.
#[test]
fn a_solid_particle_is_put_back_only_from_half_a_cell() {
    let dx = params().dx();
    for shape in [rotated_box(), sphere()] {
        for material in [Material::Elastic, Material::Snow, Material::Viscoplastic] {
            let what = format!("{shape:?} {material:?}");
            let (kept, _, col) = step_one_of(
                material,
                0.4,
                &shape,
                BoundaryCondition::Separate,
                true,
                None,
            );
            let phi = col.shape.sdf(&kept.x);
            assert!(
                phi < -PROJECT_DEPTH_CELLS * dx,
                "{what}: {} cells inside",
                -phi / dx
            );
            assert!(
                phi >= -SOLID_PROJECT_DEPTH_CELLS * dx,
                "{what}: {} cells inside",
                -phi / dx
            );
            assert!(
                kept.v.dot(&col.shape.normal(&kept.x)) >= -1e-6,
                "{what}: v {}",
                kept.v
            );
            let (back, _, _) = step_one_of(
                material,
                0.8,
                &shape,
                BoundaryCondition::Separate,
                true,
                None,
            );
            let phi = col.shape.sdf(&back.x);
            assert!(phi.abs() <= 1e-3 * dx, "{what}: {phi} m from the surface");
            // water as deep as the kept solid goes onto the surface
            let (w, _, _) = step_one_of(
                Material::Water,
                0.4,
                &shape,
                BoundaryCondition::Separate,
                true,
                None,
            );
            assert!(col.shape.sdf(&w.x).abs() <= 1e-3 * dx, "{what}: water");
        }
    }
}
