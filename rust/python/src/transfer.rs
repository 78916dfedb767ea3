//! `grid_p2g`, `grid_g2p`, `grid_advect`: the particle–grid transfers of the
//! learned grid model (`hybridmpm_mpm::transfer`); `surface_p2g`: the exact
//! float64 p2g of the fluid surfaces (`hybridmpm.render.surface`).

use hybridmpm_mpm::{self as core, Pressure, TransferGrid};
use numpy::{
    PyArray1, PyArray2, PyArrayMethods, PyReadonlyArray1, PyReadonlyArrayDyn, PyUntypedArrayMethods,
};
use pyo3::prelude::*;

use crate::args::f32_array;
use crate::errors::{invalid_input, to_py};

fn grid<const D: usize>(
    py: Python<'_>,
    origin: &[f32],
    spacing: &[f32],
    nodes: usize,
) -> PyResult<TransferGrid<D>> {
    if origin.len() != D || spacing.len() != D {
        return Err(invalid_input(
            py,
            "origin",
            format!(
                "origin and spacing must have {D} values, got {} and {}",
                origin.len(),
                spacing.len()
            ),
        ));
    }
    let g = TransferGrid {
        origin: origin.try_into().expect("length checked"),
        spacing: spacing.try_into().expect("length checked"),
        nodes,
    };
    g.validate().map_err(|e| to_py(py, e))?;
    Ok(g)
}

fn rows<const D: usize>(a: &PyReadonlyArrayDyn<'_, f32>) -> Vec<[f32; D]> {
    a.as_array()
        .iter()
        .copied()
        .collect::<Vec<f32>>()
        .as_chunks::<D>()
        .0
        .to_vec()
}

fn flat(a: &PyReadonlyArrayDyn<'_, f32>) -> Vec<f32> {
    a.as_array().iter().copied().collect()
}

fn out2<'py>(
    py: Python<'py>,
    v: Vec<f32>,
    rows: usize,
    cols: usize,
) -> PyResult<Bound<'py, PyAny>> {
    Ok(PyArray1::from_vec(py, v).reshape([rows, cols])?.into_any())
}

/// p2g of `values` float32 [N, C] at `positions` float32 [N, D] onto the
/// grid `(origin [D], spacing [D], nodes)`: float32 [nodes^D, C].
#[pyfunction]
#[pyo3(signature = (positions, values, origin, spacing, nodes))]
pub fn grid_p2g<'py>(
    py: Python<'py>,
    positions: &Bound<'py, PyAny>,
    values: &Bound<'py, PyAny>,
    origin: Vec<f32>,
    spacing: Vec<f32>,
    nodes: usize,
) -> PyResult<Bound<'py, PyAny>> {
    let x = f32_array(positions, "positions", &[None, None])?;
    let (n, d) = (x.shape()[0], x.shape()[1]);
    let v = f32_array(values, "values", &[Some(n), None])?;
    let c = v.shape()[1];
    let vals = flat(&v);
    let (out, len) = match d {
        2 => {
            let g = grid::<2>(py, &origin, &spacing, nodes)?;
            let p = rows::<2>(&x);
            (py.detach(|| core::p2g(&g, &p, &vals, c)), g.len())
        }
        3 => {
            let g = grid::<3>(py, &origin, &spacing, nodes)?;
            let p = rows::<3>(&x);
            (py.detach(|| core::p2g(&g, &p, &vals, c)), g.len())
        }
        _ => {
            return Err(invalid_input(
                py,
                "positions",
                format!("expected shape [N, 2] or [N, 3], got [N, {d}]"),
            ));
        }
    };
    out2(py, out.map_err(|e| to_py(py, e))?, len, c)
}

