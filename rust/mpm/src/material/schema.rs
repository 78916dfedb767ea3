//! The one schema of the materials' parameters: the row of a table
//! ([`Param`]: name, the user's alias, unit, range, choices, description,
//! source), the trait a params struct declares its table with
//! ([`MaterialSchema`], whose `validate()` every model shares), the one
//! range checker it calls ([`check`]) and the rows several models share (density, E, ν). Each
//! model declares its own table beside its update (`water.rs`,
//! `sand/mod.rs`, ...); `material_schema` (`mod.rs`) lists them all.
//!
//! The defaults are the structs' `Default`, read in table order through
//! [`MaterialSchema::values`]. The Python binding exports the tables
//! (`hybridmpm._core.material_schema()`), and Python's materials, the HTTP
//! pour body and docs/materials.md's table are read from or tested against
//! them: a range is written here only.

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

pub(super) const fn gt(value: f64) -> Option<Limit> {
    Some(Limit {
        value,
        inclusive: false,
    })
}

pub(super) const fn ge(value: f64) -> Option<Limit> {
    Some(Limit {
        value,
        inclusive: true,
    })
}

pub(super) const fn lt(value: f64) -> Option<Limit> {
    gt(value)
}

pub(super) const fn le(value: f64) -> Option<Limit> {
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

    /// Checks the set, naming the first bad field `{prefix}.{name}`: its
    /// ranges ([`Self::check_ranges`]), and what else a model asks (sand:
    /// cohesion needs friction).
    fn validate_at(&self, prefix: &str) -> Result<()> {
        self.check_ranges(prefix)
    }

    /// Checks the set, naming the first bad field under the material's
    /// name (`water.viscosity`).
    fn validate(&self) -> Result<()> {
        self.validate_at(Self::MATERIAL.name())
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

pub(super) const DENSITY: Param = Param {
    name: "density",
    alias: None,
    unit: "kg/m³",
    lower: gt(0.0),
    upper: None,
    choices: &[],
    description: "rest density ρ",
    source: "a mass needs a positive density",
};

pub(super) const YOUNGS: Param = Param {
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
pub(super) const POISSON: Param = Param {
    name: "poisson_ratio",
    alias: Some("nu"),
    unit: "-",
    lower: ge(0.0),
    upper: lt(0.5),
    choices: &[],
    description: "Poisson's ratio ν",
    source: "λ = Eν/((1 + ν)(1 − 2ν)) is finite and ≥ 0 for ν in [0, 0.5)",
};

pub(super) const fn at_least_zero(
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
