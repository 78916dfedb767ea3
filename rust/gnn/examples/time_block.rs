//! Times `edge_block` and `edge_encoder` on a synthetic graph: `cargo run --release -p hybridmpm-gnn --example time_block [EDGES]`.
use hybridmpm_gnn::{L, Mlp, Serial, edge_block, edge_encoder, uses_fma};
use std::time::Instant;

fn main() {
    let ne: usize = std::env::args()
        .nth(1)
        .and_then(|a| a.parse().ok())
        .unwrap_or(10_000);
    let n = ne / 12 + 1;
    let v = |k: usize, s: usize| -> Vec<f32> {
        (0..k)
            .map(|i| (((i * 7919 + s * 104729) % 1000) as f32 / 1000.0 - 0.5) * 0.3)
            .collect()
    };
    let (w1, b1, w2, b2, w3, b3) = (
        v(L * L, 1),
        vec![0.0; L],
        v(L * L, 2),
        v(L, 3),
        v(L * L, 4),
        v(L, 5),
    );
    let kvar = vec![1.0 / L as f32; L];
    let m = Mlp {
        w1: &w1,
        b1: &b1,
        w2: &w2,
        b2: &b2,
        w3: &w3,
        b3: &b3,
        kvar: &kvar,
        eps: 1e-5,
    };
    let e = v(ne * L, 6);
    let (hr, hs) = (v(n * L, 7), v(n * L, 8));
    let recv: Vec<i64> = (0..ne).map(|k| (k / 12) as i64).collect();
    let send: Vec<i64> = (0..ne).map(|k| ((k * 31) % n) as i64).collect();
    let (mut out, mut agg) = (vec![0.0; ne * L], vec![0.0; n * L]);
    for _ in 0..3 {
        edge_block(&m, &e, &hr, &hs, &recv, &send, &mut out, &mut agg, &Serial).unwrap();
    }
    let reps = 50;
    let t = Instant::now();
    for _ in 0..reps {
        edge_block(&m, &e, &hr, &hs, &recv, &send, &mut out, &mut agg, &Serial).unwrap();
    }
    let dt = t.elapsed().as_secs_f64() / reps as f64;
    println!(
        "edge_block: {ne} edges, {:.1} us, {:.2} ns/edge (fma {})",
        dt * 1e6,
        dt * 1e9 / ne as f64,
        uses_fma()
    );
    let w1e = v(3 * L, 9);
    let me = Mlp {
        w1: &w1e,
        b1: &b2,
        ..m
    };
    let disp = v(ne * 2, 10);
    let dist = v(ne, 11);
    let t = Instant::now();
    for _ in 0..reps {
        edge_encoder(&me, 2, &disp, &dist, &mut out, &Serial).unwrap();
    }
    let dt = t.elapsed().as_secs_f64() / reps as f64;
    println!(
        "edge_encoder: {:.1} us, {:.2} ns/edge",
        dt * 1e6,
        dt * 1e9 / ne as f64
    );
}
