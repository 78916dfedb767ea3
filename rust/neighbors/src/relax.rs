//! Density relaxation of a particle cloud: a position-based correction that
//! pushes apart particles packed denser than a rest density.
//!
//! A learned simulator of a nearly incompressible material (water, sand) lets
//! particles cluster over a rollout: the packing grows step by step, which
//! no one-step loss sees (Toshev et al., "Neural SPH: Improved Neural
//! Modeling of Lagrangian Fluid Dynamics", ICML 2024, arXiv 2402.06275, Sec.
//! 4: SPH relaxation between network steps). The correction here is one
//! constraint per particle in the form of Position Based Fluids (Macklin &
//! Müller, SIGGRAPH 2013, Eqs. 1-12), made *unilateral*: only compression is
//! corrected, so free surfaces and splashes (less dense) are left alone.
//!
//! # Definitions
//!
//! With the connectivity radius `R`, `q = |x_i - x_j| / R` and the kernel
//! `W(q) = (1 - q)^2` for `q < 1` (0 beyond; `W(0) = 1`, the particle itself):
//!
//! ```text
//! rho_i    = sum_j W(q_ij)                        (self included)
//! C_i      = max(rho_i / rho_0 - 1, 0)
//! grad_ij  = dW/dx_i = -2 (1 - q_ij) / (R |x_i - x_j|) (x_i - x_j)   (j != i)
//! lambda_i = -C_i / ((sum_j |grad_ij|^2 + |sum_j grad_ij|^2) / rho_0^2 + eps)
//! dx_i     = omega / rho_0 * sum_j (lambda_i + lambda_j) grad_ij
//! ```
//!
//! with `eps = 1e-6 / R^2`. Each iteration computes every `lambda` from the
//! current positions, then moves every movable particle by `dx_i` (Jacobi),
//! its length capped at [`MAX_MOVE`]` * R`.
//!
//! Two configurations that clipping predictions to the walls produces
//! (particles stacked on a wall line, several clipped into one corner point)
//! and that a clumping network produces would otherwise break the correction:
//!
//! * a *coincident* pair (`|x_i - x_j| = 0`) has no direction: it is given
//!   the direction of the first axis, `x_i - x_j := sign(i - j) e_0` at
//!   distance 0, so its gradient is `-(2 / R) sign(i - j) e_0` (antisymmetric,
//!   as every pair's) and a stack of coincident particles spreads out along
//!   that axis in index order instead of staying stacked (before, such a
//!   pair had no gradient and the stack's `lambda` was `-C / eps`);
//! * in a clump far above the rest density `lambda` is large and `dx_i`
//!   reaches several `R` in one iteration: the cap keeps the correction a
//!   local one. Measured before the cap and the coincident rule: a particle
//!   next to a sand pile clipped into a corner thrown 85 R in one network
//!   step (three iterations), which the next network step extrapolated out
//!   of the domain; on the shipped water2d model the largest move per
//!   network step was 0.5-1 R, 4.5 R once in 150 steps.
//!
//! The neighbour list is found once, at the given positions, and kept
//! through the iterations (PBF does the same); a pair that moves apart past
//! `R` then contributes nothing. Each pair's separation and its length are
//! taken from the radius graph and recomputed only for pairs of particles
//! that moved in the iteration before; the gradient sums are formed only for
//! compressed particles, and the iterations stop once nothing moves. These
//! change no bit (a test holds the result to the plain implementation's,
//! bit for bit) and cut the cost of an iteration, where typically a few per
//! cent of the particles are compressed. Immovable particles (obstacles) count in
//! their neighbours' density, never move, and carry `lambda = 0`.
//!
//! Every sum is a gather over the receiver's own edges (the radius graph is
//! symmetric and grouped by receiver), so the result is bitwise identical
//! for any number of threads.

use rayon::prelude::*;

use crate::{GraphError, GraphParams, radius_graph};

/// Particles per rayon task, where the crate uses rayon at all ([`crate::uses_rayon`]).
const CHUNK: usize = 4096;

