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

// One concept a module; this file holds the public entry points with their
// checks of the arguments:
// - `simd`: the `Lanes` trait (a latent row in registers) with its portable,
//   AVX2 and AVX-512 implementations, and `Isa`, the copy this CPU runs;
// - `mlp`: `Mlp`, its checked `Weights` and the layers on a tile of rows;
// - `parallel`: `ParallelFor`, the fixed parts of each kernel and the
//   output slices they write;
// - `kernels`: one body per kernel, its compiled copies and the dispatch to
//   them, with the tile loop they share;
// - `testing`: what the tests share.
mod kernels;
mod mlp;
mod parallel;
mod simd;
#[cfg(test)]
mod testing;

pub use kernels::node_block::NODE_IN;
pub use kernels::node_encoder::MAX_NODE_FEATURES;
pub use mlp::Mlp;
pub use parallel::{PART_EDGES, PART_NODES, ParallelFor, Serial};
pub use simd::{Isa, isa, uses_fma};

use kernels::edge_block::Block;
use kernels::node_encoder::Features;
use mlp::{Weights, rows};
use parallel::{block_parts, encoder_parts, node_parts, slices, slices_of};

/// Latent width the kernels are compiled for.
pub const L: usize = 16;

/// A latent row, `L` values.
type Row = [f32; L];

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

/// The edge encoder (module docs): `displacement` `[E, D]` and `distance`
/// `[E]` (float32, the radius graph's; D = `dim` ∈ {2, 3}) →
/// `out` `[E, 16]`, with `mlp.w1` of shape `[D + 1, 16]`, computed
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
        kernels::edge_encoder::run(isa, &w, dim, disp, dist, &mut o);
    });
    Ok(())
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
        kernels::edge_block::run(isa, &w, &b, &mut o, &mut a);
    });
    Ok(())
}

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
        kernels::node_block::run(
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
        kernels::node_encoder::run(isa, &w, &f, parts[p].clone(), &mut o);
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
        kernels::decoder::run(isa, &w, hp, dim, &mut a);
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

#[cfg(test)]
mod tests {
    use super::*;
    use crate::testing::{mlp, owned};

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
