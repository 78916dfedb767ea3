//! Particle–grid transfers on any regular grid: p2g, g2p and advection with
//! the MLS-MPM quadratic B-spline ([`crate::kernel`]).
//!
//! These are the run-time halves of the learned grid model (a NeuralMPM-style
//! simulator, arXiv 2408.15753; `hybridmpm.train.grid` holds the torch
//! versions it is trained with, and the tests hold the two equal): particle
//! values are splatted onto a grid, a network maps grid to grid, and the
//! particles read the result back and move.
//!
//! A [`TransferGrid`] has `nodes` nodes per dimension at
//! `origin + i·spacing`, stored row-major (first axis slowest), `C` values
//! per node, channel fastest. A particle's stencil is the 3^D nodes from
//! `base = ⌊(x − origin)/spacing − 1/2⌋`, its base clamped to
//! `[0, nodes − 3]` (callers keep particles inside the grid). Everything is
//! f32 and serial: the same bits on any machine and thread count.

use crate::error::{MpmError, Result};
use crate::kernel::quadratic_weights;

/// Largest grid, in nodes in all (`nodes^D`), a transfer accepts.
pub const MAX_TRANSFER_NODES: usize = 1 << 24;

/// A regular grid of `nodes^D` nodes at `origin + i·spacing` [m].
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct TransferGrid<const D: usize> {
    /// Position of node 0 [m].
    pub origin: [f32; D],
    /// Node spacing per axis [m], > 0.
    pub spacing: [f32; D],
    /// Nodes per dimension, in [4, 4096] with `nodes^D ≤ MAX_TRANSFER_NODES`.
    pub nodes: usize,
}

impl<const D: usize> TransferGrid<D> {
    /// Checks the grid; errors name `origin`, `spacing` or `nodes`.
    pub fn validate(&self) -> Result<()> {
        if !(4..=4096).contains(&self.nodes)
            || self
                .nodes
                .checked_pow(D as u32)
                .is_none_or(|t| t > MAX_TRANSFER_NODES)
        {
            return Err(MpmError::invalid(
                "nodes",
                format!(
                    "must be in [4, 4096] with nodes^{D} <= {MAX_TRANSFER_NODES}, got {}",
                    self.nodes
                ),
            ));
        }
        if !self.origin.iter().all(|v| v.is_finite()) {
            return Err(MpmError::invalid("origin", "must be finite"));
        }
        if !self.spacing.iter().all(|v| v.is_finite() && *v > 0.0) {
            return Err(MpmError::invalid("spacing", "must be finite and > 0"));
        }
        Ok(())
    }

    /// Nodes in all, `nodes^D`.
    pub fn len(&self) -> usize {
        self.nodes.pow(D as u32)
    }

    /// Always false (a valid grid has at least 4^D nodes).
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// The 3^D stencil nodes (flat indices) and weights of a particle at `x`;
    /// returns how many (3^D). Weights are products over the axes in axis order.
    #[inline]
    fn stencil(&self, x: &[f32; D], node: &mut [usize; 27], weight: &mut [f32; 27]) -> usize {
        let g = self.nodes;
        let mut base = [0usize; D];
        let mut w = [[0.0f32; 3]; D];
        for d in 0..D {
            let u = (x[d] - self.origin[d]) / self.spacing[d];
            let b = (u - 0.5).floor();
            w[d] = quadratic_weights(u - b);
            base[d] = (b as i64).clamp(0, g as i64 - 3) as usize;
        }
        if D == 2 {
            let row = base[0] * g + base[1];
            for i in 0..3 {
                for j in 0..3 {
                    node[3 * i + j] = row + i * g + j;
                    weight[3 * i + j] = w[0][i] * w[1][j];
                }
            }
            return 9;
        }
        let k = 3usize.pow(D as u32);
        for s in 0..k {
            let mut rem = s;
            let mut digit = [0usize; D];
            for d in (0..D).rev() {
                digit[d] = rem % 3;
                rem /= 3;
            }
            let mut lin = 0usize;
            let mut wt = w[0][digit[0]];
            for d in 0..D {
                lin = lin * g + base[d] + digit[d];
                if d > 0 {
                    wt *= w[d][digit[d]];
                }
            }
            node[s] = lin;
            weight[s] = wt;
        }
        k
    }
}

