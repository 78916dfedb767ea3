//! Rigid colliders given as signed-distance shapes, static or moving.
//!
//! A grid node whose position has `sdf < 0` lies inside the collider and its
//! velocity is constrained by the collider's [`BoundaryCondition`].
//!
//! A collider may translate (a paddle, a dragged obstacle): its *anchor*
//! ([`Shape::anchor`]: a box's or sphere's centre, a sampled shape's
//! `origin`) moves and the shape moves with it, unrotated. A moving
//! collider's condition acts on the grid velocity relative to its own
//! ([`apply_condition_moving`]), so it pushes the fluid. The solver moves
//! it ([`crate::Solver::move_collider`]); a collider that does not move
//! takes the static path ([`apply_condition`]) bit for bit.
//!
//! A collider holds only if enough grid nodes fall inside it: a node in the
//! lower half of a plate gets the bottom face's normal and lets fluid from
//! above through. Measured (2D water and sand dropped on a plate spanning
//! the domain, 200 frames, plate offsets of 0.05-cell steps against the
//! nodes): plates of 1, 1.5, 1.75 and 1.9 cells let up to 494 of 494
//! particles through, 2 cells and more none; circles of radius up to 1.45
//! cells let particles through their centre, 1.5 cells and more none.
//! [`Collider::validate_resolution`] therefore refuses boxes thinner than
//! [`MIN_BOX_THICKNESS_CELLS`] and spheres of radius below
//! [`MIN_SPHERE_RADIUS_CELLS`]. (A box of exactly 2 cells rotated by 5-10°
//! still let up to 14 of 806 particles through in the same test; 3 cells held.)
//!
//! A [`Shape::Sampled`] collider (a triangle mesh's signed distance sampled
//! on a grid, made by the Python scene layer) holds by the same rule stated
//! on its samples: [`Collider::validate_resolution`] refuses one whose
//! deepest sample lies less than [`MIN_SAMPLED_DEPTH_CELLS`] cells inside
//! (a plate's centre is 1 cell deep at the 2-cell box limit).

use std::sync::Arc;

use nalgebra::{SMatrix, SVector};

use crate::boundary::BoundaryCondition;
use crate::error::{MpmError, Result};

/// A signed-distance shape in `D` dimensions.
#[derive(Clone, Debug, PartialEq)]
pub enum Shape<const D: usize> {
    /// Box with centre, half extents and a rotation (columns = local axes in
    /// world coordinates; a rotated box makes a ramp).
    Box {
        center: SVector<f32, D>,
        half_extents: SVector<f32, D>,
        rotation: SMatrix<f32, D, D>,
    },
    /// Sphere (circle in 2D).
    Sphere {
        center: SVector<f32, D>,
        radius: f32,
    },
    /// Signed distance [m] sampled on a regular grid (a triangle mesh's, in
    /// practice): node `(i_0, .., i_{D-1})` sits at `origin + cell · i` and
    /// holds `values[((i_0 · dims[1] + i_1) · dims[2] + i_2) ...]` (row-major,
    /// the last axis fastest). Inside the grid the distance is the
    /// multilinear interpolant of the samples; outside it, the interpolant
    /// at the nearest point of the grid's box plus the distance to that box
    /// (positive when the border samples are, as a margin around the mesh
    /// makes them). The normal is the normalised multilinear interpolant of
    /// `normals` (at the nearest point of the box outside it); without
    /// `normals`, the normalised central difference, step `cell`, of the
    /// distance. (A central difference fails inside parts a few cells thin,
    /// where the slopes of the two faces cancel: there a mesh's sampled
    /// normals point to the nearest surface point, as a box's least
    /// penetration does.)
    Sampled {
        origin: SVector<f32, D>,
        cell: f32,
        dims: [usize; D],
        values: Arc<[f32]>,
        /// Optional outward unit normals at the nodes, `D` numbers per node
        /// in the order of `values` (a mesh's: the direction between the
        /// node and its nearest surface point where a central difference of
        /// the distance fails).
        normals: Option<Arc<[f32]>>,
    },
}

/// Most samples a [`Shape::Sampled`] may hold (64 MiB of `f32`).
pub const MAX_SAMPLED_NODES: usize = 1 << 24;

/// `⌊u⌋` as an index, for `0 ≤ u < 2^32` (the index of a sampled grid's
/// node or below; NaN gives 0 as `floor` would): the cast truncates, which
/// is the floor there. `f32::floor` would be a call to libm's `floorf` in
/// the portable x86-64 build (SSE2 has no rounding instruction).
#[inline(always)]
fn floor_index(u: f32) -> usize {
    debug_assert!(
        u.is_nan() || (0.0..4294967296.0).contains(&u),
        "floor_index of {u}"
    );
    u as u32 as usize
}

