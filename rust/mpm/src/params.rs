//! Solver parameters: one `...Params` struct per concept, each with `Default`,
//! documented SI units and a `validate()` that names the bad field.

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

/// How a boundary acts on the grid velocity of nodes inside it.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum BoundaryCondition {
    /// Velocity set to the boundary's (zero): no slip.
    Sticky,
    /// Normal component removed both ways (no penetration, no separation).
    Slip,
    /// Only the inward normal component removed; Coulomb friction on the
    /// tangential part while in contact.
    Separate,
}

impl BoundaryCondition {
    pub fn parse(field: &str, s: &str) -> Result<Self> {
        match s {
            "sticky" => Ok(Self::Sticky),
            "slip" => Ok(Self::Slip),
            "separate" => Ok(Self::Separate),
            other => Err(MpmError::invalid(
                field,
                format!("must be one of 'sticky', 'slip', 'separate', got '{other}'"),
            )),
        }
    }

    pub fn name(self) -> &'static str {
        match self {
            Self::Sticky => "sticky",
            Self::Slip => "slip",
            Self::Separate => "separate",
        }
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
#[derive(Clone, Debug, PartialEq)]
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
#[derive(Clone, Debug, PartialEq)]
pub struct SolverParams<const D: usize> {
    /// Grid cells per dimension over the unit domain (dx = 1 / n_grid), in [16, 4096].
    pub n_grid: usize,
    /// Gravity [m/s²].
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
