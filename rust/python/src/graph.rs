//! `hybridmpm._core.radius_graph`: binding of the `hybridmpm-neighbors` crate.

use hybridmpm_neighbors::{self as nb, GraphError, GraphParams, Neighbors};
use numpy::prelude::*;
use numpy::{PyArray1, PyArray2, PyUntypedArray};
use pyo3::exceptions::PyRuntimeError;
use pyo3::prelude::*;
use pyo3::sync::PyOnceLock;

use crate::errors::invalid_input;

type Edges<'py> = (
    Bound<'py, PyArray1<i64>>,
    Bound<'py, PyArray1<i64>>,
    Bound<'py, PyArray2<f32>>,
    Bound<'py, PyArray1<f32>>,
);

/// [`nb::CONNECTIVITY_RADIUS`] as a Python float: its shortest decimal, as
/// serde writes the solver's `f32` defaults, so that Python reads the
/// decimal value, not the `f32` widened (the `f32` of either is the same).
fn connectivity_radius() -> f64 {
    let r = nb::CONNECTIVITY_RADIUS;
    r.to_string().parse().unwrap_or(f64::from(r))
}

/// Copies rows of a float32 [N, D] array (any strides) into `[f32; D]`.
fn rows<const D: usize>(arr: &Bound<'_, PyArray2<f32>>) -> PyResult<Vec<[f32; D]>> {
    let ro = arr
        .try_readonly()
        .map_err(|e| invalid_input(arr.py(), "positions", format!("cannot be read: {e}")))?;
    // `as_slice` also accepts Fortran order: take the fast path only for C order.
    if arr.is_c_contiguous()
        && let Ok(flat) = ro.as_slice()
    {
        return Ok(flat.as_chunks::<D>().0.to_vec());
    }
    let view = ro.as_array();
    Ok(view
        .rows()
        .into_iter()
        .map(|row| {
            let mut p = [0.0f32; D];
            for (dst, src) in p.iter_mut().zip(row.iter()) {
                *dst = *src;
            }
            p
        })
        .collect())
}

/// `numpy.empty(shape, dtype)`: numpy's allocator advises the kernel to back
/// large arrays with huge pages, which makes writing the edge arrays (tens of
/// MB) markedly cheaper than first-touching fresh 4 KiB pages.
fn empty<'py>(
    py: Python<'py>,
    shape: impl IntoPyObject<'py>,
    dtype: &str,
) -> PyResult<Bound<'py, PyAny>> {
    static EMPTY: PyOnceLock<Py<PyAny>> = PyOnceLock::new();
    EMPTY.import(py, "numpy", "empty")?.call1((shape, dtype))
}

/// ``positions`` as a float32 [N, D] array, D in {2, 3}, and D; else an
/// ``InvalidInputError`` naming ``positions``.
fn positions_array<'py>(
    py: Python<'py>,
    positions: &Bound<'py, PyAny>,
) -> PyResult<(Bound<'py, PyArray2<f32>>, usize)> {
    let expect = "must be a numpy.ndarray of dtype float32 and shape (N, 2) or (N, 3)";
    let Ok(untyped) = positions.cast::<PyUntypedArray>() else {
        let ty = positions.get_type().name()?;
        return Err(invalid_input(
            py,
            "positions",
            format!("{expect}, got {ty}"),
        ));
    };
    let dtype = untyped.dtype();
    if !dtype.is_equiv_to(&numpy::dtype::<f32>(py)) {
        return Err(invalid_input(
            py,
            "positions",
            format!("{expect}, got dtype {dtype}"),
        ));
    }
    let shape = untyped.shape();
    if shape.len() != 2 || !(shape[1] == 2 || shape[1] == 3) {
        let dims: Vec<String> = shape.iter().map(|d| d.to_string()).collect();
        let tuple = if dims.len() == 1 {
            format!("({},)", dims[0])
        } else {
            format!("({})", dims.join(", "))
        };
        return Err(invalid_input(
            py,
            "positions",
            format!("{expect}, got shape {tuple}"),
        ));
    }
    Ok((positions.cast::<PyArray2<f32>>()?.clone(), shape[1]))
}

