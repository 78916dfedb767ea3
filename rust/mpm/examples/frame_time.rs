//! Wall time per 2.5 ms frame of the standard benchmark scenes (median of
//! `frames` frames after 5 warm-up frames), for profiling without Python.
//!
//! Run: `cargo run --release -p hybridmpm-mpm --example frame_time -- SCENE THREADS [FRAMES]`
//! with SCENE one of water2d, sand2d, water3d, water3d_32k, sand3d. Set
//! `HMPM_PROFILE=1` for per-stage substep timings on stderr.

use hybridmpm_mpm::{Dim, DimOps, Material, Solver, SolverParams, lattice};

fn run<const D: usize>(
    n_grid: usize,
    origin: [f32; D],
    side: usize,
    mat: Material,
    substeps: usize,
    threads: usize,
    frames: usize,
) -> f64
where
    Dim<D>: DimOps<D>,
{
    let p = SolverParams::<D> {
        n_grid,
        substeps: Some(substeps),
        num_threads: threads,
        ..Default::default()
    };
    let dx = p.dx();
    let rho = p.water.density;
    let mut s = Solver::new(p, vec![]).unwrap();
    s.set_particles(lattice(origin, side, dx / 2.0, mat, rho))
        .unwrap();
    for _ in 0..5 {
        s.step_frame(2.5e-3).unwrap();
    }
    let mut t: Vec<f64> = (0..frames)
        .map(|_| {
            let t0 = std::time::Instant::now();
            s.step_frame(2.5e-3).unwrap();
            t0.elapsed().as_secs_f64() * 1e3
        })
        .collect();
    t.sort_by(|a, b| a.partial_cmp(b).unwrap());
    t[frames / 2]
}

fn main() {
    let a: Vec<String> = std::env::args().collect();
    let scene = a.get(1).map(String::as_str).unwrap_or("water2d");
    let threads: usize = a.get(2).and_then(|s| s.parse().ok()).unwrap_or(2);
    let frames: usize = a.get(3).and_then(|s| s.parse().ok()).unwrap_or(40);
    let ms = match scene {
        "water2d" => run::<2>(128, [0.1, 0.1], 64, Material::Water, 16, threads, frames),
        "sand2d" => run::<2>(128, [0.1, 0.1], 64, Material::Sand, 16, threads, frames),
        "water3d" => run::<3>(64, [0.3, 0.1, 0.3], 16, Material::Water, 8, threads, frames),
        "water3d_32k" => run::<3>(
            64,
            [0.25, 0.1, 0.25],
            32,
            Material::Water,
            8,
            threads,
            frames,
        ),
        "sand3d" => run::<3>(64, [0.3, 0.1, 0.3], 16, Material::Sand, 8, threads, frames),
        other => panic!("unknown scene {other}"),
    };
    println!("{scene} threads={threads}: {ms:.3} ms/frame (median of {frames})");
}
