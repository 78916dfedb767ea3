//! The solver's parameters in and out of Python, by the core's own types.
//!
//! `read_params` reads the dict `MpmSolver` takes into `SolverParams`,
//! `ColliderParams` and `BodyParams` through [`crate::pyde`] (the core's
//! serde derives: its keys, defaults and refusals); `default_params` and
//! `default_collider` hand the core's defaults to Python, which builds its
//! dataclass defaults from them.

use hybridmpm_mpm::{BodyParams, ColliderParams, SolverParams};
use pyo3::prelude::*;
use pyo3::types::{PyDict, PyList};

use crate::errors::invalid_input;
use crate::pyde::read;

/// The solver parameters (`SolverParams<D>`), colliders and bodies of the
/// dict `MpmSolver` takes; its `dim` key is the caller's to read. Raises
/// `InvalidInputError` naming the field (`water.density`, `colliders[0].center`,
/// `bodies[1].density`).
pub fn read_params<const D: usize>(
    d: &Bound<'_, PyDict>,
) -> PyResult<(SolverParams<D>, Vec<ColliderParams>, Vec<BodyParams>)> {
    let py = d.py();
    let rest = d.copy()?;
    let colliders = rest.get_item("colliders")?;
    let bodies = rest.get_item("bodies")?;
    for key in ["dim", "colliders", "bodies"] {
        if rest.contains(key)? {
            rest.del_item(key)?;
        }
    }
    let params = read::<SolverParams<D>>(rest.as_any(), "").map_err(|e| {
        e.with_root_keys(&["dim"], &["colliders", "bodies"])
            .into_py(py)
    })?;
    let colliders = match colliders {
        Some(c) if !c.is_none() => read(&c, "colliders").map_err(|e| e.into_py(py))?,
        _ => Vec::new(),
    };
    let bodies = match bodies {
        Some(b) if !b.is_none() => read(&b, "bodies").map_err(|e| e.into_py(py))?,
        _ => Vec::new(),
    };
    Ok((params, colliders, bodies))
}

/// The Python value of `x` as serialised by serde (f32 written shortest, so
/// `0.4f32` reads as the float `0.4`).
fn to_py<'py, T: serde::Serialize>(py: Python<'py>, x: &T) -> PyResult<Bound<'py, PyAny>> {
    let json = serde_json::to_string(x)
        .map_err(|e| pyo3::exceptions::PyRuntimeError::new_err(e.to_string()))?;
    py.import("json")?.call_method1("loads", (json,))
}

/// The solver's default parameters in `dim` (2 or 3) dimensions, as the
/// dict `MpmSolver` takes (what `hybridmpm.mpm.MpmParams(dim=dim).to_dict()`
/// gives): `dim`, `n_grid`, `gravity` [m/s²], `cfl`, `substeps`,
/// `max_substeps`, `num_threads`, `water`, `sand`, `walls` (no face
/// overrides) and `colliders` (empty). Raises `InvalidInputError` (field
/// `dim`) for another `dim`.
#[pyfunction]
fn default_params(py: Python<'_>, dim: usize) -> PyResult<Bound<'_, PyDict>> {
    let params = match dim {
        2 => to_py(py, &SolverParams::<2>::default())?,
        3 => to_py(py, &SolverParams::<3>::default())?,
        _ => {
            return Err(invalid_input(
                py,
                "dim",
                format!("must be 2 or 3, got {dim}"),
            ));
        }
    };
    let out = PyDict::new(py);
    out.set_item("dim", dim)?;
    for (k, v) in params.cast_into::<PyDict>()?.iter() {
        out.set_item(k, v)?;
    }
    out.set_item("colliders", PyList::empty(py))?;
    Ok(out)
}

/// The defaults of a collider's optional keys: `{"condition": "separate",
/// "friction": 0.0}` (a collider's `shape`, `center` and the shape's size
/// have none).
#[pyfunction]
fn default_collider(py: Python<'_>) -> PyResult<Bound<'_, PyAny>> {
    to_py(py, &ColliderParams::default())
}

pub fn register(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add_function(wrap_pyfunction!(default_params, m)?)?;
    m.add_function(wrap_pyfunction!(default_collider, m)?)?;
    // how deep [cells] a particle, and a solid's particle, may end a substep
    // inside an obstacle that projects particles before it is put back
    m.add(
        "PROJECT_DEPTH_CELLS",
        hybridmpm_mpm::collider::PROJECT_DEPTH_CELLS,
    )?;
    m.add(
        "SOLID_PROJECT_DEPTH_CELLS",
        hybridmpm_mpm::collider::SOLID_PROJECT_DEPTH_CELLS,
    )?;
    // the names `integrator` takes, the default first
    let names: Vec<&str> = hybridmpm_mpm::Integrator::ALL
        .iter()
        .map(|i| i.name())
        .collect();
    m.add("INTEGRATORS", pyo3::types::PyTuple::new(m.py(), names)?)?;
    Ok(())
}
