//! Fused kernels of the shipped GNS inference graph (latent width 16).
//!
//! The compiled inference graph (`hybridmpm.neural.compile`, layout
//! `compiled-3`; paper App. A, Sanchez-Gonzalez et al. 2020) runs every
//! edge-sized stage as a chain of onnxruntime operators, each one a pass over
//! an `[E, 16]` array in memory: two `Gather`s, an `Add`, three `Gemm`s with
//! their `Relu`s, five folded-LayerNorm operators, the residual `Add` and the
//! `ScatterND` sum over receivers. At width 16 every pass costs a few
//! nanoseconds per edge whatever it computes, so the chain, not the
//! arithmetic, bounds a step (docs/neural.md, "What bounds it"). The
//! kernels here do the same arithmetic in one pass, a tile of rows at a
//! time in registers:
//!
//! * [`edge_encoder`]: `ε = LN(MLP([d, |d|]))` from each edge's displacement
//!   `d` (D = 2 or 3) and distance, the edge encoder;
//! * [`edge_block`]: one message-passing step's edge update
//!   `e' = e + LN(MLP(e W_e + (h W_r + b)[r] + (h W_s)[s]))` together with
//!   its sum over receivers `agg[i] = Σ_{r(k) = i} e'_k` (the first layer
//!   factored: the node projections `h W_r + b` and `h W_s` are computed on
//!   the nodes, outside, and gathered here);
//! * [`node_block`]: the node update `h' = h + LN(MLP([h, agg, degree]))`;
//! * [`node_encoder`]: the node features from the position history and
//!   `h = LN(MLP(features) + table[type])`;
//! * [`decoder`]: the acceleration `MLP(h)` and the Euler step.
//!
//! The MLPs are the graph's: `x → relu(x W₁ + b₁) → relu(· W₂ + b₂) → · W₃ + b₃`
//! with row-major `[in, 16]` weights, and the LayerNorm is the graph's folded
//! one: the centring and the gain are already in `W₃`, `b₃` and in the next
//! layers, so what is left is `z / sqrt(Σ_j k_j z_j² + ε)` with the graph's
//! one-column variance weights `k` and `ε`.
//!
//! **Numerics.** The same operations as the graph in float32, but not in the
//! same order (the dot products are summed in another order, with fused
//! multiply-adds where the CPU has them), so the results agree with
//! onnxruntime's to float32 rounding, not bit for bit; the sum over
//! receivers adds the edges in edge order, as `ScatterND` does on one
//! thread. Each kernel cuts its rows into fixed parts run by a
//! [`ParallelFor`] (onnxruntime's intra-op pool, or [`Serial`]); every row,
//! and every node's sum, is one part's, so the same inputs give the same
//! bits on any number of threads, on a given copy (AVX-512, AVX2 + FMA or
//! portable, picked from the CPU at run time).
//!
//! Safe Rust except the run-time dispatch to the SIMD copies.

#![deny(unsafe_op_in_unsafe_fn)]
// The tile loops index several fixed-size arrays by the same lane `t` or column `j`.
#![allow(clippy::needless_range_loop)]

/// Latent width the kernels are compiled for.
pub const L: usize = 16;

/// An invalid argument; the message names the field.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("{field}: {message}")]
pub struct KernelError {
    /// The offending argument.
    pub field: &'static str,
    /// What is wrong with it.
    pub message: String,
}

fn bad(field: &'static str, message: impl Into<String>) -> KernelError {
    KernelError {
        field,
        message: message.into(),
    }
}

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

/// The edge ranges of the encoder's parts.
fn encoder_parts(e: usize) -> Vec<std::ops::Range<usize>> {
    (0..e.div_ceil(PART_EDGES).max(1))
        .map(|p| p * PART_EDGES..((p + 1) * PART_EDGES).min(e))
        .collect()
}

