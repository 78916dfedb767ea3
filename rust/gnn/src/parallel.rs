//! How the kernels cut their rows into fixed parts and run them: the
//! [`ParallelFor`] a caller passes, the parts of each kind of kernel, and
//! the output slices each part writes.

use crate::L;

/// Runs `f(0), …, f(n − 1)`, in any order and possibly at once: a thread
/// pool's parallel for. The kernels split their edges into parts whose
/// results do not depend on how the parts are run, so any implementation
/// gives the same bits as [`Serial`].
pub trait ParallelFor {
    /// Calls `f(i)` once for every `i < n` and returns when all have returned.
    fn run(&self, n: usize, f: &(dyn Fn(usize) + Sync));
}

/// [`ParallelFor`] one part after another on the calling thread.
#[derive(Debug, Clone, Copy, Default)]
pub struct Serial;

impl ParallelFor for Serial {
    fn run(&self, n: usize, f: &(dyn Fn(usize) + Sync)) {
        (0..n).for_each(f);
    }
}

/// Edges per part of a kernel's work (a part of an edge block ends at the
/// first receiver change after this many). Fixed, so the parts, and with
/// them the results, do not depend on the thread count.
pub const PART_EDGES: usize = 1024;

/// Nodes per part of [`node_block`](crate::node_block) (fixed: the parts do not depend on the thread count).
pub const PART_NODES: usize = 256;

/// The edge ranges of the encoder's parts.
pub(crate) fn encoder_parts(e: usize) -> Vec<std::ops::Range<usize>> {
    (0..e.div_ceil(PART_EDGES).max(1))
        .map(|p| p * PART_EDGES..((p + 1) * PART_EDGES).min(e))
        .collect()
}

/// The parts of an edge block over `n` nodes: `(edges, nodes)` ranges, each
/// part's receivers inside its node range, the node ranges covering `0..n`
/// without overlap (so each part zeroes and sums its own slice of `agg`, and
/// every node's sum is one part's, in edge order). Receivers not sorted
/// (the radius graph sorts them) make one part.
pub(crate) fn block_parts(
    receivers: &[usize],
    n: usize,
) -> Vec<(std::ops::Range<usize>, std::ops::Range<usize>)> {
    let e = receivers.len();
    if e <= PART_EDGES || receivers.windows(2).any(|w| w[0] > w[1]) {
        return vec![(0..e, 0..n)];
    }
    let mut cuts = vec![0];
    let mut c = PART_EDGES;
    while c < e {
        while c < e && receivers[c] == receivers[c - 1] {
            c += 1;
        }
        if c < e {
            cuts.push(c);
        }
        c += PART_EDGES;
    }
    (0..cuts.len())
        .map(|p| {
            let (lo, hi) = (cuts[p], cuts.get(p + 1).copied().unwrap_or(e));
            let n0 = if p == 0 { 0 } else { receivers[lo] };
            let n1 = if hi == e { n } else { receivers[hi] };
            (lo..hi, n0..n1)
        })
        .collect()
}

/// Splits `0..n` into parts of [`PART_NODES`] (fixed: independent of the thread count).
pub(crate) fn node_parts(n: usize) -> Vec<std::ops::Range<usize>> {
    (0..n.div_ceil(PART_NODES).max(1))
        .map(|p| p * PART_NODES..((p + 1) * PART_NODES).min(n))
        .collect()
}

/// `out` cut into consecutive slices of `lens[p] · L` values, each behind
/// its own lock (the parts write disjoint slices; the locks are never contended).
pub(crate) fn slices(
    out: &mut [f32],
    lens: impl Iterator<Item = usize>,
) -> Vec<std::sync::Mutex<&mut [f32]>> {
    slices_of(out, L, lens)
}

/// `out` cut into consecutive slices of `lens[p] · width` values, each behind its own lock.
pub(crate) fn slices_of(
    mut out: &mut [f32],
    width: usize,
    lens: impl Iterator<Item = usize>,
) -> Vec<std::sync::Mutex<&mut [f32]>> {
    lens.map(|len| {
        let (head, tail) = std::mem::take(&mut out).split_at_mut(len * width);
        out = tail;
        std::sync::Mutex::new(head)
    })
    .collect()
}

#[cfg(test)]
mod tests {
    use super::{PART_EDGES, Serial, block_parts};
    use crate::L;
    use crate::testing::{Threads, mlp, owned, values};
    use crate::{Mlp, edge_block, edge_encoder};

    #[test]
    fn parts_run_at_once_give_the_same_bits_as_one_pass() {
        let o = owned(L, 7);
        let zeros = vec![0.0f32; L];
        let m = Mlp {
            b1: &zeros,
            ..mlp(&o)
        };
        // 700 nodes, every fifth without in-edges, 3-17 in-edges each: several parts
        let n = 700usize;
        let mut receivers = Vec::new();
        for i in 0..n {
            if i % 5 != 2 {
                receivers.extend(std::iter::repeat_n(i as i64, 3 + (i * 7) % 15));
            }
        }
        let ne = receivers.len();
        assert!(
            ne > 4 * PART_EDGES
                && block_parts(
                    &receivers.iter().map(|&r| r as usize).collect::<Vec<_>>(),
                    n
                )
                .len()
                    > 4
        );
        let senders: Vec<i64> = (0..ne).map(|k| ((k * 131) % n) as i64).collect();
        let (e, hr, hs) = (values(41, ne * L), values(42, n * L), values(43, n * L));
        let mut shuffled = receivers.clone();
        shuffled.swap(0, ne - 1); // unsorted: one part
        for recv in [&receivers, &shuffled] {
            let (mut o1, mut a1) = (vec![0.0; ne * L], vec![0.0; n * L]);
            edge_block(&m, &e, &hr, &hs, recv, &senders, &mut o1, &mut a1, &Serial).unwrap();
            let (mut o2, mut a2) = (vec![f32::NAN; ne * L], vec![f32::NAN; n * L]);
            edge_block(&m, &e, &hr, &hs, recv, &senders, &mut o2, &mut a2, &Threads).unwrap();
            let bits = |v: &[f32]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
            assert_eq!(bits(&o1), bits(&o2));
            assert_eq!(bits(&a1), bits(&a2));
            assert!(a1[2 * L..3 * L].iter().all(|&v| v == 0.0)); // node 2 has no in-edges
        }
        let enc = owned(3, 8);
        let (disp, dist) = (values(44, ne * 2), values(45, ne));
        let (mut o1, mut o2) = (vec![0.0; ne * L], vec![f32::NAN; ne * L]);
        edge_encoder(&mlp(&enc), 2, &disp, &dist, &mut o1, &Serial).unwrap();
        edge_encoder(&mlp(&enc), 2, &disp, &dist, &mut o2, &Threads).unwrap();
        assert!(o1.iter().zip(&o2).all(|(a, b)| a.to_bits() == b.to_bits()));
    }
}
