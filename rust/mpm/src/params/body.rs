//! A rigid body as the parameter dict gives it ([`BodyParams`]), the same in
//! 2D and 3D, and the [`Body`] it builds.

use std::sync::Arc;

use nalgebra::{SMatrix, SVector};

use crate::body::{Body, BodyShape, Hull, MAX_BODY_DENSITY, MIN_BODY_DENSITY};
use crate::error::{MpmError, Result};

/// The shape of a body in the parameter dict: `"box"`, `"sphere"`
/// (`"circle"` is a synonym), `"capsule"`, or `"mesh"` (3D: the convex hull
/// of `vertices`).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[cfg_attr(
    feature = "serde",
    derive(serde::Serialize, serde::Deserialize),
    serde(rename_all = "lowercase")
)]
pub enum BodyShapeKind {
    Box,
    #[cfg_attr(feature = "serde", serde(alias = "circle"))]
    Sphere,
    Capsule,
    Mesh,
}

/// A rigid body as the parameter dict gives it, the same in 2D and 3D: the
/// shape's fields flat (a box: `center`, `half_extents`, and `rotation` or,
/// in 2D, `angle_deg`; a sphere: `center`, `radius`; a capsule: `radius`
/// and `half_height`; a mesh: `vertices`), its density or mass,
/// initial velocity and angular velocity, and Coulomb friction against the
/// fluid. [`BodyParams::build`] makes the [`Body`] of a `D`-dimensional solver.
#[derive(Clone, Debug, Default, PartialEq)]
#[cfg_attr(
    feature = "serde",
    derive(serde::Serialize, serde::Deserialize),
    serde(default, deny_unknown_fields)
)]
pub struct BodyParams {
    /// Box or sphere (required).
    pub shape: Option<BodyShapeKind>,
    /// Centre [m], `D` numbers (required).
    pub center: Option<Vec<f32>>,
    /// Box half extents [m], `D` numbers (required for a box).
    pub half_extents: Option<Vec<f32>>,
    /// Sphere or capsule radius [m] (required for both).
    pub radius: Option<f32>,
    /// Capsule: half the length of its segment along the body's y axis [m]
    /// (required for a capsule).
    pub half_height: Option<f32>,
    /// Mesh (3D): the points whose convex hull is the body, `[x, y, z]` [m]
    /// in the mesh's own frame; `center` is where that frame's origin goes,
    /// and the body's centre of mass is the hull's (required for a mesh).
    pub vertices: Option<Vec<Vec<f32>>>,
    /// Mesh: the file the points were read from (by the Python side; only
    /// the name of the field an error about the points gives: `path`
    /// instead of `vertices`).
    pub path: Option<String>,
    /// Rotation [degrees] counter-clockwise, 2D only (`rotation` wins).
    pub angle_deg: Option<f64>,
    /// Rotation matrix, `D` rows of `D` numbers (columns: the body's axes in
    /// world coordinates); identity when neither it nor `angle_deg` is given.
    pub rotation: Option<Vec<Vec<f32>>>,
    /// Density [kg/m³] (give it or `mass`).
    pub density: Option<f32>,
    /// Mass [kg; per unit depth in 2D, as the particles' masses] (instead of `density`).
    pub mass: Option<f32>,
    /// Initial velocity [m/s], `D` numbers (zero when not given).
    pub velocity: Option<Vec<f32>>,
    /// Initial angular velocity [rad/s]: 1 number in 2D (counter-clockwise),
    /// 3 in 3D (zero when not given).
    pub angular_velocity: Option<Vec<f32>>,
    /// Coulomb friction coefficient μ against the fluid (≥ 0; default 0).
    pub friction: Option<f32>,
}

