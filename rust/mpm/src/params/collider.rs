//! A collider as the parameter dict gives it ([`ColliderParams`]), the
//! same in 2D and 3D, and the [`Collider`] it builds.

use nalgebra::{SMatrix, SVector};

use super::BoundaryCondition;
use crate::collider::{Collider, Shape};
use crate::error::{MpmError, Result};

/// The shape of a collider in the parameter dict: `"box"`, `"sphere"`
/// (`"circle"` is a synonym) or `"sampled"` (a signed distance sampled on a
/// grid: a scene's mesh obstacle).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[cfg_attr(
    feature = "serde",
    derive(serde::Serialize, serde::Deserialize),
    serde(rename_all = "lowercase")
)]
pub enum ShapeKind {
    Box,
    #[cfg_attr(feature = "serde", serde(alias = "circle"))]
    Sphere,
    Sampled,
}

/// Declares [`ColliderParams`] with the shape's fields first: each an
/// `Option`, `None` by default and (`serde` feature) written only when set;
/// then the fields every collider has, each with its default. (So neither
/// the attribute nor the default of a shape field is written per field.)
macro_rules! collider_params {
    (
        $(#[$meta:meta])*
        pub struct $name:ident {
            $( $(#[$shape_meta:meta])* pub $shape:ident: Option<$shape_ty:ty>, )*
        }
        every collider {
            $( $(#[$meta_all:meta])* pub $field:ident: $ty:ty = $default:expr, )*
        }
    ) => {
        $(#[$meta])*
        #[derive(Clone, Debug, PartialEq)]
        #[cfg_attr(
            feature = "serde",
            derive(serde::Serialize, serde::Deserialize),
            serde(default, deny_unknown_fields)
        )]
        pub struct $name {
            $(
                $(#[$shape_meta])*
                #[cfg_attr(feature = "serde", serde(skip_serializing_if = "Option::is_none"))]
                pub $shape: Option<$shape_ty>,
            )*
            $( $(#[$meta_all])* pub $field: $ty, )*
        }

        impl Default for $name {
            /// No shape; condition `Separate`, no friction, particles projected.
            fn default() -> Self {
                $name {
                    $( $shape: None, )*
                    $( $field: $default, )*
                }
            }
        }
    };
}

collider_params! {
    /// A static collider as the parameter dict gives it, the same in 2D and 3D:
    /// the shape's fields flat (a box: `center`, `half_extents`, and
    /// `rotation` or, in 2D, `angle_deg`; a sphere: `center`, `radius`; a
    /// sampled signed distance: `origin`, `cell`, `dims`, `values`, optional
    /// `normals`), its boundary condition and Coulomb friction.
    /// [`ColliderParams::build`] makes the [`Collider`] of a `D`-dimensional
    /// solver; fields the shape does not use are ignored.
    pub struct ColliderParams {
        /// Box, sphere or sampled (required).
        pub shape: Option<ShapeKind>,
        /// Centre [m], `D` numbers (required).
        pub center: Option<Vec<f32>>,
        /// Box half extents [m], `D` numbers (required for a box).
        pub half_extents: Option<Vec<f32>>,
        /// Box rotation [degrees] counter-clockwise, 2D only (`rotation` wins).
        pub angle_deg: Option<f64>,
        /// Box rotation matrix, `D` rows of `D` numbers (columns: the box's
        /// axes in world coordinates); identity when neither it nor
        /// `angle_deg` is given.
        pub rotation: Option<Vec<Vec<f32>>>,
        /// Sphere radius [m] (required for a sphere).
        pub radius: Option<f32>,
        /// Sampled: position of the first sample [m], `D` numbers.
        pub origin: Option<Vec<f32>>,
        /// Sampled: spacing of the samples [m].
        pub cell: Option<f32>,
        /// Sampled: samples per axis, `D` integers.
        pub dims: Option<Vec<usize>>,
        /// Sampled: the signed distances [m], row-major (last axis fastest);
        /// see [`Shape::Sampled`].
        pub values: Option<Vec<f32>>,
        /// Sampled (optional): outward unit normals at the samples, `D` numbers
        /// per sample in the order of `values`.
        pub normals: Option<Vec<f32>>,
    }
    every collider {
        pub condition: BoundaryCondition = BoundaryCondition::Separate,
        /// Coulomb friction coefficient μ (≥ 0; used with `Separate`).
        pub friction: f32 = 0.0,
        /// Put particles that end a substep inside the collider back on its
        /// surface ([`Collider::project`]); default on. (The registered ramps
        /// scenes set it off: their models and datasets were made without it.)
        pub project: bool = true,
    }
}

impl ColliderParams {
    /// The collider in `D` dimensions. Errors name the field under `field`
    /// (e.g. `colliders[0].center`): a missing shape, centre, half extents
    /// (box) or radius (sphere), a vector of other than `D` numbers, a
    /// rotation that is not `D`×`D`, an `angle_deg` in 3D. Ranges are left
    /// to [`Collider::validate`].
    pub fn build<const D: usize>(&self, field: &str) -> Result<Collider<D>> {
        let name = |key: &str| format!("{field}.{key}");
        let missing = |key: &str| MpmError::invalid(name(key), "missing");
        let vector = |key: &str, v: &Option<Vec<f32>>| -> Result<SVector<f32, D>> {
            let v = v.as_ref().ok_or_else(|| missing(key))?;
            if v.len() != D {
                return Err(MpmError::invalid(
                    name(key),
                    format!("expected {D} numbers, got {}", v.len()),
                ));
            }
            Ok(SVector::from_column_slice(v))
        };
        let kind = self.shape.ok_or_else(|| {
            MpmError::invalid(name("shape"), "missing ('box', 'sphere' or 'sampled')")
        })?;
        if kind == ShapeKind::Sampled {
            let origin = vector("origin", &self.origin)?;
            let dims = self.dims.as_ref().ok_or_else(|| missing("dims"))?;
            let dims: [usize; D] = dims.as_slice().try_into().map_err(|_| {
                MpmError::invalid(
                    name("dims"),
                    format!("expected {D} integers, got {}", dims.len()),
                )
            })?;
            let values = self.values.as_ref().ok_or_else(|| missing("values"))?;
            return Ok(Collider {
                shape: Shape::Sampled {
                    origin,
                    cell: self.cell.ok_or_else(|| missing("cell"))?,
                    dims,
                    values: values.as_slice().into(),
                    normals: self.normals.as_ref().map(|n| n.as_slice().into()),
                },
                condition: self.condition,
                friction: self.friction,
                project: self.project,
            });
        }
        let center = vector("center", &self.center)?;
        let shape = match kind {
            ShapeKind::Box => {
                let half_extents = vector("half_extents", &self.half_extents)?;
                let mut rotation = SMatrix::<f32, D, D>::identity();
                if let Some(rows) = &self.rotation {
                    if rows.len() != D || rows.iter().any(|row| row.len() != D) {
                        return Err(MpmError::invalid(
                            name("rotation"),
                            format!("expected a {D}x{D} nested list"),
                        ));
                    }
                    rotation = SMatrix::from_fn(|i, j| rows[i][j]);
                } else if let Some(a) = self.angle_deg {
                    if D != 2 {
                        return Err(MpmError::invalid(
                            name("angle_deg"),
                            "only in 2D; give 'rotation' in 3D",
                        ));
                    }
                    let (s, c) = (a.to_radians() as f32).sin_cos();
                    rotation[(0, 0)] = c;
                    rotation[(0, 1)] = -s;
                    rotation[(1, 0)] = s;
                    rotation[(1, 1)] = c;
                }
                Shape::Box {
                    center,
                    half_extents,
                    rotation,
                }
            }
            ShapeKind::Sphere => Shape::Sphere {
                center,
                radius: self.radius.ok_or_else(|| missing("radius"))?,
            },
            ShapeKind::Sampled => unreachable!("built above"),
        };
        Ok(Collider {
            shape,
            condition: self.condition,
            friction: self.friction,
            project: self.project,
        })
    }
}
