//! Static rigid colliders given as signed-distance shapes.
//!
//! A grid node whose position has `sdf < 0` lies inside the collider and its
//! velocity is constrained by the collider's [`BoundaryCondition`].
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

use nalgebra::{SMatrix, SVector};

use crate::error::{MpmError, Result};
use crate::params::BoundaryCondition;

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
}

/// A static collider: shape + boundary condition + Coulomb friction.
#[derive(Clone, Debug, PartialEq)]
pub struct Collider<const D: usize> {
    pub shape: Shape<D>,
    pub condition: BoundaryCondition,
    pub friction: f32,
}

impl<const D: usize> Shape<D> {
    /// Signed distance [m] (negative inside).
    pub fn sdf(&self, p: &SVector<f32, D>) -> f32 {
        match self {
            Shape::Box {
                center,
                half_extents,
                rotation,
            } => {
                let local = rotation.transpose() * (p - center);
                let q = local.abs() - half_extents;
                let outside = q.map(|x| x.max(0.0)).norm();
                let inside = q.max().min(0.0);
                outside + inside
            }
            Shape::Sphere { center, radius } => (p - center).norm() - radius,
        }
    }

    /// Outward unit normal at `p` (gradient of the SDF).
    pub fn normal(&self, p: &SVector<f32, D>) -> SVector<f32, D> {
        match self {
            Shape::Box {
                center,
                half_extents,
                rotation,
            } => {
                let local = rotation.transpose() * (p - center);
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
            Shape::Sphere { center, .. } => {
                let d = p - center;
                let len = d.norm();
                if len > 0.0 {
                    d / len
                } else {
                    let mut n = SVector::<f32, D>::zeros();
                    n[1] = 1.0;
                    n
                }
            }
        }
    }

    /// Radius of a ball around the shape's centre that contains it.
    pub fn bounding_radius(&self) -> f32 {
        match self {
            Shape::Box { half_extents, .. } => half_extents.norm(),
            Shape::Sphere { radius, .. } => *radius,
        }
    }

    pub fn center(&self) -> SVector<f32, D> {
        match self {
            Shape::Box { center, .. } | Shape::Sphere { center, .. } => *center,
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

impl<const D: usize> Collider<D> {
    /// Refuses a collider too thin for a grid of spacing `dx` (particles
    /// would fall through it; see the module docs for the measurement):
    /// a box with a side below [`MIN_BOX_THICKNESS_CELLS`] cells (field
    /// `{field}.half_extents`), a sphere of radius below
    /// [`MIN_SPHERE_RADIUS_CELLS`] cells (`{field}.radius`).
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
        }
        Ok(())
    }
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