/// g2p of `field` float32 [nodes^D, C] at `positions` float32 [N, D]: float32 [N, C].
#[pyfunction]
#[pyo3(signature = (field, positions, origin, spacing, nodes))]
pub fn grid_g2p<'py>(
    py: Python<'py>,
    field: &Bound<'py, PyAny>,
    positions: &Bound<'py, PyAny>,
    origin: Vec<f32>,
    spacing: Vec<f32>,
    nodes: usize,
) -> PyResult<Bound<'py, PyAny>> {
    let x = f32_array(positions, "positions", &[None, None])?;
    let (n, d) = (x.shape()[0], x.shape()[1]);
    let f = f32_array(field, "field", &[None, None])?;
    let c = f.shape()[1];
    let vals = flat(&f);
    let out = match d {
        2 => {
            let g = grid::<2>(py, &origin, &spacing, nodes)?;
            let p = rows::<2>(&x);
            py.detach(|| core::g2p(&g, &vals, c, &p))
        }
        3 => {
            let g = grid::<3>(py, &origin, &spacing, nodes)?;
            let p = rows::<3>(&x);
            py.detach(|| core::g2p(&g, &vals, c, &p))
        }
        _ => {
            return Err(invalid_input(
                py,
                "positions",
                format!("expected shape [N, 2] or [N, 3], got [N, {d}]"),
            ));
        }
    };
    out2(py, out.map_err(|e| to_py(py, e))?, n, c)
}

#[allow(clippy::too_many_arguments)]
fn advect_d<const D: usize>(
    py: Python<'_>,
    x: &PyReadonlyArrayDyn<'_, f32>,
    moving: Vec<bool>,
    velocity: &PyReadonlyArrayDyn<'_, f32>,
    extra: &PyReadonlyArrayDyn<'_, f32>,
    drift: &PyReadonlyArrayDyn<'_, f32>,
    dt: f32,
    bounds: (&[f32], &[f32]),
    g: TransferGrid<D>,
    pressure: Option<Pressure>,
) -> PyResult<Vec<f32>> {
    if bounds.0.len() != D || bounds.1.len() != D {
        return Err(invalid_input(
            py,
            "bounds",
            format!("lo and hi must have {D} values"),
        ));
    }
    let (lo, hi): ([f32; D], [f32; D]) = (
        bounds.0.try_into().expect("checked"),
        bounds.1.try_into().expect("checked"),
    );
    let (p, e, dr, v) = (
        rows::<D>(x),
        rows::<D>(extra),
        rows::<D>(drift),
        flat(velocity),
    );
    py.detach(|| core::advect(&g, &p, &moving, &v, &e, &dr, dt, lo, hi, pressure))
        .map_err(|e| to_py(py, e))
}

/// Frame-by-frame advection (`hybridmpm_mpm::transfer::advect`): positions
/// float32 [N, D], `moving` numpy bool [N], `velocity` float32 [K, nodes^D, D],
/// `extra` float32 [N, D], `drift` float32 [K, D] → float32 [K, N, D];
/// `pressure` `(strength, rest_count)` adds a density correction per frame.
#[pyfunction]
#[pyo3(signature = (positions, moving, velocity, extra, drift, dt, lo, hi, origin, spacing, nodes, pressure=None))]
#[allow(clippy::too_many_arguments)]
pub fn grid_advect<'py>(
    py: Python<'py>,
    positions: &Bound<'py, PyAny>,
    moving: PyReadonlyArray1<'py, bool>,
    velocity: &Bound<'py, PyAny>,
    extra: &Bound<'py, PyAny>,
    drift: &Bound<'py, PyAny>,
    dt: f32,
    lo: Vec<f32>,
    hi: Vec<f32>,
    origin: Vec<f32>,
    spacing: Vec<f32>,
    nodes: usize,
    pressure: Option<(f32, f32)>,
) -> PyResult<Bound<'py, PyAny>> {
    let pressure = pressure.map(|(strength, rest_count)| Pressure {
        strength,
        rest_count,
    });
    let x = f32_array(positions, "positions", &[None, None])?;
    let (n, d) = (x.shape()[0], x.shape()[1]);
    let v = f32_array(velocity, "velocity", &[None, None, Some(d)])?;
    let k = v.shape()[0];
    let e = f32_array(extra, "extra", &[Some(n), Some(d)])?;
    let dr = f32_array(drift, "drift", &[Some(k), Some(d)])?;
    let moving: Vec<bool> = moving.as_array().iter().copied().collect();
    let out = match d {
        2 => advect_d::<2>(
            py,
            &x,
            moving,
            &v,
            &e,
            &dr,
            dt,
            (&lo, &hi),
            grid::<2>(py, &origin, &spacing, nodes)?,
            pressure,
        )?,
        3 => advect_d::<3>(
            py,
            &x,
            moving,
            &v,
            &e,
            &dr,
            dt,
            (&lo, &hi),
            grid::<3>(py, &origin, &spacing, nodes)?,
            pressure,
        )?,
        _ => {
            return Err(invalid_input(
                py,
                "positions",
                format!("expected shape [N, 2] or [N, 3], got [N, {d}]"),
            ));
        }
    };
    Ok(PyArray1::from_vec(py, out).reshape([k, n, d])?.into_any())
}

