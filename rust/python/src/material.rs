//! Material codes from Python (`0` water, `1` sand, `2` elastic, `3` snow,
//! `4` viscoplastic, ...: `Material::from_code`) and parameter-set indices: one
//! for every particle or one per particle.

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

/// The codes, as error messages list them (`0 = water, 1 = sand, ...`, from `Material::ALL`).
fn codes() -> String {
    let each: Vec<String> = Material::ALL
        .iter()
        .map(|m| format!("{} = {}", *m as u8, m.name()))
        .collect();
    each.join(", ")
}

fn unknown_code(py: Python<'_>, code: &str) -> PyErr {
    invalid_input(
        py,
        "material",
        format!("unknown material code {code} ({})", codes()),
    )
}

/// Material codes from an int, a numpy integer or an integer array; an
/// unknown code is reported as given (`2**64 - 1`, not its int64 wrap).
pub(crate) fn material_codes(value: &Bound<'_, PyAny>) -> PyResult<Codes> {
    let py = value.py();
    let expect = format!("expected an integer code or an integer array ({})", codes());
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

/// Parameter-set indices (`Particle::set`, in [0, 65535]): one for every
/// particle or one per particle, from an int or an integer array [N]
/// (argument `field`).
pub(crate) fn set_indices(value: &Bound<'_, PyAny>, field: &str) -> PyResult<Vec<u16>> {
    let py = value.py();
    let expect = "expected an integer parameter-set index or an integer array [N]";
    if value.is_instance_of::<PyBool>() {
        return Err(invalid_input(
            py,
            field,
            format!("{expect}, got {}", repr(value)),
        ));
    }
    let np = py.import("numpy")?;
    let arr = np.call_method1("asarray", (value,))?;
    let kind: String = arr.getattr("dtype")?.getattr("kind")?.extract()?;
    let shape: Vec<usize> = arr.getattr("shape")?.extract()?;
    if (kind != "i" && kind != "u") || shape.len() > 1 {
        return Err(invalid_input(
            py,
            field,
            format!(
                "{expect}, got dtype {} shape {shape:?}",
                arr.getattr("dtype")?.str()?
            ),
        ));
    }
    let size: usize = arr.getattr("size")?.extract()?;
    if size > 0 {
        for ext in ["min", "max"] {
            let v = arr.call_method0(ext)?.call_method0("item")?;
            if v.extract::<i64>()
                .ok()
                .and_then(|c| u16::try_from(c).ok())
                .is_none()
            {
                return Err(invalid_input(
                    py,
                    field,
                    format!(
                        "a parameter-set index must be in [0, 65535], got {}",
                        v.str()?
                    ),
                ));
            }
        }
    }
    let flat: Vec<i64> = arr
        .call_method1("astype", ("int64",))?
        .call_method0("ravel")?
        .call_method0("tolist")?
        .extract()?;
    Ok(flat.into_iter().map(|c| c as u16).collect())
}

/// `sets` (one, or one per particle) for `n` particles (field `field`).
pub(crate) fn expand_sets(sets: &[u16], n: usize, scalar: bool) -> core::Result<Vec<u16>> {
    if scalar {
        return Ok(vec![sets[0]; n]);
    }
    if sets.len() != n {
        return Err(MpmError::invalid(
            "material_set",
            format!("expected shape [{n}], got [{}]", sets.len()),
        ));
    }
    Ok(sets.to_vec())
}