/// ``radius`` as a positive finite float32, else an ``InvalidInputError`` naming ``radius``.
fn radius_f32(py: Python<'_>, radius: f64) -> PyResult<f32> {
    if !(radius.is_finite() && radius > 0.0) {
        return Err(invalid_input(
            py,
            "radius",
            format!("must be finite and > 0, got {radius}"),
        ));
    }
    let r32 = radius as f32;
    if !(r32.is_finite() && r32 > 0.0) {
        return Err(invalid_input(
            py,
            "radius",
            format!("{radius} is not representable as a positive finite float32"),
        ));
    }
    Ok(r32)
}

/// ``movable`` as a bool vector, else an ``InvalidInputError`` naming it
/// (its length is checked against the positions by the crate).
fn movable_vec(py: Python<'_>, movable: &Bound<'_, PyAny>) -> PyResult<Vec<bool>> {
    let Ok(mv) = movable.cast::<PyArray1<bool>>() else {
        return Err(invalid_input(
            py,
            "movable",
            "must be a numpy.ndarray of dtype bool and shape (N,)",
        ));
    };
    Ok(mv
        .try_readonly()
        .map_err(|e| invalid_input(py, "movable", format!("cannot be read: {e}")))?
        .as_array()
        .to_vec())
}

/// The relaxation's settings (checked again, field by field, by the crate).
fn relax_params(
    py: Python<'_>,
    radius: f64,
    rest_density: f64,
    iterations: i64,
    omega: f64,
) -> PyResult<nb::RelaxParams> {
    let r = radius_f32(py, radius)?;
    let Ok(iterations) = usize::try_from(iterations) else {
        return Err(invalid_input(
            py,
            "iterations",
            format!("must be >= 0, got {iterations}"),
        ));
    };
    Ok(nb::RelaxParams {
        radius: r,
        rest_density: rest_density as f32,
        iterations,
        omega: omega as f32,
    })
}

/// The radius graph's settings, else an ``InvalidInputError`` naming the field.
fn graph_params(
    py: Python<'_>,
    radius: f64,
    self_edges: bool,
    max_neighbors: Option<i64>,
    max_edges: Option<&Bound<'_, PyAny>>,
) -> PyResult<GraphParams> {
    let r32 = radius_f32(py, radius)?;
    let max_neighbors = match max_neighbors {
        None => None,
        Some(k) if k >= 1 => Some(usize::try_from(k).unwrap_or(usize::MAX)),
        Some(k) => {
            return Err(invalid_input(
                py,
                "max_neighbors",
                format!("must be >= 1 or None, got {k}"),
            ));
        }
    };
    let max_edges = match max_edges {
        Some(m) if !m.is_none() => Some(crate::args::extract_count(
            m,
            "max_edges",
            "an integer >= 0 or None",
        )?),
        _ => None,
    };
    Ok(GraphParams {
        radius: r32,
        self_edges,
        max_neighbors,
        max_edges,
    })
}

fn to_py(py: Python<'_>) -> impl Fn(GraphError) -> PyErr + '_ {
    move |e: GraphError| match e {
        GraphError::InvalidInput { field, msg } => invalid_input(py, field, msg),
    }
}

/// Kernel density of every particle (``hybridmpm.graph.kernel_density``).
///
/// ``rho_i = sum_j W(|x_i - x_j| / R)`` with ``W(q) = (1 - q)^2`` for
/// ``q < 1``, self included (an isolated particle has 1).
///
/// Parameters: ``positions`` numpy float32 (N, D), D in {2, 3}; ``radius``
/// R > 0 (position units). Returns float32 (N,). Raises
/// ``InvalidInputError`` naming ``positions`` or ``radius``.
#[pyfunction]
fn kernel_density<'py>(
    py: Python<'py>,
    positions: &Bound<'py, PyAny>,
    radius: f64,
) -> PyResult<Bound<'py, PyArray1<f32>>> {
    let (arr, dim) = positions_array(py, positions)?;
    let r = radius_f32(py, radius)?;
    let rho = if dim == 2 {
        let pos = rows::<2>(&arr)?;
        py.detach(|| crate::pool::install_for(pos.len(), || nb::kernel_density(&pos, r)))
    } else {
        let pos = rows::<3>(&arr)?;
        py.detach(|| crate::pool::install_for(pos.len(), || nb::kernel_density(&pos, r)))
    }
    .map_err(to_py(py))?;
    Ok(PyArray1::from_vec(py, rho))
}