impl BodyParams {
    /// The body in `D` dimensions. Errors name the field under `field`
    /// (e.g. `bodies[0].density`): a missing or malformed shape, centre,
    /// size, density or mass, a vector of other than `D` numbers, a rotation
    /// that is not a `D`×`D` rotation. Ranges against the grid are left to
    /// [`Body::validate`].
    pub fn build<const D: usize>(&self, field: &str) -> Result<Body<D>> {
        let name = |key: &str| format!("{field}.{key}");
        let missing = |key: &str| MpmError::invalid(name(key), "missing");
        let numbers = |key: &str, v: &Option<Vec<f32>>, n: usize| -> Result<Option<Vec<f32>>> {
            let Some(v) = v else { return Ok(None) };
            if v.len() != n || !v.iter().all(|x| x.is_finite()) {
                return Err(MpmError::invalid(
                    name(key),
                    format!("expected {n} finite numbers, got {v:?}"),
                ));
            }
            Ok(Some(v.clone()))
        };
        let kind = self.shape.ok_or_else(|| {
            MpmError::invalid(
                name("shape"),
                "missing ('box', 'sphere', 'capsule' or 'mesh')",
            )
        })?;
        let center = numbers("center", &self.center, D)?.ok_or_else(|| missing("center"))?;
        let shape = match kind {
            BodyShapeKind::Box => {
                let h = numbers("half_extents", &self.half_extents, D)?
                    .ok_or_else(|| missing("half_extents"))?;
                if !h.iter().all(|&x| x > 0.0) {
                    return Err(MpmError::invalid(
                        name("half_extents"),
                        format!("must be > 0, got {h:?}"),
                    ));
                }
                BodyShape::Box {
                    half_extents: SVector::from_column_slice(&h),
                }
            }
            BodyShapeKind::Sphere => BodyShape::Ball {
                radius: self.positive("radius", self.radius, field)?,
            },
            BodyShapeKind::Capsule => BodyShape::Capsule {
                radius: self.positive("radius", self.radius, field)?,
                half_height: self.positive("half_height", self.half_height, field)?,
            },
            BodyShapeKind::Mesh => {
                if D != 3 {
                    return Err(MpmError::invalid(
                        name("shape"),
                        format!("'mesh' bodies are 3D only (dim = 3); this solver has dim = {D}"),
                    ));
                }
                let key = if self.path.is_some() {
                    "path"
                } else {
                    "vertices"
                };
                let v = self.vertices.as_ref().ok_or_else(|| missing(key))?;
                if let Some(i) = v.iter().position(|p| p.len() != 3) {
                    return Err(MpmError::invalid(
                        name(key),
                        format!("point {i}: expected 3 numbers, got {:?}", v[i]),
                    ));
                }
                let points: Vec<[f32; 3]> = v.iter().map(|p| [p[0], p[1], p[2]]).collect();
                BodyShape::Hull(Arc::new(Hull::new(&points, field, key)?))
            }
        };
        let rotation = self.rotation_matrix::<D>(field)?;
        let volume = shape.volume();
        let density = match (self.density, self.mass) {
            (Some(_), Some(_)) => {
                return Err(MpmError::invalid(
                    name("mass"),
                    "give density or mass, not both",
                ));
            }
            (Some(rho), None) => rho,
            (None, Some(m)) => {
                let rho = m / volume;
                if !(m.is_finite() && (MIN_BODY_DENSITY..=MAX_BODY_DENSITY).contains(&rho)) {
                    return Err(MpmError::invalid(
                        name("mass"),
                        format!(
                            "must give a density in [{MIN_BODY_DENSITY}, {MAX_BODY_DENSITY:e}] kg/m^3 for the body's volume {volume} (a mass in [{}, {}] kg), got {m:?} kg",
                            MIN_BODY_DENSITY * volume,
                            MAX_BODY_DENSITY * volume
                        ),
                    ));
                }
                rho
            }
            (None, None) => return Err(missing("density")),
        };
        if !(density.is_finite() && (MIN_BODY_DENSITY..=MAX_BODY_DENSITY).contains(&density)) {
            return Err(MpmError::invalid(
                name("density"),
                format!(
                    "must be in [{MIN_BODY_DENSITY}, {MAX_BODY_DENSITY:e}] kg/m^3 (lighter bodies are thrown by the coupling's round-off, heavier ones are past rapier's f32 integration), got {density:?}"
                ),
            ));
        }
        let velocity = numbers("velocity", &self.velocity, D)?.unwrap_or(vec![0.0; D]);
        let n_ang = if D == 2 { 1 } else { 3 };
        let w =
            numbers("angular_velocity", &self.angular_velocity, n_ang)?.unwrap_or(vec![0.0; n_ang]);
        let angular_velocity = if D == 2 {
            [0.0, 0.0, w[0]]
        } else {
            [w[0], w[1], w[2]]
        };
        let friction = self.friction.unwrap_or(0.0);
        if !(friction.is_finite() && friction >= 0.0) {
            return Err(MpmError::invalid(
                name("friction"),
                format!("must be a finite number >= 0, got {friction}"),
            ));
        }
        let mut center = SVector::<f32, D>::from_column_slice(&center);
        if let BodyShape::Hull(hull) = &shape {
            // `center` is where the points' origin goes: the centre of mass
            // lies at the hull's offset from it, turned with the body
            center += rotation * SVector::<f32, D>::from_fn(|d, _| hull.offset[d]);
        }
        Ok(Body {
            shape,
            center,
            rotation,
            density,
            velocity: SVector::from_column_slice(&velocity),
            angular_velocity,
            friction,
        })
    }

