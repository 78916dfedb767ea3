//! The edge criterion in arithmetic: for one pair ([`sub`], [`dot`]) and for
//! a row of candidates at a time ([`compact`]: the distance test and the
//! compaction of the accepted ones, with AVX-512 in the `avx512` module
//! where the CPU has it, else portable).

/// Candidates of a row tested at a time ([`CellList::accept`]).
///
/// [`CellList::accept`]: crate::cell_list::CellList::accept
pub(crate) const LANES: usize = 8;

/// Appends to `out[len..]`, in order, the `idx[t]` (`t < n`) whose squared
/// distance to `p`, `Σ_k (cols[k][t] - p[k])²` summed left to right without
/// fused multiply-adds (the crate's criterion), is at most `rr`; returns the
/// new length. `cols[k]` and `idx` hold at least `n` entries, `out` at least
/// `len + n`. Sixteen candidates at a time with AVX-512 (a compare mask and
/// a compress) where the CPU has it, else [`LANES`] at a time, compacted
/// branch-free: the same candidates either way (same operations, same order).
#[inline(always)]
pub(crate) fn compact<const D: usize>(
    cols: [&[f32]; D],
    idx: &[u32],
    n: usize,
    p: &[f32; D],
    rr: f32,
    out: &mut [u32],
    len: usize,
) -> usize {
    assert!(idx.len() >= n && cols.iter().all(|c| c.len() >= n) && out.len() >= len + n);
    #[cfg(target_arch = "x86_64")]
    if avx512::available() {
        // SAFETY: the CPU has AVX-512F/VL (checked); lengths asserted above.
        #[allow(unsafe_code)]
        return unsafe { avx512::compact(cols, idx, n, p, rr, out, len) };
    }
    compact_portable(cols, idx, n, p, rr, out, len)
}

/// [`compact`] without SIMD intrinsics (the reference of the AVX-512 copy).
#[inline(always)]
fn compact_portable<const D: usize>(
    cols: [&[f32]; D],
    idx: &[u32],
    n: usize,
    p: &[f32; D],
    rr: f32,
    out: &mut [u32],
    mut len: usize,
) -> usize {
    let mut t = 0;
    while t < n {
        let m = (n - t).min(LANES);
        let mut dd = [0.0f32; LANES];
        for (l, x) in dd.iter_mut().enumerate().take(m) {
            let d = cols[0][t + l] - p[0];
            let mut acc = d * d;
            for k in 1..D {
                let d = cols[k][t + l] - p[k];
                acc += d * d;
            }
            *x = acc;
        }
        // branch-free compaction (the accept pattern is unpredictable)
        for (&j, &x) in idx[t..t + m].iter().zip(&dd) {
            out[len] = j;
            len += (x <= rr) as usize;
        }
        t += LANES;
    }
    len
}

#[cfg(target_arch = "x86_64")]
#[allow(unsafe_code)]
pub(crate) mod avx512 {
    use std::arch::x86_64::*;
    use std::sync::OnceLock;

    /// Whether the CPU has AVX-512F and VL, and `HYBRIDMPM_ISA` allows
    /// x86-64-v4 (`hybridmpm-isa`'s vocabulary, shared with the MPM frame
    /// loop and the network kernels; `baseline` and `x86-64-v3`/`avx2` keep
    /// the portable code). Read once per process.
    pub(crate) fn available() -> bool {
        static ON: OnceLock<bool> = OnceLock::new();
        *ON.get_or_init(|| {
            hybridmpm_isa::Level::X86_64V4.allows() && hybridmpm_isa::cpu::avx512f_vl()
        })
    }

    /// [`super::compact`], sixteen candidates at a time.
    ///
    /// # Safety
    /// The CPU must have AVX-512F and VL; `cols[k]` and `idx` hold at least
    /// `n` entries, `out` at least `len + n`.
    #[target_feature(enable = "avx512f,avx512vl,popcnt")]
    pub(crate) unsafe fn compact<const D: usize>(
        cols: [&[f32]; D],
        idx: &[u32],
        n: usize,
        p: &[f32; D],
        rr: f32,
        out: &mut [u32],
        mut len: usize,
    ) -> usize {
        let limit = _mm512_set1_ps(rr);
        let mut t = 0;
        while t < n {
            let m = (n - t).min(16);
            let live: __mmask16 = if m == 16 { u16::MAX } else { (1u16 << m) - 1 };
            // SAFETY (all loads and the store): masked to the `m` entries left,
            // which the slices hold (caller); masked-off lanes are not accessed.
            unsafe {
                let x = _mm512_maskz_loadu_ps(live, cols[0].as_ptr().add(t));
                let d = _mm512_sub_ps(x, _mm512_set1_ps(p[0]));
                let mut acc = _mm512_mul_ps(d, d);
                for k in 1..D {
                    let x = _mm512_maskz_loadu_ps(live, cols[k].as_ptr().add(t));
                    let d = _mm512_sub_ps(x, _mm512_set1_ps(p[k]));
                    acc = _mm512_add_ps(acc, _mm512_mul_ps(d, d));
                }
                let hit = _mm512_mask_cmp_ps_mask::<_CMP_LE_OQ>(live, acc, limit);
                let j = _mm512_maskz_loadu_epi32(live, idx.as_ptr().add(t) as *const i32);
                let kept = _mm512_maskz_compress_epi32(hit, j);
                let count = hit.count_ones() as usize;
                let first: __mmask16 = if count == 16 {
                    u16::MAX
                } else {
                    (1u16 << count) - 1
                };
                _mm512_mask_storeu_epi32(out.as_mut_ptr().add(len) as *mut i32, first, kept);
                len += count;
            }
            t += 16;
        }
        len
    }

