//! criterion benches: one 2.5 ms frame of the standard benchmark scenes
//! (particles on a lattice at spacing dx/2, released as a dam break).
//!
//! Run: `cargo bench -p hybridmpm-bench --bench substep`

use criterion::{Criterion, criterion_group, criterion_main};
use hybridmpm_mpm::{Dim, DimOps, Material, Solver, SolverParams, lattice};

fn scene<const D: usize>(
    n_grid: usize,
    origin: [f32; D],
    side: usize,
    mat: Material,
    substeps: usize,
    threads: usize,
) -> Solver<D>
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
    // warm up into a moving state
    for _ in 0..5 {
        s.step_frame(2.5e-3).unwrap();
    }
    s
}

fn bench(c: &mut Criterion) {
    let mut g = c.benchmark_group("frame");
    g.sample_size(20);
    for threads in [1usize, 2] {
        let mut s = scene::<2>(128, [0.1, 0.1], 64, Material::Water, 16, threads);
        g.bench_function(format!("water2d_4k_128_t{threads}"), |b| {
            b.iter(|| s.step_frame(2.5e-3).unwrap())
        });
        let mut s = scene::<2>(128, [0.1, 0.1], 64, Material::Sand, 16, threads);
        g.bench_function(format!("sand2d_4k_128_t{threads}"), |b| {
            b.iter(|| s.step_frame(2.5e-3).unwrap())
        });
        let mut s = scene::<3>(64, [0.3, 0.1, 0.3], 16, Material::Water, 8, threads);
        g.bench_function(format!("water3d_4k_64_t{threads}"), |b| {
            b.iter(|| s.step_frame(2.5e-3).unwrap())
        });
        let mut s = scene::<3>(128, [0.3, 0.1, 0.3], 16, Material::Water, 16, threads);
        g.bench_function(format!("water3d_4k_128_t{threads}"), |b| {
            b.iter(|| s.step_frame(2.5e-3).unwrap())
        });
        let mut s = scene::<3>(64, [0.25, 0.1, 0.25], 32, Material::Water, 8, threads);
        g.bench_function(format!("water3d_32k_64_t{threads}"), |b| {
            b.iter(|| s.step_frame(2.5e-3).unwrap())
        });
    }
    g.finish();
}

criterion_group!(benches, bench);
criterion_main!(benches);
