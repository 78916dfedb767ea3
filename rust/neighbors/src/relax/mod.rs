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

use crate::{GraphError, GraphParams, Neighbors, radius_graph};

mod graph;
mod pairs;
#[cfg(test)]
mod reference;
#[cfg(test)]
mod tests;

pub use graph::{RelaxedGraph, relax_then_graph};
use pairs::{Pairs, mirror, pair_terms, separation};

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
    let (offsets, senders) = Neighbors::search(positions, &gp)?.csr();
    Ok(relax_on(positions, movable, params, &offsets, &senders))
}

/// The iterations of [`relax_density`] on the neighbour lists of
/// `positions` within `params.radius`, self-edges left out (CSR, as
/// [`Neighbors::csr`] gives them). Inputs already checked.
///
/// Each iteration brings the pair cache up to date ([`Solver::refresh`]),
/// computes the `lambda` of the particles whose neighbourhood changed
/// ([`Solver::lambdas`]) and moves the particles near a compressed one
/// ([`Solver::moves`]).
fn relax_on<const D: usize>(
    positions: &mut [[f32; D]],
    movable: &[bool],
    params: &RelaxParams,
    offsets: &[usize],
    senders: &[u32],
) -> RelaxStats {
    let n = positions.len();
    let mut stats = RelaxStats::default();
    if params.iterations == 0 || n == 0 {
        return stats;
    }
    let (radius, rho0, omega) = (params.radius, params.rest_density, params.omega);
    // below SERIAL_PARTICLES everything runs on the calling thread, without rayon (`uses_rayon`)
    let parallel = crate::uses_rayon(n);
    let ne = senders.len();
    // Each edge's separation x_i - x_j (receiver minus sender), its squared
    // length and kernel terms, kept between iterations: recomputed only for
    // the pairs of particles that moved (the others would give the same bits).
    let mut pairs = Pairs::<D> {
        sep: vec![[0.0; D]; ne],
        dd: vec![0.0; ne],
        len: vec![0.0; ne],
        w: vec![0.0; ne],
        scale: vec![0.0; ne],
    };
    pairs.separations(positions, offsets, senders, None, parallel);
    pairs.terms(radius, parallel);
    let mut moved = vec![false; n];
    let solver = Solver {
        movable,
        offsets,
        senders,
        radius,
        rho0,
        omega,
        eps: 1e-6 / (radius * radius),
        inv_rho0_sq: 1.0 / (rho0 * rho0),
        parallel,
    };
    let mut lambda = vec![0.0f32; n];
    let mut compression = vec![0.0f32; n];
    let mut next = positions.to_vec();
    // `dirty[i]`: particle i or a neighbour moved in the iteration before, so its
    // density and lambda must be recomputed (all in the first iteration);
    // `touched[i]`: i or a neighbour has a nonzero lambda, so i may move.
    let mut dirty = vec![true; n];
    let mut touched = vec![false; n];
    for it in 0..params.iterations {
        let x: &[[f32; D]] = positions;
        if it > 0 {
            solver.refresh(&mut pairs, x, &moved, &mut dirty);
        }
        solver.lambdas(&pairs, &dirty, &mut lambda, &mut compression);
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
        solver.spread(&hot, &mut touched);
        solver.moves(&pairs, x, &lambda, &touched, &mut next, &mut moved);
        positions.copy_from_slice(&next);
        if !moved.iter().any(|&m| m) {
            break; // nothing moved: every later iteration would compute the same and move nothing
        }
    }
    stats
}

/// What the steps of [`relax_on`] read and no iteration changes: the
/// neighbour lists (CSR, symmetric, without self-edges), which particles
/// may move, and the constants of the constraint (module docs).
struct Solver<'a> {
    movable: &'a [bool],
    offsets: &'a [usize],
    senders: &'a [u32],
    /// `R`.
    radius: f32,
    /// `rho_0`.
    rho0: f32,
    /// `omega`.
    omega: f32,
    /// `eps = 1e-6 / R^2`.
    eps: f32,
    /// `1 / rho_0^2`.
    inv_rho0_sq: f32,
    /// Whether the steps run on rayon ([`crate::uses_rayon`]).
    parallel: bool,
}

