//! Frame time of the dam break under each integrator, on the same
//! particles and the same threads:
//! `CARGO_TARGET_DIR=target/checks cargo run --profile checks -p hybridmpm-mpm --example large_step -- 3d 2 150`
//! (dimension `2d` or `3d`, threads, frames timed after 15). The column is
//! `dam_break2d`'s (128², base 24 cells) or `dam_break3d`'s (34³, base 7
//! cells, wall to wall in z), at 2 particles per cell per axis.
//! docs/large-step.md quotes it.
use hybridmpm_mpm::particles::lattice_box;
use hybridmpm_mpm::{Dim, DimOps, Integrator, Material, Particle, Solver, SolverParams};
use std::time::Instant;

fn column<const D: usize>(n: usize, a_cells: usize) -> Vec<Particle<D>> {
    let dx = 1.0 / n as f32;
    let face = 2.0 * dx; // the default walls (3 cells): fluid rests on (cells − 1)·dx
    let sp = dx / 2.0;
    let counts: [usize; D] = std::array::from_fn(|d| match d {
        0 => 2 * a_cells,
        1 => 4 * a_cells,
        _ => ((1.0 - 2.0 * face) / sp).round() as usize,
    });
    lattice_box([face; D], counts, sp, Material::Water, 1000.0)
}

fn time<const D: usize>(n: usize, a_cells: usize, threads: usize, frames: usize)
where
    Dim<D>: DimOps<D>,
{
    let ps = column::<D>(n, a_cells);
    let mut ms = Vec::new();
    for integrator in Integrator::ALL {
        let params = SolverParams::<D> {
            n_grid: n,
            num_threads: threads,
            integrator,
            ..Default::default()
        };
        let mut solver = Solver::new(params, vec![]).unwrap();
        solver.set_particles(ps.clone()).unwrap();
        let (mut wall, mut steps) = (0.0, 0);
        for f in 0..15 + frames {
            let t = Instant::now();
            let stats = solver.step_frame(2.5e-3).unwrap();
            if f >= 15 {
                wall += t.elapsed().as_secs_f64() * 1e3;
                steps += stats.substeps;
            }
        }
        let nf = frames as f64;
        println!(
            "{D}D {n} grid, {} particles, {threads} threads: {} {:.2} ms/frame ({:.2} steps a frame)",
            ps.len(),
            integrator.name(),
            wall / nf,
            steps as f64 / nf,
        );
        ms.push(wall);
    }
    println!("projection / explicit: {:.2}", ms[1] / ms[0]);
}

fn main() {
    let a: Vec<String> = std::env::args().collect();
    let dim = a.get(1).map(String::as_str).unwrap_or("3d");
    let threads: usize = a.get(2).and_then(|s| s.parse().ok()).unwrap_or(2);
    let frames: usize = a.get(3).and_then(|s| s.parse().ok()).unwrap_or(150);
    match dim {
        "2d" => time::<2>(128, 24, threads, frames),
        _ => time::<3>(34, 7, threads, frames),
    }
}
