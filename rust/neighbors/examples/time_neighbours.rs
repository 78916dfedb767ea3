//! Times the radius graph, the density relaxation and the two together
//! (`relax_then_graph` against `relax_density` then `radius_graph`) on a
//! saved particle cloud, medians over repeats, one thread:
//!
//! ```text
//! cargo run --release -p hybridmpm-neighbors --example time_neighbours -- FILE D R RHO0 [REPEATS]
//! ```
//!
//! `FILE` holds raw little-endian float32 [N, D] (numpy:
//! `positions.astype(np.float32).tofile(FILE)`), e.g. a network's clipped
//! prediction; every particle is movable. The edge arrays are written into
//! buffers kept between calls, as the Python binding writes into numpy arrays.
use std::time::Instant;

use hybridmpm_neighbors::{
    GraphParams, Neighbors, RelaxParams, relax_density, relax_then_graph, write_edges,
};

fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(|a, b| a.total_cmp(b));
    v[v.len() / 2]
}

fn run<const D: usize>(raw: &[f32], radius: f32, rho0: f32, repeats: usize) {
    let pos: Vec<[f32; D]> = raw
        .chunks_exact(D)
        .map(|c| std::array::from_fn(|k| c[k]))
        .collect();
    let movable = vec![true; pos.len()];
    let gp = GraphParams {
        radius,
        ..GraphParams::default()
    };
    let rp = RelaxParams {
        radius,
        rest_density: rho0,
        iterations: 3,
        omega: 1.0,
    };
    let time = |f: &mut dyn FnMut()| {
        let mut ts = Vec::with_capacity(repeats);
        for _ in 0..repeats {
            let t0 = Instant::now();
            f();
            ts.push(t0.elapsed().as_secs_f64() * 1e6);
        }
        median(ts)
    };
    let edges = Neighbors::search(&pos, &gp)
        .expect("finite positions")
        .num_edges();
    let cap = 2 * edges + pos.len();
    let (mut s, mut r) = (vec![0i64; cap], vec![0i64; cap]);
    let (mut dp, mut ds) = (vec![[0.0f32; D]; cap], vec![0.0f32; cap]);
    let mut p = pos.clone();
    let graph = time(&mut || {
        let nb = Neighbors::search(&pos, &gp).expect("finite positions");
        let e = nb.num_edges();
        nb.write(&mut s[..e], &mut r[..e], &mut dp[..e], &mut ds[..e])
            .expect("sized");
    });
    let relax = time(&mut || {
        p.copy_from_slice(&pos);
        relax_density(&mut p, &movable, &rp).expect("valid");
    });
    let in_turn = time(&mut || {
        p.copy_from_slice(&pos);
        relax_density(&mut p, &movable, &rp).expect("valid");
        let nb = Neighbors::search(&p, &gp).expect("finite positions");
        let e = nb.num_edges();
        nb.write(&mut s[..e], &mut r[..e], &mut dp[..e], &mut ds[..e])
            .expect("sized");
    });
    let mut searched = 0;
    let fused = time(&mut || {
        p.copy_from_slice(&pos);
        let g = relax_then_graph(&mut p, &movable, &rp, None, &gp).expect("valid");
        let e = g.senders.len();
        write_edges(
            &p,
            &g.offsets,
            &g.senders,
            &mut s[..e],
            &mut r[..e],
            &mut dp[..e],
            &mut ds[..e],
        )
        .expect("sized");
        searched = g.searched;
    });
    println!(
        "N {} E {edges}: radius_graph {graph:.1} us, relax_density (3 iterations) {relax:.1}, \
         both in turn {in_turn:.1}, relax_then_graph {fused:.1} (searched again: {searched})",
        pos.len()
    );
}

fn main() {
    let a: Vec<String> = std::env::args().collect();
    if a.len() < 5 {
        eprintln!("usage: time_neighbours FILE D R RHO0 [REPEATS]");
        std::process::exit(2);
    }
    let bytes = std::fs::read(&a[1]).expect("read FILE");
    let raw: Vec<f32> = bytes
        .chunks_exact(4)
        .map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]]))
        .collect();
    let d: usize = a[2].parse().expect("D");
    let radius: f32 = a[3].parse().expect("R");
    let rho0: f32 = a[4].parse().expect("RHO0");
    let repeats: usize = a.get(5).map_or(300, |s| s.parse().expect("REPEATS"));
    match d {
        2 => run::<2>(&raw, radius, rho0, repeats),
        3 => run::<3>(&raw, radius, rho0, repeats),
        _ => panic!("D must be 2 or 3"),
    }
}
