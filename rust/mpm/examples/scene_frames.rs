//! Time frames of a scene dumped from Python (its parameter dict as JSON and
//! a `checkpoint()` blob of its initial state):
//! `cargo run --release -p hybridmpm-mpm --features serde --example scene_frames -- PARAMS.json STATE.ckpt THREADS [WARMUP] [FRAMES] [REPEATS]`
//!
//! Each repeat restores the state, steps `WARMUP` frames untimed, then times
//! `FRAMES` frames; prints the median ms per frame of each repeat, the
//! substeps per frame and the ns per particle-substep of the best repeat,
//! and a bitwise hash of the final state (the same for any thread count).
//! With `HYBRIDMPM_PROFILE=1` the solver prints per-stage substep times.
use hybridmpm_mpm::{ColliderParams, Dim, DimOps, Solver, SolverParams};
use std::time::Instant;

fn run<const D: usize>(
    params: serde_json::Value,
    colliders: &[ColliderParams],
    blob: &[u8],
    threads: usize,
    warmup: usize,
    frames: usize,
    repeats: usize,
) where
    Dim<D>: DimOps<D>,
    SolverParams<D>: serde::de::DeserializeOwned,
{
    let mut p: SolverParams<D> = serde_json::from_value(params).expect("solver parameters");
    p.num_threads = threads;
    let colliders = colliders
        .iter()
        .enumerate()
        .map(|(i, c)| c.build::<D>(&format!("colliders[{i}]")).unwrap())
        .collect();
    let mut s = Solver::new(p, colliders).unwrap();
    let dt_frame = 2.5e-3;
    let mut best = f64::INFINITY;
    let mut medians = Vec::new();
    let (mut subs, mut hash) = (0usize, 0u64);
    for _ in 0..repeats {
        s.restore(blob).unwrap();
        for _ in 0..warmup {
            s.step_frame(dt_frame).unwrap();
        }
        let mut times = Vec::new();
        subs = 0;
        if std::env::var_os("TIME_SUBSTEPS_FOR").is_some() {
            let t = Instant::now();
            for _ in 0..frames {
                std::hint::black_box(s.substeps_for(dt_frame).unwrap());
            }
            println!(
                "substeps_for: {:.1} us",
                t.elapsed().as_secs_f64() * 1e6 / frames as f64
            );
        }
        for _ in 0..frames {
            let t = Instant::now();
            let st = s.step_frame(dt_frame).unwrap();
            times.push(t.elapsed().as_secs_f64());
            subs += st.substeps;
        }
        let total: f64 = times.iter().sum();
        times.sort_by(f64::total_cmp);
        medians.push(times[times.len() / 2] * 1e3);
        best = best.min(total);
        // FNV-1a of the state's bytes
        hash = s.checkpoint().iter().fold(0xcbf29ce484222325u64, |h, &b| {
            (h ^ b as u64).wrapping_mul(0x100000001b3)
        });
    }
    let n = s.num_particles();
    println!(
        "{}D n_grid {} particles {n} threads {threads}: median ms/frame per repeat {:.3?}; best mean {:.3} ms/frame, {:.2} substeps/frame, {:.1} ns/particle-substep; mode runs (alone, team) {:?}; state hash {hash:016x}",
        D,
        s.params().n_grid,
        medians,
        best * 1e3 / frames as f64,
        subs as f64 / frames as f64,
        best * 1e9 / (subs * n) as f64,
        s.mode_runs(),
    );
}

fn main() {
    let a: Vec<String> = std::env::args().collect();
    let mut params: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&a[1]).unwrap()).unwrap();
    let blob = std::fs::read(&a[2]).unwrap();
    let threads: usize = a.get(3).and_then(|s| s.parse().ok()).unwrap_or(2);
    let warmup: usize = a.get(4).and_then(|s| s.parse().ok()).unwrap_or(20);
    let frames: usize = a.get(5).and_then(|s| s.parse().ok()).unwrap_or(100);
    let repeats: usize = a.get(6).and_then(|s| s.parse().ok()).unwrap_or(3);
    let obj = params.as_object_mut().unwrap();
    let dim = obj.remove("dim").and_then(|d| d.as_u64()).unwrap_or(2);
    let colliders: Vec<ColliderParams> = obj
        .remove("colliders")
        .map(|c| serde_json::from_value(c).expect("colliders"))
        .unwrap_or_default();
    match dim {
        2 => run::<2>(params, &colliders, &blob, threads, warmup, frames, repeats),
        3 => run::<3>(params, &colliders, &blob, threads, warmup, frames, repeats),
        _ => panic!("dim {dim}"),
    }
}