    /// `value` (parameter `key`): present, finite and > 0 [m].
    fn positive(&self, key: &str, value: Option<f32>, field: &str) -> Result<f32> {
        let r = value.ok_or_else(|| MpmError::invalid(format!("{field}.{key}"), "missing"))?;
        if !(r.is_finite() && r > 0.0) {
            return Err(MpmError::invalid(
                format!("{field}.{key}"),
                format!("must be a finite number > 0, got {r}"),
            ));
        }
        Ok(r)
    }

    /// The rotation from `rotation` (checked orthonormal with determinant
    /// 1) or, in 2D, `angle_deg`; identity when neither is given.
    fn rotation_matrix<const D: usize>(&self, field: &str) -> Result<SMatrix<f32, D, D>> {
        let mut r = SMatrix::<f32, D, D>::identity();
        if let Some(rows) = &self.rotation {
            let bad = |msg: String| MpmError::invalid(format!("{field}.rotation"), msg);
            if rows.len() != D || rows.iter().any(|row| row.len() != D) {
                return Err(bad(format!("expected a {D}x{D} nested list")));
            }
            r = SMatrix::from_fn(|i, j| rows[i][j]);
            let err = (r.transpose() * r - SMatrix::<f32, D, D>::identity())
                .abs()
                .max();
            if !(err < 1e-4 && det(&r) > 0.0) {
                return Err(bad(
                    "must be a rotation (orthonormal, determinant 1)".to_string()
                ));
            }
        } else if let Some(a) = self.angle_deg {
            if D != 2 {
                return Err(MpmError::invalid(
                    format!("{field}.angle_deg"),
                    "only in 2D; give 'rotation' in 3D",
                ));
            }
            if !a.is_finite() {
                return Err(MpmError::invalid(
                    format!("{field}.angle_deg"),
                    format!("must be finite, got {a}"),
                ));
            }
            // the angle modulo a turn in f64 first: a huge angle (1e308°) is
            // still a finite angle, and its radians in f32 would not be
            let (s, c) = (a.rem_euclid(360.0).to_radians() as f32).sin_cos();
            r[(0, 0)] = c;
            r[(0, 1)] = -s;
            r[(1, 0)] = s;
            r[(1, 1)] = c;
        }
        Ok(r)
    }
}

/// Determinant of a 2×2 or 3×3 matrix.
fn det<const D: usize>(r: &SMatrix<f32, D, D>) -> f32 {
    if D == 2 {
        r[(0, 0)] * r[(1, 1)] - r[(0, 1)] * r[(1, 0)]
    } else {
        let c = |i: usize, j: usize| r[(i, j)];
        c(0, 0) * (c(1, 1) * c(2, 2) - c(1, 2) * c(2, 1))
            - c(0, 1) * (c(1, 0) * c(2, 2) - c(1, 2) * c(2, 0))
            + c(0, 2) * (c(1, 0) * c(2, 1) - c(1, 1) * c(2, 0))
    }
}