    /// Sorts up to 64 distinct values ascending without branches on the
    /// data: each value's rank is the number of values below it (compare
    /// masks against the list held in up to four registers, counted), and
    /// it is stored at its rank.
    ///
    /// # Safety
    /// The CPU must have AVX-512F; `v.len() <= 64` and the values distinct.
    #[target_feature(enable = "avx512f,popcnt")]
    pub(crate) unsafe fn rank_sort(v: &mut [u32]) {
        let n = v.len();
        assert!(n <= 64);
        let used = n.div_ceil(16);
        let pad = _mm512_set1_epi32(-1); // u32::MAX: never below a value
        let mut vecs = [pad; 4];
        let mut copy = [0u32; 64];
        for (q, vq) in vecs.iter_mut().enumerate().take(used) {
            let m = (n - 16 * q).min(16);
            let live: __mmask16 = if m == 16 { u16::MAX } else { (1u16 << m) - 1 };
            // SAFETY: masked to the `m` entries of `v` from 16·q; `copy` holds 64.
            unsafe {
                *vq = _mm512_mask_loadu_epi32(pad, live, v.as_ptr().add(16 * q) as *const i32);
                _mm512_storeu_si512(copy.as_mut_ptr().add(16 * q) as *mut __m512i, *vq);
            }
        }
        for &x in &copy[..n] {
            let b = _mm512_set1_epi32(x as i32);
            let mut rank = 0u32;
            for vq in &vecs[..used] {
                rank += _mm512_cmplt_epu32_mask(*vq, b).count_ones();
            }
            v[rank as usize] = x;
        }
        debug_assert!(
            v.windows(2).all(|w| w[0] < w[1]),
            "rank_sort: values must be distinct"
        );
    }
}

#[inline(always)]
pub(crate) fn sub<const D: usize>(a: &[f32; D], b: &[f32; D]) -> [f32; D] {
    let mut d = [0.0f32; D];
    for k in 0..D {
        d[k] = a[k] - b[k];
    }
    d
}

#[inline(always)]
pub(crate) fn dot<const D: usize>(d: &[f32; D]) -> f32 {
    // Left-to-right sum, the order documented in the crate docs.
    let mut s = d[0] * d[0];
    for x in &d[1..] {
        s += x * x;
    }
    s
}

#[cfg(test)]
mod tests {
    /// The AVX-512 compaction keeps exactly the candidates of the portable
    /// one, in the same order, for every length (full and partial vectors),
    /// with candidates exactly at the radius and the output appended after
    /// existing entries; the portable one is held to the criterion itself.
    #[test]
    fn compaction_copies_agree_with_the_criterion() {
        fn check<const D: usize>(seed: u64) {
            let mut s = seed;
            let mut next = || {
                s = s
                    .wrapping_mul(6364136223846793005)
                    .wrapping_add(1442695040888963407);
                ((s >> 40) as f32) / (1u64 << 24) as f32
            };
            // on a 1/1024 grid, so that a candidate 0.25 away along an axis is at
            // squared distance 0.0625 = rr exactly (a tie, which is kept)
            let p: [f32; D] = std::array::from_fn(|_| (next() * 1024.0).floor() / 1024.0);
            let rr = 0.0625f32;
            for n in [0usize, 1, 7, 8, 15, 16, 17, 31, 33, 64, 100] {
                let mut cols: [Vec<f32>; D] =
                    std::array::from_fn(|_| (0..n).map(|_| next()).collect());
                // some candidates exactly on the sphere, some at the receiver
                for t in (0..n).step_by(5) {
                    for (k, c) in cols.iter_mut().enumerate() {
                        c[t] = p[k];
                    }
                    cols[0][t] = p[0] + 0.25;
                }
                for t in (2..n).step_by(7) {
                    for (k, c) in cols.iter_mut().enumerate() {
                        c[t] = p[k];
                    }
                }
                let idx: Vec<u32> = (0..n as u32).map(|i| 3 * i + 1).collect();
                let want: Vec<u32> = (0..n)
                    .filter(|&t| {
                        let d = cols[0][t] - p[0];
                        let mut acc = d * d;
                        for k in 1..D {
                            let d = cols[k][t] - p[k];
                            acc += d * d;
                        }
                        acc <= rr
                    })
                    .map(|t| idx[t])
                    .collect();
                let refs: [&[f32]; D] = std::array::from_fn(|k| &cols[k][..]);
                let mut out = vec![7u32; 3 + n];
                let len = super::compact_portable(refs, &idx, n, &p, rr, &mut out, 3);
                assert_eq!(&out[3..len], &want[..], "portable, D {D}, n {n}");
                assert_eq!(&out[..3], &[7, 7, 7]);
                #[cfg(target_arch = "x86_64")]
                if super::avx512::available() {
                    let mut out2 = vec![7u32; 3 + n];
                    #[allow(unsafe_code)]
                    // SAFETY: checked above; lengths as `compact` asserts.
                    let len2 =
                        unsafe { super::avx512::compact(refs, &idx, n, &p, rr, &mut out2, 3) };
                    assert_eq!(&out2[..len2], &out[..len], "AVX-512, D {D}, n {n}");
                    assert!(
                        out2[len2..].iter().all(|&v| v == 7),
                        "wrote past the kept ones"
                    );
                }
            }
        }
        for seed in 0..20 {
            check::<2>(seed);
            check::<3>(seed + 100);
        }
    }
}
