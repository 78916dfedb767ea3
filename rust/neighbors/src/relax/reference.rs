//! The plain implementation of the relaxation (before the per-pair cache),
//! kept as the reference the solver must match bit for bit (`tests.rs`).

use super::*;

/// Per-edge kernel gradient `dW/dx_i` of the pair (receiver `i`, sender `j`)
/// and its kernel value; a coincident pair takes the direction `sign(i - j) e_0`
/// (module docs). The reference's; the solver uses `Pairs::gradient`.
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

/// The implementation before the separation cache (5bee28c..4b1aafb),
/// kept as the reference the cached one must match bit for bit.
#[allow(clippy::needless_range_loop)]
pub(super) fn relax_reference<const D: usize>(
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
