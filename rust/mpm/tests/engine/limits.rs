//! What the solver refuses, before allocating or changing anything: grids and
//! particle counts beyond the memory budget, frames needing more substeps
//! than `max_substeps`, colliders too thin for the grid.

use hybridmpm_mpm::collider::{MIN_BOX_THICKNESS_CELLS, MIN_SPHERE_RADIUS_CELLS};
use hybridmpm_mpm::{
    BoundaryCondition, Collider, Material, MpmError, Particle, Shape, Solver, SolverParams,
};
use nalgebra::{SMatrix, SVector};

fn water<const D: usize>(n: usize, p: &SolverParams<D>) -> Vec<Particle<D>> {
    let vol = (0.5 * p.dx()).powi(D as i32);
    (0..n)
        .map(|i| {
            let x = SVector::<f32, D>::from_element(0.45 + 0.1 * i as f32 / n as f32);
            Particle::new(x, Material::Water, p.water.density * vol, vol)
        })
        .collect()
}

#[test]
fn a_grid_beyond_the_budget_is_refused_naming_n_grid_and_the_bytes() {
    let p = SolverParams::<3> {
        n_grid: 4096,
        ..Default::default()
    };
    assert_eq!(Solver::<3>::grid_bytes(4096), Some(8_640_364_608));
    let e = Solver::with_memory_budget(p.clone(), vec![], Some(1 << 30))
        .err()
        .unwrap();
    assert_eq!(e.field(), Some("n_grid"));
    let msg = e.to_string();
    assert!(
        msg.starts_with("n_grid: ") && msg.contains("8640364608 bytes") && msg.contains("8.0 GiB"),
        "{msg}"
    );
    // the default grids fit a small budget
    let small = SolverParams::<3>::default();
    let need = Solver::<3>::grid_bytes(small.n_grid).unwrap() as u64;
    assert!(Solver::with_memory_budget(small.clone(), vec![], Some(need)).is_ok());
    assert!(Solver::with_memory_budget(small, vec![], Some(need - 1)).is_err());
}

#[test]
fn particles_beyond_the_budget_are_refused_and_change_nothing() {
    let p = SolverParams::<2>::default();
    let per = Solver::<2>::bytes_per_particle();
    assert!((400..800).contains(&per), "{per}");
    assert!((600..1400).contains(&Solver::<3>::bytes_per_particle()));
    let grid = Solver::<2>::grid_bytes(p.n_grid).unwrap() as u64;
    let budget = grid.max(100 * per as u64);
    let mut s = Solver::with_memory_budget(p.clone(), vec![], Some(budget)).unwrap();
    let room = budget as usize / per;
    s.add_particles(water(room, &p)).unwrap();
    let before = s.checkpoint();
    let e = s.add_particles(water(1, &p)).unwrap_err();
    assert_eq!(e.field(), Some("positions"));
    assert!(e.to_string().contains(&format!("{} particles", room + 1)));
    assert_eq!(s.checkpoint(), before);
    assert!(s.set_particles(water(room + 1, &p)).is_err());
    assert_eq!(s.checkpoint(), before);
}

#[test]
fn a_frame_needing_more_than_max_substeps_names_the_speed() {
    let p = SolverParams::<2>::default();
    let mut s = Solver::new(p.clone(), vec![]).unwrap();
    let mut ps = water(4, &p);
    for q in ps.iter_mut() {
        q.v = SVector::<f32, 2>::new(1e30, 1e30);
    }
    s.set_particles(ps).unwrap();
    let before = s.checkpoint();
    for e in [
        s.substeps_for(2.5e-3).unwrap_err(),
        s.step_frame(2.5e-3).unwrap_err(),
    ] {
        let MpmError::TooManySubsteps {
            needed, max_speed, ..
        } = e
        else {
            panic!("{e:?}")
        };
        assert!((max_speed - 1.414e30).abs() < 1e27 && needed > 1e29, "{e}");
        assert!(e.to_string().contains("1.414e30 m/s"), "{e}");
    }
    assert_eq!(s.checkpoint(), before);
    // dt_frame out of (0, 1] is an input error, never a saturated count
    assert_eq!(s.substeps_for(1e30).unwrap_err().field(), Some("dt_frame"));
    // max_substeps has an upper bound
    let mut big = p.clone();
    big.max_substeps = usize::MAX;
    assert_eq!(big.validate().unwrap_err().field(), Some("max_substeps"));
}

#[test]
fn colliders_too_thin_for_the_grid_are_refused() {
    let p = SolverParams::<2>::default();
    let dx = p.dx();
    let collider = |shape| Collider::<2> {
        shape,
        condition: BoundaryCondition::Separate,
        friction: 0.0,
        project: true,
    };
    let plate = |half: f32| {
        collider(Shape::Box {
            center: SVector::<f32, 2>::new(0.5, 0.4),
            half_extents: SVector::<f32, 2>::new(0.3, half),
            rotation: SMatrix::<f32, 2, 2>::identity(),
        })
    };
    let ball = |r: f32| {
        collider(Shape::Sphere {
            center: SVector::<f32, 2>::new(0.5, 0.4),
            radius: r,
        })
    };
    let half_min = 0.5 * MIN_BOX_THICKNESS_CELLS * dx;
    assert!(Solver::new(p.clone(), vec![plate(half_min)]).is_ok());
    let e = Solver::new(p.clone(), vec![plate(half_min * 0.99)])
        .err()
        .unwrap();
    assert_eq!(e.field(), Some("colliders[0].half_extents"), "{e}");
    assert!(Solver::new(p.clone(), vec![ball(MIN_SPHERE_RADIUS_CELLS * dx)]).is_ok());
    let e = Solver::new(p.clone(), vec![plate(0.1), ball(dx)])
        .err()
        .unwrap();
    assert_eq!(e.field(), Some("colliders[1].radius"), "{e}");
}
