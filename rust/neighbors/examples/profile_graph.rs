use hybridmpm_neighbors::{GraphParams, Neighbors, radius_graph};
use std::time::Instant;
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

fn main() {
    let p2 = case_2d();
    let p3 = case_3d();
    let params2 = GraphParams {
        radius: 0.015,
        ..Default::default()
    };
    let params3 = GraphParams {
        radius: 2.5 * 0.5 / 64.0,
        ..Default::default()
    };
    let reps: usize = std::env::var("REPS")
        .ok()
        .and_then(|s| s.parse().ok())
        .unwrap_or(20);
    match std::env::var("ONLY").as_deref() {
        Ok("2d") => {
            let mut best = f64::MAX;
            for _ in 0..reps * 50 {
                let t = Instant::now();
                let nb = Neighbors::search(&p2, &params2).unwrap();
                best = best.min(t.elapsed().as_secs_f64());
                drop(nb);
            }
            println!("2d search best {:.3} ms", best * 1e3);
        }
        Ok("rand2d") => {
            let mut st = 9u32;
            let n: usize = std::env::var("N")
                .ok()
                .and_then(|s| s.parse().ok())
                .unwrap_or(4096);
            let side = 0.32 * (n as f32 / 4096.0).sqrt();
            let pr: Vec<[f32; 2]> = (0..n)
                .map(|_| {
                    [
                        (jitter(&mut st) + 0.5) * side,
                        (jitter(&mut st) + 0.5) * side,
                    ]
                })
                .collect();
            let mut best = f64::MAX;
            let mut e = 0;
            for _ in 0..reps * 50 {
                let t = Instant::now();
                let nb = Neighbors::search(&pr, &params2).unwrap();
                best = best.min(t.elapsed().as_secs_f64());
                e = nb.num_edges();
                drop(nb);
            }
            println!("rand2d n={n} E={e} search best {:.3} ms", best * 1e3);
        }
        Ok("rand3d") => {
            let mut st = 9u32;
            let side = 0.25f32;
            let pr: Vec<[f32; 3]> = (0..32768)
                .map(|_| {
                    [
                        (jitter(&mut st) + 0.5) * side,
                        (jitter(&mut st) + 0.5) * side,
                        (jitter(&mut st) + 0.5) * side,
                    ]
                })
                .collect();
            let mut best = f64::MAX;
            let mut e = 0;
            for _ in 0..reps * 3 {
                let t = Instant::now();
                let nb = Neighbors::search(&pr, &params3).unwrap();
                best = best.min(t.elapsed().as_secs_f64());
                e = nb.num_edges();
                drop(nb);
            }
            println!("rand3d E={e} search best {:.3} ms", best * 1e3);
        }
        Ok("3d") => {
            let mut best = f64::MAX;
            for _ in 0..reps * 3 {
                let t = Instant::now();
                let nb = Neighbors::search(&p3, &params3).unwrap();
                best = best.min(t.elapsed().as_secs_f64());
                drop(nb);
            }
            println!("3d search best {:.3} ms", best * 1e3);
        }
        _ => {
            let (mut t2, mut t3, mut e2, mut e3) = (f64::MAX, f64::MAX, 0, 0);
            for _ in 0..reps {
                let t = Instant::now();
                let g = radius_graph(&p2, &params2).unwrap();
                t2 = t2.min(t.elapsed().as_secs_f64());
                e2 = g.num_edges();
                let t = Instant::now();
                let g = radius_graph(&p3, &params3).unwrap();
                t3 = t3.min(t.elapsed().as_secs_f64());
                e3 = g.num_edges();
            }
            println!(
                "2d: {:.3} ms  E={e2}   3d: {:.3} ms  E={e3}",
                t2 * 1e3,
                t3 * 1e3
            );
        }
    }
}