/// Largest move of a particle in one iteration, as a fraction of `R`: a
/// quarter of the radius is about half the rest spacing of a material whose
/// particles have 12 neighbours within `R` in 2D (`h ≈ R (π/12)^½`), more
/// than a density correction needs (measured on the shipped water2d model:
/// the largest move per network step, three iterations, is 0.5-1 R).
pub const MAX_MOVE: f32 = 0.25;

/// Settings of [`relax_density`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RelaxParams {
    /// Connectivity radius `R` (position units), finite and > 0: the kernel's support.
    pub radius: f32,
    /// Rest density `rho_0` in kernel units (`W(0) = 1` per particle), finite and > 0;
    /// e.g. a high percentile of [`kernel_density`] of the material at rest.
    pub rest_density: f32,
    /// Jacobi iterations (0: positions unchanged); at most [`RelaxParams::MAX_ITERATIONS`].
    pub iterations: usize,
    /// Relaxation factor `omega` in (0, 2].
    pub omega: f32,
}

impl RelaxParams {
    /// Upper bound on `iterations`.
    pub const MAX_ITERATIONS: usize = 100;

    /// Checks every field; the error names it (`"radius"`, `"rest_density"`,
    /// `"iterations"`, `"omega"`).
    ///
    /// # Errors
    /// [`GraphError::InvalidInput`] for a value out of range.
    pub fn validate(&self) -> Result<(), GraphError> {
        if !(self.radius.is_finite() && self.radius > 0.0) {
            return Err(GraphError::invalid(
                "radius",
                format!("must be finite and > 0, got {}", self.radius),
            ));
        }
        if !(self.rest_density.is_finite() && self.rest_density > 0.0) {
            return Err(GraphError::invalid(
                "rest_density",
                format!("must be finite and > 0, got {}", self.rest_density),
            ));
        }
        if self.iterations > Self::MAX_ITERATIONS {
            return Err(GraphError::invalid(
                "iterations",
                format!(
                    "must be at most {}, got {}",
                    Self::MAX_ITERATIONS,
                    self.iterations
                ),
            ));
        }
        if !(self.omega.is_finite() && self.omega > 0.0 && self.omega <= 2.0) {
            return Err(GraphError::invalid(
                "omega",
                format!("must be in (0, 2], got {}", self.omega),
            ));
        }
        Ok(())
    }
}

/// What [`relax_density`] found and did.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct RelaxStats {
    /// Movable particles denser than `rho_0` before the first iteration.
    pub compressed_before: usize,
    /// Largest `C_i = rho_i / rho_0 - 1` of a movable particle before the first iteration (0 if none).
    pub max_compression_before: f32,
}

/// `W(q) = (1 - q)^2` for `q < 1`, else 0.
#[inline]
fn kernel(q: f32) -> f32 {
    let t = (1.0 - q).max(0.0);
    t * t
}

/// Kernel density `rho_i = sum_j W(|x_i - x_j| / R)` of every particle, self
/// included (module docs), in kernel units: an isolated particle has 1.
///
/// # Errors
/// As [`radius_graph`] (`"positions"`, `"radius"`).
pub fn kernel_density<const D: usize>(
    positions: &[[f32; D]],
    radius: f32,
) -> Result<Vec<f32>, GraphError> {
    let params = GraphParams {
        radius,
        self_edges: true,
        ..GraphParams::default()
    };
    let g = radius_graph(positions, &params)?;
    let mut rho = vec![0.0f32; positions.len()];
    for (&r, &d) in g.receivers.iter().zip(&g.distance) {
        rho[r as usize] += kernel(d / radius);
    }
    Ok(rho)
}

#[cfg(test)] // the reference implementation's (tests); the solver uses `gradient_from`
/// Per-edge kernel gradient `dW/dx_i` of the pair (receiver `i`, sender `j`)
/// and its kernel value; a coincident pair takes the direction `sign(i - j) e_0`
/// (module docs).
#[inline]
fn gradient<const D: usize>(
    xi: &[f32; D],
    xj: &[f32; D],
    i: usize,
    j: usize,
    radius: f32,
) -> (f32, [f32; D]) {
    let mut d = [0.0f32; D];
    let mut dd = 0.0f32;
    for k in 0..D {
        d[k] = xi[k] - xj[k];
        dd += d[k] * d[k];
    }
    let r = dd.sqrt();
    let q = r / radius;
    if q >= 1.0 {
        return (0.0, [0.0; D]);
    }
    let w = kernel(q);
    let mut g = [0.0f32; D];
    if r == 0.0 {
        // coincident: unit direction sign(i - j) e_0, |dW/dr| at q = 0 is 2 / R
        g[0] = if i < j { 2.0 / radius } else { -2.0 / radius };
        return (w, g);
    }
    let s = -2.0 * (1.0 - q) / (radius * r);
    for k in 0..D {
        g[k] = s * d[k];
    }
    (w, g)
}