fn check_positions<const D: usize>(field: &str, x: &[[f32; D]]) -> Result<()> {
    match x.iter().position(|p| !p.iter().all(|v| v.is_finite())) {
        Some(i) => Err(MpmError::invalid(
            field,
            format!("particle {i} has a non-finite coordinate"),
        )),
        None => Ok(()),
    }
}

/// p2g: `Σ_p w_pi · values_p` per node. `values` is `[N][C]` (flat,
/// `N·C` long); returns `[nodes^D][C]`. Errors: bad grid, `values` of
/// another length, non-finite positions.
pub fn p2g<const D: usize>(
    grid: &TransferGrid<D>,
    positions: &[[f32; D]],
    values: &[f32],
    channels: usize,
) -> Result<Vec<f32>> {
    grid.validate()?;
    check_positions("positions", positions)?;
    if channels == 0 || values.len() != positions.len() * channels {
        return Err(MpmError::invalid(
            "values",
            format!(
                "expected [{}, C] with C >= 1, got {} values for C = {channels}",
                positions.len(),
                values.len()
            ),
        ));
    }
    let mut out = vec![0.0f32; grid.len() * channels];
    let (mut node, mut weight) = ([0usize; 27], [0.0f32; 27]);
    for (p, x) in positions.iter().enumerate() {
        let k = grid.stencil(x, &mut node, &mut weight);
        let v = &values[p * channels..(p + 1) * channels];
        for s in 0..k {
            let row = &mut out[node[s] * channels..(node[s] + 1) * channels];
            for (o, vi) in row.iter_mut().zip(v) {
                *o += weight[s] * vi;
            }
        }
    }
    Ok(out)
}

/// g2p: `Σ_i w_pi · field_i` per particle. `field` is `[nodes^D][C]`;
/// returns `[N][C]`. Errors: bad grid, `field` of another length,
/// non-finite positions.
pub fn g2p<const D: usize>(
    grid: &TransferGrid<D>,
    field: &[f32],
    channels: usize,
    positions: &[[f32; D]],
) -> Result<Vec<f32>> {
    grid.validate()?;
    check_positions("positions", positions)?;
    if channels == 0 || field.len() != grid.len() * channels {
        return Err(MpmError::invalid(
            "field",
            format!(
                "expected [{}, C] with C >= 1, got {} values for C = {channels}",
                grid.len(),
                field.len()
            ),
        ));
    }
    let mut out = vec![0.0f32; positions.len() * channels];
    let (mut node, mut weight) = ([0usize; 27], [0.0f32; 27]);
    for (p, x) in positions.iter().enumerate() {
        let k = grid.stencil(x, &mut node, &mut weight);
        let o = &mut out[p * channels..(p + 1) * channels];
        for s in 0..k {
            let row = &field[node[s] * channels..(node[s] + 1) * channels];
            for (oi, fi) in o.iter_mut().zip(row) {
                *oi += weight[s] * fi;
            }
        }
    }
    Ok(out)
}

