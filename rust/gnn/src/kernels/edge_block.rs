//! The edge block's body: one message-passing step's edge update and its
//! sum over receivers, in edge order.

use super::{copies, tiles};
use crate::L;
use crate::mlp::{Weights, layer, rest};
use crate::simd::{Isa, Lanes, Portable};

/// The inputs of one part of an edge block (all of it on one thread): its
/// edges' latents, receivers and senders, the whole node projections, and
/// the first node of its slice of `agg` (its receivers are `node0` on).
pub(crate) struct Block<'a> {
    pub(crate) e: &'a [f32],
    pub(crate) hr: &'a [f32],
    pub(crate) hs: &'a [f32],
    pub(crate) receivers: &'a [usize],
    pub(crate) senders: &'a [usize],
    pub(crate) node0: usize,
}

/// The edge block over the part's edges, `T` at a time, and the sum over
/// receivers in edge order into the part's slice of `agg` (zeroed first).
#[inline(always)]
unsafe fn block<S: Lanes, const T: usize>(
    w: &Weights,
    b: &Block<'_>,
    out: &mut [f32],
    agg: &mut [f32],
) {
    agg.fill(0.0);
    let e = b.receivers.len();
    // the running sum of the current receiver, in a register: the same
    // additions in the same (edge) order as adding each edge into `agg`,
    // without a store and a reload per edge; written back when the receiver
    // changes (the receivers of a part are sorted, or the part is the whole
    // unsorted graph, where a change writes back and a later edge of the same
    // receiver reloads the sum)
    let mut current = usize::MAX;
    // SAFETY: the caller runs with `S`'s instruction set.
    let mut sum = unsafe { S::zero() };
    let mut pad = [[0.0f32; L]; T];
    for tile in tiles::<T>(e) {
        let base = tile.base;
        // a full tile's edge latents are read in place; the last one, padded by
        // repeating its last edge, from a copy
        let x: &[[f32; L]; T] = match b.e[base * L..].as_chunks::<L>().0.get(..T) {
            Some(rows) if tile.count == T => rows.try_into().expect("T rows"),
            _ => {
                for (t, row) in pad.iter_mut().enumerate() {
                    let k = tile.row(t);
                    row.copy_from_slice(&b.e[k * L..(k + 1) * L]);
                }
                &pad
            }
        };
        // SAFETY: the caller runs with `S`'s instruction set; indices were checked against N; rows are L long.
        unsafe {
            let mut y = [S::zero(); T];
            for t in 0..T {
                let k = tile.row(t);
                let (r, s) = (b.receivers[k], b.senders[k]);
                y[t] = S::add(
                    S::load(&b.hr[r * L..(r + 1) * L]),
                    S::load(&b.hs[s * L..(s + 1) * L]),
                );
            }
            let y = rest::<S, T>(w, layer::<S, T, L>(x, &w.w1, y));
            for t in 0..tile.count {
                let k = base + t;
                let v = S::add(S::load(&x[t]), y[t]);
                S::store(&mut out[k * L..(k + 1) * L], v);
                let r = b.receivers[k] - b.node0;
                if r != current {
                    if current != usize::MAX {
                        S::store(&mut agg[current * L..(current + 1) * L], sum);
                    }
                    current = r;
                    sum = S::load(&agg[r * L..(r + 1) * L]);
                }
                sum = S::add(sum, v);
            }
        }
    }
    if current != usize::MAX {
        // SAFETY: as above.
        unsafe { S::store(&mut agg[current * L..(current + 1) * L], sum) };
    }
}

