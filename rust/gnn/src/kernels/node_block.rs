//! The node block's body: one message-passing step's node update
//! `h' = h + LN(MLP([h, agg, degree]))`.

use super::{copies, tiles};
use crate::L;
use crate::mlp::{Weights, layer, rest};
use crate::simd::{Isa, Lanes, Portable};

/// Inputs of a node block's first layer: the node latent, its sum over in-edges and its in-degree.
pub const NODE_IN: usize = 2 * L + 1;

/// The node block over the part's nodes, `T` at a time: `out = h + LN(MLP([h, agg, degree]))`
/// with the first layer over the `NODE_IN` concatenated inputs.
#[inline(always)]
unsafe fn node<S: Lanes, const T: usize>(
    w: &Weights,
    h: &[f32],
    agg: &[f32],
    degree: &[f32],
    out: &mut [f32],
) {
    let n = degree.len();
    for tile in tiles::<T>(n) {
        let mut x = [[0.0f32; NODE_IN]; T];
        for (t, xt) in x.iter_mut().enumerate() {
            let i = tile.row(t);
            xt[..L].copy_from_slice(&h[i * L..(i + 1) * L]);
            xt[L..2 * L].copy_from_slice(&agg[i * L..(i + 1) * L]);
            xt[2 * L] = degree[i];
        }
        // SAFETY: the caller runs with `S`'s instruction set; every row read or written is L long.
        unsafe {
            let y = rest::<S, T>(w, layer::<S, T, NODE_IN>(&x, &w.w1, [S::load(&w.b1); T]));
            for t in 0..tile.count {
                let i = tile.base + t;
                let v = S::add(S::load(&x[t][..L]), y[t]);
                S::store(&mut out[i * L..(i + 1) * L], v);
            }
        }
    }
}

copies!(node, node_avx2, node_avx512, (w: &Weights, h: &[f32], agg: &[f32], deg: &[f32], out: &mut [f32]));

/// Runs the node block with the copy `isa`, which the CPU must have ([`isa`](crate::isa) checks it).
pub(crate) fn run(isa: Isa, w: &Weights, h: &[f32], agg: &[f32], deg: &[f32], out: &mut [f32]) {
    // SAFETY: the callers pass `isa()` (or, in the tests, a copy it allows), so the CPU has the copy's features.
    unsafe {
        match isa {
            #[cfg(target_arch = "x86_64")]
            Isa::Avx512 => node_avx512(w, h, agg, deg, out),
            #[cfg(target_arch = "x86_64")]
            Isa::Avx2 => node_avx2(w, h, agg, deg, out),
            _ => node::<Portable, 1>(w, h, agg, deg, out),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::{NODE_IN, run as run_node};
    use crate::L;
    use crate::mlp::Weights;
    use crate::simd::Isa;
    use crate::testing::{Threads, close, dense, mlp, owned, reference, values};
    use crate::{PART_NODES, Serial, isa, node_block};

    #[test]
    fn node_block_matches_the_layers_written_out_on_every_copy_and_in_parts() {
        for n in [0usize, 1, 5, 9, 3 * PART_NODES + 7] {
            let o = owned(NODE_IN, 21);
            let (h, agg) = (values(22, n * L), values(23, n * L));
            let deg: Vec<f32> = (0..n).map(|i| (i % 13) as f32).collect();
            let mut want = Vec::new();
            for i in 0..n {
                let mut x: Vec<f64> = h[i * L..(i + 1) * L].iter().map(|&v| v as f64).collect();
                x.extend(agg[i * L..(i + 1) * L].iter().map(|&v| v as f64));
                x.push(deg[i] as f64);
                let y = reference(&o, dense(&x, &o.w1, &o.b1, false));
                want.extend(y.iter().enumerate().map(|(j, v)| v + h[i * L + j] as f64));
            }
            let mut out = vec![f32::NAN; n * L];
            node_block(&mlp(&o), &h, &agg, &deg, &mut out, &Serial).unwrap();
            close(&out, &want);
            let mut par = vec![f32::NAN; n * L];
            node_block(&mlp(&o), &h, &agg, &deg, &mut par, &Threads).unwrap();
            assert!(
                out.iter()
                    .zip(&par)
                    .all(|(a, b)| a.to_bits() == b.to_bits())
            );
            let w = Weights::new(&mlp(&o), NODE_IN).unwrap();
            let best = isa();
            for c in [Isa::Portable, Isa::Avx2, Isa::Avx512] {
                if c == Isa::Avx512 && best != Isa::Avx512
                    || c == Isa::Avx2 && best == Isa::Portable
                {
                    continue;
                }
                let mut one = vec![f32::NAN; n * L];
                run_node(c, &w, &h, &agg, &deg, &mut one);
                close(&one, &want);
            }
        }
        let o = owned(NODE_IN, 1);
        let mut out = vec![0.0f32; 2 * L];
        let err = node_block(
            &mlp(&o),
            &[0.0; L],
            &[0.0; 2 * L],
            &[1.0, 2.0],
            &mut out,
            &Serial,
        )
        .unwrap_err();
        assert_eq!(err.field, "h");
        let err = node_block(
            &mlp(&owned(L, 1)),
            &[0.0; 2 * L],
            &[0.0; 2 * L],
            &[1.0, 2.0],
            &mut out,
            &Serial,
        )
        .unwrap_err();
        assert_eq!(err.field, "w1");
    }
}
