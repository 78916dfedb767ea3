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

/// The kernel terms of one pair from its squared separation `dd` (summed
/// left to right, as [`gradient`] and the radius graph sum it): its length
/// `r = sqrt(dd)`, `W(q)` (0 for `q >= 1`) and the gradient's scale
/// `-2 (1 - q) / (R r)` (meaningless where `W = 0` or `r = 0`). Each value
/// is the one [`gradient`] computes (same operations, same order), so the
/// per-pair cache changes no bit. Written branch-free so that a pass over
/// many pairs vectorises (IEEE `sqrt` and division are correctly rounded
/// in any lane width).
#[inline(always)]
fn pair_terms(dd: f32, radius: f32) -> (f32, f32, f32) {
    let r = dd.sqrt();
    let q = r / radius;
    let t = 1.0 - q;
    let w = if q < 1.0 { t * t } else { 0.0 };
    (r, w, -2.0 * t / (radius * r))
}

/// One chunk of [`Pairs::terms`]: `dd` in; `len`, `w`, `scale` out.
type TermsChunk<'a> = (&'a [f32], &'a mut [f32], &'a mut [f32], &'a mut [f32]);

/// Per-pair cache of [`relax_density`], by edge of the receiver-grouped
/// lists: the separation `x_i - x_j`, its squared length, and
/// [`pair_terms`] of it.
struct Pairs<const D: usize> {
    sep: Vec<[f32; D]>,
    dd: Vec<f32>,
    len: Vec<f32>,
    w: Vec<f32>,
    scale: Vec<f32>,
}

impl<const D: usize> Pairs<D> {
    /// [`pair_terms`] of every edge from `dd`, in one vectorisable pass
    /// (chunks in parallel where the crate uses rayon).
    fn terms(&mut self, radius: f32, parallel: bool) {
        let c = CHUNK * 16;
        let parts = self
            .dd
            .chunks(c)
            .zip(self.len.chunks_mut(c))
            .zip(self.w.chunks_mut(c))
            .zip(self.scale.chunks_mut(c))
            .map(|(((dd, len), w), scale)| (dd, len, w, scale));
        let run = |(dd, len, w, scale): TermsChunk<'_>| {
            for (((&dd, len), w), scale) in dd.iter().zip(len).zip(w).zip(scale) {
                (*len, *w, *scale) = pair_terms(dd, radius);
            }
        };
        if parallel {
            parts.par_bridge().for_each(run);
        } else {
            parts.for_each(run);
        }
    }

    /// Recomputes the separation and squared length of the edges from the
    /// positions `x`, receiver by receiver (`x_i` read once): all of them,
    /// or with `changed = Some((dirty, moved))` those of a dirty receiver
    /// whose receiver or sender moved. Chunks of receivers in parallel
    /// where the crate uses rayon.
    fn separations(
        &mut self,
        x: &[[f32; D]],
        offsets: &[usize],
        senders: &[u32],
        changed: Option<(&[bool], &[bool])>,
        parallel: bool,
    ) {
        let n = x.len();
        let fill = |first: usize, sep: &mut [[f32; D]], dd: &mut [f32]| {
            let base = offsets[first];
            let last = (first + CHUNK).min(n);
            for i in first..last {
                let all = match changed {
                    None => true,
                    Some((dt, _)) if !dt[i] => continue,
                    Some((_, mv)) => mv[i],
                };
                let xi = &x[i];
                for e in offsets[i]..offsets[i + 1] {
                    let j = senders[e] as usize;
                    if all || changed.is_some_and(|(_, mv)| mv[j]) {
                        (sep[e - base], dd[e - base]) = separation(xi, &x[j]);
                    }
                }
            }
        };
        // the edges of each chunk of CHUNK receivers
        let lens: Vec<usize> = (0..n)
            .step_by(CHUNK)
            .map(|f| offsets[(f + CHUNK).min(n)] - offsets[f])
            .collect();
        let parts = crate::split_by(&mut self.sep, &lens)
            .into_iter()
            .zip(crate::split_by(&mut self.dd, &lens))
            .enumerate();
        if parallel {
            parts
                .collect::<Vec<_>>()
                .into_par_iter()
                .for_each(|(c, (sep, dd))| fill(c * CHUNK, sep, dd));
        } else {
            parts.for_each(|(c, (sep, dd))| fill(c * CHUNK, sep, dd));
        }
    }

    /// `dW/dx_i` of edge `e` (receiver `i`, sender `j`), as [`gradient`]
    /// gives it; `None` where the pair is `R` or more apart (zero gradient).
    #[inline(always)]
    fn gradient(&self, e: usize, i: usize, j: usize, radius: f32) -> Option<[f32; D]> {
        if self.w[e] == 0.0 {
            // q >= 1 (for q < 1, W = (1 - q)^2 >= 2^-48 > 0)
            return None;
        }
        let mut g = [0.0f32; D];
        if self.len[e] == 0.0 {
            g[0] = if i < j { 2.0 / radius } else { -2.0 / radius };
        } else {
            for (g, &d) in g.iter_mut().zip(&self.sep[e]) {
                *g = self.scale[e] * d;
            }
        }
        Some(g)
    }
}

