//! The arguments the binding reads from Python: counts, memory budgets and
//! float32 arrays, checked (type, dtype, shape, finite) with errors that
//! name the argument.

use numpy::{PyArrayDyn, PyArrayMethods, PyReadonlyArrayDyn, PyUntypedArrayMethods};
use pyo3::prelude::*;
use pyo3::types::PyBool;

use crate::errors::{invalid_input, repr};

/// A non-negative integer (Python `int` or numpy integer; not a bool, a
/// float or a string), else `InvalidInputError` naming `field`.
pub fn extract_count(v: &Bound<'_, PyAny>, field: &str, what: &str) -> PyResult<usize> {
    let bad = || invalid_input(v.py(), field, format!("expected {what}, got {}", repr(v)));
    if v.is_instance_of::<PyBool>() {
        return Err(bad());
    }
    v.extract::<usize>().map_err(|_| bad())
}

/// An optional memory budget in bytes (`None`: unlimited), an integer >= 1.
pub fn extract_budget(v: Option<&Bound<'_, PyAny>>) -> PyResult<Option<u64>> {
    match v {
        None => Ok(None),
        Some(v) if v.is_none() => Ok(None),
        Some(v) => {
            let b = extract_count(
                v,
                "memory_budget",
                "an integer number of bytes >= 1 or None",
            )?;
            if b == 0 {
                return Err(invalid_input(
                    v.py(),
                    "memory_budget",
                    "must be >= 1 byte, got 0",
                ));
            }
            Ok(Some(b as u64))
        }
    }
}

/// Borrow a float32 array, checking dtype and shape; `shape` uses `None` for "any".
pub fn f32_array<'py>(
    obj: &Bound<'py, PyAny>,
    field: &str,
    shape: &[Option<usize>],
) -> PyResult<PyReadonlyArrayDyn<'py, f32>> {
    let py = obj.py();
    let arr = match obj.cast::<PyArrayDyn<f32>>() {
        Ok(a) => a
            .try_readonly()
            .map_err(|e| invalid_input(py, field, format!("cannot be read: {e}")))?,
        Err(_) => {
            let dtype = obj
                .getattr("dtype")
                .map(|d| d.to_string())
                .unwrap_or_else(|_| obj.get_type().to_string());
            return Err(invalid_input(
                py,
                field,
                format!("expected a float32 numpy array, got {dtype}"),
            ));
        }
    };
    let got = arr.shape().to_vec();
    let ok = got.len() == shape.len()
        && got
            .iter()
            .zip(shape)
            .all(|(g, s)| s.is_none_or(|s| s == *g));
    if !ok {
        let want: Vec<String> = shape
            .iter()
            .map(|s| s.map_or("*".to_string(), |v| v.to_string()))
            .collect();
        return Err(invalid_input(
            py,
            field,
            format!("expected shape [{}], got {:?}", want.join(", "), got),
        ));
    }
    if arr.as_array().iter().any(|x| !x.is_finite()) {
        return Err(invalid_input(py, field, "contains NaN or inf"));
    }
    Ok(arr)
}

/// Copy of a validated float32 array (dtype, shape, finite) as a flat Vec.
pub fn f32_vec(obj: &Bound<'_, PyAny>, field: &str, shape: &[Option<usize>]) -> PyResult<Vec<f32>> {
    let arr = f32_array(obj, field, shape)?;
    Ok(match arr.as_slice() {
        Ok(flat) => flat.to_vec(),
        Err(_) => arr.as_array().iter().copied().collect(),
    })
}
