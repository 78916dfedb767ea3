//! Solver parameters: one `...Params` struct per concept, each with `Default`,
//! documented SI units and a `validate()` that names the bad field.
//!
//! These structs are the one schema of the parameters. With the `serde`
//! feature they (de)serialise as the parameter dict of the Python binding:
//! every field optional (a missing one takes its `Default`), an unknown key
//! refused, boundary conditions as `"sticky"`, `"slip"`, `"separate"`. The
//! binding reads its dict with them and gives Python the defaults from them.

use nalgebra::{SMatrix, SVector};

pub use crate::boundary::BoundaryCondition;
use crate::collider::{Collider, Shape};
use crate::error::{MpmError, Result};

fn finite(field: &str, x: f32) -> Result<()> {
    if x.is_finite() {
        Ok(())
    } else {
        Err(MpmError::invalid(field, format!("must be finite, got {x}")))
    }
}

fn positive(field: &str, x: f32) -> Result<()> {
    finite(field, x)?;
    if x > 0.0 {
        Ok(())
    } else {
        Err(MpmError::invalid(field, format!("must be > 0, got {x}")))
    }
}

/// Weakly compressible water (mpm88 style, Hu et al. 2018): the particle
/// carries `J` only; Kirchhoff stress `τ = K·J·(J − 1)·I + η·J·(C + Cᵀ)`.
#[derive(Clone, Debug, PartialEq)]
#[cfg_attr(
    feature = "serde",
    derive(serde::Serialize, serde::Deserialize),
    serde(default, deny_unknown_fields)
)]
pub struct WaterParams {
    /// Rest density ρ [kg/m³].
    pub density: f32,
    /// Bulk modulus K [Pa]; the sound speed is `sqrt(K/ρ)`.
    pub bulk_modulus: f32,
    /// Dynamic viscosity η [Pa·s] (0 = inviscid).
    pub viscosity: f32,
}

impl Default for WaterParams {
    fn default() -> Self {
        // K/ρ = 400 m²/s²: sound speed 20 m/s, the usual weakly compressible choice.
        WaterParams {
            density: 1000.0,
            bulk_modulus: 4.0e5,
            viscosity: 0.0,
        }
    }
}

impl WaterParams {
    pub fn validate(&self) -> Result<()> {
        positive("water.density", self.density)?;
        positive("water.bulk_modulus", self.bulk_modulus)?;
        finite("water.viscosity", self.viscosity)?;
        if self.viscosity < 0.0 {
            return Err(MpmError::invalid(
                "water.viscosity",
                format!("must be >= 0, got {}", self.viscosity),
            ));
        }
        Ok(())
    }

    /// Longitudinal wave speed [m/s].
    pub fn wave_speed(&self) -> f32 {
        (self.bulk_modulus / self.density).sqrt()
    }
}

/// Sand: Drucker–Prager elastoplasticity in Hencky strain with SVD return
/// mapping (Klár et al. 2016) and the volume correction of Tampubolon et al. 2017.
#[derive(Clone, Debug, PartialEq)]
#[cfg_attr(
    feature = "serde",
    derive(serde::Serialize, serde::Deserialize),
    serde(default, deny_unknown_fields)
)]
pub struct SandParams {
    /// Density ρ [kg/m³].
    pub density: f32,
    /// Young's modulus E [Pa].
    pub youngs_modulus: f32,
    /// Poisson's ratio ν [-], in (−1, 0.5).
    pub poisson_ratio: f32,
    /// Internal friction angle φ [degrees], in [0, 80].
    pub friction_angle_deg: f32,
    /// Cohesion c [Pa] (≥ 0): shifts the cone apex to the tensile mean stress `c / tan φ`.
    pub cohesion: f32,
}

impl Default for SandParams {
    fn default() -> Self {
        SandParams {
            density: 1000.0,
            youngs_modulus: 3.5e5,
            poisson_ratio: 0.3,
            friction_angle_deg: 30.0,
            cohesion: 0.0,
        }
    }
}

