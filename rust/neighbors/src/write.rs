//! Phase 2 of the radius graph: the per-edge arrays written from the
//! neighbour lists ([`Neighbors::write`], [`write_edges`]).

use rayon::prelude::*;

use crate::compact::{dot, sub};
use crate::search::{Found, Loc, Neighbors};
use crate::{CHUNK, EdgeIndex, Graph, GraphError, SERIAL_EDGES, uses_rayon};

/// Splits `v` into consecutive pieces of the given lengths (sum <= len).
pub(crate) fn split_by<'a, T>(mut v: &'a mut [T], lens: &[usize]) -> Vec<&'a mut [T]> {
    let mut out = Vec::with_capacity(lens.len());
    for &l in lens {
        let (head, tail) = v.split_at_mut(l);
        out.push(head);
        v = tail;
    }
    out
}

/// Output slices of one chunk of receivers (in index order).
struct OutChunk<'a, const D: usize, I> {
    first: usize,
    s: &'a mut [I],
    r: &'a mut [I],
    dp: &'a mut [[f32; D]],
    ds: &'a mut [f32],
}

impl<const D: usize, I: EdgeIndex> OutChunk<'_, D, I> {
    fn fill(self, positions: &[[f32; D]], found: &[Found], loc: &[Loc]) {
        let mut e = 0;
        for (i, l) in (self.first..).zip(loc) {
            let end = e + l.len as usize;
            let list = &found[l.chunk as usize].senders[l.start..l.start + l.len as usize];
            for (dst, &j) in self.s[e..end].iter_mut().zip(list) {
                *dst = I::from_u32(j);
            }
            self.r[e..end].fill(I::from_u32(i as u32));
            let pi = &positions[i];
            for ((&j, dp), ds) in list
                .iter()
                .zip(&mut self.dp[e..end])
                .zip(&mut self.ds[e..end])
            {
                let d = sub(&positions[j as usize], pi);
                *dp = d;
                *ds = dot(&d);
            }
            e = end;
        }
        // Squared distances -> distances, in one vectorisable pass.
        for x in self.ds.iter_mut() {
            *x = x.sqrt();
        }
    }
}

impl<const D: usize> Neighbors<'_, D> {
    /// Writes the edges (as in [`Graph`]) into caller-provided slices, in
    /// parallel; every element is overwritten, so they may hold anything.
    ///
    /// # Errors
    /// [`GraphError::InvalidInput`] (field `"output"`) if a slice's length is
    /// not [`Neighbors::num_edges`].
    pub fn write<I: EdgeIndex>(
        &self,
        senders: &mut [I],
        receivers: &mut [I],
        displacement: &mut [[f32; D]],
        distance: &mut [f32],
    ) -> Result<(), GraphError> {
        let e = self.num_edges;
        check_output(
            e,
            [
                senders.len(),
                receivers.len(),
                displacement.len(),
                distance.len(),
            ],
        )?;
        // Receivers in index order, CHUNK at a time.
        let lens: Vec<usize> = self
            .loc
            .chunks(CHUNK)
            .map(|c| c.iter().map(|l| l.len as usize).sum())
            .collect();
        let mut s = split_by(senders, &lens).into_iter();
        let mut r = split_by(receivers, &lens).into_iter();
        let mut dp = split_by(displacement, &lens).into_iter();
        let mut ds = split_by(distance, &lens).into_iter();
        let mut parts = Vec::with_capacity(lens.len());
        for c in 0..lens.len() {
            if let (Some(s), Some(r), Some(dp), Some(ds)) =
                (s.next(), r.next(), dp.next(), ds.next())
            {
                parts.push((
                    OutChunk {
                        first: c * CHUNK,
                        s,
                        r,
                        dp,
                        ds,
                    },
                    c,
                ));
            }
        }
        let (positions, found) = (self.positions, &self.found[..]);
        let run = |(o, c): (OutChunk<'_, D, I>, usize)| {
            let loc = &self.loc[c * CHUNK..((c + 1) * CHUNK).min(self.loc.len())];
            o.fill(positions, found, loc);
        };
        if !uses_rayon(self.positions.len()) || e < SERIAL_EDGES {
            parts.into_iter().for_each(run);
        } else {
            parts.into_par_iter().for_each(run);
        }
        Ok(())
    }

    /// Allocates the per-edge arrays and writes the edges into them.
    pub fn into_graph<I: EdgeIndex>(self) -> Graph<D, I> {
        let e = self.num_edges;
        let mut g = Graph::<D, I> {
            senders: vec![I::default(); e],
            receivers: vec![I::default(); e],
            displacement: vec![[0.0f32; D]; e],
            distance: vec![0.0f32; e],
            dropped: self.dropped,
        };
        // Lengths match by construction.
        let written = self.write(
            &mut g.senders,
            &mut g.receivers,
            &mut g.displacement,
            &mut g.distance,
        );
        debug_assert!(written.is_ok());
        g
    }
}

/// The output slices' lengths against the number of edges `e`.
fn check_output(e: usize, lens: [usize; 4]) -> Result<(), GraphError> {
    if lens.iter().any(|&l| l != e) {
        return Err(GraphError::invalid(
            "output",
            format!("slices must have length {e} (the number of edges), got {lens:?}"),
        ));
    }
    Ok(())
}

/// Writes the edges of neighbour lists in CSR form (receiver `i`'s senders
/// `senders[offsets[i]..offsets[i + 1]]`, as [`Neighbors::csr`] gives them)
/// as [`Neighbors::write`] does: senders, receivers, `p[sender] -
/// p[receiver]` and its length, in receiver order.
///
/// # Errors
/// [`GraphError::InvalidInput`] (field `"output"`) if a slice's length is
/// not the number of edges or `offsets` does not fit `positions`.
pub fn write_edges<const D: usize, I: EdgeIndex>(
    positions: &[[f32; D]],
    offsets: &[usize],
    senders: &[u32],
    out_senders: &mut [I],
    out_receivers: &mut [I],
    displacement: &mut [[f32; D]],
    distance: &mut [f32],
) -> Result<(), GraphError> {
    let e = senders.len();
    check_output(
        e,
        [
            out_senders.len(),
            out_receivers.len(),
            displacement.len(),
            distance.len(),
        ],
    )?;
    let n = positions.len();
    if offsets.len() != n + 1
        || offsets.first() != Some(&0)
        || offsets.last() != Some(&e)
        || offsets.windows(2).any(|w| w[0] > w[1])
        || senders.iter().any(|&j| j as usize >= n)
    {
        return Err(GraphError::invalid(
            "output",
            format!("offsets must ascend from 0 to {e} over {n} particles and senders be < {n}"),
        ));
    }
    for i in 0..positions.len() {
        let (a, b) = (offsets[i], offsets[i + 1]);
        let pi = &positions[i];
        for e in a..b {
            let j = senders[e];
            out_senders[e] = I::from_u32(j);
            out_receivers[e] = I::from_u32(i as u32);
            let d = sub(&positions[j as usize], pi);
            displacement[e] = d;
            distance[e] = dot(&d);
        }
    }
    for x in distance.iter_mut() {
        *x = x.sqrt();
    }
    Ok(())
}