/// [`gradient`] from the pair's separation `d = x_i - x_j` and its length
/// `r = sqrt(d · d)` (summed left to right, as [`gradient`] and the radius
/// graph compute them): the same bits as [`gradient`] on the positions.
#[inline]
fn gradient_from<const D: usize>(
    d: &[f32; D],
    r: f32,
    i: usize,
    j: usize,
    radius: f32,
) -> (f32, [f32; D]) {
    let q = r / radius;
    if q >= 1.0 {
        return (0.0, [0.0; D]);
    }
    let w = kernel(q);
    let mut g = [0.0f32; D];
    if r == 0.0 {
        g[0] = if i < j { 2.0 / radius } else { -2.0 / radius };
        return (w, g);
    }
    let s = -2.0 * (1.0 - q) / (radius * r);
    for k in 0..D {
        g[k] = s * d[k];
    }
    (w, g)
}

/// `x_i - x_j` and its length, summed left to right (no fused multiply-add).
#[inline]
fn separation<const D: usize>(xi: &[f32; D], xj: &[f32; D]) -> ([f32; D], f32) {
    let mut d = [0.0f32; D];
    let mut dd = 0.0f32;
    for k in 0..D {
        d[k] = xi[k] - xj[k];
        dd += d[k] * d[k];
    }
    (d, dd.sqrt())
}