/// Frame-by-frame advection through `K` grid velocity fields.
///
/// For each frame `k` every moving particle takes the velocity
/// `g2p(velocity_k)(x) + extra_p + drift_k` [m/s], moves by it times `dt`
/// [s] and is clipped to `[lo, hi]`; the others stay at `x0`. `velocity` is
/// `[K][nodes^D][D]` (flat), `extra` `[N][D]`, `drift` `[K][D]`. Returns the
/// positions after each frame, `[K][N][D]` (flat). With `pressure`, each
/// frame ends with one density correction ([`Pressure`], `pressure_step`).
/// Errors name the argument of a wrong length or non-finite value.
#[allow(clippy::too_many_arguments)]
pub fn advect<const D: usize>(
    grid: &TransferGrid<D>,
    x0: &[[f32; D]],
    moving: &[bool],
    velocity: &[f32],
    extra: &[[f32; D]],
    drift: &[[f32; D]],
    dt: f32,
    lo: [f32; D],
    hi: [f32; D],
    pressure: Option<Pressure>,
) -> Result<Vec<f32>> {
    grid.validate()?;
    check_positions("positions", x0)?;
    if let Some(p) = pressure
        && !(p.strength.is_finite()
            && p.strength >= 0.0
            && p.rest_count.is_finite()
            && p.rest_count > 0.0)
    {
        return Err(MpmError::invalid(
            "pressure",
            "strength must be finite and >= 0, rest_count finite and > 0",
        ));
    }
    let (n, k) = (x0.len(), drift.len());
    if moving.len() != n {
        return Err(MpmError::invalid(
            "moving",
            format!("length {} != particle count {n}", moving.len()),
        ));
    }
    if extra.len() != n {
        return Err(MpmError::invalid(
            "extra",
            format!("length {} != particle count {n}", extra.len()),
        ));
    }
    if k == 0 || velocity.len() != k * grid.len() * D {
        return Err(MpmError::invalid(
            "velocity",
            format!(
                "expected [{k}, {}, {D}] with K >= 1, got {} values",
                grid.len(),
                velocity.len()
            ),
        ));
    }
    if !velocity.iter().all(|v| v.is_finite()) {
        return Err(MpmError::invalid("velocity", "contains NaN or inf"));
    }
    if !(dt.is_finite() && dt > 0.0) {
        return Err(MpmError::invalid("dt", format!("must be > 0 s, got {dt}")));
    }
    if !(0..D).all(|d| lo[d].is_finite() && hi[d].is_finite() && lo[d] <= hi[d]) {
        return Err(MpmError::invalid("bounds", "must be finite with lo <= hi"));
    }
    let stride = grid.len() * D;
    let mut x = x0.to_vec();
    let mut out = Vec::with_capacity(k * n * D);
    let (mut node, mut weight) = ([0usize; 27], [0.0f32; 27]);
    for f in 0..k {
        let field = &velocity[f * stride..(f + 1) * stride];
        for p in 0..n {
            if moving[p] {
                let m = grid.stencil(&x[p], &mut node, &mut weight);
                let mut u = [0.0f32; D];
                for s in 0..m {
                    let row = &field[node[s] * D..(node[s] + 1) * D];
                    for d in 0..D {
                        u[d] += weight[s] * row[d];
                    }
                }
                for d in 0..D {
                    let v = u[d] + extra[p][d] + drift[f][d];
                    x[p][d] = (x[p][d] + v * dt).max(lo[d]).min(hi[d]);
                }
            }
        }
        if let Some(pr) = pressure {
            pressure_step(grid, &mut x, moving, pr, lo, hi);
        }
        for p in x.iter() {
            out.extend_from_slice(p);
        }
    }
    Ok(out)
}

/// Strength and rest count of [`advect`]'s density correction.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Pressure {
    /// Displacement per unit excess-density gradient, in node spacings (> 0).
    pub strength: f32,
    /// Particles per node in resting fluid (> 0).
    pub rest_count: f32,
}

