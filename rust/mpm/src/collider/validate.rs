//! The checks of a collider: finite, well-formed fields, and thick enough
//! for the grid.
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

use nalgebra::SMatrix;

use super::{Collider, MAX_SAMPLED_NODES, Shape};
use crate::error::{MpmError, Result};

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
