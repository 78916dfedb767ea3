//! The node encoder's body: each node's features from its position history,
//! then `h = LN(MLP(features) + table[type])`.

use super::{copies, tiles};
use crate::mlp::{Weights, layer, rest};
use crate::simd::{Isa, Lanes, Portable};
use crate::{L, Row};

/// Most node features a [`node_encoder`](crate::node_encoder) takes (velocities and walls): `(T − 1)·D + 2D ≤ 32`.
pub const MAX_NODE_FEATURES: usize = 32;

/// The node-encoder inputs the kernel reads, checked.
pub(crate) struct Features<'a> {
    pub(crate) positions: &'a [f32],
    pub(crate) types: &'a [usize],
    pub(crate) lower: &'a [f32],
    pub(crate) upper: &'a [f32],
    pub(crate) inv_w: f32,
    pub(crate) table: &'a [Row],
    pub(crate) t_in: usize,
    pub(crate) dim: usize,
    pub(crate) n: usize,
}

impl Features<'_> {
    /// Node `i`'s features: the `T − 1` position differences, oldest first,
    /// then `(x − lower)/w` and `(upper − x)/w` of its last position, clipped to [−1, 1].
    #[inline(always)]
    fn row(&self, i: usize, x: &mut [f32; MAX_NODE_FEATURES]) {
        let (d, n) = (self.dim, self.n);
        let at = |t: usize, k: usize| self.positions[(t * n + i) * d + k];
        for t in 0..self.t_in - 1 {
            for k in 0..d {
                x[t * d + k] = at(t + 1, k) - at(t, k);
            }
        }
        let v = (self.t_in - 1) * d;
        for k in 0..d {
            let last = at(self.t_in - 1, k);
            x[v + k] = ((last - self.lower[k]) * self.inv_w).clamp(-1.0, 1.0);
            x[v + d + k] = ((self.upper[k] - last) * self.inv_w).clamp(-1.0, 1.0);
        }
    }
}

/// The node encoder over nodes `range`, `T` at a time: features (above),
/// `LN(MLP(x) + table[type])` with the type term added after the first layer.
#[inline(always)]
unsafe fn node_enc<S: Lanes, const T: usize>(
    w: &Weights,
    f: &Features<'_>,
    range: std::ops::Range<usize>,
    out: &mut [f32],
) {
    let n = range.len();
    for tile in tiles::<T>(n) {
        let mut x = [[0.0f32; MAX_NODE_FEATURES]; T];
        for (t, xt) in x.iter_mut().enumerate() {
            f.row(range.start + tile.row(t), xt);
        }
        // SAFETY: the caller runs with `S`'s instruction set; every row read or written is L long.
        unsafe {
            let mut y = layer::<S, T, MAX_NODE_FEATURES>(&x, &w.w1, [S::load(&w.b1); T]);
            for t in 0..T {
                let ty = f.types[range.start + tile.row(t)];
                y[t] = S::add(y[t], S::load(&f.table[ty]));
            }
            let y = rest::<S, T>(w, y);
            for t in 0..tile.count {
                let i = tile.base + t;
                S::store(&mut out[i * L..(i + 1) * L], y[t]);
            }
        }
    }
}

