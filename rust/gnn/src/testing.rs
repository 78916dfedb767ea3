//! What the tests share: deterministic inputs, random MLPs, the graph's
//! arithmetic written the plain way in f64, and a [`ParallelFor`] that runs
//! the parts out of order on several threads.

use crate::{L, Mlp, ParallelFor};

/// A small deterministic generator (xorshift), values in [-1, 1).
pub(crate) fn values(seed: u64, n: usize) -> Vec<f32> {
    let mut s = seed.wrapping_mul(0x9E37_79B9_7F4A_7C15) | 1;
    (0..n)
        .map(|_| {
            s ^= s << 13;
            s ^= s >> 7;
            s ^= s << 17;
            ((s >> 40) as f32 / (1u64 << 24) as f32) * 2.0 - 1.0
        })
        .collect()
}

/// The weights of one MLP, owned ([`mlp`] borrows them).
pub(crate) struct Owned {
    pub(crate) w1: Vec<f32>,
    pub(crate) b1: Vec<f32>,
    pub(crate) w2: Vec<f32>,
    pub(crate) b2: Vec<f32>,
    pub(crate) w3: Vec<f32>,
    pub(crate) b3: Vec<f32>,
    pub(crate) kvar: Vec<f32>,
}

/// Random weights of an MLP with `inputs` inputs (the variance weights positive).
pub(crate) fn owned(inputs: usize, seed: u64) -> Owned {
    Owned {
        w1: values(seed, inputs * L),
        b1: values(seed + 1, L),
        w2: values(seed + 2, L * L),
        b2: values(seed + 3, L),
        w3: values(seed + 4, L * L),
        b3: values(seed + 5, L),
        kvar: values(seed + 6, L)
            .iter()
            .map(|v| v.abs() / L as f32)
            .collect(),
    }
}

/// `o` as the kernels take it, with `ε = 1e-5`.
pub(crate) fn mlp(o: &Owned) -> Mlp<'_> {
    Mlp {
        w1: &o.w1,
        b1: &o.b1,
        w2: &o.w2,
        b2: &o.b2,
        w3: &o.w3,
        b3: &o.b3,
        kvar: &o.kvar,
        eps: 1e-5,
    }
}

/// The graph's arithmetic, written the plain way in f64: one layer.
pub(crate) fn dense(x: &[f64], w: &[f32], b: &[f32], relu: bool) -> Vec<f64> {
    (0..L)
        .map(|j| {
            let v = b[j] as f64
                + x.iter()
                    .enumerate()
                    .map(|(k, &xk)| xk * w[k * L + j] as f64)
                    .sum::<f64>();
            if relu { v.max(0.0) } else { v }
        })
        .collect()
}

/// Layers 2 and 3 and the folded LayerNorm in f64, from the first layer's pre-activation.
pub(crate) fn reference(o: &Owned, first: Vec<f64>) -> Vec<f64> {
    let h = dense(
        &first.iter().map(|v| v.max(0.0)).collect::<Vec<_>>(),
        &o.w2,
        &o.b2,
        true,
    );
    let z = dense(&h, &o.w3, &o.b3, false);
    let var: f64 = z
        .iter()
        .zip(&o.kvar)
        .map(|(v, k)| v * v * *k as f64)
        .sum::<f64>()
        + 1e-5;
    z.iter().map(|v| v / var.sqrt()).collect()
}

/// Asserts that `a` matches `b` to float32 rounding.
pub(crate) fn close(a: &[f32], b: &[f64]) {
    assert_eq!(a.len(), b.len());
    for (i, (x, y)) in a.iter().zip(b).enumerate() {
        assert!(
            (*x as f64 - y).abs() <= 2e-5 * (1.0 + y.abs()),
            "value {i}: {x} against {y}"
        );
    }
}

/// Runs the parts from last to first, spread over three threads.
pub(crate) struct Threads;

impl ParallelFor for Threads {
    fn run(&self, n: usize, f: &(dyn Fn(usize) + Sync)) {
        std::thread::scope(|s| {
            for t in 0..3 {
                s.spawn(move || (0..n).rev().filter(|i| i % 3 == t).for_each(f));
            }
        });
    }
}
