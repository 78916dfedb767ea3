//! `material_schema()`: each model's parameter table (the core's
//! `material_schema`, beside each model in `rust/mpm/src/material/`) as Python dicts, from which `hybridmpm.materials`
//! builds its range checks, user aliases and defaults; `MATERIAL_CODES`: each model's solver code by
//! name (the registry's `materials!` list, `Material::ALL`), from which `hybridmpm.conventions` takes
//! its `MATERIALS`.

use hybridmpm_mpm::{Material, Param, ParamValue};
use pyo3::prelude::*;
use pyo3::types::{PyDict, PyList};

/// An f32 as the f64 of its shortest decimal (`0.3`, not `0.30000001192092896`),
/// as `default_params` gives the defaults.
fn decimal(x: f32) -> f64 {
    format!("{x}").parse().unwrap_or(f64::from(x))
}

/// One parameter as a dict (keys documented on `material_schema`).
fn param<'py>(py: Python<'py>, p: &Param, default: ParamValue) -> PyResult<Bound<'py, PyDict>> {
    let d = PyDict::new(py);
    d.set_item("name", p.name)?;
    d.set_item("key", p.key())?;
    d.set_item("unit", p.unit)?;
    d.set_item("lower", p.lower.map(|l| l.value))?;
    d.set_item("lower_inclusive", p.lower.map(|l| l.inclusive))?;
    d.set_item("upper", p.upper.map(|u| u.value))?;
    d.set_item("upper_inclusive", p.upper.map(|u| u.inclusive))?;
    d.set_item("choices", p.choices.to_vec())?;
    d.set_item("range", p.range_text())?;
    match default {
        ParamValue::Number(x) => d.set_item("default", decimal(x))?,
        ParamValue::Name(n) => d.set_item("default", n)?,
    }
    d.set_item("description", p.description)?;
    d.set_item("source", p.source)?;
    Ok(d)
}

/// `{model: [param, ...]}` for every model of the registry, in code order, each
/// param `{name, key (the user's name: "E" for youngs_modulus), unit, lower,
/// lower_inclusive, upper, upper_inclusive (None when unbounded), choices
/// (names a named parameter takes; [] for a number), range (the words every
/// refusal uses: "in [0, 0.5)"), default, description, source}`, in the
/// parameter struct's field order.
#[pyfunction]
fn material_schema(py: Python<'_>) -> PyResult<Bound<'_, PyDict>> {
    let out = PyDict::new(py);
    for (material, params, defaults) in hybridmpm_mpm::material_schema() {
        let list = PyList::empty(py);
        for (p, d) in params.iter().zip(defaults) {
            list.append(param(py, p, d)?)?;
        }
        out.set_item(material.name(), list)?;
    }
    Ok(out)
}

/// `{name: code}` of every material, in code order (`Material::ALL`: `{"water": 0, "sand": 1, ...}`).
fn material_codes(py: Python<'_>) -> PyResult<Bound<'_, PyDict>> {
    let out = PyDict::new(py);
    for m in Material::ALL {
        out.set_item(m.name(), m as u8)?;
    }
    Ok(out)
}

pub fn register(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add("MATERIAL_CODES", material_codes(m.py())?)?;
    m.add_function(wrap_pyfunction!(material_schema, m)?)
}
