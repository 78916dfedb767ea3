//! Material codes from Python (`0` water, `1` sand: `Material::from_code`):
//! one for every particle or one per particle.

use hybridmpm_mpm as core;
use hybridmpm_mpm::{Material, MpmError};
use pyo3::prelude::*;
use pyo3::types::{PyBool, PyInt};

use crate::errors::{invalid_input, repr};

/// Material codes: one for every particle, or one per particle.
pub(crate) enum Codes {
    All(Material),
    Each(Vec<Material>),
}

impl Codes {
    pub(crate) fn expand(&self, n: usize) -> core::Result<Vec<Material>> {
        match self {
            Codes::All(m) => Ok(vec![*m; n]),
            Codes::Each(v) if v.len() == n => Ok(v.clone()),
            Codes::Each(v) => Err(MpmError::invalid(
                "material",
                format!("expected shape [{n}], got [{}]", v.len()),
            )),
        }
    }
}

fn unknown_code(py: Python<'_>, code: &str) -> PyErr {
    invalid_input(
        py,
        "material",
        format!("unknown material code {code} (0 = water, 1 = sand)"),
    )
}

/// Material codes from an int, a numpy integer or an integer array; an
/// unknown code is reported as given (`2**64 - 1`, not its int64 wrap).
pub(crate) fn material_codes(value: &Bound<'_, PyAny>) -> PyResult<Codes> {
    let py = value.py();
    let expect = "expected an integer code or an integer array (0 = water, 1 = sand)";
    if value.is_instance_of::<PyBool>() {
        return Err(invalid_input(
            py,
            "material",
            format!("{expect}, got {}", repr(value)),
        ));
    }
    if value.is_instance_of::<PyInt>() {
        return match value.extract::<i64>().ok().and_then(Material::from_code) {
            Some(m) => Ok(Codes::All(m)),
            None => Err(unknown_code(py, &value.str()?.to_string())),
        };
    }
    let np = py.import("numpy")?;
    let arr = np.call_method1("asarray", (value,))?;
    let kind: String = arr.getattr("dtype")?.getattr("kind")?.extract()?;
    if kind != "i" && kind != "u" {
        return Err(invalid_input(
            py,
            "material",
            format!("{expect}, got dtype {}", arr.getattr("dtype")?.str()?),
        ));
    }
    let shape: Vec<usize> = arr.getattr("shape")?.extract()?;
    if shape.len() > 1 {
        return Err(invalid_input(
            py,
            "material",
            format!("expected shape [N], got {shape:?}"),
        ));
    }
    let size: usize = arr.getattr("size")?.extract()?;
    if size > 0 {
        // every code must fit an int64 before the conversion (uint64 would wrap)
        for ext in ["min", "max"] {
            let v = arr.call_method0(ext)?.call_method0("item")?;
            if v.extract::<i64>()
                .ok()
                .and_then(Material::from_code)
                .is_none()
            {
                return Err(unknown_code(py, &v.str()?.to_string()));
            }
        }
    }
    let as64 = arr
        .call_method1("astype", ("int64",))?
        .call_method0("ravel")?;
    let codes: Vec<i64> = as64.call_method0("tolist")?.extract()?;
    let mats = codes
        .iter()
        .map(|&c| Material::from_code(c).ok_or_else(|| unknown_code(py, &c.to_string())))
        .collect::<PyResult<Vec<Material>>>()?;
    if shape.is_empty() {
        return Ok(Codes::All(mats[0]));
    }
    Ok(Codes::Each(mats))
}
