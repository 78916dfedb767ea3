//! The relaxation and the radius graph of its result in one call
//! ([`relax_then_graph`]), the graph built from the relaxation's neighbour
//! lists where few particles moved.

use super::{RelaxParams, RelaxStats, relax_on};
use crate::cell_list::{CellList, reach};
use crate::{GraphError, GraphParams, Neighbors};

/// What [`relax_then_graph`] returns besides the moved positions.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct RelaxedGraph {
    /// The relaxation's statistics, as [`relax_density`] gives them.
    ///
    /// [`relax_density`]: super::relax_density
    pub stats: RelaxStats,
    /// Particles that had a coordinate outside the bounds after the
    /// relaxation (then clipped again; the first clipping is not counted).
    pub clamped: usize,
    /// Receiver `i`'s senders are `senders[offsets[i]..offsets[i + 1]]`,
    /// ascending: the radius graph of the final positions as
    /// [`Neighbors::csr`] gives it (write it out with [`write_edges`]).
    ///
    /// [`write_edges`]: crate::write_edges
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
/// [`radius_graph`]: crate::radius_graph
/// [`relax_density`]: super::relax_density
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
    let cells = CellList::build(x, reach(rr));
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
