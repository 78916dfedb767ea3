//! The thin pyo3 binding: module `hybridmpm._core`.
//!
//! Borrows numpy arrays in, moves results out, releases the GIL around work,
//! and maps each core error to a Python exception of `hybridmpm.errors`.

use pyo3::prelude::*;

mod args;
mod bodies;
mod errors;
mod fields;
mod graph;
mod grid_mass;
mod material;
mod ort_ops;
mod params;
mod particles;
mod pool;
mod pyde;
mod schema;
mod solver;
mod transfer;

#[pymodule]
fn _core(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add("__version__", env!("CARGO_PKG_VERSION"))?;
    solver::register(m)?;
    bodies::register(m)?;
    grid_mass::register(m)?;
    params::register(m)?;
    schema::register(m)?;
    graph::register(m)?;
    transfer::register(m)?;
    Ok(())
}
