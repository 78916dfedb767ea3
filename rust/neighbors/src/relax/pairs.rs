//! The per-pair cache of the relaxation ([`Pairs`]): each edge's
//! separation and kernel terms, kept between iterations.

use rayon::prelude::*;

use super::CHUNK;
use crate::write::split_by;

/// The kernel terms of one pair from its squared separation `dd` (summed
/// left to right, as the tests' reference `gradient` and the radius graph
/// sum it): its length `r = sqrt(dd)`, `W(q)` (0 for `q >= 1`) and the
/// gradient's scale `-2 (1 - q) / (R r)` (meaningless where `W = 0` or
/// `r = 0`). Each value is the one `gradient` computes (same operations,
/// same order), so the per-pair cache changes no bit. Written branch-free
/// so that a pass over many pairs vectorises (IEEE `sqrt` and division are
/// correctly rounded in any lane width).
#[inline(always)]
pub(super) fn pair_terms(dd: f32, radius: f32) -> (f32, f32, f32) {
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
///
/// [`relax_density`]: super::relax_density
pub(super) struct Pairs<const D: usize> {
    pub(super) sep: Vec<[f32; D]>,
    pub(super) dd: Vec<f32>,
    pub(super) len: Vec<f32>,
    pub(super) w: Vec<f32>,
    pub(super) scale: Vec<f32>,
}

impl<const D: usize> Pairs<D> {
    /// [`pair_terms`] of every edge from `dd`, in one vectorisable pass
    /// (chunks in parallel where the crate uses rayon).
    pub(super) fn terms(&mut self, radius: f32, parallel: bool) {
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
    pub(super) fn separations(
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
        let parts = split_by(&mut self.sep, &lens)
            .into_iter()
            .zip(split_by(&mut self.dd, &lens))
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

    /// `dW/dx_i` of edge `e` (receiver `i`, sender `j`), as the tests'
    /// reference `gradient` gives it; `None` where the pair is `R` or more
    /// apart (zero gradient).
    #[inline(always)]
    pub(super) fn gradient(&self, e: usize, i: usize, j: usize, radius: f32) -> Option<[f32; D]> {
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
pub(super) fn separation<const D: usize>(xi: &[f32; D], xj: &[f32; D]) -> ([f32; D], f32) {
    let mut d = [0.0f32; D];
    let mut dd = 0.0f32;
    for k in 0..D {
        d[k] = xi[k] - xj[k];
        dd += d[k] * d[k];
    }
    (d, dd)
}

/// The edge `(receiver i, sender j)` of the receiver-grouped lists (it
/// exists: the lists are symmetric).
#[inline]
pub(super) fn mirror(offsets: &[usize], senders: &[u32], i: usize, j: usize) -> usize {
    let list = &senders[offsets[i]..offsets[i + 1]];
    offsets[i] + list.partition_point(|&s| (s as usize) < j)
}