copies!(node_enc, node_enc_avx2, node_enc_avx512, (w: &Weights, f: &Features<'_>, r: std::ops::Range<usize>, out: &mut [f32]));

/// Runs the node encoder with the copy `isa`, which the CPU must have ([`isa`](crate::isa) checks it).
pub(crate) fn run(
    isa: Isa,
    w: &Weights,
    f: &Features<'_>,
    r: std::ops::Range<usize>,
    out: &mut [f32],
) {
    // SAFETY: the callers pass `isa()` (or, in the tests, a copy it allows), so the CPU has the copy's features.
    unsafe {
        match isa {
            #[cfg(target_arch = "x86_64")]
            Isa::Avx512 => node_enc_avx512(w, f, r, out),
            #[cfg(target_arch = "x86_64")]
            Isa::Avx2 => node_enc_avx2(w, f, r, out),
            _ => node_enc::<Portable, 1>(w, f, r, out),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::{Features, run as run_node_enc};
    use crate::L;
    use crate::kernels::decoder::run as run_dec;
    use crate::mlp::{Weights, rows};
    use crate::simd::Isa;
    use crate::testing::{Threads, close, dense, mlp, owned, reference, values};
    use crate::{Mlp, PART_NODES, ParallelFor, Serial, decoder, isa, node_encoder};

    #[test]
    fn node_encoder_and_decoder_match_the_layers_written_out() {
        for dim in [2usize, 3] {
            let (t_in, n, types) = (6usize, 3 * PART_NODES + 5, 4usize);
            let nf = (t_in - 1) * dim + 2 * dim;
            let o = owned(nf, 30 + dim as u64);
            let pos = values(31, t_in * n * dim);
            let ptype: Vec<i64> = (0..n).map(|i| ((i * 7) % types) as i64).collect();
            let table = values(32, types * L);
            let (lower, upper) = (vec![-0.9f32; dim], vec![0.8f32; dim]);
            let inv_w = 2.5f32;
            let m = mlp(&o);
            let encode = |pos: &[f32], ptype: &[i64], out: &mut [f32], par: &dyn ParallelFor| {
                node_encoder(&m, dim, pos, ptype, &lower, &upper, inv_w, &table, out, par)
            };
            let mut h = vec![f32::NAN; n * L];
            encode(&pos, &ptype, &mut h, &Serial).unwrap();
            let at = |t: usize, i: usize, k: usize| pos[(t * n + i) * dim + k] as f64;
            let mut want = Vec::new();
            for i in 0..n {
                let mut x = Vec::new();
                for t in 0..t_in - 1 {
                    x.extend((0..dim).map(|k| at(t + 1, i, k) - at(t, i, k)));
                }
                let last: Vec<f64> = (0..dim).map(|k| at(t_in - 1, i, k)).collect();
                x.extend(
                    (0..dim).map(|k| ((last[k] - lower[k] as f64) * inv_w as f64).clamp(-1.0, 1.0)),
                );
                x.extend(
                    (0..dim).map(|k| ((upper[k] as f64 - last[k]) * inv_w as f64).clamp(-1.0, 1.0)),
                );
                let ty = ptype[i] as usize;
                let first: Vec<f64> = dense(&x, &o.w1, &o.b1, false)
                    .iter()
                    .enumerate()
                    .map(|(j, v)| v + table[ty * L + j] as f64)
                    .collect();
                want.extend(reference(&o, first));
            }
            close(&h, &want);
            let mut h2 = vec![f32::NAN; n * L];
            encode(&pos, &ptype, &mut h2, &Threads).unwrap();
            assert!(h.iter().zip(&h2).all(|(a, b)| a.to_bits() == b.to_bits()));
            let bad_type: Vec<i64> = (0..n as i64)
                .map(|i| if i == 3 { types as i64 } else { 0 })
                .collect();
            let err = encode(&pos, &bad_type, &mut h2, &Serial).unwrap_err();
            assert_eq!(err.field, "particle_type");
            let err = encode(&pos[1..], &ptype, &mut h2, &Serial).unwrap_err();
            assert_eq!(err.field, "positions");

            // the decoder: an MLP without LayerNorm to D outputs, then the Euler step; type 3 is kinematic
            let d = owned(L, 40 + dim as u64);
            let (w3, b3) = (values(41, L * dim), values(42, dim));
            let dm = Mlp {
                w3: &w3,
                b3: &b3,
                ..mlp(&d)
            };
            let (mut acc, mut next) = (vec![f32::NAN; n * dim], vec![f32::NAN; n * dim]);
            decoder(&dm, dim, &h, &pos, &ptype, 3, &mut acc, &mut next, &Serial).unwrap();
            let (mut acc2, mut next2) = (vec![f32::NAN; n * dim], vec![f32::NAN; n * dim]);
            decoder(
                &dm, dim, &h, &pos, &ptype, 3, &mut acc2, &mut next2, &Threads,
            )
            .unwrap();
            assert!(
                acc.iter()
                    .chain(&next)
                    .zip(acc2.iter().chain(&next2))
                    .all(|(a, b)| a.to_bits() == b.to_bits())
            );
            let mut want_acc = Vec::new();
            for i in 0..n {
                let x: Vec<f64> = h[i * L..(i + 1) * L].iter().map(|&v| v as f64).collect();
                let y = dense(&dense(&x, &d.w1, &d.b1, true), &d.w2, &d.b2, true);
                want_acc.extend((0..dim).map(|k| {
                    b3[k] as f64 + (0..L).map(|j| y[j] * w3[j * dim + k] as f64).sum::<f64>()
                }));
            }
            close(&acc, &want_acc);
            for i in 0..n {
                for k in 0..dim {
                    let (l, p) = (
                        pos[((t_in - 1) * n + i) * dim + k],
                        pos[((t_in - 2) * n + i) * dim + k],
                    );
                    let want = if ptype[i] == 3 {
                        l
                    } else {
                        ((l + l) - p) + acc[i * dim + k]
                    };
                    assert_eq!(next[i * dim + k].to_bits(), want.to_bits());
                }
            }
            let err = decoder(
                &dm,
                dim,
                &h[L..],
                &pos,
                &ptype,
                3,
                &mut acc,
                &mut next,
                &Serial,
            )
            .unwrap_err();
            assert_eq!(err.field, "h");
            // every copy this CPU has gives the layers' values
            let best = isa();
            let types_u: Vec<usize> = ptype.iter().map(|&t| t as usize).collect();
            let table_rows = rows("table", &table, types).unwrap();
            let f = Features {
                positions: &pos,
                types: &types_u,
                lower: &lower,
                upper: &upper,
                inv_w,
                table: &table_rows,
                t_in,
                dim,
                n,
            };
            let we = Weights::new(&mlp(&o), nf).unwrap();
            let mut w3p = vec![0.0f32; L * L];
            let mut b3p = vec![0.0f32; L];
            for k in 0..L {
                w3p[k * L..k * L + dim].copy_from_slice(&w3[k * dim..(k + 1) * dim]);
            }
            b3p[..dim].copy_from_slice(&b3);
            let ones = [1.0f32; L];
            let wd = Weights::new(
                &Mlp {
                    w3: &w3p,
                    b3: &b3p,
                    kvar: &ones,
                    eps: 1.0,
                    ..mlp(&d)
                },
                L,
            )
            .unwrap();
            for c in [Isa::Portable, Isa::Avx2, Isa::Avx512] {
                if c == Isa::Avx512 && best != Isa::Avx512
                    || c == Isa::Avx2 && best == Isa::Portable
                {
                    continue;
                }
                let mut hc = vec![f32::NAN; n * L];
                run_node_enc(c, &we, &f, 0..n, &mut hc);
                close(&hc, &want);
                let mut ac = vec![f32::NAN; n * dim];
                run_dec(c, &wd, &h, dim, &mut ac);
                close(&ac, &want_acc);
            }
        }
    }
}