fn relax_run<const D: usize>(
    py: Python<'_>,
    arr: &Bound<'_, PyArray2<f32>>,
    movable: &[bool],
    params: &nb::RelaxParams,
) -> PyResult<(Vec<f32>, nb::RelaxStats)> {
    let mut pos = rows::<D>(arr)?;
    let stats = py
        .detach(|| {
            crate::pool::install_for(pos.len(), || nb::relax_density(&mut pos, movable, params))
        })
        .map_err(to_py(py))?;
    Ok((pos.into_iter().flatten().collect(), stats))
}

/// Density relaxation (``hybridmpm.graph.relax_density``): unilateral
/// Position Based Fluids density constraint, Jacobi iterations; see the
/// ``hybridmpm-neighbors`` crate's ``relax`` module for the formulas.
///
/// Parameters: ``positions`` numpy float32 (N, D), D in {2, 3};
/// ``movable`` numpy bool (N,); ``radius`` R > 0; ``rest_density`` > 0
/// (kernel units); ``iterations`` in [0, 100]; ``omega`` in (0, 2].
/// Returns ``(positions float32 (N, D), compressed_before, max_compression_before)``.
/// Raises ``InvalidInputError`` naming the field.
#[pyfunction]
#[pyo3(signature = (positions, movable, radius, rest_density, iterations = 3, omega = 1.0))]
fn relax_density<'py>(
    py: Python<'py>,
    positions: &Bound<'py, PyAny>,
    movable: &Bound<'py, PyAny>,
    radius: f64,
    rest_density: f64,
    iterations: i64,
    omega: f64,
) -> PyResult<(Bound<'py, PyArray2<f32>>, usize, f32)> {
    let (arr, dim) = positions_array(py, positions)?;
    let mv = movable_vec(py, movable)?;
    let params = relax_params(py, radius, rest_density, iterations, omega)?;
    let (flat, stats) = if dim == 2 {
        relax_run::<2>(py, &arr, &mv, &params)?
    } else {
        relax_run::<3>(py, &arr, &mv, &params)?
    };
    let n = flat.len() / dim;
    let out = PyArray1::from_vec(py, flat).reshape([n, dim])?;
    Ok((out, stats.compressed_before, stats.max_compression_before))
}

/// Fresh numpy edge arrays of `e` edges (senders, receivers int64; displacement
/// float32 [e, D]; distance float32), filled by `write` with the GIL released.
fn edge_arrays<'py, const D: usize>(
    py: Python<'py>,
    e: usize,
    write: impl FnOnce(&mut [i64], &mut [i64], &mut [[f32; D]], &mut [f32]) -> Result<(), GraphError>
    + Send,
) -> PyResult<Edges<'py>> {
    let senders = empty(py, (e,), "int64")?.cast_into::<PyArray1<i64>>()?;
    let receivers = empty(py, (e,), "int64")?.cast_into::<PyArray1<i64>>()?;
    let displacement = empty(py, (e, D), "float32")?.cast_into::<PyArray2<f32>>()?;
    let distance = empty(py, (e,), "float32")?.cast_into::<PyArray1<f32>>()?;
    {
        // Fresh arrays: borrowing them cannot fail, but do not panic if it did.
        let borrow = |e: numpy::BorrowError| PyRuntimeError::new_err(e.to_string());
        let mut s = senders.try_readwrite().map_err(borrow)?;
        let mut r = receivers.try_readwrite().map_err(borrow)?;
        let mut dp = displacement.try_readwrite().map_err(borrow)?;
        let mut ds = distance.try_readwrite().map_err(borrow)?;
        let (s, r, dp, ds) = (
            s.as_slice_mut()?,
            r.as_slice_mut()?,
            dp.as_slice_mut()?,
            ds.as_slice_mut()?,
        );
        let dp = dp.as_chunks_mut::<D>().0;
        py.detach(|| write(s, r, dp, ds)).map_err(to_py(py))?;
    }
    Ok((senders, receivers, displacement, distance))
}

fn run<'py, const D: usize>(
    py: Python<'py>,
    arr: &Bound<'py, PyArray2<f32>>,
    params: GraphParams,
) -> PyResult<Edges<'py>> {
    let pos = rows::<D>(arr)?;
    let nb = py
        .detach(|| crate::pool::install_for(pos.len(), || Neighbors::search(&pos, &params)))
        .map_err(to_py(py))?;
    let n = pos.len();
    edge_arrays::<D>(py, nb.num_edges(), |s, r, dp, ds| {
        crate::pool::install_for(n, || nb.write(s, r, dp, ds))
    })
}