copies!(block, block_avx2, block_avx512, (w: &Weights, b: &Block<'_>, out: &mut [f32], agg: &mut [f32]));

/// Runs the edge block with the copy `isa`, which the CPU must have ([`isa`](crate::isa) checks it).
pub(crate) fn run(isa: Isa, w: &Weights, b: &Block<'_>, out: &mut [f32], agg: &mut [f32]) {
    // SAFETY: the callers pass `isa()` (or, in the tests, a copy it allows), so the CPU has the copy's features.
    unsafe {
        match isa {
            #[cfg(target_arch = "x86_64")]
            Isa::Avx512 => block_avx512(w, b, out, agg),
            #[cfg(target_arch = "x86_64")]
            Isa::Avx2 => block_avx2(w, b, out, agg),
            _ => block::<Portable, 1>(w, b, out, agg),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::{Block, run as run_block};
    use crate::mlp::Weights;
    use crate::simd::Isa;
    use crate::testing::{close, dense, mlp, owned, reference, values};
    use crate::{L, Mlp, Serial, edge_block, isa};

    #[test]
    fn block_matches_the_layers_written_out_and_sums_over_receivers() {
        let n = 7;
        for ne in [0usize, 1, 5, 8, 13] {
            let o = owned(L, 3);
            let zeros = vec![0.0f32; L];
            let m = Mlp {
                b1: &zeros,
                ..mlp(&o)
            };
            let e = values(21, ne * L);
            let hr = values(22, n * L);
            let hs = values(23, n * L);
            let receivers: Vec<i64> = (0..ne as i64).map(|k| (k * 3) % (n as i64 - 1)).collect();
            let senders: Vec<i64> = (0..ne as i64).map(|k| (k * 5 + 1) % n as i64).collect();
            let mut out = vec![f32::NAN; ne * L];
            let mut agg = vec![f32::NAN; n * L];
            edge_block(
                &m, &e, &hr, &hs, &receivers, &senders, &mut out, &mut agg, &Serial,
            )
            .unwrap();
            let mut want = Vec::new();
            let mut want_agg = vec![0.0f64; n * L];
            for k in 0..ne {
                let (r, s) = (receivers[k] as usize, senders[k] as usize);
                let x: Vec<f64> = e[k * L..(k + 1) * L].iter().map(|&v| v as f64).collect();
                let mut first = dense(&x, &o.w1, &zeros, false);
                for j in 0..L {
                    first[j] += hr[r * L + j] as f64 + hs[s * L + j] as f64;
                }
                let ln = reference(&o, first);
                for j in 0..L {
                    let v = x[j] + ln[j];
                    want.push(v);
                    want_agg[r * L + j] += v;
                }
            }
            close(&out, &want);
            close(&agg, &want_agg);
            // node n - 1 receives no edge: its sum is exactly zero
            assert!(agg[(n - 1) * L..].iter().all(|&v| v == 0.0));
        }
    }

    #[test]
    fn every_copy_the_cpu_has_agrees_with_the_portable_one() {
        let o = owned(L, 5);
        let zeros = vec![0.0f32; L];
        let m = Mlp {
            b1: &zeros,
            ..mlp(&o)
        };
        let (n, ne) = (9usize, 23usize);
        let e = values(31, ne * L);
        let hr = values(32, n * L);
        let hs = values(33, n * L);
        let receivers: Vec<usize> = (0..ne).map(|k| k % n).collect();
        let senders: Vec<usize> = (0..ne).map(|k| (k * 7) % n).collect();
        let b = Block {
            e: &e,
            hr: &hr,
            hs: &hs,
            receivers: &receivers,
            senders: &senders,
            node0: 0,
        };
        let w = Weights::new(&m, L).unwrap();
        let (mut o1, mut a1) = (vec![0.0; ne * L], vec![0.0; n * L]);
        run_block(Isa::Portable, &w, &b, &mut o1, &mut a1);
        let best = isa();
        let copies: Vec<Isa> = [Isa::Avx2, Isa::Avx512]
            .into_iter()
            .filter(|&c| best == Isa::Avx512 || (best == Isa::Avx2 && c == Isa::Avx2))
            .collect();
        for c in copies {
            let (mut o2, mut a2) = (vec![f32::NAN; ne * L], vec![f32::NAN; n * L]);
            run_block(c, &w, &b, &mut o2, &mut a2);
            for (x, y) in o1.iter().zip(&o2).chain(a1.iter().zip(&a2)) {
                assert!(
                    (x - y).abs() <= 1e-5 * (1.0 + x.abs()),
                    "{c:?}: {x} against {y}"
                );
            }
        }
    }
}
