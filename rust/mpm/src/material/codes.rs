//! The material codes and the registry's list. The list (`materials!`)
//! names every constitutive model once; here it makes [`Material`], the
//! code a particle carries, which reads nothing of the models, so that
//! `particles` and the models' files can name a material without the
//! models' registration (`material/mod.rs`, `registry.rs`).

/// The registry: every constitutive model, one line each, in code order
/// (`Variant = code => module::{ParamsStruct, Model}`; the module's name
/// is the material's name in parameter dicts and scene files, and the
/// field of its default set in `SolverParams`). `materials!(then)` hands
/// the list to the macro `then`: here `material_codes!` makes of it
/// [`Material`]; `register!` (`registry.rs`) makes [`MaterialParams`],
/// `Model` and their dispatch and `material_schema` (`material/mod.rs`);
/// `params` makes the default sets of `SolverParams` and its table.
macro_rules! materials {
    ($then:ident) => {
        $then! { ($)
            /// Weakly compressible water (carries `J`).
            Water = 0 => water::{WaterParams, Water},
            /// Drucker–Prager sand (carries the elastic deformation gradient `F`).
            Sand = 1 => sand::{SandParams, Sand},
            /// Elastic solid, fixed-corotated or neo-Hookean (carries `F`).
            Elastic = 2 => elastic::{ElasticParams, Elastic},
            /// Snow, Stomakhin et al. 2013 (carries the elastic `F_E` in `f` and
            /// the plastic volume ratio `J_P` in `j`).
            Snow = 3 => snow::{SnowParams, Snow},
            /// Viscoplastic solid: von Mises with viscous relaxation (carries the
            /// elastic `F`).
            Viscoplastic = 4 => viscoplastic::{ViscoplasticParams, Viscoplastic},
        }
    };
}
pub(crate) use materials;

/// The codes of the registry's list: [`Material`], its `ALL` and names.
macro_rules! material_codes {
    (($d:tt) $(
        $(#[$doc:meta])*
        $name:ident = $code:literal => $module:ident::{$params:ident, $model:ident},
    )*) => {
        /// Material of a particle. The numeric codes are the public API
        /// (`material` arrays on the Python side).
        #[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
        #[repr(u8)]
        pub enum Material {
            $($(#[$doc])* $name = $code,)*
        }

        impl Material {
            /// Every material, by code.
            pub const ALL: [Material; [$(Material::$name),*].len()] = [$(Material::$name),*];

            /// The material's name in parameter dicts and scene files.
            pub fn name(self) -> &'static str {
                match self {
                    $(Material::$name => stringify!($module),)*
                }
            }
        }

        // The codes are `0..n` in the list's order (`Material::from_code`
        // indexes `ALL`).
        const _: () = {
            let mut i = 0;
            while i < Material::ALL.len() {
                assert!(Material::ALL[i] as usize == i, "material codes are 0..n in order");
                i += 1;
            }
        };
    };
}

materials!(material_codes);