/// Radius graph of a particle cloud (GNS neighbour search).
///
/// Connects every pair of particles at most ``radius`` apart and returns the
/// directed edges with their features, as used by Graph Network-based
/// Simulators (Sanchez-Gonzalez et al., "Learning to Simulate Complex Physics
/// with Graph Networks", ICML 2020, App. A: edges between particles within the
/// connectivity radius R; edge feature = relative displacement and its norm).
///
/// Parameters
/// ----------
/// positions : numpy.ndarray, float32, shape (N, D), D in {2, 3}
///     Particle positions (any length unit; any strides). N may be 0.
/// radius : float, default ``CONNECTIVITY_RADIUS``
///     Connectivity radius R (same unit as ``positions``), finite and > 0;
///     rounded to float32. The default is the connectivity radius
///     ``hybridmpm._core.CONNECTIVITY_RADIUS`` (the same as
///     ``hybridmpm.conventions.CONNECTIVITY_RADIUS``).
/// self_edges : bool, default True
///     Include the self-edge (i, i) of every particle (displacement 0).
/// max_neighbors : int or None, default None
///     If given (>= 1), each receiver keeps only its ``max_neighbors`` nearest
///     senders (ties: lower sender index; a self-edge counts, at distance 0),
///     still listed by ascending sender. The removed edges are not returned:
///     compare with ``np.bincount`` of an uncapped call's receivers to count
///     them.
/// max_edges : int or None, default None
///     Edge budget (>= 0): a graph of more than ``max_edges`` edges (after
///     ``max_neighbors``) is refused with ``InvalidInputError`` naming
///     ``radius``, before its arrays are allocated (the search counts edges
///     and stops once over). None: no budget (``hybridmpm.graph.radius_graph``
///     derives one from the memory budget).
///
/// Returns
/// -------
/// senders : numpy.ndarray, int64, shape (E,)
/// receivers : numpy.ndarray, int64, shape (E,)
///     Edge e goes from particle ``senders[e]`` to ``receivers[e]``. Edges are
///     sorted by receiver, then by sender (both ascending).
/// displacement : numpy.ndarray, float32, shape (E, D)
///     ``positions[senders] - positions[receivers]`` (position units).
/// distance : numpy.ndarray, float32, shape (E,)
///     Euclidean norm of ``displacement`` (position units).
///
/// The pair (j, i) is an edge iff, in float32, ``d = p[j] - p[i]`` satisfies
/// ``d[0]*d[0] + d[1]*d[1] (+ d[2]*d[2]) <= R*R`` (i.e. distance <= R, like
/// ``scipy.spatial.cKDTree.query_ball_point``), so the graph is symmetric.
/// Computed on the CPU with a cell list over the data's bounding box (cell
/// size >= R; particles may be anywhere) in parallel over receivers; the
/// output is bitwise identical for any number of threads
/// (``RAYON_NUM_THREADS``). The GIL is released during the computation.
///
/// Raises
/// ------
/// hybridmpm.errors.InvalidInputError (a ValueError)
///     ``positions`` not a float32 array of shape (N, 2) or (N, 3), or with a
///     NaN / inf entry (field ``"positions"``); ``radius`` not finite and > 0
///     (``"radius"``); ``max_neighbors`` < 1 (``"max_neighbors"``);
///     ``max_edges`` < 0 (``"max_edges"``); more than ``max_edges`` edges
///     (``"radius"``, with the count).
#[pyfunction]
#[pyo3(signature = (positions, radius = connectivity_radius(), *, self_edges = true, max_neighbors = None, max_edges = None))]
fn radius_graph<'py>(
    py: Python<'py>,
    positions: &Bound<'py, PyAny>,
    radius: f64,
    self_edges: bool,
    max_neighbors: Option<i64>,
    max_edges: Option<&Bound<'py, PyAny>>,
) -> PyResult<Edges<'py>> {
    let (arr, dim) = positions_array(py, positions)?;
    let params = graph_params(py, radius, self_edges, max_neighbors, max_edges)?;
    if dim == 2 {
        run::<2>(py, &arr, params)
    } else {
        run::<3>(py, &arr, params)
    }
}

type Relaxed<'py> = (
    Bound<'py, PyArray2<f32>>,
    usize,
    f32,
    usize,
    usize,
    Edges<'py>,
);

