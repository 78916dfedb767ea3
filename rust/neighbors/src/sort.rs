//! Sorting of index lists: a receiver's accepted senders ([`insertion_sort`],
//! by rank with AVX-512 where the CPU has it) and a cell's candidate union
//! ([`sort_distinct`], by bitmap where the span allows).

#[cfg(target_arch = "x86_64")]
use crate::compact::avx512;

/// Sorts a short list of distinct indices ascending (a receiver's accepted
/// senders, a few dozen): up to 64 by rank with AVX-512 where the CPU has it
/// (no data-dependent branches: the insertion sort's comparisons mispredict,
/// a quarter of a 3D search's time by `perf annotate`), else by insertion;
/// longer ones by `sort_unstable`.
pub(crate) fn insertion_sort(v: &mut [u32]) {
    if v.len() > 64 {
        v.sort_unstable();
        return;
    }
    #[cfg(target_arch = "x86_64")]
    if v.len() > 1 && avx512::available() {
        // SAFETY: the CPU has AVX-512F (checked); at most 64 entries.
        #[allow(unsafe_code)]
        unsafe {
            avx512::rank_sort(v)
        };
        return;
    }
    insertion_sort_portable(v);
}

/// The insertion sort of [`insertion_sort`] (any length).
fn insertion_sort_portable(v: &mut [u32]) {
    for i in 1..v.len() {
        let x = v[i];
        let mut k = i;
        while k > 0 && v[k - 1] > x {
            v[k] = v[k - 1];
            k -= 1;
        }
        v[k] = x;
    }
}

/// Words of the two-level bitmap of [`sort_distinct`] (spans below
/// `64 * BITMAP_WORDS`).
const BITMAP_WORDS: usize = 4096;

/// Bitmaps of [`sort_distinct`]: `words` (one bit per index) and `summary`
/// (one bit per word, two-level variant) are all zero between uses.
pub(crate) struct BitSorter {
    words: Vec<u64>,
    summary: [u64; BITMAP_WORDS / 64],
}

impl Default for BitSorter {
    fn default() -> Self {
        BitSorter {
            words: Vec::new(),
            summary: [0; BITMAP_WORDS / 64],
        }
    }
}

/// Sorts distinct indices ascending. A comparison sort costs ~7 ns per
/// element for the 30-130 neighbours of a 3D receiver; a bitmap over the
/// index span is cheaper where it fits (thresholds from measurements on
/// lattice-ordered and randomly ordered clouds): a single-level bitmap for
/// spans of at most 8 words, or for lists of 32 or more when it is dense
/// (<= 2 words per element + 8); a two-level one (only touched words are
/// visited) for other lists of 32 or more with spans below 2^18; else
/// `sort_unstable`.
pub(crate) fn sort_distinct(v: &mut [u32], bs: &mut BitSorter) {
    let n = v.len();
    if n < 8 {
        v.sort_unstable();
        return;
    }
    let (mut lo, mut hi) = (u32::MAX, 0u32);
    for &x in v.iter() {
        lo = lo.min(x);
        hi = hi.max(x);
    }
    let span = (hi - lo) as usize;
    let words = (span >> 6) + 1;
    let mut k = 0;
    if words <= 8 || (n >= 32 && words <= 2 * n + 8) {
        // Dense enough for a single-level bitmap over the span (typical of
        // spatially coherent indices).
        bs.words.clear();
        bs.words.resize(words, 0);
        for &x in v.iter() {
            let o = (x - lo) as usize;
            bs.words[o >> 6] |= 1u64 << (o & 63);
        }
        for (w, &word) in bs.words.iter().enumerate() {
            let mut m = word;
            let base = lo as usize + 64 * w;
            while m != 0 {
                v[k] = (base + m.trailing_zeros() as usize) as u32;
                k += 1;
                m &= m - 1;
            }
        }
        bs.words.clear();
    } else if n >= 32 && words <= BITMAP_WORDS {
        // Sparse: two-level bitmap, only touched words are visited.
        if bs.words.len() < BITMAP_WORDS {
            bs.words.resize(BITMAP_WORDS, 0);
        }
        for &x in v.iter() {
            let o = (x - lo) as usize;
            let w = o >> 6;
            bs.words[w] |= 1u64 << (o & 63);
            bs.summary[w >> 6] |= 1u64 << (w & 63);
        }
        for si in 0..=(span >> 12) {
            let mut sm = std::mem::take(&mut bs.summary[si]);
            while sm != 0 {
                let w = si * 64 + sm.trailing_zeros() as usize;
                sm &= sm - 1;
                let mut m = std::mem::take(&mut bs.words[w]);
                let base = lo as usize + 64 * w;
                while m != 0 {
                    v[k] = (base + m.trailing_zeros() as usize) as u32;
                    k += 1;
                    m &= m - 1;
                }
            }
        }
    } else {
        v.sort_unstable();
        k = n;
    }
    debug_assert_eq!(k, n, "indices must be distinct");
}

#[cfg(test)]
mod tests {
    use super::sort_distinct;

    #[test]
    fn sort_distinct_both_paths() {
        let mut bits = super::BitSorter::default();
        let mut s = 1u64;
        let mut next = || {
            s = s
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            (s >> 33) as u32
        };
        for n in [0usize, 1, 7, 8, 9, 30, 31, 32, 33, 64, 200] {
            for span in [
                n as u32 + 1,
                300,
                511,
                512,
                4 * n as u32 + 64,
                5000,
                (1 << 18) - 1,
                1 << 18,
                1 << 20,
                u32::MAX,
            ] {
                let mut set = std::collections::BTreeSet::new();
                while set.len() < n {
                    let base = u32::MAX - span.min(u32::MAX - 1);
                    set.insert(base + next() % span.max(1));
                }
                let want: Vec<u32> = set.into_iter().collect();
                let mut v = want.clone();
                for i in (1..v.len()).rev() {
                    let j = next() as usize % (i + 1);
                    v.swap(i, j);
                }
                sort_distinct(&mut v, &mut bits);
                assert_eq!(v, want, "n {n} span {span}");
            }
        }
    }

    /// The sort of a receiver's accepted senders, for every length up to 70
    /// (the AVX-512 rank sort up to 64 where the CPU has it, `sort_unstable`
    /// above), against a plain sort, with values near `u32::MAX` (the rank
    /// sort's padding).
    #[test]
    fn short_sorts_sort() {
        let mut s = 9u64;
        let mut next = || {
            s = s
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            (s >> 33) as u32
        };
        for n in 0..=70usize {
            for top in [false, true] {
                let mut set = std::collections::BTreeSet::new();
                while set.len() < n {
                    let x = next() % 5000;
                    set.insert(if top { u32::MAX - x } else { x });
                }
                let want: Vec<u32> = set.into_iter().collect();
                let mut v = want.clone();
                for i in (1..v.len()).rev() {
                    let j = next() as usize % (i + 1);
                    v.swap(i, j);
                }
                let mut w = v.clone();
                super::insertion_sort(&mut v);
                assert_eq!(v, want, "n {n}");
                super::insertion_sort_portable(&mut w);
                assert_eq!(w, want, "n {n}, portable");
            }
        }
    }
}