/// The multilinear interpolant of the node vectors `normals` (`D` per node)
/// at the nearest point of the grid's box to `rel`, the point relative to
/// the grid's origin ([`Shape::local`]).
fn sampled_normal<const D: usize>(
    cell: f32,
    dims: &[usize; D],
    normals: &[f32],
    rel: &SVector<f32, D>,
) -> SVector<f32, D> {
    let mut idx = [0usize; D];
    let mut t = [0.0f32; D];
    for d in 0..D {
        let uc = (rel[d] / cell).clamp(0.0, (dims[d] - 1) as f32);
        let i = floor_index(uc).min(dims[d] - 2);
        idx[d] = i;
        t[d] = uc - i as f32;
    }
    let mut acc = SVector::<f32, D>::zeros();
    for corner in 0..(1usize << D) {
        let mut w = 1.0f32;
        let mut lin = 0usize;
        for d in 0..D {
            let b = (corner >> d) & 1;
            w *= if b == 1 { t[d] } else { 1.0 - t[d] };
            lin = lin * dims[d] + idx[d] + b;
        }
        if w != 0.0 {
            for d in 0..D {
                acc[d] += w * normals[lin * D + d];
            }
        }
    }
    acc
}

/// The multilinear interpolant of a sampled grid at `rel`, the point
/// relative to the grid's origin ([`Shape::local`]), extended outside the
/// grid's box by the distance to the box (see [`Shape::Sampled`]).
fn sampled_sdf<const D: usize>(
    cell: f32,
    dims: &[usize; D],
    values: &[f32],
    rel: &SVector<f32, D>,
) -> f32 {
    let mut outside2 = 0.0f32;
    let mut idx = [0usize; D];
    let mut t = [0.0f32; D];
    for d in 0..D {
        let u = rel[d] / cell;
        let top = (dims[d] - 1) as f32;
        let uc = u.clamp(0.0, top);
        let excess = (u - uc) * cell;
        outside2 += excess * excess;
        let i = floor_index(uc).min(dims[d] - 2);
        idx[d] = i;
        t[d] = uc - i as f32;
    }
    let mut acc = 0.0f32;
    for corner in 0..(1usize << D) {
        let mut w = 1.0f32;
        let mut lin = 0usize;
        for d in 0..D {
            let b = (corner >> d) & 1;
            w *= if b == 1 { t[d] } else { 1.0 - t[d] };
            lin = lin * dims[d] + idx[d] + b;
        }
        acc += w * values[lin];
    }
    acc + outside2.sqrt()
}

/// The plane estimate `φ_0 + n_0·off` of the distance at `rel` (the point
/// relative to a sampled grid's origin, [`Shape::local`]) of corner 0 (the
/// lowest) of the grid's cell `idx`, with `off = rel − x_0`: a lower bound
/// of the cell's largest corner estimate ([`Shape::step_below`]). Returns
/// the corner's row-major position, `off` and the estimate.
#[inline(always)]
fn corner0_estimate<const D: usize>(
    cell: f32,
    dims: &[usize; D],
    values: &[f32],
    normals: &[f32],
    rel: &SVector<f32, D>,
    idx: &[usize; D],
) -> (usize, SVector<f32, D>, f32) {
    let mut lin = 0usize;
    let mut off = SVector::<f32, D>::zeros();
    for d in 0..D {
        lin = lin * dims[d] + idx[d];
        // (idx < 2^24, MAX_SAMPLED_NODES: exact through u32, which converts
        // in one instruction where usize does not)
        off[d] = rel[d] - idx[d] as u32 as f32 * cell;
    }
    let mut est = values[lin];
    for d in 0..D {
        est += normals[lin * D + d] * off[d];
    }
    (lin, off, est)
}

/// A collider: shape + boundary condition + Coulomb friction, and whether
/// particles that end a substep inside it are put back on its surface
/// ([`Collider::project_particle`]).
#[derive(Clone, Debug, PartialEq)]
pub struct Collider<const D: usize> {
    pub shape: Shape<D>,
    pub condition: BoundaryCondition,
    pub friction: f32,
    /// Project particles out of the collider after each substep's g2p
    /// ([`Collider::project_particle`]). Off, the collider acts on grid
    /// nodes only, as it always did, and particles may end up to about a
    /// cell inside it.
    pub project: bool,
}

impl<const D: usize> Shape<D> {
    /// The query point `p` [m] in the shape's own frame: relative to its
    /// [`Shape::anchor`] where the shape is now (a moving collider's anchor
    /// moves), and for a box along its local axes. Every distance and normal
    /// is evaluated there.
    fn local(&self, p: &SVector<f32, D>) -> SVector<f32, D> {
        let rel = p - self.anchor();
        match self {
            Shape::Box { rotation, .. } => rotation.transpose() * rel,
            Shape::Sphere { .. } | Shape::Sampled { .. } => rel,
        }
    }

    /// Signed distance [m] (negative inside).
    pub fn sdf(&self, p: &SVector<f32, D>) -> f32 {
        let local = self.local(p);
        match self {
            Shape::Box { half_extents, .. } => {
                let q = local.abs() - half_extents;
                let outside = q.map(|x| x.max(0.0)).norm();
                let inside = q.max().min(0.0);
                outside + inside
            }
            Shape::Sphere { radius, .. } => local.norm() - radius,
            Shape::Sampled {
                cell, dims, values, ..
            } => sampled_sdf(*cell, dims, values, &local),
        }
    }