impl SandParams {
    pub fn validate(&self) -> Result<()> {
        positive("sand.density", self.density)?;
        positive("sand.youngs_modulus", self.youngs_modulus)?;
        finite("sand.poisson_ratio", self.poisson_ratio)?;
        if !(self.poisson_ratio > -1.0 && self.poisson_ratio < 0.5) {
            return Err(MpmError::invalid(
                "sand.poisson_ratio",
                format!("must be in (-1, 0.5), got {}", self.poisson_ratio),
            ));
        }
        finite("sand.friction_angle_deg", self.friction_angle_deg)?;
        if !(0.0..=80.0).contains(&self.friction_angle_deg) {
            return Err(MpmError::invalid(
                "sand.friction_angle_deg",
                format!(
                    "must be in [0, 80] degrees, got {}",
                    self.friction_angle_deg
                ),
            ));
        }
        finite("sand.cohesion", self.cohesion)?;
        if self.cohesion < 0.0 {
            return Err(MpmError::invalid(
                "sand.cohesion",
                format!("must be >= 0, got {}", self.cohesion),
            ));
        }
        if self.cohesion > 0.0 && self.friction_angle_deg <= 0.0 {
            return Err(MpmError::invalid(
                "sand.cohesion",
                "cohesion needs a friction angle > 0",
            ));
        }
        Ok(())
    }

    /// Lamé parameters (μ, λ) [Pa].
    pub fn lame(&self) -> (f32, f32) {
        let (e, nu) = (self.youngs_modulus, self.poisson_ratio);
        (
            e / (2.0 * (1.0 + nu)),
            e * nu / ((1.0 + nu) * (1.0 - 2.0 * nu)),
        )
    }

    /// P-wave speed `sqrt((λ + 2μ)/ρ)` [m/s].
    pub fn wave_speed(&self) -> f32 {
        let (mu, la) = self.lame();
        ((la + 2.0 * mu) / self.density).sqrt()
    }
}

/// Boundary condition and Coulomb friction of one face of the domain walls.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct WallFace {
    pub condition: BoundaryCondition,
    /// Coulomb friction coefficient μ (≥ 0; used with `Separate`).
    pub friction: f32,
}

/// The walls of the unit domain `[0, 1]^D`: a band of `cells` grid cells
/// inside each face, whose grid nodes get the face's boundary condition
/// with the face's inward normal.
///
/// `condition` and `friction` apply to every face; `faces` overrides them
/// face by face. Faces are named by axis and side: `x-` (x = 0), `x+`
/// (x = 1), `y-` (the floor: y is up, gravity points to −y), `y+` (the
/// ceiling), `z-`, `z+` (3D only). A rough floor with slipping side walls,
/// the usual granular-collapse setup, is `condition = Separate`,
/// `friction = 0` and `faces[1][0] = Some(WallFace { condition: Separate,
/// friction: μ })`.
///
/// In the parameter dict (`serde` feature) `faces` maps a face name to
/// `{"condition": ..., "friction": ...}`; a key the face leaves out takes
/// the all-faces value, and only overridden faces are written.
#[derive(Clone, Debug, PartialEq)]
#[cfg_attr(
    feature = "serde",
    derive(serde::Serialize, serde::Deserialize),
    serde(from = "wire::Walls", into = "wire::Walls")
)]
pub struct WallParams {
    /// Thickness of the wall band in grid cells, in [2, n_grid/4).
    pub cells: usize,
    /// Condition of every face without an override.
    pub condition: BoundaryCondition,
    /// Coulomb friction coefficient μ of every face without an override
    /// (used with `Separate`).
    pub friction: f32,
    /// Per-face overrides `faces[axis][side]` (side 0: the lower face `x-`,
    /// `y-`, `z-`; side 1: the upper face); `None` uses `condition` and
    /// `friction`. The z row must stay `None` in 2D.
    pub faces: [[Option<WallFace>; 2]; 3],
}

impl Default for WallParams {
    fn default() -> Self {
        WallParams {
            cells: 3,
            condition: BoundaryCondition::Separate,
            friction: 0.0,
            faces: [[None; 2]; 3],
        }
    }
}

