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
        let i = (uc.floor() as usize).min(dims[d] - 2);
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
        let i = (uc.floor() as usize).min(dims[d] - 2);
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
                idx[d] = (u.max(0.0).floor() as usize).min(dims[d] - 2);
            }
            if inside {
                // corner 0's offset and row-major position
                let mut lin0 = 0usize;
                let mut off0 = SVector::<f32, D>::zeros();
                for d in 0..D {
                    lin0 = lin0 * dims[d] + idx[d];
                    off0[d] = rel[d] - idx[d] as f32 * cell;
                }
                // corner 0's estimate bounds the largest from below
                let mut est0 = values[lin0];
                for d in 0..D {
                    est0 += normals[lin0 * D + d] * off0[d];
                }
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
    /// `depth` = [`PROJECT_DEPTH_CELLS`] cells). A particle at `x` with
    /// signed distance `φ < −depth` (deeper inside than that) goes to the
    /// surface along the outward normal `n`, `x ← x − φ·n` (`φ` and `n` from
    /// [`Shape::surface_step`]: exactly onto a box's face of least
    /// penetration or a sphere's surface, onto a sampled shape's to first
    /// order), and its
    /// velocity relative to the collider's (`v_obs`, `None` for a collider
    /// at rest) loses its inward normal part: `Sticky` takes the collider's
    /// velocity, `Slip` keeps the tangential part and an outward normal
    /// part, `Separate` does the same with Coulomb friction μ on the
    /// tangential speed as the grid condition does ([`apply_condition`]).
    ///
    /// `reach` is the collider's bounding ball ([`Collider::reach`]): a
    /// particle outside it returns at once, untouched. Returns whether the
    /// particle moved.
    #[inline]
    pub fn project_particle(
        &self,
        reach: &(SVector<f32, D>, f32),
        depth: f32,
        x: &mut SVector<f32, D>,
        v: &mut SVector<f32, D>,
        v_obs: Option<&SVector<f32, D>>,
    ) -> bool {
        let (centre, r2) = reach;
        if (*x - centre).norm_squared() >= *r2 {
            return false;
        }
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

    /// The ball the shape lies in, as [`Collider::project_particle`] takes
    /// it: its centre ([`Shape::center`]) and squared radius
    /// ([`Shape::bounding_radius`], widened by a thousandth and a micrometre
    /// against rounding). A point outside it has `sdf > 0`.
    pub fn reach(&self) -> (SVector<f32, D>, f32) {
        let r = self.shape.bounding_radius() * 1.001 + 1e-6;
        (self.shape.center(), r * r)
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