/// `surface_p2g`: `values` float64 [N] spread from `positions` float64 [N, D]
/// [m] onto the nodes `(origin + i)·spacing`, `i ∈ [0, shape)`, with the
/// quadratic B-spline weights of MLS-MPM rounded per axis to multiples of
/// `1/weight_scale`: float64 `shape`, row-major (first axis slowest)
/// (`hybridmpm_mpm::surface::surface_p2g`).
///
/// The weights are the engine's (`kernel.rs`), which have the bits of
/// numpy's `w = 0.5·(1.5 − f)², 0.75 − (f − 1)², 0.5·(f − 0.5)²`, rounded as
/// `rint(w·weight_scale)·(1/weight_scale)`, `f = x/spacing − ⌊x/spacing −
/// 1/2⌋`, and summed in float64, one particle after the other: where every
/// product and partial sum is exact (`values` quantised, see the surface
/// module), the field has the same bits for any particle order. Serial, so
/// the same bits for any thread count. Errors name `positions` (shape,
/// non-finite, a stencil outside the grid), `values`, `spacing`, `origin`,
/// `shape` or `weight_scale`.
#[pyfunction]
#[pyo3(signature = (positions, values, spacing, origin, shape, weight_scale))]
pub fn surface_p2g<'py>(
    py: Python<'py>,
    positions: &Bound<'py, PyAny>,
    values: &Bound<'py, PyAny>,
    spacing: f64,
    origin: Vec<i64>,
    shape: Vec<usize>,
    weight_scale: f64,
) -> PyResult<Bound<'py, PyAny>> {
    let x = positions
        .cast::<PyArray2<f64>>()
        .map_err(|_| invalid_input(py, "positions", "expected a float64 numpy array [N, D]"))?
        .try_readonly()
        .map_err(|e| invalid_input(py, "positions", format!("cannot be read: {e}")))?;
    let v = values
        .cast::<PyArray1<f64>>()
        .map_err(|_| invalid_input(py, "values", "expected a float64 numpy array [N]"))?
        .try_readonly()
        .map_err(|e| invalid_input(py, "values", format!("cannot be read: {e}")))?;
    let (n, d) = (x.shape()[0], x.shape()[1]);
    // copied (while the GIL is held, so no Python thread changes them mid-read), then the GIL is released
    let (xs, vals) = (x.as_array(), v.as_array());
    let xs: Vec<f64> = match xs.as_slice() {
        Some(s) => s.to_vec(),
        None => xs.iter().copied().collect(),
    };
    let vals: Vec<f64> = match vals.as_slice() {
        Some(s) => s.to_vec(),
        None => vals.iter().copied().collect(),
    };
    let out = py
        .detach(|| core::surface_p2g(&xs, [n, d], &vals, spacing, &origin, &shape, weight_scale))
        .map_err(|e| to_py(py, e))?;
    Ok(PyArray1::from_vec(py, out).reshape(shape)?.into_any())
}

pub fn register(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add_function(wrap_pyfunction!(surface_p2g, m)?)?;
    m.add_function(wrap_pyfunction!(grid_p2g, m)?)?;
    m.add_function(wrap_pyfunction!(grid_g2p, m)?)?;
    m.add_function(wrap_pyfunction!(grid_advect, m)?)?;
    Ok(())
}
