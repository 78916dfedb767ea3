//! The MLP with its folded LayerNorm: the borrowed weights ([`Mlp`]), the
//! same checked as fixed-size rows (`Weights`), and the layers every kernel
//! body runs on a tile of rows in registers (`layer`, `hidden`, `rest`).

use crate::simd::Lanes;
use crate::{KernelError, L, Row, bad};

/// Weights of one MLP with its folded LayerNorm (crate docs), borrowed.
#[derive(Debug, Clone, Copy)]
pub struct Mlp<'a> {
    /// First layer `[in, 16]` row-major (`in` = D + 1 for the encoder, 16 for an edge block).
    pub w1: &'a [f32],
    /// First layer's bias `[16]` (the encoder's; an edge block's is inside its receiver projection).
    pub b1: &'a [f32],
    /// Second layer `[16, 16]`.
    pub w2: &'a [f32],
    /// Second layer's bias `[16]`.
    pub b2: &'a [f32],
    /// Third layer `[16, 16]` (centred: the LayerNorm's mean is folded in).
    pub w3: &'a [f32],
    /// Third layer's bias `[16]`.
    pub b3: &'a [f32],
    /// One-column variance weights `k` `[16]`.
    pub kvar: &'a [f32],
    /// The variance's `ε`.
    pub eps: f32,
}

/// The weights as fixed-size rows, checked.
pub(crate) struct Weights {
    pub(crate) w1: Vec<Row>,
    pub(crate) b1: Row,
    pub(crate) w2: [Row; L],
    pub(crate) b2: Row,
    pub(crate) w3: [Row; L],
    pub(crate) b3: Row,
    pub(crate) kvar: Row,
    pub(crate) eps: f32,
}

pub(crate) fn rows(field: &'static str, w: &[f32], n: usize) -> Result<Vec<Row>, KernelError> {
    if w.len() != n * L {
        return Err(bad(
            field,
            format!("expected {n} x {L} values, got {}", w.len()),
        ));
    }
    Ok(w.chunks_exact(L)
        .map(|c| c.try_into().expect("chunk of L"))
        .collect())
}

fn row(field: &'static str, v: &[f32]) -> Result<Row, KernelError> {
    v.try_into()
        .map_err(|_| bad(field, format!("expected {L} values, got {}", v.len())))
}

fn square(field: &'static str, w: &[f32]) -> Result<[Row; L], KernelError> {
    let r = rows(field, w, L)?;
    Ok(std::array::from_fn(|i| r[i]))
}

impl Weights {
    pub(crate) fn new(m: &Mlp<'_>, inputs: usize) -> Result<Self, KernelError> {
        let w = Weights {
            w1: rows("w1", m.w1, inputs)?,
            b1: row("b1", m.b1)?,
            w2: square("w2", m.w2)?,
            b2: row("b2", m.b2)?,
            w3: square("w3", m.w3)?,
            b3: row("b3", m.b3)?,
            kvar: row("kvar", m.kvar)?,
            eps: m.eps,
        };
        let all = [&w.b1[..], &w.b2, &w.b3, &w.kvar].into_iter().flatten();
        let mats = w.w1.iter().chain(&w.w2).chain(&w.w3).flatten();
        if !all
            .chain(mats)
            .chain(std::iter::once(&w.eps))
            .all(|v| v.is_finite())
        {
            return Err(bad("weights", "must be finite"));
        }
        Ok(w)
    }
}

/// `y[t] += x[t] · w` for a tile of `T` rows; `x[t]` holds `K` inputs in
/// memory, broadcast one at a time, and the accumulators stay in registers.
#[inline(always)]
pub(crate) unsafe fn layer<S: Lanes, const T: usize, const K: usize>(
    x: &[[f32; K]; T],
    w: &[Row],
    mut y: [S::R; T],
) -> [S::R; T] {
    for (k, wk) in w.iter().enumerate().take(K) {
        // SAFETY: the caller runs with `S`'s instruction set; rows are L long.
        unsafe {
            let wv = S::load(wk);
            for t in 0..T {
                y[t] = S::madd(x[t][k], wv, y[t]);
            }
        }
    }
    y
}

/// Layers 2 and 3 from the first layer's pre-activation:
/// `relu(relu(y) W₂ + b₂) W₃ + b₃` (the decoder's output; the others' before the LayerNorm).
#[inline(always)]
pub(crate) unsafe fn hidden<S: Lanes, const T: usize>(w: &Weights, y: [S::R; T]) -> [S::R; T] {
    // SAFETY: the caller runs with `S`'s instruction set; every row is L long.
    unsafe {
        let mut buf = [[0.0f32; L]; T];
        for t in 0..T {
            S::store(&mut buf[t], S::relu(y[t]));
        }
        let z = layer::<S, T, L>(&buf, &w.w2, [S::load(&w.b2); T]);
        for t in 0..T {
            S::store(&mut buf[t], S::relu(z[t]));
        }
        layer::<S, T, L>(&buf, &w.w3, [S::load(&w.b3); T])
    }
}

/// Layers 2 and 3 and the folded LayerNorm from the first layer's pre-activation.
#[inline(always)]
pub(crate) unsafe fn rest<S: Lanes, const T: usize>(w: &Weights, y: [S::R; T]) -> [S::R; T] {
    // SAFETY: the caller runs with `S`'s instruction set; every row is L long.
    unsafe {
        let o = hidden::<S, T>(w, y);
        let k = S::load(&w.kvar);
        let mut out = o;
        for t in 0..T {
            out[t] = S::norm(o[t], k, w.eps); // a loop, not `map`: a closure would not be inlined into the copy
        }
        out
    }
}
