//! Solver parameters: one `...Params` struct per concept, each with `Default`,
//! documented SI units and a `validate()` that names the bad field.
//!
//! These structs are the one schema of the parameters. With the `serde`
//! feature they (de)serialise as the parameter dict of the Python binding:
//! every field optional (a missing one takes its `Default`), an unknown key
//! refused, boundary conditions as `"sticky"`, `"slip"`, `"separate"`. The
//! binding reads its dict with them and gives Python the defaults from them.
//!
//! Here the solver-wide [`SolverParams`] and the checks every part shares;
//! `walls.rs` the domain's walls (and their faces by name in the dict),
//! `collider.rs` a collider as the dict gives it, `body.rs` a rigid body.
//! Each material's parameters ([`WaterParams`], ..., [`MaterialParams`], one
//! set of any of them) and their schema live with the model, in
//! `crate::material`; they are re-exported here, so that the parameter
//! dict's parts are all named under `params`.

mod body;
mod collider;
#[cfg(all(test, feature = "serde"))]
mod tests;
mod walls;

pub use crate::boundary::BoundaryCondition;
pub use crate::material::param_structs::*;
pub use crate::material::schema::{self, Limit, MaterialSchema, Param, ParamValue};
pub use crate::material::{ElasticModel, MaterialParams, lame, material_schema};
pub use body::{BodyParams, BodyShapeKind};
pub use collider::{ColliderParams, ShapeKind};
pub use walls::{WallFace, WallParams};

use crate::error::{MpmError, Result};
use crate::particles::Material;

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

fn non_negative(field: &str, x: f32) -> Result<()> {
    finite(field, x)?;
    if x < 0.0 {
        return Err(MpmError::invalid(field, format!("must be >= 0, got {x}")));
    }
    Ok(())
}

/// Largest `max_substeps`: a million substeps make a frame of minutes.
pub const MAX_SUBSTEPS: usize = 1_000_000;

/// `SolverParams`, its `Default` and its default parameter sets, one field
/// per material in the registry's order (`material::materials!`), named as
/// the material: the dict's keys and their order are those of the fields
/// written out.
macro_rules! solver_params {
    (($d:tt) $(
        $(#[$doc:meta])*
        $name:ident = $code:literal => $module:ident::{$params:ident, $model:ident},
    )*) => {
        /// Solver-wide parameters.
        ///
        /// (`serde` feature: the empty `bound` spares serde's derive the bound
        /// `SolverParams<D>: Default` it would write for `default`, which it cannot
        /// write for a struct generic over a const; the `Default` below holds for
        /// every `D`.)
        #[derive(Clone, Debug, PartialEq)]
        #[cfg_attr(
            feature = "serde",
            derive(serde::Serialize, serde::Deserialize),
            serde(default, deny_unknown_fields, bound(deserialize = ""))
        )]
        pub struct SolverParams<const D: usize> {
            /// Grid cells per dimension over the unit domain (dx = 1 / n_grid), in [16, 4096].
            pub n_grid: usize,
            /// Gravity [m/s²] (a list of `D` numbers in the parameter dict).
            #[cfg_attr(feature = "serde", serde(with = "array"))]
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
            $(
                #[doc = concat!(
                    "The default ", stringify!($module), " parameter set: table entry ",
                    stringify!($code), ", its material code (a particle's `set` is its ",
                    "code unless it names one of `sets`)."
                )]
                pub $module: $params,
            )*
            /// Further parameter sets (table entries [`BASE_SETS`], ... on): a
            /// scene's blocks of one material with different parameters (two
            /// jellies of different stiffness). At most [`MAX_SETS`] entries in all.
            pub sets: Vec<MaterialParams>,
            pub walls: WallParams,
            /// How a frame advances: the explicit MLS-MPM substeps, or the
            /// incompressible projection step ([`Integrator`]). Left out of the dict
            /// when explicit, so a scene without it serialises as before.
            #[cfg_attr(
                feature = "serde",
                serde(skip_serializing_if = "Integrator::is_explicit")
            )]
            pub integrator: Integrator,
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
                    $($module: $params::default(),)*
                    sets: Vec::new(),
                    walls: WallParams::default(),
                    integrator: Integrator::Explicit,
                }
            }
        }

        impl<const D: usize> SolverParams<D> {
            /// The default set of each material, by code.
            fn default_sets(&self) -> [MaterialParams; BASE_SETS] {
                [$(MaterialParams::$name(self.$module.clone()),)*]
            }

            /// Validates each default set, naming a bad field under its
            /// material (`water.viscosity`).
            fn validate_default_sets(&self) -> Result<()> {
                $(self.$module.validate()?;)*
                Ok(())
            }
        }
    };
}