fn relax_then_graph_run<'py, const D: usize>(
    py: Python<'py>,
    arr: &Bound<'py, PyArray2<f32>>,
    movable: &[bool],
    params: &nb::RelaxParams,
    bounds: Option<(Vec<f32>, Vec<f32>)>,
    graph: &GraphParams,
) -> PyResult<Relaxed<'py>> {
    let mut pos = rows::<D>(arr)?;
    let bounds = match bounds {
        None => None,
        Some((lo, hi)) => {
            if lo.len() != D || hi.len() != D {
                return Err(invalid_input(
                    py,
                    "bounds",
                    format!(
                        "lo and hi must have {D} entries each, got {} and {}",
                        lo.len(),
                        hi.len()
                    ),
                ));
            }
            Some((
                std::array::from_fn(|k| lo[k]),
                std::array::from_fn(|k| hi[k]),
            ))
        }
    };
    let out = py
        .detach(|| {
            crate::pool::install_for(pos.len(), || {
                nb::relax_then_graph(&mut pos, movable, params, bounds, graph)
            })
        })
        .map_err(to_py(py))?;
    let edges = edge_arrays::<D>(py, out.senders.len(), |s, r, dp, ds| {
        nb::write_edges(&pos, &out.offsets, &out.senders, s, r, dp, ds)
    })?;
    let n = pos.len();
    let flat: Vec<f32> = pos.into_iter().flatten().collect();
    let positions = PyArray1::from_vec(py, flat).reshape([n, D])?;
    Ok((
        positions,
        out.stats.compressed_before,
        out.stats.max_compression_before,
        out.clamped,
        out.searched,
        edges,
    ))
}

/// Clipping, density relaxation, clipping and the radius graph of the
/// result in one call (``hybridmpm.graph.relax_then_graph``): the same
/// result as ``numpy.clip`` to ``bounds``, ``relax_density``, ``numpy.clip``
/// again, then ``radius_graph`` (bit for bit), with the graph built from the
/// relaxation's neighbour lists where few particles moved (the
/// ``hybridmpm-neighbors`` crate's ``relax_then_graph``).
///
/// Parameters: as ``relax_density``; ``bounds`` None or ``(lo, hi)``,
/// float32 sequences of D entries, finite, ``lo <= hi``; ``graph_radius``,
/// ``self_edges``, ``max_neighbors``, ``max_edges`` as ``radius_graph``.
/// Returns ``(positions float32 (N, D), compressed_before,
/// max_compression_before, clamped, searched, (senders, receivers,
/// displacement, distance))``: ``clamped`` the particles clipped after the
/// relaxation (the second clipping), ``searched`` those whose neighbour lists were searched again.
/// Raises ``InvalidInputError`` naming the field.
#[pyfunction]
#[pyo3(signature = (positions, movable, radius, rest_density, iterations, omega, bounds, graph_radius, *, self_edges = true, max_neighbors = None, max_edges = None))]
#[allow(clippy::too_many_arguments)]
fn relax_then_graph<'py>(
    py: Python<'py>,
    positions: &Bound<'py, PyAny>,
    movable: &Bound<'py, PyAny>,
    radius: f64,
    rest_density: f64,
    iterations: i64,
    omega: f64,
    bounds: Option<(Vec<f32>, Vec<f32>)>,
    graph_radius: f64,
    self_edges: bool,
    max_neighbors: Option<i64>,
    max_edges: Option<&Bound<'py, PyAny>>,
) -> PyResult<Relaxed<'py>> {
    let (arr, dim) = positions_array(py, positions)?;
    let mv = movable_vec(py, movable)?;
    let params = relax_params(py, radius, rest_density, iterations, omega)?;
    let graph = graph_params(py, graph_radius, self_edges, max_neighbors, max_edges)?;
    if dim == 2 {
        relax_then_graph_run::<2>(py, &arr, &mv, &params, bounds, &graph)
    } else {
        relax_then_graph_run::<3>(py, &arr, &mv, &params, bounds, &graph)
    }
}

/// Adds `CONNECTIVITY_RADIUS` and the functions of this file to the module.
pub fn register(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add("CONNECTIVITY_RADIUS", connectivity_radius())?;
    m.add_function(wrap_pyfunction!(radius_graph, m)?)?;
    m.add_function(wrap_pyfunction!(kernel_density, m)?)?;
    m.add_function(wrap_pyfunction!(relax_density, m)?)?;
    m.add_function(wrap_pyfunction!(relax_then_graph, m)?)
}