    /// Outward unit normal at `p` (gradient of the SDF).
    pub fn normal(&self, p: &SVector<f32, D>) -> SVector<f32, D> {
        match self {
            Shape::Box {
                half_extents,
                rotation,
                ..
            } => {
                let local = self.local(p);
                let q = local.abs() - half_extents;
                let mut n = SVector::<f32, D>::zeros();
                if q.max() > 0.0 {
                    for d in 0..D {
                        n[d] = q[d].max(0.0) * local[d].signum();
                    }
                } else {
                    // inside: the face of least penetration
                    let d = q.imax();
                    n[d] = local[d].signum();
                }
                let n = rotation * n;
                let len = n.norm();
                if len > 0.0 { n / len } else { n }
            }
            Shape::Sphere { .. } => {
                let d = self.local(p);
                let len = d.norm();
                if len > 0.0 {
                    d / len
                } else {
                    let mut n = SVector::<f32, D>::zeros();
                    n[1] = 1.0;
                    n
                }
            }
            Shape::Sampled {
                cell,
                dims,
                normals,
                ..
            } => {
                let n = match normals {
                    Some(normals) => sampled_normal(*cell, dims, normals, &self.local(p)),
                    None => {
                        let mut n = SVector::<f32, D>::zeros();
                        for d in 0..D {
                            let mut a = *p;
                            let mut b = *p;
                            a[d] += cell;
                            b[d] -= cell;
                            n[d] = self.sdf(&a) - self.sdf(&b);
                        }
                        n
                    }
                };
                let len = n.norm();
                if len > 0.0 {
                    n / len
                } else {
                    // a flat spot (no sample differs): up, as a sphere's centre
                    let mut n = SVector::<f32, D>::zeros();
                    n[1] = 1.0;
                    n
                }
            }
        }
    }

    /// The signed distance at `p` and the outward normal to step along, as
    /// the particle projection takes them ([`Collider::project_particle`]):
    /// a box's or sphere's [`Shape::sdf`] and [`Shape::normal`]; for a
    /// sampled shape with `normals`, inside its grid, the largest of the
    /// first-order estimates `φ_i + n_i·(p − x_i)` of the corners `x_i` of
    /// the cell around `p` (the plane of each corner's nearest surface
    /// point) with that corner's normal. Multilinear interpolation of the
    /// distance misjudges depth near inner ridges and edges (a rotated
    /// plate a few cells thick reads up to half a cell shallower than it
    /// is where the corners' nearest faces differ); the largest plane
    /// estimate is exact for a convex polyhedron whose nearest faces the
    /// corners see, and within `O(cell²/R)` of a smooth surface of
    /// curvature radius `R`.
    pub fn surface_step(&self, p: &SVector<f32, D>) -> (f32, SVector<f32, D>) {
        self.step_below(p, f32::NEG_INFINITY)
            .unwrap_or((f32::NAN, SVector::zeros()))
    }

    /// [`Shape::surface_step`] where its distance is below `−depth`, else
    /// `None`; the normal is found only then, and a sampled shape's other
    /// corner planes only where the first corner's estimate (a lower bound
    /// of the largest) is below `−depth`.
    #[inline]
    pub fn step_below(&self, p: &SVector<f32, D>, depth: f32) -> Option<(f32, SVector<f32, D>)> {
        if let Shape::Sampled {
            cell,
            dims,
            values,
            normals: Some(normals),
            ..
        } = self
        {
            let rel = self.local(p);
            let mut idx = [0usize; D];
            let mut inside = true;
            for d in 0..D {
                let u = rel[d] / cell;
                inside &= u >= 0.0 && u <= (dims[d] - 1) as f32;
                idx[d] = floor_index(u.max(0.0)).min(dims[d] - 2);
            }
            if inside {
                let (lin0, off0, est0) = corner0_estimate(*cell, dims, values, normals, &rel, &idx);
                if est0 >= -depth {
                    return None;
                }
                let mut best = (est0, lin0);
                for corner in 1..(1usize << D) {
                    let mut lin = 0usize;
                    for d in 0..D {
                        lin = lin * dims[d] + idx[d] + ((corner >> d) & 1);
                    }
                    let mut est = values[lin];
                    for d in 0..D {
                        let b = ((corner >> d) & 1) as f32;
                        est += normals[lin * D + d] * (off0[d] - b * cell);
                    }
                    if est > best.0 {
                        best = (est, lin);
                    }
                }
                let (phi, lin) = best;
                let n = SVector::<f32, D>::from_fn(|d, _| normals[lin * D + d]);
                let len = n.norm();
                if len > 0.0 {
                    return (phi < -depth).then(|| (phi, n / len));
                }
            }
        }
        let phi = self.sdf(p);
        (phi < -depth).then(|| (phi, self.normal(p)))
    }