impl WallParams {
    /// Face names by `[axis][side]`.
    pub const FACE_NAMES: [[&'static str; 2]; 3] = [["x-", "x+"], ["y-", "y+"], ["z-", "z+"]];

    /// `(axis, side)` of a face name (`"x-"`, ..., `"z+"`), or `None`.
    pub fn face_index(name: &str) -> Option<(usize, usize)> {
        (0..3)
            .flat_map(|a| (0..2).map(move |s| (a, s)))
            .find(|&(a, s)| Self::FACE_NAMES[a][s] == name)
    }

    /// The condition and friction in force on face `(axis, side)`.
    pub fn face(&self, axis: usize, side: usize) -> WallFace {
        self.faces[axis][side].unwrap_or(WallFace {
            condition: self.condition,
            friction: self.friction,
        })
    }

    /// Checks the band thickness and every friction coefficient (errors
    /// name the field, e.g. `walls.faces.y-.friction`).
    pub fn validate(&self, n_grid: usize) -> Result<()> {
        if self.cells < 2 || 4 * self.cells >= n_grid {
            return Err(MpmError::invalid(
                "walls.cells",
                format!("must be in [2, n_grid/4), got {}", self.cells),
            ));
        }
        non_negative("walls.friction", self.friction)?;
        for (axis, row) in self.faces.iter().enumerate() {
            for (side, face) in row.iter().enumerate() {
                if let Some(f) = face {
                    let name = Self::FACE_NAMES[axis][side];
                    non_negative(&format!("walls.faces.{name}.friction"), f.friction)?;
                }
            }
        }
        Ok(())
    }
}

fn non_negative(field: &str, x: f32) -> Result<()> {
    finite(field, x)?;
    if x < 0.0 {
        return Err(MpmError::invalid(field, format!("must be >= 0, got {x}")));
    }
    Ok(())
}

/// Largest `max_substeps`: a million substeps make a frame of minutes.
pub const MAX_SUBSTEPS: usize = 1_000_000;

/// Solver-wide parameters.
///
/// (`serde` feature: serde's derive cannot read a struct generic over a
/// const, so `Deserialize` goes through `wire::Solver`, which the compiler
/// holds to these fields.)
#[derive(Clone, Debug, PartialEq)]
#[cfg_attr(feature = "serde", derive(serde::Serialize))]
pub struct SolverParams<const D: usize> {
    /// Grid cells per dimension over the unit domain (dx = 1 / n_grid), in [16, 4096].
    pub n_grid: usize,
    /// Gravity [m/s²] (a list of `D` numbers in the parameter dict).
    #[cfg_attr(feature = "serde", serde(serialize_with = "wire::serialize_array"))]
    pub gravity: [f32; D],
    /// CFL number: substep `dt ≤ cfl·dx / (c_max + |v|_max)`, in (0, 1].
    pub cfl: f32,
    /// Fixed substep count per frame (overrides the CFL choice), or `None`.
    pub substeps: Option<usize>,
    /// Upper bound on substeps per frame, in [1, 10^6] ([`MAX_SUBSTEPS`]);
    /// a frame that needs more is an error.
    pub max_substeps: usize,
    /// Worker threads (0 = all cores).
    pub num_threads: usize,
    pub water: WaterParams,
    pub sand: SandParams,
    pub walls: WallParams,
}

impl<const D: usize> Default for SolverParams<D> {
    fn default() -> Self {
        let mut gravity = [0.0; D];
        gravity[1] = -9.8;
        SolverParams {
            n_grid: if D == 2 { 128 } else { 64 },
            gravity,
            cfl: 0.4,
            substeps: None,
            max_substeps: 1000,
            num_threads: 0,
            water: WaterParams::default(),
            sand: SandParams::default(),
            walls: WallParams::default(),
        }
    }
}

impl<const D: usize> SolverParams<D> {
    pub fn validate(&self) -> Result<()> {
        if !(16..=4096).contains(&self.n_grid) {
            return Err(MpmError::invalid(
                "n_grid",
                format!("must be in [16, 4096], got {}", self.n_grid),
            ));
        }
        for (i, &g) in self.gravity.iter().enumerate() {
            finite(&format!("gravity[{i}]"), g)?;
        }
        positive("cfl", self.cfl)?;
        if self.cfl > 1.0 {
            return Err(MpmError::invalid(
                "cfl",
                format!("must be in (0, 1], got {}", self.cfl),
            ));
        }
        if !(1..=MAX_SUBSTEPS).contains(&self.max_substeps) {
            return Err(MpmError::invalid(
                "max_substeps",
                format!("must be in [1, {MAX_SUBSTEPS}], got {}", self.max_substeps),
            ));
        }
        if let Some(s) = self.substeps
            && (s == 0 || s > self.max_substeps)
        {
            return Err(MpmError::invalid(
                "substeps",
                format!(
                    "must be in [1, max_substeps={}], got {s}",
                    self.max_substeps
                ),
            ));
        }
        if self.num_threads > 1024 {
            return Err(MpmError::invalid(
                "num_threads",
                format!("must be in [0, 1024], got {}", self.num_threads),
            ));
        }
        self.water.validate()?;
        self.sand.validate()?;
        self.walls.validate(self.n_grid)?;
        for axis in D..3 {
            for side in 0..2 {
                if self.walls.faces[axis][side].is_some() {
                    return Err(MpmError::invalid(
                        format!("walls.faces.{}", WallParams::FACE_NAMES[axis][side]),
                        format!("a {D}D domain has no such wall (faces: x-, x+, y-, y+)"),
                    ));
                }
            }
        }
        Ok(())
    }

    pub fn dx(&self) -> f32 {
        1.0 / self.n_grid as f32
    }
}

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

/// A static collider as the parameter dict gives it, the same in 2D and 3D:
/// the shape's fields flat (a box: `center`, `half_extents`, and
/// `rotation` or, in 2D, `angle_deg`; a sphere: `center`, `radius`; a
/// sampled signed distance: `origin`, `cell`, `dims`, `values`, optional
/// `normals`), its
/// boundary condition and Coulomb friction. [`ColliderParams::build`] makes
/// the [`Collider`] of a `D`-dimensional solver; fields the shape does not
/// use are ignored.
#[derive(Clone, Debug, PartialEq)]
#[cfg_attr(
    feature = "serde",
    derive(serde::Serialize, serde::Deserialize),
    serde(default, deny_unknown_fields)
)]
pub struct ColliderParams {
    /// Box, sphere or sampled (required).
    #[cfg_attr(feature = "serde", serde(skip_serializing_if = "Option::is_none"))]
    pub shape: Option<ShapeKind>,
    /// Centre [m], `D` numbers (required).
    #[cfg_attr(feature = "serde", serde(skip_serializing_if = "Option::is_none"))]
    pub center: Option<Vec<f32>>,
    /// Box half extents [m], `D` numbers (required for a box).
    #[cfg_attr(feature = "serde", serde(skip_serializing_if = "Option::is_none"))]
    pub half_extents: Option<Vec<f32>>,
    /// Box rotation [degrees] counter-clockwise, 2D only (`rotation` wins).
    #[cfg_attr(feature = "serde", serde(skip_serializing_if = "Option::is_none"))]
    pub angle_deg: Option<f64>,
    /// Box rotation matrix, `D` rows of `D` numbers (columns: the box's
    /// axes in world coordinates); identity when neither it nor
    /// `angle_deg` is given.
    #[cfg_attr(feature = "serde", serde(skip_serializing_if = "Option::is_none"))]
    pub rotation: Option<Vec<Vec<f32>>>,
    /// Sphere radius [m] (required for a sphere).
    #[cfg_attr(feature = "serde", serde(skip_serializing_if = "Option::is_none"))]
    pub radius: Option<f32>,
    /// Sampled: position of the first sample [m], `D` numbers.
    #[cfg_attr(feature = "serde", serde(skip_serializing_if = "Option::is_none"))]
    pub origin: Option<Vec<f32>>,
    /// Sampled: spacing of the samples [m].
    #[cfg_attr(feature = "serde", serde(skip_serializing_if = "Option::is_none"))]
    pub cell: Option<f32>,
    /// Sampled: samples per axis, `D` integers.
    #[cfg_attr(feature = "serde", serde(skip_serializing_if = "Option::is_none"))]
    pub dims: Option<Vec<usize>>,
    /// Sampled: the signed distances [m], row-major (last axis fastest);
    /// see [`Shape::Sampled`].
    #[cfg_attr(feature = "serde", serde(skip_serializing_if = "Option::is_none"))]
    pub values: Option<Vec<f32>>,
    /// Sampled (optional): outward unit normals at the samples, `D` numbers
    /// per sample in the order of `values`.
    #[cfg_attr(feature = "serde", serde(skip_serializing_if = "Option::is_none"))]
    pub normals: Option<Vec<f32>>,
    pub condition: BoundaryCondition,
    /// Coulomb friction coefficient μ (≥ 0; used with `Separate`).
    pub friction: f32,
    /// Put particles that end a substep inside the collider back on its
    /// surface ([`Collider::project`]); default on. (The registered ramps
    /// scenes set it off: their models and datasets were made without it.)
    pub project: bool,
}

