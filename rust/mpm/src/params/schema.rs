//! The one schema of the materials' parameters: for each model (water, sand,
//! elastic, snow, viscoplastic) a static table of its parameters ([`Param`]:
//! name, the user's alias, unit, range, choices, description, source) and
//! the one range checker every `validate()` calls ([`check`]).
//!
//! The defaults are the structs' `Default`, read in table order through
//! [`MaterialSchema::values`]. The Python binding exports the tables
//! (`hybridmpm._core.material_schema()`), and Python's materials, the HTTP
//! pour body and docs/materials.md's table are read from or tested against
//! them: a range is written here only.

use super::{ElasticParams, SandParams, SnowParams, ViscoplasticParams, WaterParams};
use crate::error::{MpmError, Result};
use crate::particles::Material;

/// One bound of a parameter's range.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Limit {
    /// The bound, in the parameter's unit.
    pub value: f64,
    /// Whether the bound itself is in the range.
    pub inclusive: bool,
}

/// One parameter of a model: what a user, the docs and every check read.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Param {
    /// The field's name in the params struct and the parameter dict (`youngs_modulus`).
    pub name: &'static str,
    /// The name a scene block and the HTTP pour body give it (`E`), if another.
    pub alias: Option<&'static str>,
    /// SI unit (`Pa`, `kg/m³`, `Pa·s`, `deg`; `-` dimensionless).
    pub unit: &'static str,
    /// Lower bound (`None`: unbounded below).
    pub lower: Option<Limit>,
    /// Upper bound (`None`: unbounded above).
    pub upper: Option<Limit>,
    /// The names a named (non-numeric) parameter takes; empty for a number.
    pub choices: &'static [&'static str],
    /// One line: what it is.
    pub description: &'static str,
    /// Where its default and range come from.
    pub source: &'static str,
}

/// A parameter's value: a number (f32, the solver's precision) or a name.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum ParamValue {
    Number(f32),
    Name(&'static str),
}

const fn gt(value: f64) -> Option<Limit> {
    Some(Limit {
        value,
        inclusive: false,
    })
}

const fn ge(value: f64) -> Option<Limit> {
    Some(Limit {
        value,
        inclusive: true,
    })
}

const fn lt(value: f64) -> Option<Limit> {
    gt(value)
}

const fn le(value: f64) -> Option<Limit> {
    ge(value)
}

impl Param {
    /// The user's name of it: the alias, else the name.
    pub fn key(&self) -> &'static str {
        self.alias.unwrap_or(self.name)
    }

    /// The range in words, as every refusal words it: `> 0`, `>= 0`,
    /// `in [0, 0.5)`, `any number` (unbounded), or the choices.
    pub fn range_text(&self) -> String {
        if !self.choices.is_empty() {
            return format!("one of {}", self.choices.join(", "));
        }
        match (self.lower, self.upper) {
            (Some(l), Some(u)) => format!(
                "in {}{}, {}{}",
                if l.inclusive { '[' } else { '(' },
                l.value,
                u.value,
                if u.inclusive { ']' } else { ')' }
            ),
            (Some(l), None) => format!("{} {}", if l.inclusive { ">=" } else { ">" }, l.value),
            (None, Some(u)) => format!("{} {}", if u.inclusive { "<=" } else { "<" }, u.value),
            (None, None) => "any number".to_string(),
        }
    }

    /// Whether `x` is in the range (false for NaN).
    pub fn contains(&self, x: f64) -> bool {
        let above_lower = self
            .lower
            .is_none_or(|l| x > l.value || (l.inclusive && x == l.value));
        let below_upper = self
            .upper
            .is_none_or(|u| x < u.value || (u.inclusive && x == u.value));
        x.is_finite() && above_lower && below_upper
    }

    /// Checks `value` of field `field` (`sets[2].elastic.poisson_ratio`):
    /// finite and in the range, or one of the choices.
    pub fn check(&self, field: &str, value: ParamValue) -> Result<()> {
        match value {
            ParamValue::Number(x) if !x.is_finite() => {
                Err(MpmError::invalid(field, format!("must be finite, got {x}")))
            }
            ParamValue::Number(x) if !self.contains(f64::from(x)) => Err(MpmError::invalid(
                field,
                format!("must be {}, got {x}", self.range_text()),
            )),
            ParamValue::Name(n) if !self.choices.contains(&n) => Err(MpmError::invalid(
                field,
                format!("must be {}, got {n}", self.range_text()),
            )),
            _ => Ok(()),
        }
    }
}

