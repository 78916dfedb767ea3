//! Time frames of one benchmark scene (for profiling with perf):
//! `cargo run --release -p hybridmpm-mpm --example profile_frame -- water2d 1 200`
//! (`HYBRIDMPM_GAP_US=N` sleeps N µs between frames, `HYBRIDMPM_BUSY_US=N` busy-waits: a
//! caller doing other work between frames)
use hybridmpm_mpm::{Dim, DimOps, Material, Solver, SolverParams, lattice};
use std::time::Instant;

/// A benchmark scene (the standard scenes of `benchmarks/bench_mpm.py`): a
/// lattice block of `side^D` particles at spacing dx/2 from `origin`.
#[derive(Clone, Copy)]
struct Spec<const D: usize> {
    n_grid: usize,
    origin: [f32; D],
    side: usize,
    /// (left half, right half) of the block along x
    mats: (Material, Material),
    substeps: usize,
}

const W: Material = Material::Water;
const S: Material = Material::Sand;
const E: Material = Material::Elastic;
const N: Material = Material::Snow;
const V: Material = Material::Viscoplastic;

#[rustfmt::skip]
const SCENES_2D: [(&str, Spec<2>); 6] = [
    ("water2d", Spec { n_grid: 128, origin: [0.1, 0.1], side: 64, mats: (W, W), substeps: 16 }),
    ("sand2d", Spec { n_grid: 128, origin: [0.1, 0.1], side: 64, mats: (S, S), substeps: 16 }),
    ("water_sand2d", Spec { n_grid: 128, origin: [0.1, 0.1], side: 64, mats: (W, S), substeps: 16 }),
    ("elastic2d", Spec { n_grid: 128, origin: [0.1, 0.1], side: 64, mats: (E, E), substeps: 16 }),
    ("snow2d", Spec { n_grid: 128, origin: [0.1, 0.1], side: 64, mats: (N, N), substeps: 16 }),
    ("viscoplastic2d", Spec { n_grid: 128, origin: [0.1, 0.1], side: 64, mats: (V, V), substeps: 16 }),
];

#[rustfmt::skip]
const SCENES_3D: [(&str, Spec<3>); 7] = [
    ("water3d", Spec { n_grid: 64, origin: [0.3, 0.1, 0.3], side: 16, mats: (W, W), substeps: 8 }),
    ("water3d_128", Spec { n_grid: 128, origin: [0.3, 0.1, 0.3], side: 16, mats: (W, W), substeps: 16 }),
    ("water3d_32k", Spec { n_grid: 64, origin: [0.25, 0.1, 0.25], side: 32, mats: (W, W), substeps: 8 }),
    ("sand3d", Spec { n_grid: 64, origin: [0.3, 0.1, 0.3], side: 16, mats: (S, S), substeps: 8 }),
    ("elastic3d", Spec { n_grid: 64, origin: [0.3, 0.1, 0.3], side: 16, mats: (E, E), substeps: 8 }),
    ("snow3d", Spec { n_grid: 64, origin: [0.3, 0.1, 0.3], side: 16, mats: (N, N), substeps: 8 }),
    ("viscoplastic3d", Spec { n_grid: 64, origin: [0.3, 0.1, 0.3], side: 16, mats: (V, V), substeps: 8 }),
];

fn run<const D: usize>(spec: &Spec<D>, threads: usize, frames: usize)
where
    Dim<D>: DimOps<D>,
{
    let Spec {
        n_grid,
        origin,
        side,
        mats,
        substeps,
    } = *spec;
    let p = SolverParams::<D> {
        n_grid,
        substeps: Some(substeps),
        num_threads: threads,
        ..Default::default()
    };
    let dx = p.dx();
    let mut s = Solver::new(p, vec![]).unwrap();
    let mut ps = lattice(origin, side, dx / 2.0, mats.0, 1000.0);
    // split at the block's middle (water_sand2d in benchmarks/bench_mpm.py)
    let mid = origin[0] + side as f32 * dx / 4.0;
    for q in ps.iter_mut().filter(|q| q.x[0] >= mid) {
        q.material = mats.1;
        q.set = mats.1 as u16;
    }
    s.set_particles(ps).unwrap();
    for _ in 0..5 {
        s.step_frame(2.5e-3).unwrap();
    }
    let mut times = Vec::new();
    // optional idle time between frames (HYBRIDMPM_GAP_US microseconds asleep, or
    // HYBRIDMPM_BUSY_US busy on this thread): a caller doing other work between frames
    let gap_us: u64 = std::env::var("HYBRIDMPM_GAP_US")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(0);
    let busy_us: u64 = std::env::var("HYBRIDMPM_BUSY_US")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(0);
    for _ in 0..frames {
        if gap_us > 0 {
            std::thread::sleep(std::time::Duration::from_micros(gap_us));
        }
        if busy_us > 0 {
            let t = Instant::now();
            while t.elapsed().as_micros() < busy_us as u128 {
                std::hint::spin_loop();
            }
        }
        let t = Instant::now();
        s.step_frame(2.5e-3).unwrap();
        times.push(t.elapsed().as_secs_f64() * 1e3);
    }
    times.sort_by(|a, b| a.partial_cmp(b).unwrap());
    println!(
        "median {:.3} ms/frame, {:.1} us/substep",
        times[times.len() / 2],
        times[times.len() / 2] * 1e3 / substeps as f64
    );
}

fn main() {
    let a: Vec<String> = std::env::args().collect();
    let scene = a.get(1).map(String::as_str).unwrap_or("water2d");
    let threads: usize = a.get(2).and_then(|s| s.parse().ok()).unwrap_or(1);
    let frames: usize = a.get(3).and_then(|s| s.parse().ok()).unwrap_or(100);
    if let Some((_, spec)) = SCENES_2D.iter().find(|(n, _)| *n == scene) {
        run(spec, threads, frames);
    } else if let Some((_, spec)) = SCENES_3D.iter().find(|(n, _)| *n == scene) {
        run(spec, threads, frames);
    } else {
        eprintln!("unknown scene");
    }
}