    /// Whether the signed distance is `≥ 0` everywhere outside the shape's
    /// sampled grid's box: a sampled shape whose border samples are all
    /// `≥ 0` (a mesh's, with its margin of samples around the mesh, unless
    /// the mesh reaches the domain's side): outside the box the distance is
    /// the interpolant of border samples (nonnegative weights) plus a
    /// distance ([`Shape::Sampled`]). False for a box or sphere. Reads every
    /// border sample.
    fn nonnegative_outside_grid(&self) -> bool {
        let Shape::Sampled { dims, values, .. } = self else {
            return false;
        };
        let total: usize = dims.iter().product();
        // row-major strides
        let mut stride = [1usize; D];
        for d in (0..D.saturating_sub(1)).rev() {
            stride[d] = stride[d + 1] * dims[d + 1];
        }
        // each face: the samples with index 0 or dims[d] − 1 on axis d
        for d in 0..D {
            for side in [0, dims[d] - 1] {
                for k in 0..total / dims[d] {
                    // k over the other axes (row-major), index `side` on axis d
                    let (mut rest, mut lin) = (k, side * stride[d]);
                    for e in (0..D).rev().filter(|&e| e != d) {
                        lin += (rest % dims[e]) * stride[e];
                        rest /= dims[e];
                    }
                    if !(values[lin] >= 0.0) {
                        return false;
                    }
                }
            }
        }
        true
    }

    /// Radius of a ball around the shape's centre that contains it.
    pub fn bounding_radius(&self) -> f32 {
        match self {
            Shape::Box { half_extents, .. } => half_extents.norm(),
            Shape::Sphere { radius, .. } => *radius,
            Shape::Sampled { cell, dims, .. } => {
                0.5 * cell
                    * (0..D)
                        .map(|d| ((dims[d] - 1) as f32).powi(2))
                        .sum::<f32>()
                        .sqrt()
            }
        }
    }

    /// The point that places the shape: a box's or sphere's `center`, a
    /// sampled shape's `origin` [m].
    pub fn anchor(&self) -> SVector<f32, D> {
        match self {
            Shape::Box { center, .. } | Shape::Sphere { center, .. } => *center,
            Shape::Sampled { origin, .. } => *origin,
        }
    }

    /// Moves the shape (no rotation) so that its [`Shape::anchor`] is `anchor`.
    pub fn set_anchor(&mut self, anchor: SVector<f32, D>) {
        match self {
            Shape::Box { center, .. } | Shape::Sphere { center, .. } => *center = anchor,
            Shape::Sampled { origin, .. } => *origin = anchor,
        }
    }

    pub fn center(&self) -> SVector<f32, D> {
        match self {
            Shape::Box { center, .. } | Shape::Sphere { center, .. } => *center,
            Shape::Sampled {
                origin, cell, dims, ..
            } => origin + SVector::<f32, D>::from_fn(|d, _| 0.5 * cell * (dims[d] - 1) as f32),
        }
    }
}

impl<const D: usize> Collider<D> {
    pub fn validate(&self, field: &str) -> Result<()> {
        let bad = |f: &str, m: String| Err(MpmError::invalid(format!("{field}.{f}"), m));
        match &self.shape {
            Shape::Box {
                center,
                half_extents,
                rotation,
            } => {
                if !center.iter().all(|x| x.is_finite()) {
                    return bad("center", "must be finite".into());
                }
                if !half_extents.iter().all(|x| x.is_finite() && *x > 0.0) {
                    return bad(
                        "half_extents",
                        format!("must be finite and > 0, got {:?}", half_extents.as_slice()),
                    );
                }
                let i = SMatrix::<f32, D, D>::identity();
                if !rotation.iter().all(|x| x.is_finite())
                    || (rotation.transpose() * rotation - i).norm() > 1e-3
                {
                    return bad("rotation", "must be a finite orthonormal matrix".into());
                }
            }
            Shape::Sphere { center, radius } => {
                if !center.iter().all(|x| x.is_finite()) {
                    return bad("center", "must be finite".into());
                }
                if !(radius.is_finite() && *radius > 0.0) {
                    return bad("radius", format!("must be finite and > 0, got {radius}"));
                }
            }
            Shape::Sampled {
                origin,
                cell,
                dims,
                values,
                normals,
            } => {
                if !origin.iter().all(|x| x.is_finite()) {
                    return bad("origin", "must be finite".into());
                }
                if !(cell.is_finite() && *cell > 0.0) {
                    return bad("cell", format!("must be finite and > 0, got {cell}"));
                }
                if dims.iter().any(|&n| n < 2) {
                    return bad("dims", format!("must be >= 2 on every axis, got {dims:?}"));
                }
                let total = dims.iter().try_fold(1usize, |acc, &n| acc.checked_mul(n));
                match total {
                    Some(t) if t <= MAX_SAMPLED_NODES => {
                        if values.len() != t {
                            return bad(
                                "values",
                                format!(
                                    "expected {t} samples (dims {dims:?}), got {}",
                                    values.len()
                                ),
                            );
                        }
                    }
                    _ => {
                        return bad(
                            "dims",
                            format!(
                                "{dims:?} is more than the {MAX_SAMPLED_NODES} samples allowed"
                            ),
                        );
                    }
                }
                if let Some(i) = values.iter().position(|v| !v.is_finite()) {
                    return bad("values", format!("sample {i} is not finite"));
                }
                if let Some(normals) = normals {
                    if normals.len() != D * values.len() {
                        return bad(
                            "normals",
                            format!(
                                "expected {} numbers ({D} per sample), got {}",
                                D * values.len(),
                                normals.len()
                            ),
                        );
                    }
                    if let Some(i) = normals.iter().position(|v| !v.is_finite()) {
                        return bad("normals", format!("number {i} is not finite"));
                    }
                }
            }
        }
        if !(self.friction.is_finite() && self.friction >= 0.0) {
            return bad(
                "friction",
                format!("must be finite and >= 0, got {}", self.friction),
            );
        }
        Ok(())
    }
}

