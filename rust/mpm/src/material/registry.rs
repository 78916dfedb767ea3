//! What the registry (`materials!` in `codes.rs`, one line per model) makes
//! of the models: `register!` turns the list into [`Material::is_solid`],
//! one parameter set of any model ([`MaterialParams`]), one model's
//! constants ([`Model`]), the dispatch over each (`each_set!`,
//! `each_model!`) and every model's schema table ([`material_schema`]).
//! At compile time it checks that each params struct's
//! `MaterialSchema::MATERIAL` is its own line's code (`codes.rs` checks
//! that the codes are `0..n` in the list's order).
//!
//! [`Material::is_solid`]: super::Material::is_solid
//! [`MaterialParams`]: super::MaterialParams
//! [`Model`]: super::Model
//! [`material_schema`]: super::material_schema

/// The items of the registry's list (see the module's doc); `$d` is `$`,
/// for the dispatch macros it defines.
macro_rules! register {
    (($d:tt) $(
        $(#[$doc:meta])*
        $name:ident = $code:literal => $module:ident::{$params:ident, $model:ident},
    )*) => {
        /// Every model's parameter struct, re-exported here, by `params`
        /// and at the crate's root.
        pub mod param_structs {
            $(pub use super::$module::$params;)*
        }
        pub use param_structs::*;

        impl Material {
            /// Whether it is one of the solids (elastic, snow, viscoplastic):
            /// a body whose `F` keeps its shape (sand's `F` is only the
            /// elastic part of a granular flow; water has none).
            pub fn is_solid(self) -> bool {
                match self {
                    $(Material::$name => <$module::$model as Constitutive>::SOLID,)*
                }
            }
        }

        // Each struct's schema names its own line.
        const _: () = {
            $(assert!(
                <$params as MaterialSchema>::MATERIAL as u8 == Material::$name as u8,
                concat!(stringify!($params), "::MATERIAL is not Material::", stringify!($name)),
            );)*
        };

        /// One parameter set of the table particles index (`Particle::set`).
        /// The parameter dict names it by its material, the one key of a dict
        /// (`{"elastic": {"youngs_modulus": 1e6}}`, serde's externally tagged
        /// form; the keys inside as each struct's, unknown ones refused);
        /// `SolverParams::sets` (`crate::params`) lists them.
        #[derive(Clone, Debug, PartialEq)]
        #[cfg_attr(
            feature = "serde",
            derive(serde::Serialize, serde::Deserialize),
            serde(rename_all = "lowercase")
        )]
        pub enum MaterialParams {
            $($name($params),)*
        }

        impl MaterialParams {
            /// The default parameter set of `material` (its struct's
            /// `Default`).
            pub fn default_for(material: Material) -> Self {
                match material {
                    $(Material::$name => MaterialParams::$name(<$params>::default()),)*
                }
            }
        }

        /// `$body` with `$p` bound to the params struct inside `$set` (a
        /// [`MaterialParams`]), or `$ty` to its type.
        macro_rules! each_set {
            ($d set:expr, $d p:ident => $d body:expr) => {
                match $d set {
                    $(MaterialParams::$name($d p) => $d body,)*
                }
            };
            ($d set:expr, type $d ty:ident => $d body:expr) => {
                match $d set {
                    $(MaterialParams::$name(_) => {
                        type $d ty = $params;
                        $d body
                    })*
                }
            };
        }

        /// Every model's table and defaults (the struct's `Default`, in
        /// table order).
        pub fn material_schema() -> Vec<(Material, &'static [Param], Vec<ParamValue>)> {
            fn row<T: MaterialSchema>() -> (Material, &'static [Param], Vec<ParamValue>) {
                (T::MATERIAL, T::PARAMS, T::default().values())
            }
            vec![$(row::<$params>(),)*]
        }

        /// The constants of one parameter set: one model of each material.
        #[derive(Clone, Debug)]
        pub(crate) enum Model {
            $($name($module::$model),)*
        }

        /// `$body` with `$m` bound to the [`Constitutive`] model inside
        /// `$model` (a [`Model`]), or `$ty` to its type.
        macro_rules! each_model {
            ($d model:expr, $d m:ident => $d body:expr) => {
                match $d model {
                    $(Model::$name($d m) => $d body,)*
                }
            };
            ($d model:expr, type $d ty:ident => $d body:expr) => {
                match $d model {
                    $(Model::$name(_) => {
                        type $d ty = $module::$model;
                        $d body
                    })*
                }
            };
        }

        impl Model {
            /// The model of `params` in `D` dimensions.
            pub(crate) fn new<const D: usize>(params: &MaterialParams) -> Self
            where
                Dim<D>: DimOps<D>,
            {
                match params {
                    $(MaterialParams::$name(p) => Model::$name($module::$model::new::<D>(p)),)*
                }
            }
        }
    };
}

pub(super) use register;
