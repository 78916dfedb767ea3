//! [`Shape`]: a box, a sphere or a sampled signed distance; its signed
//! distance, outward normal and the step the particle projection takes.

use std::sync::Arc;

use nalgebra::{SMatrix, SVector};

use super::sampled::{corner_node, corner0_estimate, floor_index, sampled_normal, sampled_sdf};
use crate::dim::{abs, norm};

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
                let q = abs(&local) - half_extents;
                let outside = norm(&q.map(|x| x.max(0.0)));
                let inside = q.max().min(0.0);
                outside + inside
            }
            Shape::Sphere { radius, .. } => norm(&local) - radius,
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
                let q = abs(&local) - half_extents;
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
                let len = norm(&n);
                if len > 0.0 { n / len } else { n }
            }
            Shape::Sphere { .. } => {
                let d = self.local(p);
                let len = norm(&d);
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
                let len = norm(&n);
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
    ///
    /// [`Collider::project_particle`]: super::Collider::project_particle
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
                    let lin = corner_node(dims, &idx, corner);
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
                let len = norm(&n);
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
            Shape::Box { half_extents, .. } => norm(half_extents),
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

    pub fn center(&self) -> SVector<f32, D> {
        match self {
            Shape::Box { center, .. } | Shape::Sphere { center, .. } => *center,
            Shape::Sampled {
                origin, cell, dims, ..
            } => origin + SVector::<f32, D>::from_fn(|d, _| 0.5 * cell * (dims[d] - 1) as f32),
        }
    }
}