/// Moves the movable particles of `positions` in place so that none stays
/// much denser than `rest_density` (module docs: unilateral PBF density
/// constraint, `iterations` Jacobi iterations).
///
/// `movable[i]` false keeps particle `i` in place (obstacles).
///
/// # Errors
/// [`GraphError::InvalidInput`] naming `"movable"` (length differs from
/// `positions`), a field of [`RelaxParams::validate`], or as [`radius_graph`]
/// (`"positions"`). On error `positions` is unchanged.
pub fn relax_density<const D: usize>(
    positions: &mut [[f32; D]],
    movable: &[bool],
    params: &RelaxParams,
) -> Result<RelaxStats, GraphError> {
    params.validate()?;
    let n = positions.len();
    if movable.len() != n {
        return Err(GraphError::invalid(
            "movable",
            format!("has {} entries for {} particles", movable.len(), n),
        ));
    }
    let gp = GraphParams {
        radius: params.radius,
        self_edges: false,
        ..GraphParams::default()
    };
    let g = radius_graph(positions, &gp)?;
    let mut stats = RelaxStats::default();
    if params.iterations == 0 || n == 0 {
        return Ok(stats);
    }
    // CSR offsets of the receiver-grouped edges
    let mut offsets = vec![0usize; n + 1];
    for &r in &g.receivers {
        offsets[r as usize + 1] += 1;
    }
    for i in 0..n {
        offsets[i + 1] += offsets[i];
    }
    let (senders, receivers) = (&g.senders, &g.receivers);
    // Each edge's separation x_i - x_j (receiver minus sender) and its length,
    // kept between iterations and recomputed only for the pairs of particles
    // that moved: the radius graph's displacement is x_j - x_i and its
    // distance the same sqrt of the same sum, so the negation and the copy
    // give the same bits as computing them from the positions.
    let mut sep: Vec<[f32; D]> = g.displacement.iter().map(|v| v.map(|c| -c)).collect();
    let mut len: Vec<f32> = g.distance.clone();
    let mut moved = vec![false; n];
    let (radius, rho0, omega) = (params.radius, params.rest_density, params.omega);
    let eps = 1e-6 / (radius * radius);
    let inv_rho0_sq = 1.0 / (rho0 * rho0);
    // below SERIAL_PARTICLES everything runs on the calling thread, without rayon (`uses_rayon`)
    let parallel = crate::uses_rayon(n);
    let min_len = CHUNK;
    let edge_min_len = CHUNK * 16;
    let mut lambda = vec![0.0f32; n];
    let mut compression = vec![0.0f32; n];
    let mut next = positions.to_vec();
    // `dirty[i]`: particle i or a neighbour moved in the iteration before, so its
    // density and lambda must be recomputed (all in the first iteration);
    // `touched[i]`: i or a neighbour has a nonzero lambda, so i may move.
    let mut dirty = vec![true; n];
    let mut touched = vec![false; n];
    // marks `flags[i]` for every listed particle and all its neighbours (the graph is symmetric)
    let spread = |list: &[usize], flags: &mut [bool]| {
        flags.fill(false);
        for &i in list {
            flags[i] = true;
            for &j in &senders[offsets[i]..offsets[i + 1]] {
                flags[j as usize] = true;
            }
        }
    };
    for it in 0..params.iterations {
        let x: &[[f32; D]] = positions;
        if it > 0 {
            let list: Vec<usize> = (0..n).filter(|&i| moved[i]).collect();
            spread(&list, &mut dirty);
            let (mv, dt): (&[bool], &[bool]) = (&moved, &dirty);
            let update = |(e, (s, l)): (usize, (&mut [f32; D], &mut f32))| {
                let (i, j) = (receivers[e] as usize, senders[e] as usize);
                if dt[i] && (mv[i] || mv[j]) {
                    (*s, *l) = separation(&x[i], &x[j]);
                }
            };
            if parallel {
                sep.par_iter_mut()
                    .zip(len.par_iter_mut())
                    .enumerate()
                    .with_min_len(edge_min_len)
                    .for_each(update);
            } else {
                sep.iter_mut()
                    .zip(len.iter_mut())
                    .enumerate()
                    .for_each(update);
            }
        }
        let (sep, len): (&[[f32; D]], &[f32]) = (&sep, &len);
        let dt: &[bool] = &dirty;
        let density = |(i, (lam, comp)): (usize, (&mut f32, &mut f32))| {
            if !dt[i] {
                return; // nothing it depends on moved: the same lambda as before
            }
            *lam = 0.0;
            *comp = 0.0;
            if !movable[i] {
                return;
            }
            let edges = offsets[i]..offsets[i + 1];
            // the density first; the gradient sums only for a compressed particle
            // (each sum in the same order as before: the same bits)
            let mut rho = 1.0f32;
            for e in edges.clone() {
                let q = len[e] / radius;
                if q < 1.0 {
                    rho += kernel(q);
                }
            }
            let c = rho / rho0 - 1.0;
            if c > 0.0 {
                let mut sum = [0.0f32; D];
                let mut sq = 0.0f32;
                for e in edges {
                    let (_, gw) = gradient_from(&sep[e], len[e], i, senders[e] as usize, radius);
                    for k in 0..D {
                        sum[k] += gw[k];
                        sq += gw[k] * gw[k];
                    }
                }
                let norm: f32 = sum.iter().map(|v| v * v).sum();
                *comp = c;
                *lam = -c / ((sq + norm) * inv_rho0_sq + eps);
            }
        };
        if parallel {
            lambda
                .par_iter_mut()
                .zip(compression.par_iter_mut())
                .enumerate()
                .with_min_len(min_len)
                .for_each(density);
        } else {
            lambda
                .iter_mut()
                .zip(compression.iter_mut())
                .enumerate()
                .for_each(density);
        }
        if it == 0 {
            for (&c, &m) in compression.iter().zip(movable) {
                if m && c > 0.0 {
                    stats.compressed_before += 1;
                    stats.max_compression_before = stats.max_compression_before.max(c);
                }
            }
        }
        let hot: Vec<usize> = (0..n).filter(|&i| lambda[i] != 0.0).collect();
        if hot.is_empty() {
            break; // no particle is compressed: nothing moves now or later
        }
        spread(&hot, &mut touched);
        let (lam, tc): (&[f32], &[bool]) = (&lambda, &touched);
        let step = |(i, (out, mv)): (usize, (&mut [f32; D], &mut bool))| {
            *out = x[i];
            *mv = false;
            if !movable[i] || !tc[i] {
                return; // no lambda around i: every term of its move is zero
            }
            let mut dx = [0.0f32; D];
            for e in offsets[i]..offsets[i + 1] {
                let j = senders[e] as usize;
                let s = lam[i] + lam[j];
                if s == 0.0 {
                    continue;
                }
                let (_, gw) = gradient_from(&sep[e], len[e], i, j, radius);
                for k in 0..D {
                    dx[k] += s * gw[k];
                }
            }
            let mut len2 = 0.0f32;
            for v in dx.iter_mut() {
                *v *= omega / rho0;
                len2 += *v * *v;
            }
            let cap = MAX_MOVE * radius;
            let scale = if len2 > cap * cap {
                cap / len2.sqrt()
            } else {
                1.0
            };
            for k in 0..D {
                out[k] += scale * dx[k];
            }
            *mv = out.map(f32::to_bits) != x[i].map(f32::to_bits); // bits: a -0.0 turned +0.0 counts as moved
        };
        if parallel {
            next.par_iter_mut()
                .zip(moved.par_iter_mut())
                .enumerate()
                .with_min_len(min_len)
                .for_each(step);
        } else {
            next.iter_mut()
                .zip(moved.iter_mut())
                .enumerate()
                .for_each(step);
        }
        positions.copy_from_slice(&next);
        if !moved.iter().any(|&m| m) {
            break; // nothing moved: every later iteration would compute the same and move nothing
        }
    }
    Ok(stats)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The implementation before the separation cache (5bee28c..4b1aafb),
    /// kept as the reference the cached one must match bit for bit.
    #[allow(clippy::needless_range_loop)]
    fn relax_reference<const D: usize>(
        positions: &mut [[f32; D]],
        movable: &[bool],
        params: &RelaxParams,
    ) -> Result<RelaxStats, GraphError> {
        params.validate()?;
        let n = positions.len();
        if movable.len() != n {
            return Err(GraphError::invalid(
                "movable",
                format!("has {} entries for {} particles", movable.len(), n),
            ));
        }
        let gp = GraphParams {
            radius: params.radius,
            self_edges: false,
            ..GraphParams::default()
        };
        let g = radius_graph(positions, &gp)?;
        let mut stats = RelaxStats::default();
        if params.iterations == 0 || n == 0 {
            return Ok(stats);
        }
        // CSR offsets of the receiver-grouped edges
        let mut offsets = vec![0usize; n + 1];
        for &r in &g.receivers {
            offsets[r as usize + 1] += 1;
        }
        for i in 0..n {
            offsets[i + 1] += offsets[i];
        }
        let senders = &g.senders;
        let (radius, rho0, omega) = (params.radius, params.rest_density, params.omega);
        let eps = 1e-6 / (radius * radius);
        let inv_rho0_sq = 1.0 / (rho0 * rho0);
        let min_len = if n < 2 * CHUNK { n } else { CHUNK };
        let mut lambda = vec![0.0f32; n];
        let mut compression = vec![0.0f32; n];
        let mut next = positions.to_vec();
        for it in 0..params.iterations {
            let x: &[[f32; D]] = positions;
            lambda
                .par_iter_mut()
                .zip(compression.par_iter_mut())
                .enumerate()
                .with_min_len(min_len)
                .for_each(|(i, (lam, comp))| {
                    *lam = 0.0;
                    *comp = 0.0;
                    if !movable[i] {
                        return;
                    }
                    let mut rho = 1.0f32;
                    let mut sum = [0.0f32; D];
                    let mut sq = 0.0f32;
                    for &j in &senders[offsets[i]..offsets[i + 1]] {
                        let (w, gw) = gradient(&x[i], &x[j as usize], i, j as usize, radius);
                        rho += w;
                        for k in 0..D {
                            sum[k] += gw[k];
                            sq += gw[k] * gw[k];
                        }
                    }
                    let c = rho / rho0 - 1.0;
                    if c > 0.0 {
                        let norm: f32 = sum.iter().map(|v| v * v).sum();
                        *comp = c;
                        *lam = -c / ((sq + norm) * inv_rho0_sq + eps);
                    }
                });
            if it == 0 {
                for (&c, &m) in compression.iter().zip(movable) {
                    if m && c > 0.0 {
                        stats.compressed_before += 1;
                        stats.max_compression_before = stats.max_compression_before.max(c);
                    }
                }
            }
            let lam: &[f32] = &lambda;
            next.par_iter_mut()
                .enumerate()
                .with_min_len(min_len)
                .for_each(|(i, out)| {
                    *out = x[i];
                    if !movable[i] {
                        return;
                    }
                    let mut dx = [0.0f32; D];
                    for &j in &senders[offsets[i]..offsets[i + 1]] {
                        let j = j as usize;
                        let s = lam[i] + lam[j];
                        if s == 0.0 {
                            continue;
                        }
                        let (_, gw) = gradient(&x[i], &x[j], i, j, radius);
                        for k in 0..D {
                            dx[k] += s * gw[k];
                        }
                    }
                    let mut len2 = 0.0f32;
                    for v in dx.iter_mut() {
                        *v *= omega / rho0;
                        len2 += *v * *v;
                    }
                    let cap = MAX_MOVE * radius;
                    let scale = if len2 > cap * cap {
                        cap / len2.sqrt()
                    } else {
                        1.0
                    };
                    for k in 0..D {
                        out[k] += scale * dx[k];
                    }
                });
            positions.copy_from_slice(&next);
        }
        Ok(stats)
    }

    #[test]
    fn the_separation_cache_changes_no_bit() {
        // clouds with compressed clumps, stacks on one point and obstacles, 2D and 3D
        for seed in 0..6u32 {
            let mut x2: Vec<[f32; 2]> = (0..400)
                .map(|i| {
                    let t = (i as u32 * 7919 + seed * 104_729) as f32;
                    [(t * 0.618_034).fract(), (t * 0.754_877_7).fract()]
                })
                .collect();
            for p in x2.iter_mut().take(30) {
                *p = [0.5 + 0.001 * p[0], 0.5 + 0.001 * p[1]]; // a clump
            }
            for p in x2.iter_mut().skip(30).take(8) {
                *p = [0.0, 0.0]; // a stack on one point
            }
            let movable: Vec<bool> = (0..x2.len()).map(|i| i % 11 != 3).collect();
            let rho0 = 2.0 + seed as f32 * 0.5;
            for iterations in [1usize, 3, 7] {
                let params = RelaxParams {
                    radius: 0.08,
                    rest_density: rho0,
                    iterations,
                    omega: 1.0,
                };
                let (mut a, mut b) = (x2.clone(), x2.clone());
                let sa = relax_density(&mut a, &movable, &params).unwrap();
                let sb = relax_reference(&mut b, &movable, &params).unwrap();
                assert_eq!(sa, sb);
                assert!(
                    a.iter()
                        .zip(&b)
                        .all(|(p, q)| p.map(f32::to_bits) == q.map(f32::to_bits)),
                    "2D seed {seed}, {iterations} iterations"
                );
            }
            let x3: Vec<[f32; 3]> = x2
                .iter()
                .enumerate()
                .map(|(i, p)| [p[0], p[1], ((i as f32) * 0.381_966).fract() * 0.3])
                .collect();
            let params = RelaxParams {
                radius: 0.12,
                rest_density: rho0,
                iterations: 3,
                omega: 1.0,
            };
            let (mut a, mut b) = (x3.clone(), x3.clone());
            assert_eq!(
                relax_density(&mut a, &movable, &params).unwrap(),
                relax_reference(&mut b, &movable, &params).unwrap()
            );
            assert!(
                a.iter()
                    .zip(&b)
                    .all(|(p, q)| p.map(f32::to_bits) == q.map(f32::to_bits)),
                "3D seed {seed}"
            );
        }
    }

    #[test]
    fn the_parallel_path_matches_the_reference_bit_for_bit() {
        // above SERIAL_PARTICLES the iterations run on rayon; below it on the calling thread
        // (the test above): both must give the reference's bits, on two threads as on one
        let n = crate::SERIAL_PARTICLES + 3000;
        assert!(crate::uses_rayon(n) && !crate::uses_rayon(400));
        let mut x: Vec<[f32; 2]> = (0..n)
            .map(|i| {
                let t = i as f32;
                [(t * 0.618_034).fract(), (t * 0.754_877_7).fract()]
            })
            .collect();
        for p in x.iter_mut().take(300) {
            *p = [0.25 + 0.002 * p[0], 0.75 + 0.002 * p[1]]; // a clump
        }
        let movable: Vec<bool> = (0..n).map(|i| i % 13 != 5).collect();
        let params = RelaxParams {
            radius: 0.02,
            rest_density: 4.0,
            iterations: 3,
            omega: 1.0,
        };
        let mut want = x.clone();
        let sw = relax_reference(&mut want, &movable, &params).unwrap();
        assert!(sw.compressed_before > 200, "{sw:?}");
        for threads in [1, 2] {
            let pool = rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .build()
                .unwrap();
            let mut got = x.clone();
            let sg = pool.install(|| relax_density(&mut got, &movable, &params).unwrap());
            assert_eq!(sg, sw);
            assert!(
                got.iter()
                    .zip(&want)
                    .all(|(p, q)| p.map(f32::to_bits) == q.map(f32::to_bits)),
                "{threads} threads"
            );
        }
    }

    fn lattice(n: usize, h: f32) -> Vec<[f32; 2]> {
        let mut v = Vec::new();
        for i in 0..n {
            for j in 0..n {
                v.push([i as f32 * h, j as f32 * h]);
            }
        }
        v
    }

    fn brute_density(x: &[[f32; 2]], r: f32) -> Vec<f32> {
        x.iter()
            .map(|a| {
                x.iter()
                    .map(|b| {
                        let d = ((a[0] - b[0]).powi(2) + (a[1] - b[1]).powi(2)).sqrt();
                        kernel(d / r)
                    })
                    .sum()
            })
            .collect()
    }

    #[test]
    fn kernel_density_matches_brute_force() {
        let x: Vec<[f32; 2]> = (0..200)
            .map(|i| {
                let t = i as f32;
                [(t * 0.618_034).fract(), (t * 0.754_877_7).fract()]
            })
            .collect();
        let rho = kernel_density(&x, 0.1).unwrap();
        for (a, b) in rho.iter().zip(brute_density(&x, 0.1)) {
            assert!((a - b).abs() < 1e-5, "{a} vs {b}");
        }
    }

    #[test]
    fn a_compressed_lattice_expands_and_one_at_rest_does_not_move() {
        let r = 2.0;
        let rest = lattice(8, 1.0);
        let rho0 = kernel_density(&rest, r)
            .unwrap()
            .into_iter()
            .fold(0.0f32, f32::max);
        let params = RelaxParams {
            radius: r,
            rest_density: rho0,
            iterations: 5,
            omega: 1.0,
        };
        let movable = vec![true; rest.len()];
        let mut same = rest.clone();
        let st = relax_density(&mut same, &movable, &params).unwrap();
        assert_eq!(
            same, rest,
            "no particle is denser than rho_0: nothing moves"
        );
        assert_eq!(st.compressed_before, 0);
        // squeezed to 80% spacing: denser; the relaxation lowers the peak density
        let mut squeezed = lattice(8, 0.8);
        let before = kernel_density(&squeezed, r).unwrap();
        let st = relax_density(&mut squeezed, &movable, &params).unwrap();
        let after = kernel_density(&squeezed, r).unwrap();
        let peak = |v: &[f32]| v.iter().copied().fold(0.0f32, f32::max);
        assert!(st.compressed_before > 0 && st.max_compression_before > 0.1);
        assert!(
            peak(&after) - rho0 < 0.5 * (peak(&before) - rho0),
            "{} -> {}",
            peak(&before),
            peak(&after)
        );
        // momentum-like symmetry: the centroid stays (pairwise equal and opposite moves)
        let c = |v: &[[f32; 2]]| {
            let s = v
                .iter()
                .fold([0.0f64; 2], |a, p| [a[0] + p[0] as f64, a[1] + p[1] as f64]);
            [s[0] / v.len() as f64, s[1] / v.len() as f64]
        };
        let (c0, c1) = (c(&lattice(8, 0.8)), c(&squeezed));
        assert!((c0[0] - c1[0]).abs() < 1e-4 && (c0[1] - c1[1]).abs() < 1e-4);
    }

    #[test]
    fn a_stack_and_a_clump_spread_without_throwing_particles() {
        // a wall-clipped corner (20 particles at one point) and a clump (20 on a circle of
        // 0.01 R), inside a lattice at rest spacing
        let r = 1.0;
        let rest = lattice(7, 0.5);
        let rho0 = kernel_density(&rest, r)
            .unwrap()
            .into_iter()
            .fold(0.0f32, f32::max);
        let mut x = rest.clone();
        x.extend(std::iter::repeat_n([0.0f32, 0.0], 20));
        x.extend((0..20).map(|k| {
            let a = k as f32 * std::f32::consts::TAU / 20.0;
            [1.5 + 0.01 * r * a.cos(), 1.5 + 0.01 * r * a.sin()]
        }));
        let orig = x.clone();
        let movable = vec![true; x.len()];
        let params = RelaxParams {
            radius: r,
            rest_density: rho0,
            iterations: 3,
            omega: 1.0,
        };
        let before = kernel_density(&x, r).unwrap();
        relax_density(&mut x, &movable, &params).unwrap();
        let after = kernel_density(&x, r).unwrap();
        let bound = params.iterations as f32 * MAX_MOVE * r * (1.0 + 1e-5);
        for (a, b) in x.iter().zip(&orig) {
            assert!(a.iter().all(|v| v.is_finite()));
            let m = ((a[0] - b[0]).powi(2) + (a[1] - b[1]).powi(2)).sqrt();
            assert!(m <= bound, "moved {m} > {bound}");
        }
        // the stack separates: no two of its particles coincide any more
        let stack = &x[rest.len()..rest.len() + 20];
        for (k, a) in stack.iter().enumerate() {
            for b in &stack[k + 1..] {
                assert!(a != b, "still coincident at {a:?}");
            }
        }
        let peak = |v: &[f32]| v.iter().copied().fold(0.0f32, f32::max);
        assert!(
            peak(&after) < 0.8 * peak(&before),
            "{} -> {}",
            peak(&before),
            peak(&after)
        );
    }

    #[test]
    fn immovable_particles_stay_and_bad_input_names_the_field() {
        let mut x = lattice(6, 0.5);
        let orig = x.clone();
        let movable: Vec<bool> = (0..x.len()).map(|i| i % 6 != 0).collect();
        let params = RelaxParams {
            radius: 2.0,
            rest_density: 2.0,
            iterations: 3,
            omega: 1.0,
        };
        relax_density(&mut x, &movable, &params).unwrap();
        for (i, (a, b)) in x.iter().zip(&orig).enumerate() {
            assert_eq!(movable[i], a != b, "particle {i}");
        }
        let field = |e: GraphError| match e {
            GraphError::InvalidInput { field, .. } => field,
        };
        let bad = [
            (
                RelaxParams {
                    radius: 0.0,
                    ..params
                },
                "radius",
            ),
            (
                RelaxParams {
                    rest_density: f32::NAN,
                    ..params
                },
                "rest_density",
            ),
            (
                RelaxParams {
                    iterations: 101,
                    ..params
                },
                "iterations",
            ),
            (
                RelaxParams {
                    omega: 2.5,
                    ..params
                },
                "omega",
            ),
        ];
        for (p, name) in bad {
            let mut y = orig.clone();
            assert_eq!(
                field(relax_density(&mut y, &movable, &p).unwrap_err()),
                name
            );
            assert_eq!(y, orig);
        }
        let mut y = orig.clone();
        assert_eq!(
            field(relax_density(&mut y, &movable[1..], &params).unwrap_err()),
            "movable"
        );
        y[3][0] = f32::NAN;
        assert_eq!(
            field(relax_density(&mut y, &movable, &params).unwrap_err()),
            "positions"
        );
    }
}
