//! `grid_mass`: the grid-mass field of the accuracy metric
//! (`hybridmpm_mpm::grid_mass`).

use hybridmpm_mpm as core;
use numpy::{PyArray1, PyArrayMethods, PyUntypedArrayMethods};
use pyo3::prelude::*;

use crate::args::{extract_budget, extract_count, f32_array};
use crate::errors::{invalid_input, to_py};

/// Normalised grid mass (docs/design.md "Grid-mass error"; paper Sec. 3.1.1):
/// p2g of particle mass with quadratic B-splines onto the nodes `i·dx`,
/// `i ∈ [0, n_grid)^D`, `dx = 1/n_grid`, divided by the total.
///
/// `positions`: float32 [N, D], D ∈ {2, 3}, in the unit domain;
/// `n_grid`: an integer in [3, 4096]; `masses`: float32 [N] or None (equal
/// masses, 1/N each); `memory_budget`: bytes or None (no budget): a grid of
/// more than that (12 bytes per node: an f64 accumulator and the f32
/// result) is refused before anything is allocated, naming `n_grid`.
/// Returns float32 [n_grid]*D summing to 1. Stencil nodes outside the grid
/// are clamped to the edge. Raises `InvalidInputError` naming the field.
#[pyfunction]
#[pyo3(signature = (positions, n_grid, masses=None, *, memory_budget=None))]
pub fn grid_mass(
    py: Python<'_>,
    positions: &Bound<'_, PyAny>,
    n_grid: &Bound<'_, PyAny>,
    masses: Option<&Bound<'_, PyAny>>,
    memory_budget: Option<&Bound<'_, PyAny>>,
) -> PyResult<Py<PyAny>> {
    let n_grid = extract_count(n_grid, "n_grid", "an integer in [3, 4096]")?;
    let budget = extract_budget(memory_budget)?;
    let x = f32_array(positions, "positions", &[None, None])?;
    let (n, d) = (x.shape()[0], x.shape()[1]);
    if d != 2 && d != 3 {
        return Err(invalid_input(
            py,
            "positions",
            format!("expected shape [N, 2] or [N, 3], got [N, {d}]"),
        ));
    }
    // refuse the grid before copying anything
    if !(3..=4096).contains(&n_grid) {
        return Err(invalid_input(
            py,
            "n_grid",
            format!("must be in [3, 4096], got {n_grid}"),
        ));
    }
    core::error::check_budget(
        "n_grid",
        &format!("a {d}D grid-mass grid of {n_grid}^{d} nodes"),
        core::grid_mass_bytes(n_grid, d),
        budget,
    )
    .map_err(|e| to_py(py, e))?;
    let m = masses
        .map(|m| f32_array(m, "masses", &[Some(n)]))
        .transpose()?;
    let mv: Option<Vec<f32>> = m.map(|m| m.as_array().iter().copied().collect());
    let flat: Vec<f32> = x.as_array().iter().copied().collect();
    let res = if d == 2 {
        let pts: Vec<[f32; 2]> = flat.chunks_exact(2).map(|c| [c[0], c[1]]).collect();
        py.detach(|| core::grid_mass_with_budget::<2>(&pts, mv.as_deref(), n_grid, budget))
    } else {
        let pts: Vec<[f32; 3]> = flat.chunks_exact(3).map(|c| [c[0], c[1], c[2]]).collect();
        py.detach(|| core::grid_mass_with_budget::<3>(&pts, mv.as_deref(), n_grid, budget))
    };
    let g = res.map_err(|e| to_py(py, e))?;
    let arr = PyArray1::from_vec(py, g);
    Ok(arr.reshape(vec![n_grid; d])?.into_any().unbind())
}

pub fn register(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add_function(wrap_pyfunction!(grid_mass, m)?)?;
    Ok(())
}