/// Thinnest box (in grid cells, along each of its local axes) that holds.
pub const MIN_BOX_THICKNESS_CELLS: f32 = 2.0;
/// Smallest sphere radius (in grid cells) that holds.
pub const MIN_SPHERE_RADIUS_CELLS: f32 = 1.5;
/// Least depth (in grid cells) of the deepest sample of a sampled shape:
/// half of [`MIN_BOX_THICKNESS_CELLS`].
pub const MIN_SAMPLED_DEPTH_CELLS: f32 = 0.5 * MIN_BOX_THICKNESS_CELLS;

impl<const D: usize> Collider<D> {
    /// Refuses a collider too thin for a grid of spacing `dx` (particles
    /// would fall through it; see the module docs for the measurement):
    /// a box with a side below [`MIN_BOX_THICKNESS_CELLS`] cells (field
    /// `{field}.half_extents`), a sphere of radius below
    /// [`MIN_SPHERE_RADIUS_CELLS`] cells (`{field}.radius`), a sampled shape
    /// with no sample [`MIN_SAMPLED_DEPTH_CELLS`] cells inside (`{field}.values`).
    pub fn validate_resolution(&self, field: &str, dx: f32) -> Result<()> {
        match &self.shape {
            Shape::Box { half_extents, .. } => {
                let min_thickness = MIN_BOX_THICKNESS_CELLS * dx;
                if let Some(axis) = (0..D).find(|&d| 2.0 * half_extents[d] < min_thickness) {
                    let t = 2.0 * half_extents[axis];
                    return Err(MpmError::invalid(
                        format!("{field}.half_extents"),
                        format!(
                            "thinner than {MIN_BOX_THICKNESS_CELLS} grid cells along its axis {axis}: thickness {t} m = {:.3} cells (dx = {dx} m); particles would fall through it. Make it at least {min_thickness} m thick (half extent >= {}) or use a finer grid",
                            t / dx,
                            0.5 * min_thickness
                        ),
                    ));
                }
            }
            Shape::Sphere { radius, .. } => {
                let min_radius = MIN_SPHERE_RADIUS_CELLS * dx;
                if *radius < min_radius {
                    return Err(MpmError::invalid(
                        format!("{field}.radius"),
                        format!(
                            "smaller than {MIN_SPHERE_RADIUS_CELLS} grid cells: radius {radius} m = {:.3} cells (dx = {dx} m); particles would pass through it. Make it at least {min_radius} m or use a finer grid",
                            radius / dx
                        ),
                    ));
                }
            }
            Shape::Sampled { values, .. } => {
                let deepest = values.iter().fold(f32::INFINITY, |a, &v| a.min(v));
                if !(deepest <= -MIN_SAMPLED_DEPTH_CELLS * dx) {
                    return Err(MpmError::invalid(
                        format!("{field}.values"),
                        format!(
                            "thinner than the solver holds: its deepest sample is {:.3} cells inside (dx = {dx} m), less than {MIN_SAMPLED_DEPTH_CELLS}; particles would fall through it. Make it thicker (at least {MIN_BOX_THICKNESS_CELLS} cells) or use a finer grid",
                            (-deepest / dx).max(0.0)
                        ),
                    ));
                }
            }
        }
        Ok(())
    }
}

impl<const D: usize> Collider<D> {
    /// The particle projection of a collider with [`Collider::project`]
    /// (the solver calls it for each particle after g2p has moved it, with
    /// `depth` = [`PROJECT_DEPTH_CELLS`] cells, the threshold `reach` was
    /// made with: [`Collider::reach`]). A particle at `x` with signed
    /// distance `φ < −depth` (deeper inside than that) goes to the surface
    /// along the outward normal `n`, `x ← x − φ·n` (`φ` and `n` from
    /// [`Shape::step_below`]: exactly onto a box's face of least
    /// penetration or a sphere's surface, onto a sampled shape's to first
    /// order), and its velocity relative to the collider's (`v_obs`, `None`
    /// for a collider at rest) loses its inward normal part: `Sticky` takes
    /// the collider's velocity, `Slip` keeps the tangential part and an
    /// outward normal part, `Separate` does the same with Coulomb friction μ
    /// on the tangential speed as the grid condition does
    /// ([`apply_condition`]). Returns whether the particle moved.
    ///
    /// A particle where `reach` says the projection cannot act returns at
    /// once, untouched ([`Reach::may_act`], inlined here: most particles).
    #[inline(always)]
    pub fn project_particle(
        &self,
        reach: &Reach<'_, D>,
        x: &mut SVector<f32, D>,
        v: &mut SVector<f32, D>,
        v_obs: Option<&SVector<f32, D>>,
    ) -> bool {
        reach.may_act(x) && self.project_deeper(reach.depth, x, v, v_obs)
    }