/// A params struct described by a table.
pub trait MaterialSchema: Default {
    /// The model it parameterises.
    const MATERIAL: Material;
    /// Its parameters, in the struct's field order.
    const PARAMS: &'static [Param];
    /// Its values in the order of [`Self::PARAMS`].
    fn values(&self) -> Vec<ParamValue>;

    /// Checks every value against its range, naming the first bad field
    /// `{prefix}.{name}`.
    fn check_ranges(&self, prefix: &str) -> Result<()> {
        check(prefix, Self::PARAMS, &self.values())
    }
}

/// Checks `values` (in the order of `params`) against their ranges, naming
/// the first bad one `{prefix}.{name}`.
pub fn check(prefix: &str, params: &[Param], values: &[ParamValue]) -> Result<()> {
    debug_assert_eq!(params.len(), values.len());
    for (p, &v) in params.iter().zip(values) {
        p.check(&format!("{prefix}.{}", p.name), v)?;
    }
    Ok(())
}

/// Every model's table and defaults (the struct's `Default`, in table order).
pub fn material_schema() -> Vec<(Material, &'static [Param], Vec<ParamValue>)> {
    fn row<T: MaterialSchema>() -> (Material, &'static [Param], Vec<ParamValue>) {
        (T::MATERIAL, T::PARAMS, T::default().values())
    }
    vec![
        row::<WaterParams>(),
        row::<SandParams>(),
        row::<ElasticParams>(),
        row::<SnowParams>(),
        row::<ViscoplasticParams>(),
    ]
}

const DENSITY: Param = Param {
    name: "density",
    alias: None,
    unit: "kg/m³",
    lower: gt(0.0),
    upper: None,
    choices: &[],
    description: "rest density ρ",
    source: "a mass needs a positive density",
};

const YOUNGS: Param = Param {
    name: "youngs_modulus",
    alias: Some("E"),
    unit: "Pa",
    lower: gt(0.0),
    upper: None,
    choices: &[],
    description: "Young's modulus E",
    source: "a stable elastic energy needs E > 0",
};

/// ν of the solids: `[0, 0.5)` (λ is infinite at 0.5; auxetic solids are left out).
const POISSON: Param = Param {
    name: "poisson_ratio",
    alias: Some("nu"),
    unit: "-",
    lower: ge(0.0),
    upper: lt(0.5),
    choices: &[],
    description: "Poisson's ratio ν",
    source: "λ = Eν/((1 + ν)(1 − 2ν)) is finite and ≥ 0 for ν in [0, 0.5)",
};

const fn at_least_zero(
    name: &'static str,
    unit: &'static str,
    description: &'static str,
    source: &'static str,
) -> Param {
    Param {
        name,
        alias: None,
        unit,
        lower: ge(0.0),
        upper: None,
        choices: &[],
        description,
        source,
    }
}

impl MaterialSchema for WaterParams {
    const MATERIAL: Material = Material::Water;
    const PARAMS: &'static [Param] = &[
        DENSITY,
        Param {
            name: "bulk_modulus",
            alias: None,
            unit: "Pa",
            lower: gt(0.0),
            upper: None,
            choices: &[],
            description: "bulk modulus K: the sound speed is √(K/ρ)",
            source: "mpm88 (Hu et al. 2018): K/ρ = 400 m²/s², a 20 m/s sound speed",
        },
        at_least_zero(
            "viscosity",
            "Pa·s",
            "dynamic viscosity η (0: inviscid)",
            "Newtonian water: η ≥ 0",
        ),
    ];
    fn values(&self) -> Vec<ParamValue> {
        use ParamValue::Number as N;
        vec![N(self.density), N(self.bulk_modulus), N(self.viscosity)]
    }
}