impl Default for ColliderParams {
    /// No shape; condition `Separate`, no friction, particles projected.
    fn default() -> Self {
        ColliderParams {
            shape: None,
            center: None,
            half_extents: None,
            angle_deg: None,
            rotation: None,
            radius: None,
            origin: None,
            cell: None,
            dims: None,
            values: None,
            normals: None,
            condition: BoundaryCondition::Separate,
            friction: 0.0,
            project: true,
        }
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

/// The dict forms that differ from the structs (`serde` feature): `[f32; D]`
/// as a list, [`SolverParams`] read through a mirror, [`WallParams`] with its
/// face overrides by name.
#[cfg(feature = "serde")]
mod wire {
    use std::fmt;

    use serde::de::{self, DeserializeSeed, MapAccess, Visitor};
    use serde::ser::SerializeMap;
    use serde::{Deserialize, Deserializer, Serialize, Serializer};

    use super::{BoundaryCondition, SandParams, SolverParams, WallFace, WallParams, WaterParams};

    /// `[f32; D]` as a list of `D` numbers (serde's own array impls need a
    /// literal length).
    pub fn serialize_array<S: Serializer, const D: usize>(
        a: &[f32; D],
        s: S,
    ) -> Result<S::Ok, S::Error> {
        a.as_slice().serialize(s)
    }

    /// `[f32; D]` read from a list of `D` numbers.
    pub struct Array<const D: usize>([f32; D]);

    impl<'de, const D: usize> Deserialize<'de> for Array<D> {
        fn deserialize<De: Deserializer<'de>>(d: De) -> Result<Self, De::Error> {
            let v = Vec::<f32>::deserialize(d)?;
            <[f32; D]>::try_from(v.as_slice())
                .map(Array)
                .map_err(|_| de::Error::invalid_length(v.len(), &format!("{D} numbers").as_str()))
        }
    }

    /// [`SolverParams`] with its gravity as a type parameter (`Array<D>`),
    /// which serde's derive can read. The conversions below name every field
    /// without `..`, so the compiler holds the two to the same fields; the
    /// defaults are `SolverParams`'s.
    #[derive(Deserialize)]
    #[serde(
        default,
        deny_unknown_fields,
        rename = "SolverParams",
        bound(deserialize = "G: Deserialize<'de>, Solver<G>: Default")
    )]
    pub struct Solver<G> {
        n_grid: usize,
        gravity: G,
        cfl: f32,
        substeps: Option<usize>,
        max_substeps: usize,
        num_threads: usize,
        water: WaterParams,
        sand: SandParams,
        walls: WallParams,
    }

    impl<const D: usize> Default for Solver<Array<D>> {
        fn default() -> Self {
            let SolverParams {
                n_grid,
                gravity,
                cfl,
                substeps,
                max_substeps,
                num_threads,
                water,
                sand,
                walls,
            } = SolverParams::<D>::default();
            Solver {
                n_grid,
                gravity: Array(gravity),
                cfl,
                substeps,
                max_substeps,
                num_threads,
                water,
                sand,
                walls,
            }
        }
    }

    impl<const D: usize> From<Solver<Array<D>>> for SolverParams<D> {
        fn from(w: Solver<Array<D>>) -> Self {
            let Solver {
                n_grid,
                gravity,
                cfl,
                substeps,
                max_substeps,
                num_threads,
                water,
                sand,
                walls,
            } = w;
            SolverParams {
                n_grid,
                gravity: gravity.0,
                cfl,
                substeps,
                max_substeps,
                num_threads,
                water,
                sand,
                walls,
            }
        }
    }

    impl<'de, const D: usize> Deserialize<'de> for SolverParams<D> {
        fn deserialize<De: Deserializer<'de>>(d: De) -> Result<Self, De::Error> {
            Solver::<Array<D>>::deserialize(d).map(Into::into)
        }
    }

    /// [`WallParams`] as written: a face override keeps the keys it leaves
    /// out (`None`) until the all-faces values are known.
    #[derive(Serialize, Deserialize)]
    #[serde(default, deny_unknown_fields, rename = "WallParams")]
    pub struct Walls {
        cells: usize,
        condition: BoundaryCondition,
        friction: f32,
        #[serde(skip_serializing_if = "Faces::is_empty")]
        faces: Faces,
    }

    impl Default for Walls {
        fn default() -> Self {
            WallParams::default().into()
        }
    }

    #[derive(Clone, Copy, Default, Serialize, Deserialize)]
    #[serde(default, deny_unknown_fields, rename = "WallFace")]
    struct Face {
        #[serde(skip_serializing_if = "Option::is_none")]
        condition: Option<BoundaryCondition>,
        #[serde(skip_serializing_if = "Option::is_none")]
        friction: Option<f32>,
    }

    /// Face overrides by `[axis][side]`, written as a map keyed by
    /// [`WallParams::FACE_NAMES`].
    #[derive(Default)]
    struct Faces([[Option<Face>; 2]; 3]);

    /// [`WallParams::FACE_NAMES`] in one list (for error messages).
    static FACE_LIST: [&str; 6] = {
        let n = WallParams::FACE_NAMES;
        [n[0][0], n[0][1], n[1][0], n[1][1], n[2][0], n[2][1]]
    };

    impl Faces {
        fn is_empty(&self) -> bool {
            self.0.iter().flatten().all(Option::is_none)
        }
    }

    impl Serialize for Faces {
        fn serialize<S: Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
            let mut map = s.serialize_map(None)?;
            for (names, row) in WallParams::FACE_NAMES.iter().zip(&self.0) {
                for (name, face) in names.iter().zip(row) {
                    if let Some(face) = face {
                        map.serialize_entry(name, face)?;
                    }
                }
            }
            map.end()
        }
    }

    impl<'de> Deserialize<'de> for Faces {
        fn deserialize<De: Deserializer<'de>>(d: De) -> Result<Self, De::Error> {
            d.deserialize_map(FacesVisitor)
        }
    }

    struct FacesVisitor;

    impl<'de> Visitor<'de> for FacesVisitor {
        type Value = Faces;

        fn expecting(&self, f: &mut fmt::Formatter) -> fmt::Result {
            f.write_str("a map of wall face name to {condition, friction}")
        }

        fn visit_map<A: MapAccess<'de>>(self, mut map: A) -> Result<Faces, A::Error> {
            let mut faces = Faces::default();
            while let Some((axis, side)) = map.next_key_seed(FaceName)? {
                faces.0[axis][side] = Some(map.next_value()?);
            }
            Ok(faces)
        }
    }

    /// A face name read as `(axis, side)`; any other name is an unknown field.
    struct FaceName;

    impl<'de> DeserializeSeed<'de> for FaceName {
        type Value = (usize, usize);

        fn deserialize<De: Deserializer<'de>>(self, d: De) -> Result<Self::Value, De::Error> {
            d.deserialize_identifier(self)
        }
    }

    impl<'de> Visitor<'de> for FaceName {
        type Value = (usize, usize);

        fn expecting(&self, f: &mut fmt::Formatter) -> fmt::Result {
            f.write_str("a wall face name")
        }

        fn visit_str<E: de::Error>(self, v: &str) -> Result<Self::Value, E> {
            WallParams::face_index(v).ok_or_else(|| E::unknown_field(v, &FACE_LIST))
        }
    }

    impl From<Walls> for WallParams {
        fn from(w: Walls) -> Self {
            let faces = w.faces.0.map(|row| {
                row.map(|face| {
                    face.map(|f| WallFace {
                        condition: f.condition.unwrap_or(w.condition),
                        friction: f.friction.unwrap_or(w.friction),
                    })
                })
            });
            WallParams {
                cells: w.cells,
                condition: w.condition,
                friction: w.friction,
                faces,
            }
        }
    }

    impl From<WallParams> for Walls {
        fn from(w: WallParams) -> Self {
            let faces = w.faces.map(|row| {
                row.map(|face| {
                    face.map(|f| Face {
                        condition: Some(f.condition),
                        friction: Some(f.friction),
                    })
                })
            });
            Walls {
                cells: w.cells,
                condition: w.condition,
                friction: w.friction,
                faces: Faces(faces),
            }
        }
    }
}