    /// [`Collider::project_particle`] past its inlined test.
    #[inline]
    fn project_deeper(
        &self,
        depth: f32,
        x: &mut SVector<f32, D>,
        v: &mut SVector<f32, D>,
        v_obs: Option<&SVector<f32, D>>,
    ) -> bool {
        let Some((phi, n)) = self.shape.step_below(x, depth) else {
            return false;
        };
        *x -= n * phi;
        match v_obs {
            None => project_velocity(v, &n, self.condition, self.friction),
            Some(u) => {
                let mut rel = *v - u;
                project_velocity(&mut rel, &n, self.condition, self.friction);
                *v = u + rel;
            }
        }
        true
    }

    /// Where [`Collider::project_particle`] with threshold `depth` can act,
    /// at the collider's current pose ([`Reach`]): given `shallow`, the
    /// [`ShallowCells`] of this sampled shape for `depth` (made once per
    /// collider: they read every sample), its grid; else the ball the shape
    /// lies in.
    pub fn reach<'a>(&'a self, depth: f32, shallow: Option<&'a ShallowCells>) -> Reach<'a, D> {
        let r = self.shape.bounding_radius() * 1.001 + 1e-6;
        let (centre, r2) = (self.shape.center(), r * r);
        let ball = Reach {
            depth,
            region: Region::Ball(centre, r2),
        };
        let (
            Shape::Sampled {
                origin,
                cell,
                dims,
                values,
                normals: Some(normals),
            },
            Some(shallow),
        ) = (&self.shape, shallow)
        else {
            return ball;
        };
        if !(Arc::ptr_eq(values, &shallow.values)
            && Arc::ptr_eq(normals, &shallow.normals)
            && depth == shallow.depth)
            || dims.iter().any(|&n| n > MAX_SAMPLED_NODES)
        {
            // made for other samples or another threshold; or not a valid
            // shape (`GridReach` counts on dims ≤ 2^24)
            return ball;
        }
        // four times the rounding of the quotient either way (`GridReach`)
        let eps: [f32; D] = std::array::from_fn(|d| (dims[d] + 1) as f32 / (1u32 << 20) as f32);
        Reach {
            depth,
            region: Region::Grid(GridReach {
                centre,
                r2,
                nonnegative_outside: shallow.nonnegative_outside,
                origin: *origin,
                cell: *cell,
                inv_cell: 1.0 / cell,
                u_range: std::array::from_fn(|d| (-eps[d], (dims[d] - 1) as f32 + eps[d])),
                frac_range: std::array::from_fn(|d| (eps[d], 1.0 - eps[d])),
                last_cell: std::array::from_fn(|d| (dims[d] - 2) as u32),
                dims,
                values,
                normals,
                shallow: &shallow.bits,
            }),
        }
    }
}

/// Where a collider's particle projection with threshold `depth` can act
/// ([`Collider::reach`]): a particle elsewhere is left alone after this one
/// test ([`Reach::may_act`]).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Reach<'a, const D: usize> {
    depth: f32,
    region: Region<'a, D>,
}

#[derive(Clone, Copy, Debug, PartialEq)]
enum Region<'a, const D: usize> {
    /// The ball the shape lies in (its centre, [`Shape::center`], and
    /// squared radius, [`Shape::bounding_radius`] widened by a thousandth
    /// and a micrometre against rounding): a point outside it has `sdf > 0`.
    Ball(SVector<f32, D>, f32),
    /// A sampled shape's grid.
    Grid(GridReach<'a, D>),
}

impl<const D: usize> Reach<'_, D> {
    /// Whether the projection may act at `x`: false only where
    /// [`Shape::step_below`] is sure to return `None` (for a NaN coordinate
    /// too).
    #[inline(always)]
    pub fn may_act(&self, x: &SVector<f32, D>) -> bool {
        match &self.region {
            Region::Ball(centre, r2) => (x - centre).norm_squared() < *r2,
            Region::Grid(g) => g.may_act(x, self.depth),
        }
    }
}

