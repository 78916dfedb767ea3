//! The kernel bodies, one file each, written once over [`Lanes`] and
//! compiled into one copy per instruction set; each file's `run` calls the
//! copy an [`Isa`] names.
//!
//! Every body walks its rows a tile of `T` at a time ([`tiles`]): it loads
//! `T` rows, runs the MLP on all of them in registers and stores the rows
//! that exist.
//!
//! [`Lanes`]: crate::simd::Lanes
//! [`Isa`]: crate::Isa

pub(crate) mod decoder;
pub(crate) mod edge_block;
pub(crate) mod edge_encoder;
pub(crate) mod node_block;
pub(crate) mod node_encoder;

/// Rows `base..base + count` of a kernel's input, `0 < count ≤ T`. The body
/// computes all `T` lanes and stores the first `count`: the lanes past the
/// end repeat the last row.
#[derive(Debug, Clone, Copy)]
pub(crate) struct Tile {
    /// The tile's first row.
    pub(crate) base: usize,
    /// How many of its `T` lanes are rows of the input.
    pub(crate) count: usize,
}

impl Tile {
    /// The row lane `t` computes: `base + t`, or the last row for a lane past the end.
    #[inline(always)]
    pub(crate) fn row(self, t: usize) -> usize {
        self.base + t.min(self.count - 1)
    }
}

/// The tiles of `T` rows covering rows `0..n` in order, the last one
/// shorter where `T` does not divide `n`: `for tile in tiles::<T>(n) { … }`. An iterator rather than a
/// function taking the body as a closure, so that the body stays in the
/// kernel's own function and is inlined into each compiled copy.
#[inline(always)]
pub(crate) fn tiles<const T: usize>(n: usize) -> Tiles<T> {
    Tiles { n, base: 0 }
}

/// The iterator [`tiles`] returns.
#[derive(Debug, Clone)]
pub(crate) struct Tiles<const T: usize> {
    n: usize,
    base: usize,
}

impl<const T: usize> Iterator for Tiles<T> {
    type Item = Tile;

    #[inline(always)]
    fn next(&mut self) -> Option<Tile> {
        if self.base >= self.n {
            return None;
        }
        let tile = Tile {
            base: self.base,
            count: T.min(self.n - self.base),
        };
        self.base += tile.count;
        Some(tile)
    }
}

/// `$avx2` and `$avx512`: the kernel body `$kernel` compiled with AVX2 + FMA
/// on tiles of 4 rows and with AVX-512F on tiles of 8 (x86-64 only), with the
/// body's arguments; a `<const K>` after the body's name stays a parameter of
/// both copies.
macro_rules! copies {
    ($kernel:ident $(<const $k:ident>)?, $avx2:ident, $avx512:ident, ($($arg:ident: $ty:ty),* $(,)?)) => {
        #[cfg(target_arch = "x86_64")]
        #[target_feature(enable = "avx,avx2,fma")]
        fn $avx2$(<const $k: usize>)?($($arg: $ty),*) {
            // SAFETY: AVX2 and FMA are enabled here (the callers check the CPU).
            unsafe { $kernel::<crate::simd::Avx2, 4 $(, $k)?>($($arg),*) }
        }

        #[cfg(target_arch = "x86_64")]
        #[target_feature(enable = "avx512f")]
        fn $avx512$(<const $k: usize>)?($($arg: $ty),*) {
            // SAFETY: AVX-512F is enabled here (the callers check the CPU).
            unsafe { $kernel::<crate::simd::Avx512, 8 $(, $k)?>($($arg),*) }
        }
    };
}
use copies;

#[cfg(test)]
mod tests {
    use super::{Tile, tiles};

    #[test]
    fn tiles_cover_the_rows_in_order_and_pad_the_last_with_its_last_row() {
        let all = |n| tiles::<4>(n).map(|t| (t.base, t.count)).collect::<Vec<_>>();
        assert_eq!(all(0), []);
        assert_eq!(all(3), [(0, 3)]);
        assert_eq!(all(8), [(0, 4), (4, 4)]);
        assert_eq!(all(9), [(0, 4), (4, 4), (8, 1)]);
        let last = Tile { base: 8, count: 1 };
        assert_eq!(
            (0..4).map(|t| last.row(t)).collect::<Vec<_>>(),
            [8, 8, 8, 8]
        );
        let full = Tile { base: 4, count: 4 };
        assert_eq!(
            (0..4).map(|t| full.row(t)).collect::<Vec<_>>(),
            [4, 5, 6, 7]
        );
        assert_eq!(tiles::<1>(3).count(), 3);
    }
}