/// One density correction: the moving particles' p2g count over the rest
/// count less 1, clipped at 0 (excess density `e`), its central-difference
/// gradient on the nodes (edges replicated), and each moving particle moved
/// by `−strength · g2p(∇e) · spacing`, clipped to `[lo, hi]`
/// (`hybridmpm.train.grid.pressure_shift`: a one-iteration position-based
/// density constraint on the grid).
fn pressure_step<const D: usize>(
    grid: &TransferGrid<D>,
    x: &mut [[f32; D]],
    moving: &[bool],
    pr: Pressure,
    lo: [f32; D],
    hi: [f32; D],
) {
    let g = grid.nodes;
    let len = grid.len();
    let (mut node, mut weight) = ([0usize; 27], [0.0f32; 27]);
    let mut e = vec![0.0f32; len];
    for (p, xp) in x.iter().enumerate() {
        if moving[p] {
            let m = grid.stencil(xp, &mut node, &mut weight);
            for s in 0..m {
                e[node[s]] += weight[s];
            }
        }
    }
    for v in e.iter_mut() {
        *v = (*v / pr.rest_count - 1.0).max(0.0);
    }
    let mut grad = vec![0.0f32; len * D];
    let mut stride = [1usize; D];
    for d in (0..D.saturating_sub(1)).rev() {
        stride[d] = stride[d + 1] * g;
    }
    for i in 0..len {
        for d in 0..D {
            let c = (i / stride[d]) % g;
            let up = if c + 1 < g { i + stride[d] } else { i };
            let down = if c > 0 { i - stride[d] } else { i };
            grad[i * D + d] = 0.5 * (e[up] - e[down]);
        }
    }
    for (p, xp) in x.iter_mut().enumerate() {
        if moving[p] {
            let m = grid.stencil(xp, &mut node, &mut weight);
            let mut s_ = [0.0f32; D];
            for s in 0..m {
                for d in 0..D {
                    s_[d] += weight[s] * grad[node[s] * D + d];
                }
            }
            for d in 0..D {
                xp[d] = (xp[d] - pr.strength * (s_[d] * grid.spacing[d]))
                    .max(lo[d])
                    .min(hi[d]);
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn grid2() -> TransferGrid<2> {
        TransferGrid {
            origin: [-0.1, -0.1],
            spacing: [0.1, 0.1],
            nodes: 13,
        }
    }

    #[test]
    fn p2g_conserves_the_sum_and_g2p_reproduces_linear_fields() {
        let g = grid2();
        let x = vec![[0.33f32, 0.71], [0.05, 0.95], [0.5, 0.5]];
        let ones = vec![2.0f32; 3];
        let m = p2g(&g, &x, &ones, 1).unwrap();
        assert!((m.iter().sum::<f32>() - 6.0).abs() < 1e-5);
        // a linear field a + b·x is reproduced exactly by the quadratic B-spline
        let mut field = vec![0.0f32; g.len()];
        for i in 0..13 {
            for j in 0..13 {
                let (px, py) = (-0.1 + 0.1 * i as f32, -0.1 + 0.1 * j as f32);
                field[i * 13 + j] = 1.0 + 2.0 * px - 3.0 * py;
            }
        }
        let v = g2p(&g, &field, 1, &x).unwrap();
        for (p, xv) in x.iter().zip(&v) {
            assert!((xv - (1.0 + 2.0 * p[0] - 3.0 * p[1])).abs() < 1e-5);
        }
    }

    #[test]
    fn advect_in_a_uniform_field_moves_rigidly_and_clips() {
        let g = grid2();
        let x = vec![[0.3f32, 0.3], [0.9, 0.5], [0.2, 0.2]];
        let vel: Vec<f32> = (0..2 * 2 * g.len())
            .map(|i| if i % 2 == 0 { 1.0 } else { 0.0 })
            .collect();
        let out = advect(
            &g,
            &x,
            &[true, true, false],
            &vel,
            &[[0.0, 0.0]; 3],
            &[[0.0, -1.0], [0.0, -1.0]],
            0.05,
            [0.0, 0.0],
            [0.95, 1.0],
            None,
        )
        .unwrap();
        assert_eq!(out.len(), 2 * 3 * 2);
        assert!((out[0] - 0.35).abs() < 1e-6 && (out[1] - 0.25).abs() < 1e-6);
        assert!((out[6] - 0.4).abs() < 1e-6 && (out[7] - 0.2).abs() < 1e-6);
        assert_eq!(out[8], 0.95); // clipped at hi
        assert_eq!([out[10], out[11]], [0.2, 0.2]); // not moving
    }

    #[test]
    fn bad_input_names_the_field() {
        let g = grid2();
        let e = p2g(&g, &[[f32::NAN, 0.0]], &[1.0], 1).unwrap_err();
        assert!(e.to_string().starts_with("positions"));
        let e = p2g(&g, &[[0.1, 0.1]], &[1.0, 2.0], 1).unwrap_err();
        assert!(e.to_string().starts_with("values"));
        let bad = TransferGrid { nodes: 3, ..g };
        assert!(
            g2p(&bad, &[], 1, &[])
                .unwrap_err()
                .to_string()
                .starts_with("nodes")
        );
    }
}