/// [`Reach`] of a sampled shape with normals: [`Shape::step_below`]'s first
/// test without its division, and most often without its sample loads.
///
/// Outside the grid the projection cannot act if the distance is `≥ 0`
/// there ([`Shape::nonnegative_outside_grid`]: a mesh's margin of samples),
/// else outside the bounding ball. Inside it, `step_below` finds the
/// point's cell by dividing by `cell`, `u = (x − origin) / cell`, and
/// returns `None` where corner 0's plane estimate is at least `−depth`.
/// Here `u` is found by multiplying by `1 / cell`, within `eps =
/// 2^−20·(dims + 1)` of the quotient (four times the rounding of either):
/// where it is farther than `eps` from the grid's range, the quotient is
/// outside it too; where it is farther than `eps` from a cell's sides, the
/// quotient is in the same cell, `step_below`'s cell. There
/// [`ShallowCells`] says whether the estimate is at least `−depth`
/// anywhere in the cell, and where it cannot tell, the estimate is computed
/// as `step_below` computes it. A point within `eps` of a cell's side
/// (about one in 10^4 on a 64³ grid) is left to `step_below`. So the
/// projection's result is the same bit for bit, and most particles near a
/// mesh cost a multiply and a bit test (a bit per cell: in L1) where they
/// cost three divisions, three calls of libm's `floorf` (the portable
/// build's `f32::floor`) and four loads from the samples' 16 bytes per node,
/// and those outside the grid an interpolated distance as well.
#[derive(Clone, Copy, Debug, PartialEq)]
struct GridReach<'a, const D: usize> {
    centre: SVector<f32, D>,
    r2: f32,
    nonnegative_outside: bool,
    origin: SVector<f32, D>,
    cell: f32,
    inv_cell: f32,
    /// Per axis: `[−eps, dims − 1 + eps]`, outside which the quotient is
    /// surely outside the grid; `[eps, 1 − eps]`, the fraction of the
    /// product in which the quotient is surely in the same cell; the last
    /// cell's index (`dims − 2`).
    u_range: [(f32, f32); D],
    frac_range: [(f32, f32); D],
    last_cell: [u32; D],
    dims: &'a [usize; D],
    values: &'a [f32],
    normals: &'a [f32],
    shallow: &'a [u64],
}

impl<const D: usize> GridReach<'_, D> {
    #[inline(always)]
    fn may_act(&self, x: &SVector<f32, D>, depth: f32) -> bool {
        // as `Shape::local`
        let rel = x - self.origin;
        let mut idx = [0usize; D];
        let mut one_cell = true;
        for d in 0..D {
            let u = rel[d] * self.inv_cell;
            let (lo, hi) = self.u_range[d];
            if !(u >= lo && u <= hi) {
                // surely outside the grid (or NaN)
                return !self.nonnegative_outside && (x - self.centre).norm_squared() < self.r2;
            }
            // SAFETY: −eps ≤ u ≤ dims − 1 + eps with eps ≤ 2^5 and dims ≤
            // 2^24 (`Collider::reach`): within i32
            let i = unsafe { u.to_int_unchecked::<i32>() };
            // ⌊u⌋ where i ≥ 0 (exact where it counts: i < 2^24)
            let f = u - i as f32;
            // the quotient surely in cell i, a cell of the grid (as u32 a
            // negative i is beyond the last cell)
            let (f_lo, f_hi) = self.frac_range[d];
            one_cell &= (f >= f_lo) & (f <= f_hi) & (i as u32 <= self.last_cell[d]);
            idx[d] = i as usize;
        }
        if !one_cell {
            // at a cell's side or the grid's: `step_below` decides
            return true;
        }
        let mut cell = 0usize;
        for d in 0..D {
            cell = cell * (self.last_cell[d] as usize + 1) + idx[d];
        }
        if self.shallow[cell / 64] >> (cell % 64) & 1 == 1 {
            return false;
        }
        let (_, _, est0) =
            corner0_estimate(self.cell, self.dims, self.values, self.normals, &rel, &idx);
        est0 < -depth
    }
}

/// What the particle projection of a sampled shape with normals finds once
/// per collider ([`ShallowCells::new`]) and [`Collider::reach`] takes.
#[derive(Clone, Debug, PartialEq)]
pub struct ShallowCells {
    /// The samples and the threshold it was made for.
    values: Arc<[f32]>,
    normals: Arc<[f32]>,
    depth: f32,
    /// [`Shape::nonnegative_outside_grid`].
    nonnegative_outside: bool,
    /// A bit per cell of the grid (row-major by its lowest corner, the
    /// corner [`Shape::step_below`] estimates from): whether that corner's
    /// plane estimate `φ_0 + n_0·off` is at least `−depth` at every offset
    /// `off` in the cell: `φ_0 + Σ_d min(0, n_0d)·cell ≥ −depth`, with a
    /// margin some forty times the estimate's rounding.
    bits: Vec<u64>,
}