/// The parts of an edge block over `n` nodes: `(edges, nodes)` ranges, each
/// part's receivers inside its node range, the node ranges covering `0..n`
/// without overlap (so each part zeroes and sums its own slice of `agg`, and
/// every node's sum is one part's, in edge order). Receivers not sorted
/// (the radius graph sorts them) make one part.
fn block_parts(
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

/// `out` cut into consecutive slices of `lens[p] · L` values, each behind
/// its own lock (the parts write disjoint slices; the locks are never contended).
fn slices(out: &mut [f32], lens: impl Iterator<Item = usize>) -> Vec<std::sync::Mutex<&mut [f32]>> {
    slices_of(out, L, lens)
}

/// Weights of one MLP with its folded LayerNorm (module docs), borrowed.
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

type Row = [f32; L];

/// The weights as fixed-size rows, checked.
struct Weights {
    w1: Vec<Row>,
    b1: Row,
    w2: [Row; L],
    b2: Row,
    w3: [Row; L],
    b3: Row,
    kvar: Row,
    eps: f32,
}

fn rows(field: &'static str, w: &[f32], n: usize) -> Result<Vec<Row>, KernelError> {
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
    fn new(m: &Mlp<'_>, inputs: usize) -> Result<Self, KernelError> {
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

/// The inputs of one part of an edge block (all of it on one thread): its
/// edges' latents, receivers and senders, the whole node projections, and
/// the first node of its slice of `agg` (its receivers are `node0` on).
struct Block<'a> {
    e: &'a [f32],
    hr: &'a [f32],
    hs: &'a [f32],
    receivers: &'a [usize],
    senders: &'a [usize],
    node0: usize,
}

/// A latent row in registers and the few operations the kernels need. One
/// implementation per instruction set; the kernels below are written once,
/// over this trait, and compiled into each copy (the copy's function enables
/// the target features, and everything here is inlined into it).
///
/// # Safety
/// The methods may use the instruction set of their implementation: call
/// them only from a function compiled with it, on a CPU that has it. `load`
/// and `store` need slices of at least [`L`] values.
unsafe trait Lanes {
    /// A row of [`L`] values.
    type R: Copy;
    unsafe fn zero() -> Self::R;
    unsafe fn load(p: &[f32]) -> Self::R;
    unsafe fn store(p: &mut [f32], r: Self::R);
    unsafe fn add(a: Self::R, b: Self::R) -> Self::R;
    unsafe fn relu(a: Self::R) -> Self::R;
    /// `acc + x · w` (every lane of `w` times the scalar `x`).
    unsafe fn madd(x: f32, w: Self::R, acc: Self::R) -> Self::R;
    /// The folded LayerNorm of `o`: `o / sqrt(Σ_j k_j o_j² + eps)`.
    unsafe fn norm(o: Self::R, k: Self::R, eps: f32) -> Self::R;
}

/// Plain Rust, no FMA: the copy for any CPU.
struct Portable;

// SAFETY: plain Rust; `load` and `store` index the first L values (checked).
unsafe impl Lanes for Portable {
    type R = Row;
    #[inline(always)]
    unsafe fn zero() -> Row {
        [0.0; L]
    }
    #[inline(always)]
    unsafe fn load(p: &[f32]) -> Row {
        p[..L].try_into().expect("a row of L values")
    }
    #[inline(always)]
    unsafe fn store(p: &mut [f32], r: Row) {
        p[..L].copy_from_slice(&r);
    }
    #[inline(always)]
    unsafe fn add(a: Row, b: Row) -> Row {
        std::array::from_fn(|j| a[j] + b[j])
    }
    #[inline(always)]
    unsafe fn relu(a: Row) -> Row {
        a.map(|v| v.max(0.0))
    }
    #[inline(always)]
    unsafe fn madd(x: f32, w: Row, acc: Row) -> Row {
        std::array::from_fn(|j| x * w[j] + acc[j])
    }
    #[inline(always)]
    unsafe fn norm(o: Row, k: Row, eps: f32) -> Row {
        let var: f32 = (0..L).map(|j| o[j] * o[j] * k[j]).sum();
        let std = (var + eps).sqrt();
        o.map(|v| v / std)
    }
}

/// AVX2 + FMA: a row is two 8-lane registers.
#[cfg(target_arch = "x86_64")]
struct Avx2;

#[cfg(target_arch = "x86_64")]
// SAFETY: AVX/AVX2/FMA intrinsics, used only inside `#[target_feature(enable = "avx,avx2,fma")]` copies; rows of L values.
unsafe impl Lanes for Avx2 {
    type R = (std::arch::x86_64::__m256, std::arch::x86_64::__m256);
    #[inline(always)]
    unsafe fn zero() -> Self::R {
        use std::arch::x86_64::*;
        unsafe { (_mm256_setzero_ps(), _mm256_setzero_ps()) }
    }
    #[inline(always)]
    unsafe fn load(p: &[f32]) -> Self::R {
        use std::arch::x86_64::*;
        assert!(p.len() >= L);
        unsafe {
            (
                _mm256_loadu_ps(p.as_ptr()),
                _mm256_loadu_ps(p.as_ptr().add(8)),
            )
        }
    }
    #[inline(always)]
    unsafe fn store(p: &mut [f32], r: Self::R) {
        use std::arch::x86_64::*;
        assert!(p.len() >= L);
        unsafe {
            _mm256_storeu_ps(p.as_mut_ptr(), r.0);
            _mm256_storeu_ps(p.as_mut_ptr().add(8), r.1);
        }
    }
    #[inline(always)]
    unsafe fn add(a: Self::R, b: Self::R) -> Self::R {
        use std::arch::x86_64::*;
        unsafe { (_mm256_add_ps(a.0, b.0), _mm256_add_ps(a.1, b.1)) }
    }
    #[inline(always)]
    unsafe fn relu(a: Self::R) -> Self::R {
        use std::arch::x86_64::*;
        unsafe {
            let z = _mm256_setzero_ps();
            (_mm256_max_ps(a.0, z), _mm256_max_ps(a.1, z))
        }
    }
    #[inline(always)]
    unsafe fn madd(x: f32, w: Self::R, acc: Self::R) -> Self::R {
        use std::arch::x86_64::*;
        unsafe {
            let b = _mm256_set1_ps(x);
            (
                _mm256_fmadd_ps(b, w.0, acc.0),
                _mm256_fmadd_ps(b, w.1, acc.1),
            )
        }
    }
    #[inline(always)]
    unsafe fn norm(o: Self::R, k: Self::R, eps: f32) -> Self::R {
        use std::arch::x86_64::*;
        unsafe {
            let s = _mm256_fmadd_ps(
                _mm256_mul_ps(o.0, o.0),
                k.0,
                _mm256_mul_ps(_mm256_mul_ps(o.1, o.1), k.1),
            );
            let h = _mm_add_ps(_mm256_castps256_ps128(s), _mm256_extractf128_ps(s, 1));
            let h = _mm_add_ps(h, _mm_movehl_ps(h, h));
            let h = _mm_add_ss(h, _mm_shuffle_ps(h, h, 1));
            let d = _mm256_broadcastss_ps(_mm_sqrt_ss(_mm_add_ss(h, _mm_set_ss(eps))));
            (_mm256_div_ps(o.0, d), _mm256_div_ps(o.1, d))
        }
    }
}

/// AVX-512F: a row is one 16-lane register.
#[cfg(target_arch = "x86_64")]
struct Avx512;

#[cfg(target_arch = "x86_64")]
// SAFETY: AVX-512F intrinsics, used only inside `#[target_feature(enable = "avx512f")]` copies; rows of L values.
unsafe impl Lanes for Avx512 {
    type R = std::arch::x86_64::__m512;
    #[inline(always)]
    unsafe fn zero() -> Self::R {
        unsafe { std::arch::x86_64::_mm512_setzero_ps() }
    }
    #[inline(always)]
    unsafe fn load(p: &[f32]) -> Self::R {
        assert!(p.len() >= L);
        unsafe { std::arch::x86_64::_mm512_loadu_ps(p.as_ptr()) }
    }
    #[inline(always)]
    unsafe fn store(p: &mut [f32], r: Self::R) {
        assert!(p.len() >= L);
        unsafe { std::arch::x86_64::_mm512_storeu_ps(p.as_mut_ptr(), r) }
    }
    #[inline(always)]
    unsafe fn add(a: Self::R, b: Self::R) -> Self::R {
        unsafe { std::arch::x86_64::_mm512_add_ps(a, b) }
    }
    #[inline(always)]
    unsafe fn relu(a: Self::R) -> Self::R {
        use std::arch::x86_64::*;
        unsafe { _mm512_max_ps(a, _mm512_setzero_ps()) }
    }
    #[inline(always)]
    unsafe fn madd(x: f32, w: Self::R, acc: Self::R) -> Self::R {
        use std::arch::x86_64::*;
        unsafe { _mm512_fmadd_ps(_mm512_set1_ps(x), w, acc) }
    }
    #[inline(always)]
    unsafe fn norm(o: Self::R, k: Self::R, eps: f32) -> Self::R {
        use std::arch::x86_64::*;
        unsafe {
            let var = _mm512_reduce_add_ps(_mm512_mul_ps(_mm512_mul_ps(o, o), k));
            _mm512_div_ps(o, _mm512_set1_ps((var + eps).sqrt()))
        }
    }
}

/// `y[t] += x[t] · w` for a tile of `T` rows; `x[t]` holds `K` inputs in
/// memory, broadcast one at a time, and the accumulators stay in registers.
#[inline(always)]
unsafe fn layer<S: Lanes, const T: usize, const K: usize>(
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
unsafe fn hidden<S: Lanes, const T: usize>(w: &Weights, y: [S::R; T]) -> [S::R; T] {
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
unsafe fn rest<S: Lanes, const T: usize>(w: &Weights, y: [S::R; T]) -> [S::R; T] {
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
    let mut base = 0;
    while base < e {
        let count = T.min(e - base);
        let mut x = [[0.0f32; K]; T];
        for (t, xt) in x.iter_mut().enumerate() {
            let k = base + t.min(count - 1);
            xt[..d].copy_from_slice(&disp[k * d..(k + 1) * d]);
            xt[d] = dist[k];
        }
        // SAFETY: the caller runs with `S`'s instruction set; every row read or written is L long.
        unsafe {
            let y = rest::<S, T>(w, layer::<S, T, K>(&x, &w.w1, [S::load(&w.b1); T]));
            for t in 0..count {
                S::store(&mut out[(base + t) * L..(base + t + 1) * L], y[t]);
            }
        }
        base += count;
    }
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
    let mut base = 0;
    while base < e {
        let count = T.min(e - base);
        // a full tile's edge latents are read in place; the last one, padded by
        // repeating its last edge, from a copy
        let x: &[[f32; L]; T] = match b.e[base * L..].as_chunks::<L>().0.get(..T) {
            Some(rows) if count == T => rows.try_into().expect("T rows"),
            _ => {
                for (t, row) in pad.iter_mut().enumerate() {
                    let k = base + t.min(count - 1);
                    row.copy_from_slice(&b.e[k * L..(k + 1) * L]);
                }
                &pad
            }
        };
        // SAFETY: the caller runs with `S`'s instruction set; indices were checked against N; rows are L long.
        unsafe {
            let mut y = [S::zero(); T];
            for t in 0..T {
                let k = base + t.min(count - 1);
                let (r, s) = (b.receivers[k], b.senders[k]);
                y[t] = S::add(
                    S::load(&b.hr[r * L..(r + 1) * L]),
                    S::load(&b.hs[s * L..(s + 1) * L]),
                );
            }
            let y = rest::<S, T>(w, layer::<S, T, L>(x, &w.w1, y));
            for t in 0..count {
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
        base += count;
    }
    if current != usize::MAX {
        // SAFETY: as above.
        unsafe { S::store(&mut agg[current * L..(current + 1) * L], sum) };
    }
}

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
    let mut base = 0;
    while base < n {
        let count = T.min(n - base);
        let mut x = [[0.0f32; NODE_IN]; T];
        for (t, xt) in x.iter_mut().enumerate() {
            let i = base + t.min(count - 1);
            xt[..L].copy_from_slice(&h[i * L..(i + 1) * L]);
            xt[L..2 * L].copy_from_slice(&agg[i * L..(i + 1) * L]);
            xt[2 * L] = degree[i];
        }
        // SAFETY: the caller runs with `S`'s instruction set; every row read or written is L long.
        unsafe {
            let y = rest::<S, T>(w, layer::<S, T, NODE_IN>(&x, &w.w1, [S::load(&w.b1); T]));
            for t in 0..count {
                let i = base + t;
                let v = S::add(S::load(&x[t][..L]), y[t]);
                S::store(&mut out[i * L..(i + 1) * L], v);
            }
        }
        base += count;
    }
}

/// Most node features a [`node_encoder`] takes (velocities and walls): `(T − 1)·D + 2D ≤ 32`.
pub const MAX_NODE_FEATURES: usize = 32;

/// The node-encoder inputs the kernel reads, checked.
struct Features<'a> {
    positions: &'a [f32],
    types: &'a [usize],
    lower: &'a [f32],
    upper: &'a [f32],
    inv_w: f32,
    table: &'a [Row],
    t_in: usize,
    dim: usize,
    n: usize,
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
    let mut base = 0;
    while base < n {
        let count = T.min(n - base);
        let mut x = [[0.0f32; MAX_NODE_FEATURES]; T];
        for (t, xt) in x.iter_mut().enumerate() {
            f.row(range.start + base + t.min(count - 1), xt);
        }
        // SAFETY: the caller runs with `S`'s instruction set; every row read or written is L long.
        unsafe {
            let mut y = layer::<S, T, MAX_NODE_FEATURES>(&x, &w.w1, [S::load(&w.b1); T]);
            for t in 0..T {
                let ty = f.types[range.start + base + t.min(count - 1)];
                y[t] = S::add(y[t], S::load(&f.table[ty]));
            }
            let y = rest::<S, T>(w, y);
            for t in 0..count {
                S::store(&mut out[(base + t) * L..(base + t + 1) * L], y[t]);
            }
        }
        base += count;
    }
}

/// The decoder's MLP over the part's nodes, `T` at a time: `relu(relu(h W₁ + b₁) W₂ + b₂) W₃ + b₃`
/// with `W₃`, `b₃` padded to [`L`] columns; the first `dim` of each row go to `acc`.
#[inline(always)]
unsafe fn dec<S: Lanes, const T: usize>(w: &Weights, h: &[f32], dim: usize, acc: &mut [f32]) {
    let n = h.len() / L;
    let mut base = 0;
    while base < n {
        let count = T.min(n - base);
        let mut x = [[0.0f32; L]; T];
        for (t, xt) in x.iter_mut().enumerate() {
            let i = base + t.min(count - 1);
            xt.copy_from_slice(&h[i * L..(i + 1) * L]);
        }
        // SAFETY: the caller runs with `S`'s instruction set; every row read or written is L long.
        unsafe {
            let o = hidden::<S, T>(w, layer::<S, T, L>(&x, &w.w1, [S::load(&w.b1); T]));
            let mut row = [0.0f32; L];
            for t in 0..count {
                S::store(&mut row, o[t]);
                let i = base + t;
                acc[i * dim..(i + 1) * dim].copy_from_slice(&row[..dim]);
            }
        }
        base += count;
    }
}

/// The compiled copies: each enables its instruction set and instantiates the kernels.
#[cfg(target_arch = "x86_64")]
mod copies {
    use super::{Avx2, Avx512, Block, Features, Weights};

    /// `$name`: the kernel `$kernel` compiled with the target features
    /// `$features`, on `$lanes` rows `$tile` at a time.
    macro_rules! copy {
        ($name:ident, $features:literal, $lanes:ty, $tile:literal, $kernel:ident, ($($arg:ident: $ty:ty),*)) => {
            #[target_feature(enable = $features)]
            pub(super) fn $name($($arg: $ty),*) {
                // SAFETY: the copy's features are enabled here (the callers check the CPU).
                unsafe { super::$kernel::<$lanes, $tile>($($arg),*) }
            }
        };
    }

    #[target_feature(enable = "avx,avx2,fma")]
    pub(super) fn encoder_avx2<const K: usize>(
        w: &Weights,
        disp: &[f32],
        dist: &[f32],
        out: &mut [f32],
    ) {
        // SAFETY: AVX2 and FMA are enabled here (the callers check the CPU).
        unsafe { super::encoder::<Avx2, 4, K>(w, disp, dist, out) }
    }

    #[target_feature(enable = "avx512f")]
    pub(super) fn encoder_avx512<const K: usize>(
        w: &Weights,
        disp: &[f32],
        dist: &[f32],
        out: &mut [f32],
    ) {
        // SAFETY: AVX-512F is enabled here (the callers check the CPU).
        unsafe { super::encoder::<Avx512, 8, K>(w, disp, dist, out) }
    }

    copy!(block_avx2, "avx,avx2,fma", Avx2, 4, block, (w: &Weights, b: &Block<'_>, out: &mut [f32], agg: &mut [f32]));
    copy!(block_avx512, "avx512f", Avx512, 8, block, (w: &Weights, b: &Block<'_>, out: &mut [f32], agg: &mut [f32]));
    copy!(node_avx2, "avx,avx2,fma", Avx2, 4, node, (w: &Weights, h: &[f32], agg: &[f32], deg: &[f32], out: &mut [f32]));
    copy!(node_avx512, "avx512f", Avx512, 8, node, (w: &Weights, h: &[f32], agg: &[f32], deg: &[f32], out: &mut [f32]));
    copy!(node_enc_avx2, "avx,avx2,fma", Avx2, 4, node_enc, (w: &Weights, f: &Features<'_>, r: std::ops::Range<usize>, out: &mut [f32]));
    copy!(node_enc_avx512, "avx512f", Avx512, 8, node_enc, (w: &Weights, f: &Features<'_>, r: std::ops::Range<usize>, out: &mut [f32]));
    copy!(dec_avx2, "avx,avx2,fma", Avx2, 4, dec, (w: &Weights, h: &[f32], dim: usize, acc: &mut [f32]));
    copy!(dec_avx512, "avx512f", Avx512, 8, dec, (w: &Weights, h: &[f32], dim: usize, acc: &mut [f32]));
}

/// The instruction set the kernels run with, chosen once per call from the
/// CPU and the ceiling `HYBRIDMPM_ISA` sets (`hybridmpm-isa`'s vocabulary:
/// `baseline` forces the portable copy, `x86-64-v3` or `avx2` the AVX2 one
/// at most: for comparisons).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Isa {
    /// Plain Rust, no FMA.
    Portable,
    /// AVX2 + FMA, two 8-lane registers per latent row.
    Avx2,
    /// AVX-512F, one 16-lane register per latent row.
    Avx512,
}

/// The copy this CPU runs (see [`Isa`]).
pub fn isa() -> Isa {
    use hybridmpm_isa::{Level, cpu};
    let ceiling = Level::ceiling();
    if ceiling >= Level::X86_64V4 && cpu::avx512f() {
        Isa::Avx512
    } else if ceiling >= Level::X86_64V3 && cpu::avx2_fma() {
        Isa::Avx2
    } else {
        Isa::Portable
    }
}

/// Whether this CPU runs a copy with fused multiply-adds.
pub fn uses_fma() -> bool {
    isa() != Isa::Portable
}

/// The edge encoder (module docs): `displacement` `[E, D]` and `distance`
/// `[E]` (float32, the radius graph's; D = `dim` ∈ {2, 3}) →
/// `out` `[E, 16]`, with `mlp.w1` of shape `[D + 1, 16]`.
/// in parts of [`PART_EDGES`] edges run by `par` (the same bits for any `par`).
///
/// # Errors
/// [`KernelError`] naming `dim`, `displacement`, `out` or a weight for a
/// shape that does not fit, or `weights` for a non-finite weight.
pub fn edge_encoder(
    mlp: &Mlp<'_>,
    dim: usize,
    displacement: &[f32],
    distance: &[f32],
    out: &mut [f32],
    par: &dyn ParallelFor,
) -> Result<(), KernelError> {
    if dim != 2 && dim != 3 {
        return Err(bad("dim", format!("must be 2 or 3, got {dim}")));
    }
    let e = distance.len();
    if displacement.len() != e * dim {
        return Err(bad(
            "displacement",
            format!("expected {e} x {dim} values, got {}", displacement.len()),
        ));
    }
    if out.len() != e * L {
        return Err(bad(
            "out",
            format!("expected {e} x {L} values, got {}", out.len()),
        ));
    }
    let w = Weights::new(mlp, dim + 1)?;
    let (isa, parts) = (isa(), encoder_parts(e));
    let outs = slices(out, parts.iter().map(|r| r.len()));
    par.run(parts.len(), &|p| {
        let r = &parts[p];
        let mut o = outs[p].lock().unwrap_or_else(|e| e.into_inner());
        let (disp, dist) = (
            &displacement[r.start * dim..r.end * dim],
            &distance[r.clone()],
        );
        run_encoder(isa, &w, dim, disp, dist, &mut o);
    });
    Ok(())
}

/// Runs the edge encoder with the copy `isa`, which the CPU must have ([`isa`] checks it).
fn run_encoder(
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
            (Isa::Avx512, 2) => copies::encoder_avx512::<3>(w, displacement, distance, out),
            #[cfg(target_arch = "x86_64")]
            (Isa::Avx512, _) => copies::encoder_avx512::<4>(w, displacement, distance, out),
            #[cfg(target_arch = "x86_64")]
            (Isa::Avx2, 2) => copies::encoder_avx2::<3>(w, displacement, distance, out),
            #[cfg(target_arch = "x86_64")]
            (Isa::Avx2, _) => copies::encoder_avx2::<4>(w, displacement, distance, out),
            (_, 2) => encoder::<Portable, 1, 3>(w, displacement, distance, out),
            _ => encoder::<Portable, 1, 4>(w, displacement, distance, out),
        }
    }
}

/// One message-passing step's edge update and its sum over receivers
/// (module docs): edge latents `e` `[E, 16]`, node projections `hr`
/// (`h W_r + b`) and `hs` (`h W_s`) `[N, 16]`, `receivers` and `senders`
/// `[E]` (indices into the N nodes) → `out` `[E, 16]` (`e'`) and `agg`
/// `[N, 16]` (`Σ e'` over each node's in-edges, in edge order; zero for a
/// node without any). `mlp.w1` is `W_e` `[16, 16]`; `mlp.b1` is unused
/// (pass the zeros: the bias is inside `hr`). The work is cut into parts of
/// about [`PART_EDGES`] edges ending at receiver changes, run by `par`
/// ([`Serial`] on the calling thread); each node's sum is one part's, so the
/// result is the same bits for any `par`.
///
/// # Errors
/// [`KernelError`] naming `e`, `hs`, `senders`, `receivers`, `out`, `agg` or
/// a weight for a shape that does not fit or an index outside `[0, N)`.
#[allow(clippy::too_many_arguments)] // the operator's own inputs and outputs, one slice each
pub fn edge_block(
    mlp: &Mlp<'_>,
    e: &[f32],
    hr: &[f32],
    hs: &[f32],
    receivers: &[i64],
    senders: &[i64],
    out: &mut [f32],
    agg: &mut [f32],
    par: &dyn ParallelFor,
) -> Result<(), KernelError> {
    let ne = receivers.len();
    let n = hr.len() / L;
    if hr.len() != n * L {
        return Err(bad(
            "hr",
            format!("expected a multiple of {L} values, got {}", hr.len()),
        ));
    }
    if hs.len() != hr.len() {
        return Err(bad(
            "hs",
            format!("expected {n} x {L} values (as hr), got {}", hs.len()),
        ));
    }
    if senders.len() != ne {
        return Err(bad(
            "senders",
            format!(
                "expected {ne} indices (as receivers), got {}",
                senders.len()
            ),
        ));
    }
    if e.len() != ne * L || out.len() != ne * L {
        return Err(bad(
            if e.len() != ne * L { "e" } else { "out" },
            format!("expected {ne} x {L} values"),
        ));
    }
    if agg.len() != n * L {
        return Err(bad(
            "agg",
            format!("expected {n} x {L} values, got {}", agg.len()),
        ));
    }
    let index = |field: &'static str, v: &[i64]| -> Result<Vec<usize>, KernelError> {
        v.iter()
            .map(|&i| {
                usize::try_from(i)
                    .ok()
                    .filter(|&i| i < n)
                    .ok_or_else(|| bad(field, format!("index {i} outside [0, {n})")))
            })
            .collect()
    };
    let (receivers, senders) = (index("receivers", receivers)?, index("senders", senders)?);
    let w = Weights::new(mlp, L)?;
    let (isa, parts) = (isa(), block_parts(&receivers, n));
    let outs = slices(out, parts.iter().map(|(edges, _)| edges.len()));
    let aggs = slices(agg, parts.iter().map(|(_, nodes)| nodes.len()));
    par.run(parts.len(), &|p| {
        let (edges, nodes) = &parts[p];
        let b = Block {
            e: &e[edges.start * L..edges.end * L],
            hr,
            hs,
            receivers: &receivers[edges.clone()],
            senders: &senders[edges.clone()],
            node0: nodes.start,
        };
        let mut o = outs[p].lock().unwrap_or_else(|e| e.into_inner());
        let mut a = aggs[p].lock().unwrap_or_else(|e| e.into_inner());
        run_block(isa, &w, &b, &mut o, &mut a);
    });
    Ok(())
}

/// Runs the edge block with the copy `isa`, which the CPU must have ([`isa`] checks it).
fn run_block(isa: Isa, w: &Weights, b: &Block<'_>, out: &mut [f32], agg: &mut [f32]) {
    // SAFETY: the callers pass `isa()` (or, in the tests, a copy it allows), so the CPU has the copy's features.
    unsafe {
        match isa {
            #[cfg(target_arch = "x86_64")]
            Isa::Avx512 => copies::block_avx512(w, b, out, agg),
            #[cfg(target_arch = "x86_64")]
            Isa::Avx2 => copies::block_avx2(w, b, out, agg),
            _ => block::<Portable, 1>(w, b, out, agg),
        }
    }
}

/// Inputs of a node block's first layer: the node latent, its sum over in-edges and its in-degree.
pub const NODE_IN: usize = 2 * L + 1;

/// Nodes per part of [`node_block`] (fixed: the parts do not depend on the thread count).
pub const PART_NODES: usize = 256;

/// One message-passing step's node update (paper App. A; the graph's
/// `node_mlp` stage): `out = h + LN(MLP([h, agg, degree]))` for node latents
/// `h` `[N, 16]`, their sums over in-edges `agg` `[N, 16]` (from
/// [`edge_block`]) and in-degrees `degree` `[N]` (float32), with `mlp.w1`
/// of shape `[33, 16]` (rows in that order); `out` `[N, 16]`. Run in parts
/// of [`PART_NODES`] nodes by `par` (every row on its own: the same bits for
/// any `par`).
///
/// # Errors
/// [`KernelError`] naming `h`, `agg`, `out` or a weight for a shape that
/// does not fit.
pub fn node_block(
    mlp: &Mlp<'_>,
    h: &[f32],
    agg: &[f32],
    degree: &[f32],
    out: &mut [f32],
    par: &dyn ParallelFor,
) -> Result<(), KernelError> {
    let n = degree.len();
    for (field, v) in [("h", h.len()), ("agg", agg.len()), ("out", out.len())] {
        if v != n * L {
            return Err(bad(
                field,
                format!("expected {n} x {L} values (degree has {n}), got {v}"),
            ));
        }
    }
    let w = Weights::new(mlp, NODE_IN)?;
    let isa = isa();
    let parts = node_parts(n);
    let outs = slices(out, parts.iter().map(|r| r.len()));
    par.run(parts.len(), &|p| {
        let r = &parts[p];
        let rows = r.start * L..r.end * L;
        let mut o = outs[p].lock().unwrap_or_else(|e| e.into_inner());
        run_node(
            isa,
            &w,
            &h[rows.clone()],
            &agg[rows],
            &degree[r.clone()],
            &mut o,
        );
    });
    Ok(())
}

/// Runs the node block with the copy `isa`, which the CPU must have ([`isa`] checks it).
fn run_node(isa: Isa, w: &Weights, h: &[f32], agg: &[f32], deg: &[f32], out: &mut [f32]) {
    // SAFETY: the callers pass `isa()` (or, in the tests, a copy it allows), so the CPU has the copy's features.
    unsafe {
        match isa {
            #[cfg(target_arch = "x86_64")]
            Isa::Avx512 => copies::node_avx512(w, h, agg, deg, out),
            #[cfg(target_arch = "x86_64")]
            Isa::Avx2 => copies::node_avx2(w, h, agg, deg, out),
            _ => node::<Portable, 1>(w, h, agg, deg, out),
        }
    }
}

/// Splits `0..n` into parts of [`PART_NODES`] (fixed: independent of the thread count).
fn node_parts(n: usize) -> Vec<std::ops::Range<usize>> {
    (0..n.div_ceil(PART_NODES).max(1))
        .map(|p| p * PART_NODES..((p + 1) * PART_NODES).min(n))
        .collect()
}

/// Checks `positions` `[T, N, D]` against `n` nodes: returns `T`.
fn history_len(positions: &[f32], n: usize, dim: usize) -> Result<usize, KernelError> {
    if dim != 2 && dim != 3 {
        return Err(bad("dim", format!("must be 2 or 3, got {dim}")));
    }
    let per = n * dim;
    if per == 0 {
        return Ok(0);
    }
    if !positions.len().is_multiple_of(per) || positions.len() / per < 2 {
        return Err(bad(
            "positions",
            format!(
                "expected [T >= 2, {n}, {dim}] values, got {}",
                positions.len()
            ),
        ));
    }
    Ok(positions.len() / per)
}

/// The node encoder with its feature construction (the graph's `features`
/// and `node_encoder` stages; paper App. A, GNS node features): for
/// `positions` `[T, N, D]` (float32, oldest first) and `particle_type`
/// `[N]` (int64, rows of `table`), each node's features are its `T − 1`
/// position differences (the velocity normalisation is folded into `w1`),
/// then `(x − lower)·inv_w` and `(upper − x)·inv_w` of its last position
/// (`lower`, `upper` `[D]`), each clipped to [−1, 1]; then
/// `h = LN(MLP(features) + table[type])`, the type term added after the
/// first layer (`table` `[K, 16]`, the type embedding times the first
/// layer's rows), `mlp.w1` `[(T − 1)·D + 2D, 16]` (at most
/// [`MAX_NODE_FEATURES`] rows). `out` `[N, 16]`; run in parts of
/// [`PART_NODES`] by `par` (the same bits for any `par`).
///
/// # Errors
/// [`KernelError`] naming `dim`, `positions`, `particle_type` (a code
/// outside `[0, K)`), `lower`, `upper`, `inv_w`, `table`, `out` or a weight.
#[allow(clippy::too_many_arguments)] // the operator's own inputs and outputs, one slice each
pub fn node_encoder(
    mlp: &Mlp<'_>,
    dim: usize,
    positions: &[f32],
    particle_type: &[i64],
    lower: &[f32],
    upper: &[f32],
    inv_w: f32,
    table: &[f32],
    out: &mut [f32],
    par: &dyn ParallelFor,
) -> Result<(), KernelError> {
    let n = particle_type.len();
    let t_in = history_len(positions, n, dim)?;
    if out.len() != n * L {
        return Err(bad(
            "out",
            format!("expected {n} x {L} values, got {}", out.len()),
        ));
    }
    if n == 0 {
        return Ok(());
    }
    let features = (t_in - 1) * dim + 2 * dim;
    if features > MAX_NODE_FEATURES {
        return Err(bad(
            "positions",
            format!(
                "{t_in} steps of history in {dim}D make {features} features, more than {MAX_NODE_FEATURES}"
            ),
        ));
    }
    for (field, v) in [("lower", lower), ("upper", upper)] {
        if v.len() != dim || !v.iter().all(|x| x.is_finite()) {
            return Err(bad(
                field,
                format!("expected {dim} finite values, got {v:?}"),
            ));
        }
    }
    if !inv_w.is_finite() {
        return Err(bad("inv_w", format!("must be finite, got {inv_w}")));
    }
    let table = rows("table", table, table.len() / L)?;
    if !table.iter().flatten().all(|v| v.is_finite()) {
        return Err(bad("table", "must be finite"));
    }
    let types: Vec<usize> = particle_type
        .iter()
        .map(|&t| {
            usize::try_from(t)
                .ok()
                .filter(|&t| t < table.len())
                .ok_or_else(|| {
                    bad(
                        "particle_type",
                        format!("code {t} outside [0, {})", table.len()),
                    )
                })
        })
        .collect::<Result<_, _>>()?;
    let w = Weights::new(mlp, features)?;
    let f = Features {
        positions,
        types: &types,
        lower,
        upper,
        inv_w,
        table: &table,
        t_in,
        dim,
        n,
    };
    let (isa, parts) = (isa(), node_parts(n));
    let outs = slices(out, parts.iter().map(|r| r.len()));
    par.run(parts.len(), &|p| {
        let mut o = outs[p].lock().unwrap_or_else(|e| e.into_inner());
        run_node_enc(isa, &w, &f, parts[p].clone(), &mut o);
    });
    Ok(())
}

/// The decoder and the Euler step (the graph's `decoder` stage): `acc =
/// relu(relu(h W₁ + b₁) W₂ + b₂) W₃ + b₃` (output statistics folded;
/// `mlp.w3` `[16, D]`, `mlp.b3` `[D]`; `kvar`, `eps` unused) and `next =
/// (x_T + x_T) − x_{T−1} + acc`, or `x_T` for the particles whose type is
/// `kinematic` (obstacles), from `h` `[N, 16]`, `positions` `[T, N, D]`
/// and `particle_type` `[N]`; `acc` and `next` `[N, D]`. Run in parts of
/// [`PART_NODES`] by `par` (the same bits for any `par`).
///
/// # Errors
/// [`KernelError`] naming `dim`, `h`, `positions`, `acc`, `next` or a weight.
#[allow(clippy::too_many_arguments)] // the operator's own inputs and outputs, one slice each
pub fn decoder(
    mlp: &Mlp<'_>,
    dim: usize,
    h: &[f32],
    positions: &[f32],
    particle_type: &[i64],
    kinematic: i64,
    acc: &mut [f32],
    next: &mut [f32],
    par: &dyn ParallelFor,
) -> Result<(), KernelError> {
    let n = particle_type.len();
    let t_in = history_len(positions, n, dim)?;
    for (field, v, want) in [
        ("h", h.len(), n * L),
        ("acc", acc.len(), n * dim),
        ("next", next.len(), n * dim),
    ] {
        if v != want {
            return Err(bad(
                field,
                format!("expected {want} values ({n} nodes), got {v}"),
            ));
        }
    }
    if mlp.w3.len() != L * dim || mlp.b3.len() != dim {
        return Err(bad(
            "w3",
            format!("expected [{L}, {dim}] and a bias of {dim}"),
        ));
    }
    if n == 0 {
        return Ok(());
    }
    // the last layer padded to L columns, so that it runs as the others
    let mut w3 = vec![0.0f32; L * L];
    let mut b3 = vec![0.0f32; L];
    for k in 0..L {
        w3[k * L..k * L + dim].copy_from_slice(&mlp.w3[k * dim..(k + 1) * dim]);
    }
    b3[..dim].copy_from_slice(mlp.b3);
    let ones = [1.0f32; L];
    let padded = Mlp {
        w3: &w3,
        b3: &b3,
        kvar: &ones,
        eps: 1.0,
        ..*mlp
    };
    let w = Weights::new(&padded, L)?;
    let isa = isa();
    let parts = node_parts(n);
    let accs = slices_of(acc, dim, parts.iter().map(|r| r.len()));
    let nexts = slices_of(next, dim, parts.iter().map(|r| r.len()));
    par.run(parts.len(), &|p| {
        let r = &parts[p];
        let mut a = accs[p].lock().unwrap_or_else(|e| e.into_inner());
        let hp = &h[r.start * L..r.end * L];
        run_dec(isa, &w, hp, dim, &mut a);
        let mut x = nexts[p].lock().unwrap_or_else(|e| e.into_inner());
        let (last, prev) = ((t_in - 1) * n * dim, (t_in - 2) * n * dim);
        for (j, i) in r.clone().enumerate() {
            for k in 0..dim {
                let l = positions[last + i * dim + k];
                x[j * dim + k] = if particle_type[i] == kinematic {
                    l
                } else {
                    ((l + l) - positions[prev + i * dim + k]) + a[j * dim + k]
                };
            }
        }
    });
    Ok(())
}

/// Runs the node encoder with the copy `isa`, which the CPU must have ([`isa`] checks it).
fn run_node_enc(
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
            Isa::Avx512 => copies::node_enc_avx512(w, f, r, out),
            #[cfg(target_arch = "x86_64")]
            Isa::Avx2 => copies::node_enc_avx2(w, f, r, out),
            _ => node_enc::<Portable, 1>(w, f, r, out),
        }
    }
}

/// Runs the decoder's MLP with the copy `isa`, which the CPU must have ([`isa`] checks it).
fn run_dec(isa: Isa, w: &Weights, h: &[f32], dim: usize, acc: &mut [f32]) {
    // SAFETY: as above.
    unsafe {
        match isa {
            #[cfg(target_arch = "x86_64")]
            Isa::Avx512 => copies::dec_avx512(w, h, dim, acc),
            #[cfg(target_arch = "x86_64")]
            Isa::Avx2 => copies::dec_avx2(w, h, dim, acc),
            _ => dec::<Portable, 1>(w, h, dim, acc),
        }
    }
}

/// `out` cut into consecutive slices of `lens[p] · width` values, each behind its own lock.
fn slices_of(
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
    use super::*;

    /// A small deterministic generator (xorshift), values in [-1, 1).
    fn values(seed: u64, n: usize) -> Vec<f32> {
        let mut s = seed.wrapping_mul(0x9E37_79B9_7F4A_7C15) | 1;
        (0..n)
            .map(|_| {
                s ^= s << 13;
                s ^= s >> 7;
                s ^= s << 17;
                ((s >> 40) as f32 / (1u64 << 24) as f32) * 2.0 - 1.0
            })
            .collect()
    }

    struct Owned {
        w1: Vec<f32>,
        b1: Vec<f32>,
        w2: Vec<f32>,
        b2: Vec<f32>,
        w3: Vec<f32>,
        b3: Vec<f32>,
        kvar: Vec<f32>,
    }

    fn owned(inputs: usize, seed: u64) -> Owned {
        Owned {
            w1: values(seed, inputs * L),
            b1: values(seed + 1, L),
            w2: values(seed + 2, L * L),
            b2: values(seed + 3, L),
            w3: values(seed + 4, L * L),
            b3: values(seed + 5, L),
            kvar: values(seed + 6, L)
                .iter()
                .map(|v| v.abs() / L as f32)
                .collect(),
        }
    }

    fn mlp(o: &Owned) -> Mlp<'_> {
        Mlp {
            w1: &o.w1,
            b1: &o.b1,
            w2: &o.w2,
            b2: &o.b2,
            w3: &o.w3,
            b3: &o.b3,
            kvar: &o.kvar,
            eps: 1e-5,
        }
    }

    /// The graph's arithmetic, written the plain way in f64: one layer.
    fn dense(x: &[f64], w: &[f32], b: &[f32], relu: bool) -> Vec<f64> {
        (0..L)
            .map(|j| {
                let v = b[j] as f64
                    + x.iter()
                        .enumerate()
                        .map(|(k, &xk)| xk * w[k * L + j] as f64)
                        .sum::<f64>();
                if relu { v.max(0.0) } else { v }
            })
            .collect()
    }

    fn reference(o: &Owned, first: Vec<f64>) -> Vec<f64> {
        let h = dense(
            &first.iter().map(|v| v.max(0.0)).collect::<Vec<_>>(),
            &o.w2,
            &o.b2,
            true,
        );
        let z = dense(&h, &o.w3, &o.b3, false);
        let var: f64 = z
            .iter()
            .zip(&o.kvar)
            .map(|(v, k)| v * v * *k as f64)
            .sum::<f64>()
            + 1e-5;
        z.iter().map(|v| v / var.sqrt()).collect()
    }

    fn close(a: &[f32], b: &[f64]) {
        assert_eq!(a.len(), b.len());
        for (i, (x, y)) in a.iter().zip(b).enumerate() {
            assert!(
                (*x as f64 - y).abs() <= 2e-5 * (1.0 + y.abs()),
                "value {i}: {x} against {y}"
            );
        }
    }

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

    /// Runs the parts from last to first, spread over three threads.
    struct Threads;

    impl ParallelFor for Threads {
        fn run(&self, n: usize, f: &(dyn Fn(usize) + Sync)) {
            std::thread::scope(|s| {
                for t in 0..3 {
                    s.spawn(move || (0..n).rev().filter(|i| i % 3 == t).for_each(f));
                }
            });
        }
    }

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

    #[test]
    fn bad_arguments_are_refused_naming_the_field() {
        let o = owned(L, 1);
        let m = mlp(&o);
        let (hr, hs, e) = (vec![0.0f32; 2 * L], vec![0.0f32; 2 * L], vec![0.0f32; L]);
        let mut out = vec![0.0f32; L];
        let mut agg = vec![0.0f32; 2 * L];
        let err =
            edge_block(&m, &e, &hr, &hs, &[2], &[0], &mut out, &mut agg, &Serial).unwrap_err();
        assert_eq!(err.field, "receivers");
        let err =
            edge_block(&m, &e, &hr, &hs, &[0], &[-1], &mut out, &mut agg, &Serial).unwrap_err();
        assert_eq!(err.field, "senders");
        let err = edge_block(
            &m,
            &e,
            &hr,
            &hs[..L],
            &[0],
            &[0],
            &mut out,
            &mut agg,
            &Serial,
        )
        .unwrap_err();
        assert_eq!(err.field, "hs");
        let mut w2 = o.w2.clone();
        w2[3] = f32::NAN;
        let err = edge_block(
            &Mlp { w2: &w2, ..m },
            &e,
            &hr,
            &hs,
            &[0],
            &[0],
            &mut out,
            &mut agg,
            &Serial,
        )
        .unwrap_err();
        assert_eq!(err.field, "weights");
        let enc = owned(3, 2);
        let err = edge_encoder(&mlp(&enc), 4, &[0.0; 4], &[0.0], &mut out, &Serial).unwrap_err();
        assert_eq!(err.field, "dim");
        let err = edge_encoder(&mlp(&enc), 2, &[0.0; 3], &[0.0], &mut out, &Serial).unwrap_err();
        assert_eq!(err.field, "displacement");
        let err =
            edge_encoder(&mlp(&owned(4, 2)), 2, &[0.0; 2], &[0.0], &mut out, &Serial).unwrap_err();
        assert_eq!(err.field, "w1");
    }
}
