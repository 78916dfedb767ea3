//! Mapping of core errors to the Python exception classes of `hybridmpm.errors`.
//!
//! The classes live in Python (so that `InvalidInputError` can subclass both
//! `HybridMpmError` and `ValueError`); they are looked up on first use.
//! [`to_py`] maps each error of the core (`MpmError`) to its class; [`repr`]
//! shows a bad value in their messages. Every other module of the binding
//! may use this one; it uses none of them.

use hybridmpm_mpm::MpmError;
use pyo3::exceptions::{PyRuntimeError, PyValueError};
use pyo3::prelude::*;

fn make(py: Python<'_>, class: &str, msg: String, extra: Option<Py<PyAny>>) -> PyErr {
    let built = (|| -> PyResult<PyErr> {
        let module = py.import("hybridmpm.errors")?;
        let cls = module.getattr(class)?;
        let obj = match extra {
            Some(x) => cls.call1((msg.clone(), x))?,
            None => cls.call1((msg.clone(),))?,
        };
        Ok(PyErr::from_value(obj))
    })();
    match built {
        Ok(e) => e,
        // The Python package is not importable (e.g. the bare extension is
        // used): fall back to builtin classes with the same message.
        Err(_) => {
            if class == "SimulationError" {
                PyRuntimeError::new_err(msg)
            } else {
                PyValueError::new_err(msg)
            }
        }
    }
}

/// `InvalidInputError(msg, field)`: bad argument named `field`.
pub fn invalid_input(py: Python<'_>, field: &str, msg: impl Into<String>) -> PyErr {
    let field_obj = field.into_pyobject(py).map(|o| o.into_any().unbind()).ok();
    make(
        py,
        "InvalidInputError",
        format!("{field}: {}", msg.into()),
        field_obj,
    )
}

/// `SimulationError(msg, substep)`.
pub fn simulation_error(py: Python<'_>, substep: Option<usize>, msg: impl Into<String>) -> PyErr {
    let extra = substep.and_then(|s| s.into_pyobject(py).ok().map(|o| o.into_any().unbind()));
    make(py, "SimulationError", msg.into(), extra)
}

/// `CheckpointError(msg)`.
pub fn checkpoint_error(py: Python<'_>, msg: impl Into<String>) -> PyErr {
    make(py, "CheckpointError", msg.into(), None)
}

/// `repr(obj)` for an error message (`"?"` if it fails).
pub fn repr(obj: &Bound<'_, PyAny>) -> String {
    obj.repr()
        .map(|r| r.to_string())
        .unwrap_or_else(|_| "?".into())
}

/// How to change the memory budget, appended to budget errors.
pub const BUDGET_HINT: &str =
    "set HYBRIDMPM_MEMORY_BUDGET or call hybridmpm.limits.set_memory_budget to change it";

/// Map a core error to its Python exception.
pub fn to_py(py: Python<'_>, e: MpmError) -> PyErr {
    match e {
        MpmError::InvalidInput { field, msg } => invalid_input(py, &field, msg),
        MpmError::OverBudget { ref field, .. } => {
            let full = e.to_string();
            let msg = full.strip_prefix(&format!("{field}: ")).unwrap_or(&full);
            invalid_input(py, field, format!("{msg} ({BUDGET_HINT})"))
        }
        MpmError::NonFinite { substep, .. }
        | MpmError::Inverted { substep, .. }
        | MpmError::CflViolation { substep, .. } => {
            simulation_error(py, Some(substep), e.to_string())
        }
        MpmError::TooManySubsteps { .. } => simulation_error(py, None, e.to_string()),
        MpmError::Checkpoint(m) => checkpoint_error(py, m),
    }
}