crate::material::materials!(solver_params);

/// How the solver advances a frame (named `"explicit"` or `"projection"`
/// in the parameter dict).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
#[cfg_attr(
    feature = "serde",
    derive(serde::Serialize, serde::Deserialize),
    serde(rename_all = "lowercase")
)]
pub enum Integrator {
    /// Explicit MLS-MPM (Hu et al. 2018): substeps at the CFL bound of the
    /// materials' wave speeds (water's artificial sound speed `√(K/ρ)`).
    #[default]
    Explicit,
    /// Incompressible APIC with a pressure projection ([`crate::projection`]):
    /// steps at the flow's pace, an advective CFL of one cell. Water alone,
    /// in the box walls (free slip): no colliders, bodies, sand or solids.
    Projection,
}

impl Integrator {
    /// Every integrator, the default first.
    pub const ALL: [Integrator; 2] = [Integrator::Explicit, Integrator::Projection];

    pub fn is_explicit(&self) -> bool {
        *self == Integrator::Explicit
    }

    /// The name in the parameter dict.
    pub fn name(&self) -> &'static str {
        match self {
            Integrator::Explicit => "explicit",
            Integrator::Projection => "projection",
        }
    }
}

/// Largest parameter table (`Particle::set` is a `u16`).
pub const MAX_SETS: usize = 1 << 16;

/// Table entries before [`SolverParams::sets`]: one default per material code.
pub const BASE_SETS: usize = Material::ALL.len();

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
        self.validate_default_sets()?;
        if BASE_SETS + self.sets.len() > MAX_SETS {
            return Err(MpmError::invalid(
                "sets",
                format!(
                    "at most {} parameter sets, got {}",
                    MAX_SETS - BASE_SETS,
                    self.sets.len()
                ),
            ));
        }
        for (i, set) in self.sets.iter().enumerate() {
            set.validate(&format!("sets[{i}]"))?;
        }
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

    /// The table of parameter sets particles index: the default set of each
    /// material by code, then [`Self::sets`]. Call after [`Self::validate`].
    pub fn table(&self) -> Vec<MaterialParams> {
        let mut t = Vec::from(self.default_sets());
        t.extend(self.sets.iter().cloned());
        t
    }

    pub fn dx(&self) -> f32 {
        1.0 / self.n_grid as f32
    }
}

/// `[f32; D]` as a list of `D` numbers in the dict (serde's own array impls
/// need a literal length).
#[cfg(feature = "serde")]
mod array {
    use serde::de::{self, Deserialize, Deserializer};
    use serde::ser::{Serialize, Serializer};

    pub fn serialize<S: Serializer, const D: usize>(a: &[f32; D], s: S) -> Result<S::Ok, S::Error> {
        a.as_slice().serialize(s)
    }

    pub fn deserialize<'de, De: Deserializer<'de>, const D: usize>(
        d: De,
    ) -> Result<[f32; D], De::Error> {
        let v = Vec::<f32>::deserialize(d)?;
        <[f32; D]>::try_from(v.as_slice())
            .map_err(|_| de::Error::invalid_length(v.len(), &format!("{D} numbers").as_str()))
    }
}