#[cfg(all(test, feature = "serde"))]
mod serde_tests {
    use super::*;

    #[test]
    fn defaults_round_trip_and_fill_missing_keys() {
        let d = SolverParams::<3>::default();
        let json = serde_json::to_string(&d).unwrap();
        assert_eq!(serde_json::from_str::<SolverParams<3>>(&json).unwrap(), d);
        assert_eq!(serde_json::from_str::<SolverParams<3>>("{}").unwrap(), d);
        // f32 written shortest, so a reader in f64 gets the decimal default
        assert!(json.contains("\"cfl\":0.4,"), "{json}");
        assert!(!json.contains("faces"), "{json}");
    }

    #[test]
    fn a_face_override_falls_back_to_the_all_faces_values() {
        let p: SolverParams<2> = serde_json::from_str(
            r#"{"walls": {"faces": {"y-": {"condition": "sticky"}, "x+": {}}, "friction": 0.25}}"#,
        )
        .unwrap();
        let w = &p.walls;
        assert_eq!(
            w.faces[1][0],
            Some(WallFace {
                condition: BoundaryCondition::Sticky,
                friction: 0.25
            })
        );
        assert_eq!(w.face(0, 1), w.face(0, 0));
        assert_eq!(w.faces[0][0], None);
        let back: SolverParams<2> =
            serde_json::from_str(&serde_json::to_string(&p).unwrap()).unwrap();
        assert_eq!(back, p);
    }