impl MaterialSchema for SandParams {
    const MATERIAL: Material = Material::Sand;
    const PARAMS: &'static [Param] = &[
        DENSITY,
        YOUNGS,
        Param {
            lower: gt(-1.0),
            source: "μ = E/(2(1 + ν)) > 0 and λ finite for ν in (−1, 0.5)",
            ..POISSON
        },
        Param {
            name: "friction_angle_deg",
            alias: None,
            unit: "deg",
            lower: ge(0.0),
            upper: le(80.0),
            choices: &[],
            description: "internal friction angle φ of the Drucker–Prager cone",
            source: "Klár et al. 2016 (dry sand about 30°); the cone closes at 90°",
        },
        at_least_zero(
            "cohesion",
            "Pa",
            "cohesion c: the cone's apex at the tensile mean stress c / tan φ",
            "Tampubolon et al. 2017; c > 0 needs φ > 0",
        ),
    ];
    fn values(&self) -> Vec<ParamValue> {
        use ParamValue::Number as N;
        vec![
            N(self.density),
            N(self.youngs_modulus),
            N(self.poisson_ratio),
            N(self.friction_angle_deg),
            N(self.cohesion),
        ]
    }
}

impl MaterialSchema for ElasticParams {
    const MATERIAL: Material = Material::Elastic;
    const PARAMS: &'static [Param] = &[
        DENSITY,
        YOUNGS,
        POISSON,
        Param {
            name: "model",
            alias: None,
            unit: "-",
            lower: None,
            upper: None,
            choices: &["corotated", "neohookean"],
            description: "the energy: fixed-corotated or compressible neo-Hookean",
            source: "Stomakhin et al. 2012 (corotated); Bonet & Wood 2008 (neo-Hookean)",
        },
    ];
    fn values(&self) -> Vec<ParamValue> {
        use ParamValue::Number as N;
        vec![
            N(self.density),
            N(self.youngs_modulus),
            N(self.poisson_ratio),
            ParamValue::Name(self.model.name()),
        ]
    }
}

const fn theta(name: &'static str, description: &'static str) -> Param {
    Param {
        name,
        alias: None,
        unit: "-",
        lower: gt(0.0),
        upper: lt(1.0),
        choices: &[],
        description,
        source: "Stomakhin et al. 2013, Table 2 (θc = 2.5e-2, θs = 7.5e-3)",
    }
}

impl MaterialSchema for SnowParams {
    const MATERIAL: Material = Material::Snow;
    const PARAMS: &'static [Param] = &[
        DENSITY,
        Param {
            description: "initial Young's modulus E₀",
            ..YOUNGS
        },
        POISSON,
        theta(
            "theta_c",
            "critical compression θc: singular values of F_E ≥ 1 − θc",
        ),
        theta(
            "theta_s",
            "critical stretch θs: singular values of F_E ≤ 1 + θs",
        ),
        Param {
            name: "hardening",
            alias: None,
            unit: "-",
            lower: ge(0.0),
            upper: le(50.0),
            choices: &[],
            description: "hardening coefficient ξ: the Lamé parameters scale by e^{ξ(1 − J_P)}",
            source: "Stomakhin et al. 2013 (ξ = 10); 50 caps the factor e^{0.4ξ} at J_P = 0.6 near 5e8",
        },
    ];
    fn values(&self) -> Vec<ParamValue> {
        use ParamValue::Number as N;
        vec![
            N(self.density),
            N(self.youngs_modulus),
            N(self.poisson_ratio),
            N(self.theta_c),
            N(self.theta_s),
            N(self.hardening),
        ]
    }
}

impl MaterialSchema for ViscoplasticParams {
    const MATERIAL: Material = Material::Viscoplastic;
    const PARAMS: &'static [Param] = &[
        DENSITY,
        YOUNGS,
        POISSON,
        at_least_zero(
            "yield_stress",
            "Pa",
            "Bingham yield stress τ_y in simple shear (flow when √J₂ > τ_y)",
            "mudflow rheology (Coussot 1997): 10-1000 Pa",
        ),
        at_least_zero(
            "viscosity",
            "Pa·s",
            "plastic (Bingham) viscosity η; 0: perfect plasticity",
            "mudflow rheology (Coussot 1997): 1-100 Pa·s",
        ),
    ];
    fn values(&self) -> Vec<ParamValue> {
        use ParamValue::Number as N;
        vec![
            N(self.density),
            N(self.youngs_modulus),
            N(self.poisson_ratio),
            N(self.yield_stress),
            N(self.viscosity),
        ]
    }
}