/// `x_i - x_j` and its squared length, summed left to right (no fused multiply-add).
#[inline(always)]
fn separation<const D: usize>(xi: &[f32; D], xj: &[f32; D]) -> ([f32; D], f32) {
    let mut d = [0.0f32; D];
    let mut dd = 0.0f32;
    for k in 0..D {
        d[k] = xi[k] - xj[k];
        dd += d[k] * d[k];
    }
    (d, dd)
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
    let eps = 1e-6 / (radius * radius);
    let inv_rho0_sq = 1.0 / (rho0 * rho0);
    let min_len = CHUNK;
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
                pairs.separations(x, offsets, senders, Some((dt, mv)), parallel);
                pairs.terms(radius, parallel);
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
        let pairs_ref = &pairs;
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
                rho += pairs_ref.w[e];
            }
            let c = rho / rho0 - 1.0;
            if c > 0.0 {
                let mut sum = [0.0f32; D];
                let mut sq = 0.0f32;
                for e in edges {
                    if let Some(gw) = pairs_ref.gradient(e, i, senders[e] as usize, radius) {
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
            for (e, &j) in (offsets[i]..).zip(&senders[offsets[i]..offsets[i + 1]]) {
                let j = j as usize;
                let s = lam[i] + lam[j];
                if s == 0.0 {
                    continue;
                }
                if let Some(gw) = pairs_ref.gradient(e, i, j, radius) {
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
    stats
}

/// What [`relax_then_graph`] returns besides the moved positions.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct RelaxedGraph {
    /// The relaxation's statistics, as [`relax_density`] gives them.
    pub stats: RelaxStats,
    /// Particles that had a coordinate outside the bounds after the
    /// relaxation (then clipped again; the first clipping is not counted).
    pub clamped: usize,
    /// Receiver `i`'s senders are `senders[offsets[i]..offsets[i + 1]]`,
    /// ascending: the radius graph of the final positions as
    /// [`Neighbors::csr`] gives it (write it out with [`write_edges`]).
    pub offsets: Vec<usize>,
    /// See `offsets`.
    pub senders: Vec<u32>,
    /// Edges removed by `max_neighbors` (0 without a cap).
    pub dropped: usize,
    /// Particles whose neighbour lists were searched again at their final
    /// position (the others' lists were kept); all of them when the graph was
    /// built from scratch.
    pub searched: usize,
}

/// Every coordinate clipped to `bounds` (`lo`, `hi`; `x < lo` becomes
/// `lo`, `x > hi` becomes `hi`, as `numpy.clip`), then [`relax_density`],
/// then the coordinates clipped again, then the radius graph of the result
/// ([`radius_graph`] with `graph`): the neural simulator's work between two
/// network steps, in one call (without `bounds`: no clipping).
///
/// The graph is the one [`Neighbors::search`] finds at the final positions,
/// edge for edge, but is built from the relaxation's neighbour lists: a
/// particle that the relaxation and the clipping left where it was keeps
/// its list, less the particles that moved; each particle that moved is
/// searched again (a cell list of the final positions) and added to the
/// lists of its new neighbours (the relation is symmetric). When more than
/// a quarter of the particles moved (measured: at 46% moved, updating the
/// lists of a 2D dam break cost more than searching them again), with
/// `max_neighbors` (a cap is not symmetric), with another radius, or from
/// [`SERIAL_PARTICLES`] particles (where the search runs on rayon), the
/// graph is searched from scratch instead.
///
/// `positions` `[N][D]` `f32` in position units (m), replaced by the
/// result; `movable` `[N]`; `bounds` in position units. The relaxation is
/// the module's (Neural SPH, Toshev et al. 2024, Sec. 4; PBF, Macklin &
/// Müller 2013, Eqs. 1-12, made unilateral); the graph is GNS's radius
/// graph (Sanchez-Gonzalez et al. 2020, App. A).
///
/// # Errors
/// As [`relax_density`] and [`radius_graph`] (`graph` is checked first;
/// the edge budget `graph.max_edges` applies to the result, `"radius"`).
/// On error `positions` is unchanged.
///
/// [`SERIAL_PARTICLES`]: crate::SERIAL_PARTICLES
pub fn relax_then_graph<const D: usize>(
    positions: &mut [[f32; D]],
    movable: &[bool],
    params: &RelaxParams,
    bounds: Option<([f32; D], [f32; D])>,
    graph: &GraphParams,
) -> Result<RelaxedGraph, GraphError> {
    graph.validate()?;
    params.validate()?;
    let n = positions.len();
    if movable.len() != n {
        return Err(GraphError::invalid(
            "movable",
            format!("has {} entries for {} particles", movable.len(), n),
        ));
    }
    if let Some((lo, hi)) = &bounds
        && (0..D).any(|k| !(lo[k].is_finite() && hi[k].is_finite() && lo[k] <= hi[k]))
    {
        return Err(GraphError::invalid(
            "bounds",
            format!("must be finite with lo <= hi, got {lo:?}, {hi:?}"),
        ));
    }
    let gp = GraphParams {
        radius: params.radius,
        self_edges: false,
        ..GraphParams::default()
    };
    let mut before = positions.to_vec();
    if let Some((lo, hi)) = &bounds {
        clip(&mut before, lo, hi);
    }
    let (offsets, senders) = Neighbors::search(&before, &gp)?.csr();
    let mut work = before.clone();
    let stats = relax_on(&mut work, movable, params, &offsets, &senders);
    let clamped = match &bounds {
        Some((lo, hi)) => clip(&mut work, lo, hi),
        None => 0,
    };
    let moved: Vec<bool> = work
        .iter()
        .zip(&before)
        .map(|(a, b)| a.map(f32::to_bits) != b.map(f32::to_bits))
        .collect();
    let count = moved.iter().filter(|&&m| m).count();
    let from_scratch = count * 4 > n
        || graph.max_neighbors.is_some()
        || graph.radius.to_bits() != params.radius.to_bits()
        || crate::uses_rayon(n);
    let (offsets, senders, dropped, searched) = if from_scratch {
        let nb = Neighbors::search(&work, graph)?;
        let dropped = nb.dropped();
        let (o, s) = nb.csr();
        (o, s, dropped, n)
    } else {
        let (o, s) = updated_lists(&work, &moved, graph, &offsets, &senders)?;
        (o, s, 0, count)
    };
    positions.copy_from_slice(&work);
    Ok(RelaxedGraph {
        stats,
        clamped,
        offsets,
        senders,
        dropped,
        searched,
    })
}

/// Clips every coordinate to `[lo, hi]` (`x < lo` becomes `lo`, `x > hi`
/// becomes `hi`, as `numpy.clip`); returns the particles that had one outside.
fn clip<const D: usize>(x: &mut [[f32; D]], lo: &[f32; D], hi: &[f32; D]) -> usize {
    let mut clamped = 0;
    for p in x.iter_mut() {
        let mut out = false;
        for k in 0..D {
            if p[k] < lo[k] {
                p[k] = lo[k];
                out = true;
            } else if p[k] > hi[k] {
                p[k] = hi[k];
                out = true;
            }
        }
        clamped += out as usize;
    }
    clamped
}

/// The neighbour lists within `graph.radius` at `x` (CSR, self-edges as
/// `graph.self_edges`) from `offsets`/`senders`, the lists without
/// self-edges at the positions before the particles flagged in `moved`
/// moved (module docs of [`relax_then_graph`]).
fn updated_lists<const D: usize>(
    x: &[[f32; D]],
    moved: &[bool],
    graph: &GraphParams,
    offsets: &[usize],
    senders: &[u32],
) -> Result<(Vec<usize>, Vec<u32>), GraphError> {
    let n = x.len();
    let rr = graph.radius * graph.radius;
    let cells = crate::CellList::build(x, crate::reach(rr));
    // each moved particle's list at its final position (self-edge dropped);
    // and, for every particle that did not move, the moved ones that are now
    // its neighbours, in ascending order (moved particles are visited so)
    let mut fresh_offsets = vec![0usize];
    let mut fresh: Vec<u32> = Vec::new();
    let mut add_count = vec![0u32; n + 1];
    let mut ranges = Vec::new();
    let mut buf = Vec::new();
    for i in (0..n).filter(|&i| moved[i]) {
        let cell = cells.linear(&cells.coords(&x[i]));
        cells.neighbourhood(cell, &mut ranges);
        let total: usize = ranges.iter().map(|&(a, b)| b - a).sum();
        buf.resize(total.max(buf.len()), 0);
        let len = cells.accept(&x[i], &ranges, rr, &mut buf);
        for &j in &buf[..len] {
            if j as usize != i {
                fresh.push(j);
                if !moved[j as usize] {
                    add_count[j as usize + 1] += 1;
                }
            }
        }
        fresh_offsets.push(fresh.len());
    }
    for j in 0..n {
        add_count[j + 1] += add_count[j];
    }
    let mut adds = vec![0u32; add_count[n] as usize];
    let mut fill: Vec<u32> = add_count[..n].to_vec();
    for (m, i) in (0..n).filter(|&i| moved[i]).enumerate() {
        for &j in &fresh[fresh_offsets[m]..fresh_offsets[m + 1]] {
            if !moved[j as usize] {
                adds[fill[j as usize] as usize] = i as u32;
                fill[j as usize] += 1;
            }
        }
    }
    // merge: kept (unmoved) senders, the moved ones added, the self-edge
    let mut out_offsets = Vec::with_capacity(n + 1);
    let mut out = Vec::with_capacity(senders.len() + if graph.self_edges { n } else { 0 });
    out_offsets.push(0);
    let mut m = 0;
    for i in 0..n {
        let me = graph.self_edges.then_some(i as u32);
        if moved[i] {
            let list = &fresh[fresh_offsets[m]..fresh_offsets[m + 1]];
            merge_into(&mut out, list.iter().copied(), &[], me);
            m += 1;
        } else {
            let kept = senders[offsets[i]..offsets[i + 1]]
                .iter()
                .copied()
                .filter(|&j| !moved[j as usize]);
            let added = &adds[add_count[i] as usize..add_count[i + 1] as usize];
            merge_into(&mut out, kept, added, me);
        }
        if let Some(m) = graph.max_edges
            && out.len() > m
        {
            return Err(GraphError::invalid(
                "radius",
                format!(
                    "radius {} gives more than max_edges = {m} edges ({n} particles); use a smaller radius, set max_neighbors, or raise max_edges",
                    graph.radius
                ),
            ));
        }
        out_offsets.push(out.len());
    }
    Ok((out_offsets, out))
}

/// Appends to `out` the ascending merge of the ascending `a` and `b`
/// (disjoint) and the optional `extra` (in neither).
fn merge_into(out: &mut Vec<u32>, a: impl Iterator<Item = u32>, b: &[u32], extra: Option<u32>) {
    let mut a = a.peekable();
    let mut b = b.iter().copied().peekable();
    let mut extra = extra;
    loop {
        let next = match (a.peek(), b.peek()) {
            (Some(&x), Some(&y)) if x < y => a.next(),
            (_, Some(_)) => b.next(),
            (Some(_), None) => a.next(),
            (None, None) => None,
        };
        let Some(next) = next else { break };
        if let Some(e) = extra
            && e < next
        {
            out.push(e);
            extra = None;
        }
        out.push(next);
    }
    if let Some(e) = extra {
        out.push(e);
    }
}

/// The edge `(receiver i, sender j)` of the receiver-grouped lists (it
/// exists: the lists are symmetric).
#[inline]
fn mirror(offsets: &[usize], senders: &[u32], i: usize, j: usize) -> usize {
    let list = &senders[offsets[i]..offsets[i + 1]];
    offsets[i] + list.partition_point(|&s| (s as usize) < j)
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
        // a lattice compressed throughout: nearly every pair changes in every
        // iteration (the cache's pass over all pairs)
        let lattice: Vec<[f32; 2]> = (0..900)
            .map(|i| [(i % 30) as f32 * 0.011, (i / 30) as f32 * 0.013])
            .collect();
        let movable = vec![true; lattice.len()];
        for iterations in [2usize, 5] {
            let params = RelaxParams {
                radius: 0.04,
                rest_density: 4.0,
                iterations,
                omega: 1.0,
            };
            let (mut a, mut b) = (lattice.clone(), lattice.clone());
            assert_eq!(
                relax_density(&mut a, &movable, &params).unwrap(),
                relax_reference(&mut b, &movable, &params).unwrap()
            );
            assert!(a.iter().zip(&lattice).filter(|(p, q)| p != q).count() > 800);
            assert!(
                a.iter()
                    .zip(&b)
                    .all(|(p, q)| p.map(f32::to_bits) == q.map(f32::to_bits)),
                "compressed lattice, {iterations} iterations"
            );
        }
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

    /// `relax_density`, the clip and `radius_graph` one after the other.
    fn in_turn<const D: usize>(
        x: &[[f32; D]],
        movable: &[bool],
        params: &RelaxParams,
        bounds: Option<([f32; D], [f32; D])>,
        graph: &GraphParams,
    ) -> (Vec<[f32; D]>, RelaxStats, usize, crate::Graph<D>) {
        let mut p = x.to_vec();
        if let Some((lo, hi)) = bounds {
            for q in p.iter_mut() {
                for k in 0..D {
                    q[k] = q[k].clamp(lo[k], hi[k]);
                }
            }
        }
        let stats = relax_density(&mut p, movable, params).unwrap();
        let mut clamped = 0;
        if let Some((lo, hi)) = bounds {
            for q in p.iter_mut() {
                let before = *q;
                for k in 0..D {
                    q[k] = if q[k] < lo[k] {
                        lo[k]
                    } else if q[k] > hi[k] {
                        hi[k]
                    } else {
                        q[k]
                    };
                }
                clamped += (before != *q) as usize;
            }
        }
        let g = radius_graph(&p, graph).unwrap();
        (p, stats, clamped, g)
    }

    fn fused<const D: usize>(
        x: &[[f32; D]],
        movable: &[bool],
        params: &RelaxParams,
        bounds: Option<([f32; D], [f32; D])>,
        graph: &GraphParams,
    ) -> (Vec<[f32; D]>, RelaxedGraph, crate::Graph<D>) {
        let mut p = x.to_vec();
        let r = relax_then_graph(&mut p, movable, params, bounds, graph).unwrap();
        let e = r.senders.len();
        let mut g = crate::Graph::<D> {
            senders: vec![0; e],
            receivers: vec![0; e],
            displacement: vec![[0.0; D]; e],
            distance: vec![0.0; e],
            dropped: r.dropped,
        };
        crate::write_edges(
            &p,
            &r.offsets,
            &r.senders,
            &mut g.senders,
            &mut g.receivers,
            &mut g.displacement,
            &mut g.distance,
        )
        .unwrap();
        (p, r, g)
    }

    fn same_bits<const D: usize>(a: &[[f32; D]], b: &[[f32; D]]) -> bool {
        a.len() == b.len()
            && a.iter()
                .zip(b)
                .all(|(p, q)| p.map(f32::to_bits) == q.map(f32::to_bits))
    }

    #[test]
    fn relax_then_graph_is_relax_clip_and_graph_in_turn() {
        // clouds with a few compressed clumps (few particles move: the lists
        // are updated) and compressed throughout (most move: searched from
        // scratch), some particles pushed past the bounds, 2D and 3D, with
        // and without self-edges, a cap and another radius
        let mut updated = 0;
        let mut scratch = 0;
        for seed in 0..8u32 {
            // a jittered lattice (spacing 0.04, about 7 neighbours within R = 0.06)
            let mut state = 0x9e37_79b9_7f4a_7c15u64 ^ seed as u64;
            let mut rnd = move || {
                state = state
                    .wrapping_mul(6_364_136_223_846_793_005)
                    .wrapping_add(1_442_695_040_888_963_407);
                (state >> 40) as f32 / (1u64 << 24) as f32
            };
            let mut x2: Vec<[f32; 2]> = (0..600)
                .map(|i| {
                    let (a, b) = ((i % 25) as f32, (i / 25) as f32);
                    [
                        0.02 + 0.04 * a + 0.01 * rnd(),
                        0.02 + 0.04 * b + 0.01 * rnd(),
                    ]
                })
                .collect();
            // the rest density of the cloud before the clumps (nothing else compressed)
            let rho_max = kernel_density(&x2, 0.06)
                .unwrap()
                .into_iter()
                .fold(0.0f32, f32::max);
            for k in 0..(4 + 3 * seed as usize) {
                // clumps by the lower wall
                let c = [0.2 + 0.1 * (k % 5) as f32, 0.03];
                x2[k * 7] = [c[0] + 0.01 * rnd(), c[1] + 0.01 * rnd()];
            }
            let movable: Vec<bool> = (0..x2.len()).map(|i| i % 13 != 5).collect();
            let bounds = Some(([0.025f32, 0.03], [0.99f32, 0.99]));
            let rho0 = if seed % 4 == 3 { 0.5 } else { rho_max * 1.01 };
            for (iterations, self_edges, cap, radius) in [
                (3usize, true, None, 0.06f32),
                (1, false, None, 0.06),
                (3, true, Some(6), 0.06),
                (3, true, None, 0.05),
            ] {
                let params = RelaxParams {
                    radius: 0.06,
                    rest_density: rho0,
                    iterations,
                    omega: 1.0,
                };
                let graph = GraphParams {
                    radius,
                    self_edges,
                    max_neighbors: cap,
                    max_edges: None,
                };
                let (pa, sa, ca, ga) = in_turn(&x2, &movable, &params, bounds, &graph);
                let (pb, rb, gb) = fused(&x2, &movable, &params, bounds, &graph);
                assert!(same_bits(&pa, &pb), "2D seed {seed}");
                assert_eq!((sa, ca), (rb.stats, rb.clamped));
                assert_eq!(
                    ga, gb,
                    "2D seed {seed} {iterations} {self_edges} {cap:?} {radius}"
                );
                if rb.searched < x2.len() {
                    updated += 1;
                } else {
                    scratch += 1;
                }
            }
            let x3: Vec<[f32; 3]> = x2
                .iter()
                .enumerate()
                .map(|(i, p)| [p[0], p[1], ((i as f32) * 0.381_966).fract() * 0.2])
                .collect();
            let params = RelaxParams {
                radius: 0.09,
                rest_density: rho0,
                iterations: 3,
                omega: 1.0,
            };
            let graph = GraphParams {
                radius: 0.09,
                ..GraphParams::default()
            };
            let b3 = Some(([0.0f32, 0.015, 0.0], [1.0f32, 1.0, 0.15]));
            let (pa, sa, ca, ga) = in_turn(&x3, &movable, &params, b3, &graph);
            let (pb, rb, gb) = fused(&x3, &movable, &params, b3, &graph);
            assert!(same_bits(&pa, &pb), "3D seed {seed}");
            assert_eq!((sa, ca), (rb.stats, rb.clamped));
            assert_eq!(ga, gb, "3D seed {seed}");
            assert!(rb.clamped > 0, "the 3D bounds cut the cloud");
        }
        assert!(
            updated >= 4 && scratch >= 8,
            "both ways taken: {updated} updated, {scratch} from scratch"
        );
        // nothing to relax: the relaxation's lists, with the self-edges
        let x: Vec<[f32; 2]> = (0..50)
            .map(|i| [(i % 10) as f32 * 0.1, (i / 10) as f32 * 0.1])
            .collect();
        let params = RelaxParams {
            radius: 0.15,
            rest_density: 100.0,
            iterations: 3,
            omega: 1.0,
        };
        let graph = GraphParams {
            radius: 0.15,
            ..GraphParams::default()
        };
        let (_, rb, gb) = fused(&x, &[true; 50], &params, None, &graph);
        assert_eq!(rb.searched, 0);
        assert_eq!(gb, radius_graph(&x, &graph).unwrap());
        // empty input, bad bounds
        let (p, rb, gb) = fused::<3>(&[], &[], &params, None, &graph);
        assert!(p.is_empty() && rb.senders.is_empty() && gb.is_empty());
        let mut y = x.clone();
        let bad = relax_then_graph(
            &mut y,
            &[true; 50],
            &params,
            Some(([0.5, 0.0], [0.4, 1.0])),
            &graph,
        );
        assert!(matches!(
            bad,
            Err(GraphError::InvalidInput {
                field: "bounds",
                ..
            })
        ));
        assert!(same_bits(&x, &y));
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