impl ShallowCells {
    /// The cells of a sampled `shape` with normals (valid:
    /// [`Collider::validate`]) for the projection threshold `depth ≥ 0`;
    /// `None` for any other shape or threshold. A bit per cell.
    pub fn new<const D: usize>(shape: &Shape<D>, depth: f32) -> Option<Self> {
        let Shape::Sampled {
            cell,
            dims,
            values,
            normals: Some(normals),
            ..
        } = shape
        else {
            return None;
        };
        if !(depth >= 0.0 && depth.is_finite()) {
            return None;
        }
        let cells: [usize; D] = std::array::from_fn(|d| dims[d] - 1);
        let total: usize = cells.iter().product();
        let c = *cell as f64;
        let mut bits = vec![0u64; total.div_ceil(64)];
        let mut idx = [0usize; D];
        for k in 0..total {
            // corner 0's estimate at its lowest over the cell, less a
            // margin some forty times its rounding in f32 (a few units in
            // the last place of the sample, of its terms and of the offsets,
            // which are below dims·cell)
            let mut lin = 0usize;
            for d in 0..D {
                lin = lin * dims[d] + idx[d];
            }
            let phi = values[lin] as f64;
            let (mut low, mut scale) = (phi, phi.abs());
            for d in 0..D {
                let n = normals[lin * D + d] as f64;
                low += n.min(0.0) * c;
                scale += n.abs() * (dims[d] + 1) as f64 * c;
            }
            if low - 1e-5 * scale >= -(depth as f64) {
                bits[k / 64] |= 1 << (k % 64);
            }
            // the next cell, the last axis fastest
            for d in (0..D).rev() {
                idx[d] += 1;
                if idx[d] < cells[d] {
                    break;
                }
                idx[d] = 0;
            }
        }
        Some(ShallowCells {
            values: values.clone(),
            normals: normals.clone(),
            depth,
            nonnegative_outside: shape.nonnegative_outside_grid(),
            bits,
        })
    }
}

/// The velocity `v` (relative to the collider's) of a particle projected
/// onto a collider's surface with outward normal `n`: `Sticky` zero, `Slip`
/// and `Separate` without an inward normal part (`v·n < 0`), `Separate`
/// with Coulomb friction μ on the tangential speed ([`apply_condition`]).
#[inline]
fn project_velocity<const D: usize>(
    v: &mut SVector<f32, D>,
    n: &SVector<f32, D>,
    condition: BoundaryCondition,
    friction: f32,
) {
    match condition {
        BoundaryCondition::Sticky => *v = SVector::zeros(),
        BoundaryCondition::Slip => apply_condition(v, n, BoundaryCondition::Separate, 0.0),
        BoundaryCondition::Separate => apply_condition(v, n, condition, friction),
    }
}

/// How deep [grid cells] a particle may end a substep inside a collider
/// that projects particles ([`Collider::project_particle`]); a deeper one
/// goes back onto the surface. Particles within a fraction of a cell of the
/// surface are MPM's ordinary contact (the kernel spreads a particle over
/// nodes on both sides) and are left alone: measured (docs/obstacles.md),
/// a threshold of 0 rather than a quarter cell makes a mesh sphere's and a
/// mesh ramp's runs depart from their analytic twins' more (grid-mass
/// error 0.014 and 0.048 against 0.009 and 0.021 on a 32³ grid), and the
/// deepest particle stays below 0.3 cells either way.
pub const PROJECT_DEPTH_CELLS: f32 = 0.25;

/// Apply a boundary condition with outward normal `n` of a collider moving
/// at `v_obs` [m/s] to grid velocity `v`: the condition acts on the velocity
/// relative to the collider's, `v_rel = v − v_obs` ([`apply_condition`]),
/// and `v = v_obs + v_rel'`. `Sticky` gives the node the collider's velocity,
/// `Slip` its normal velocity with the tangential velocity kept, `Separate`
/// the same only while the node approaches the surface (`v_rel·n < 0`),
/// with Coulomb friction on the relative tangential speed. (A rigid
/// translation has one velocity everywhere: no rotation is modelled.)
#[inline]
pub fn apply_condition_moving<const D: usize>(
    v: &mut SVector<f32, D>,
    n: &SVector<f32, D>,
    condition: BoundaryCondition,
    friction: f32,
    v_obs: &SVector<f32, D>,
) {
    let mut rel = *v - v_obs;
    apply_condition(&mut rel, n, condition, friction);
    *v = v_obs + rel;
}

/// Apply a boundary condition with outward normal `n` (pointing out of the
/// solid, into the fluid) to grid velocity `v`.
#[inline]
pub fn apply_condition<const D: usize>(
    v: &mut SVector<f32, D>,
    n: &SVector<f32, D>,
    condition: BoundaryCondition,
    friction: f32,
) {
    match condition {
        BoundaryCondition::Sticky => *v = SVector::zeros(),
        BoundaryCondition::Slip => {
            let vn = v.dot(n);
            *v -= n * vn;
        }
        BoundaryCondition::Separate => {
            let vn = v.dot(n);
            if vn < 0.0 {
                let vt = *v - n * vn;
                let vt_len = vt.norm();
                if friction > 0.0 && vt_len > 0.0 {
                    // Coulomb: the tangential speed drops by μ·|v_n|.
                    let scale = (vt_len + friction * vn).max(0.0) / vt_len;
                    *v = vt * scale;
                } else {
                    *v = vt;
                }
            }
        }
    }
}
