//! The decoder's body: the acceleration `MLP(h)`, without LayerNorm (the
//! Euler step is the entry point's).

use super::{copies, tiles};
use crate::L;
use crate::mlp::{Weights, hidden, layer};
use crate::simd::{Isa, Lanes, Portable};

/// The decoder's MLP over the part's nodes, `T` at a time: `relu(relu(h W₁ + b₁) W₂ + b₂) W₃ + b₃`
/// with `W₃`, `b₃` padded to [`L`] columns; the first `dim` of each row go to `acc`.
#[inline(always)]
unsafe fn dec<S: Lanes, const T: usize>(w: &Weights, h: &[f32], dim: usize, acc: &mut [f32]) {
    let n = h.len() / L;
    for tile in tiles::<T>(n) {
        let mut x = [[0.0f32; L]; T];
        for (t, xt) in x.iter_mut().enumerate() {
            let i = tile.row(t);
            xt.copy_from_slice(&h[i * L..(i + 1) * L]);
        }
        // SAFETY: the caller runs with `S`'s instruction set; every row read or written is L long.
        unsafe {
            let o = hidden::<S, T>(w, layer::<S, T, L>(&x, &w.w1, [S::load(&w.b1); T]));
            let mut row = [0.0f32; L];
            for t in 0..tile.count {
                S::store(&mut row, o[t]);
                let i = tile.base + t;
                acc[i * dim..(i + 1) * dim].copy_from_slice(&row[..dim]);
            }
        }
    }
}

copies!(dec, dec_avx2, dec_avx512, (w: &Weights, h: &[f32], dim: usize, acc: &mut [f32]));

/// Runs the decoder's MLP with the copy `isa`, which the CPU must have ([`isa`](crate::isa) checks it).
pub(crate) fn run(isa: Isa, w: &Weights, h: &[f32], dim: usize, acc: &mut [f32]) {
    // SAFETY: the callers pass `isa()` (or, in the tests, a copy it allows), so the CPU has the copy's features.
    unsafe {
        match isa {
            #[cfg(target_arch = "x86_64")]
            Isa::Avx512 => dec_avx512(w, h, dim, acc),
            #[cfg(target_arch = "x86_64")]
            Isa::Avx2 => dec_avx2(w, h, dim, acc),
            _ => dec::<Portable, 1>(w, h, dim, acc),
        }
    }
}