impl Solver<'_> {
    /// Marks `flags[i]` for every listed particle and all its neighbours
    /// (the graph is symmetric), and clears the other flags.
    fn spread(&self, list: &[usize], flags: &mut [bool]) {
        let (offsets, senders) = (self.offsets, self.senders);
        flags.fill(false);
        for &i in list {
            flags[i] = true;
            for &j in &senders[offsets[i]..offsets[i + 1]] {
                flags[j as usize] = true;
            }
        }
    }

    /// After the particles flagged in `moved` moved to `x`: marks in
    /// `dirty` those particles and their neighbours, and recomputes the
    /// cached terms of the pairs of a moved particle with a dirty receiver
    /// (all pairs in one pass when there are many, else pair by pair).
    fn refresh<const D: usize>(
        &self,
        pairs: &mut Pairs<D>,
        x: &[[f32; D]],
        moved: &[bool],
        dirty: &mut [bool],
    ) {
        let (offsets, senders, radius) = (self.offsets, self.senders, self.radius);
        let (n, ne) = (x.len(), senders.len());
        let list: Vec<usize> = (0..n).filter(|&i| moved[i]).collect();
        self.spread(&list, dirty);
        let (mv, dt): (&[bool], &[bool]) = (moved, dirty);
        let count: usize = list
            .iter()
            .map(|&i| offsets[i + 1] - offsets[i])
            .sum::<usize>()
            * 2;
        if count * 4 >= ne {
            // many pairs changed: recompute all (the unchanged ones give
            // the same bits), the kernel terms in one vectorised pass
            // (the pairs of a moved particle with a dirty receiver; both
            // ends of such a pair are dirty: the lists are symmetric)
            pairs.separations(x, offsets, senders, Some((dt, mv)), self.parallel);
            pairs.terms(radius, self.parallel);
        } else {
            // few: pair by pair
            for &i in &list {
                for e in offsets[i]..offsets[i + 1] {
                    let j = senders[e] as usize;
                    // e = (i, j), and its mirror (j, i) in j's list
                    for (e, a, b) in [(e, i, j), (mirror(offsets, senders, j, i), j, i)] {
                        if dt[a] {
                            let (s, dd) = separation(&x[a], &x[b]);
                            pairs.sep[e] = s;
                            pairs.dd[e] = dd;
                            (pairs.len[e], pairs.w[e], pairs.scale[e]) = pair_terms(dd, radius);
                        }
                    }
                }
            }
        }
    }

    /// `lambda_i` and `C_i` (0 for a particle not compressed or not
    /// movable) of every particle flagged in `dirty`, from the pair cache;
    /// the others keep theirs (nothing they depend on moved).
    fn lambdas<const D: usize>(
        &self,
        pairs: &Pairs<D>,
        dirty: &[bool],
        lambda: &mut [f32],
        compression: &mut [f32],
    ) {
        let &Solver {
            movable,
            offsets,
            senders,
            radius,
            rho0,
            eps,
            inv_rho0_sq,
            parallel,
            ..
        } = self;
        let density = |(i, (lam, comp)): (usize, (&mut f32, &mut f32))| {
            if !dirty[i] {
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
                rho += pairs.w[e];
            }
            let c = rho / rho0 - 1.0;
            if c > 0.0 {
                let mut sum = [0.0f32; D];
                let mut sq = 0.0f32;
                for e in edges {
                    if let Some(gw) = pairs.gradient(e, i, senders[e] as usize, radius) {
                        for k in 0..D {
                            sum[k] += gw[k];
                            sq += gw[k] * gw[k];
                        }
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
                .with_min_len(CHUNK)
                .for_each(density);
        } else {
            lambda
                .iter_mut()
                .zip(compression.iter_mut())
                .enumerate()
                .for_each(density);
        }
    }

    /// The positions after the iteration into `next`, and into `moved`
    /// whether each changed: the move `dx_i` from the current positions
    /// `x` and `lambda`, capped at [`MAX_MOVE`]` * R`, of every movable
    /// particle flagged in `touched` (the others have no lambda around
    /// them and stay).
    fn moves<const D: usize>(
        &self,
        pairs: &Pairs<D>,
        x: &[[f32; D]],
        lambda: &[f32],
        touched: &[bool],
        next: &mut [[f32; D]],
        moved: &mut [bool],
    ) {
        let &Solver {
            movable,
            offsets,
            senders,
            radius,
            rho0,
            omega,
            parallel,
            ..
        } = self;
        let step = |(i, (out, mv)): (usize, (&mut [f32; D], &mut bool))| {
            *out = x[i];
            *mv = false;
            if !movable[i] || !touched[i] {
                return; // no lambda around i: every term of its move is zero
            }
            let mut dx = [0.0f32; D];
            for (e, &j) in (offsets[i]..).zip(&senders[offsets[i]..offsets[i + 1]]) {
                let j = j as usize;
                let s = lambda[i] + lambda[j];
                if s == 0.0 {
                    continue;
                }
                if let Some(gw) = pairs.gradient(e, i, j, radius) {
                    for k in 0..D {
                        dx[k] += s * gw[k];
                    }
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
                .with_min_len(CHUNK)
                .for_each(step);
        } else {
            next.iter_mut()
                .zip(moved.iter_mut())
                .enumerate()
                .for_each(step);
        }
    }
}
