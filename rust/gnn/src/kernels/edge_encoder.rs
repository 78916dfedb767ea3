//! The edge encoder's body: `ε = LN(MLP([d, |d|]))` per edge.

use super::{copies, tiles};
use crate::L;
use crate::mlp::{Weights, layer, rest};
use crate::simd::{Isa, Lanes, Portable};

/// The edge encoder over all edges, `T` at a time (the last tile padded by
/// repeating its last edge, whose extra results are not stored).
#[inline(always)]
unsafe fn encoder<S: Lanes, const T: usize, const K: usize>(
    w: &Weights,
    disp: &[f32],
    dist: &[f32],
    out: &mut [f32],
) {
    let d = K - 1;
    let e = dist.len();
    for tile in tiles::<T>(e) {
        let mut x = [[0.0f32; K]; T];
        for (t, xt) in x.iter_mut().enumerate() {
            let k = tile.row(t);
            xt[..d].copy_from_slice(&disp[k * d..(k + 1) * d]);
            xt[d] = dist[k];
        }
        // SAFETY: the caller runs with `S`'s instruction set; every row read or written is L long.
        unsafe {
            let y = rest::<S, T>(w, layer::<S, T, K>(&x, &w.w1, [S::load(&w.b1); T]));
            for t in 0..tile.count {
                let k = tile.base + t;
                S::store(&mut out[k * L..(k + 1) * L], y[t]);
            }
        }
    }
}

copies!(encoder<const K>, encoder_avx2, encoder_avx512, (w: &Weights, disp: &[f32], dist: &[f32], out: &mut [f32]));

/// Runs the edge encoder with the copy `isa`, which the CPU must have ([`isa`](crate::isa) checks it).
pub(crate) fn run(
    isa: Isa,
    w: &Weights,
    dim: usize,
    displacement: &[f32],
    distance: &[f32],
    out: &mut [f32],
) {
    // SAFETY: the callers pass `isa()` (or, in the tests, a copy it allows), so the CPU has the copy's features.
    unsafe {
        match (isa, dim) {
            #[cfg(target_arch = "x86_64")]
            (Isa::Avx512, 2) => encoder_avx512::<3>(w, displacement, distance, out),
            #[cfg(target_arch = "x86_64")]
            (Isa::Avx512, _) => encoder_avx512::<4>(w, displacement, distance, out),
            #[cfg(target_arch = "x86_64")]
            (Isa::Avx2, 2) => encoder_avx2::<3>(w, displacement, distance, out),
            #[cfg(target_arch = "x86_64")]
            (Isa::Avx2, _) => encoder_avx2::<4>(w, displacement, distance, out),
            (_, 2) => encoder::<Portable, 1, 3>(w, displacement, distance, out),
            _ => encoder::<Portable, 1, 4>(w, displacement, distance, out),
        }
    }
}

#[cfg(test)]
mod tests {
    use crate::testing::{close, dense, mlp, owned, reference, values};
    use crate::{L, Serial, edge_encoder};

    #[test]
    fn encoder_matches_the_layers_written_out() {
        for dim in [2usize, 3] {
            for ne in [0usize, 1, 3, 4, 9] {
                let o = owned(dim + 1, 7 + dim as u64);
                let disp = values(11, ne * dim);
                let dist: Vec<f32> = values(12, ne).iter().map(|v| v.abs()).collect();
                let mut out = vec![f32::NAN; ne * L];
                edge_encoder(&mlp(&o), dim, &disp, &dist, &mut out, &Serial).unwrap();
                let mut want = Vec::new();
                for k in 0..ne {
                    let mut x: Vec<f64> = disp[k * dim..(k + 1) * dim]
                        .iter()
                        .map(|&v| v as f64)
                        .collect();
                    x.push(dist[k] as f64);
                    want.extend(reference(&o, dense(&x, &o.w1, &o.b1, false)));
                }
                close(&out, &want);
            }
        }
    }
}
