//! Criterion bench of the radius graph on the GNS-sized cases:
//! 4096 particles in 2D (64x64 lattice, spacing 0.005, jitter, R = 0.015) and
//! 32768 in 3D (32^3 lattice, spacing 0.5/64, R = 2.5 spacing).
//!
//! `cargo bench -p hybridmpm-bench --bench radius_graph` (thread count: `RAYON_NUM_THREADS`).

use criterion::{Criterion, Throughput, criterion_group, criterion_main};
use hybridmpm_neighbors::{GraphParams, radius_graph};
use std::hint::black_box;

/// Deterministic jitter in [-0.5, 0.5) (LCG), so runs are reproducible.
fn jitter(state: &mut u32) -> f32 {
    *state = state.wrapping_mul(1664525).wrapping_add(1013904223);
    (*state >> 8) as f32 / (1u32 << 24) as f32 - 0.5
}

/// 64 x 64 lattice, spacing 0.005, jitter +-0.1 spacing.
pub fn case_2d() -> Vec<[f32; 2]> {
    let h = 0.005f32;
    let mut s = 1u32;
    let mut v = Vec::with_capacity(64 * 64);
    for y in 0..64 {
        for x in 0..64 {
            v.push([
                0.1 + (x as f32 + 0.2 * jitter(&mut s)) * h,
                0.1 + (y as f32 + 0.2 * jitter(&mut s)) * h,
            ]);
        }
    }
    v
}

/// 32^3 lattice, spacing 0.5/64, jitter +-0.1 spacing.
pub fn case_3d() -> Vec<[f32; 3]> {
    let h = 0.5f32 / 64.0;
    let mut s = 2u32;
    let mut v = Vec::with_capacity(32 * 32 * 32);
    for z in 0..32 {
        for y in 0..32 {
            for x in 0..32 {
                v.push([
                    0.1 + (x as f32 + 0.2 * jitter(&mut s)) * h,
                    0.1 + (y as f32 + 0.2 * jitter(&mut s)) * h,
                    0.1 + (z as f32 + 0.2 * jitter(&mut s)) * h,
                ]);
            }
        }
    }
    v
}

fn bench(c: &mut Criterion) {
    let mut g = c.benchmark_group("radius_graph");
    g.sample_size(20);

    let p2 = case_2d();
    let params2 = GraphParams {
        radius: 0.015,
        ..Default::default()
    };
    g.throughput(Throughput::Elements(p2.len() as u64));
    g.bench_function("2d_4096", |b| {
        b.iter(|| radius_graph(black_box(&p2), &params2).unwrap())
    });

    let p3 = case_3d();
    let params3 = GraphParams {
        radius: 2.5 * 0.5 / 64.0,
        ..Default::default()
    };
    g.throughput(Throughput::Elements(p3.len() as u64));
    g.bench_function("3d_32768", |b| {
        b.iter(|| radius_graph(black_box(&p3), &params3).unwrap())
    });
    let capped = GraphParams {
        max_neighbors: Some(32),
        ..params3
    };
    g.bench_function("3d_32768_cap32", |b| {
        b.iter(|| radius_graph(black_box(&p3), &capped).unwrap())
    });
    g.finish();
}

criterion_group!(benches, bench);
criterion_main!(benches);