    #[test]
    fn unknown_keys_and_faces_are_refused() {
        for (json, word) in [
            (r#"{"wter": {}}"#, "wter"),
            (r#"{"water": {"bulk": 1}}"#, "bulk"),
            (r#"{"walls": {"faces": {"w-": {}}}}"#, "w-"),
            (r#"{"walls": {"faces": {"y-": {"mu": 1}}}}"#, "mu"),
            (r#"{"gravity": [0, -9.8, 0]}"#, "2 numbers"),
            (r#"{"walls": {"condition": "glue"}}"#, "glue"),
        ] {
            let e = serde_json::from_str::<SolverParams<2>>(json).unwrap_err();
            assert!(e.to_string().contains(word), "{json}: {e}");
        }
    }

    #[test]
    fn colliders_build_in_their_dimension() {
        let c: ColliderParams = serde_json::from_str(
            r#"{"shape": "box", "center": [0.5, 0.2], "half_extents": [0.1, 0.05], "angle_deg": 90}"#,
        )
        .unwrap();
        assert_eq!(c.condition, BoundaryCondition::Separate);
        let Shape::Box { rotation, .. } = c.build::<2>("colliders[0]").unwrap().shape else {
            panic!("not a box");
        };
        assert!((rotation[(1, 0)] - 1.0).abs() < 1e-6);
        let e = c.build::<3>("colliders[0]").unwrap_err().to_string();
        assert!(e.starts_with("colliders[0].center"), "{e}");
        let s: ColliderParams =
            serde_json::from_str(r#"{"shape": "circle", "center": [0.5, 0.2]}"#).unwrap();
        let e = s.build::<2>("colliders[1]").unwrap_err().to_string();
        assert!(e.starts_with("colliders[1].radius: missing"), "{e}");
        assert_eq!(
            serde_json::to_string(&ColliderParams::default()).unwrap(),
            r#"{"condition":"separate","friction":0.0,"project":true}"#
        );
    }
}
