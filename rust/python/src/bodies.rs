//! The solver's rigid bodies from Python (`hybridmpm_mpm::body`,
//! docs/bodies.md): a body's dict read by the core's own `BodyParams`
//! (through [`crate::pyde::read`]: unknown keys refused, every error
//! naming the field, e.g. `bodies[0].density`), the bodies' state and the
//! fluid's force on them as arrays, and a body's exact state as 13 `f32`s
//! (what a checkpoint carries).

use hybridmpm_mpm as core;
use hybridmpm_mpm::body::BodyPose;
use hybridmpm_mpm::{Body, BodyParams, BodyState, Dim, DimOps, Solver};
use nalgebra::{SMatrix, SVector};
use numpy::{PyArray1, PyArrayMethods, PyReadonlyArray2, PyUntypedArrayMethods};
use pyo3::prelude::*;
use pyo3::types::PyDict;
use rayon::prelude::*;

use crate::errors::{invalid_input, to_py};

/// Numbers in a body's exact state: centre (3), rotation (4: 2D `cos θ,
/// sin θ, 0, 0`, 3D the quaternion `x, y, z, w`), velocity (3), angular
/// velocity (3), all `f32` ([`BodyState`]).
pub const STATE_LEN: usize = 13;

/// A body's parameters from a dict, fields named under `field`.
pub fn read(obj: &Bound<'_, PyAny>, field: &str) -> PyResult<BodyParams> {
    crate::pyde::read::<BodyParams>(obj, field).map_err(|e| e.into_py(obj.py()))
}

/// The body in `D` dimensions from its parameters, built (not yet checked
/// against a grid), errors naming the field under `field`.
pub fn build<const D: usize>(py: Python<'_>, p: &BodyParams, field: &str) -> PyResult<Body<D>> {
    p.build::<D>(field).map_err(|e| to_py(py, e))
}

/// A state as its 13 numbers.
pub fn flat(s: &BodyState) -> [f32; STATE_LEN] {
    let mut out = [0.0; STATE_LEN];
    out[..3].copy_from_slice(&s.x);
    out[3..7].copy_from_slice(&s.q);
    out[7..10].copy_from_slice(&s.v);
    out[10..].copy_from_slice(&s.w);
    out
}

/// A state from its 13 numbers.
pub fn unflat(v: &[f32]) -> BodyState {
    let mut s = BodyState::default();
    s.x.copy_from_slice(&v[..3]);
    s.q.copy_from_slice(&v[3..7]);
    s.v.copy_from_slice(&v[7..10]);
    s.w.copy_from_slice(&v[10..STATE_LEN]);
    s
}

/// The bodies as plain numbers, read under the solver's lock.
pub struct Snapshot {
    n: usize,
    dim: usize,
    state: Vec<f32>,
    center: Vec<f32>,
    rotation: Vec<f32>,
    velocity: Vec<f32>,
    angular_velocity: Vec<f32>,
    mass: Vec<f32>,
    force: Vec<f64>,
    torque: Vec<f64>,
}

/// The bodies of `s` now.
pub fn snapshot<const D: usize>(s: &Solver<D>) -> Snapshot
where
    core::Dim<D>: core::DimOps<D>,
{
    let b = s.bodies();
    let ang = if D == 2 { 2..3 } else { 0..3 };
    let mut out = Snapshot {
        n: b.len(),
        dim: D,
        state: Vec::new(),
        center: Vec::new(),
        rotation: Vec::new(),
        velocity: Vec::new(),
        angular_velocity: Vec::new(),
        mass: b.bodies().iter().map(|x| x.mass()).collect(),
        force: Vec::new(),
        torque: Vec::new(),
    };
    for st in b.states() {
        out.state.extend_from_slice(&flat(st));
        out.center.extend_from_slice(&st.x[..D]);
        let r = st.rotation::<D>();
        out.rotation.extend((0..D * D).map(|k| r[(k / D, k % D)]));
        out.velocity.extend_from_slice(&st.v[..D]);
        out.angular_velocity.extend_from_slice(&st.w[ang.clone()]);
    }
    for f in b.last_force() {
        out.force.extend_from_slice(&f[..D]);
        out.torque.extend_from_slice(&f[3 + ang.start..3 + ang.end]);
    }
    out
}

impl Snapshot {
    /// As a dict of numpy arrays (see `MpmSolver.bodies`).
    pub fn into_dict(self, py: Python<'_>) -> PyResult<Bound<'_, PyDict>> {
        let (n, d) = (self.n, self.dim);
        let w = if d == 2 { 1 } else { 3 };
        let out = PyDict::new(py);
        let f32s = |v: Vec<f32>, shape: Vec<usize>| PyArray1::from_vec(py, v).reshape(shape);
        out.set_item("state", f32s(self.state, vec![n, STATE_LEN])?)?;
        out.set_item("center", f32s(self.center, vec![n, d])?)?;
        out.set_item("rotation", f32s(self.rotation, vec![n, d, d])?)?;
        out.set_item("velocity", f32s(self.velocity, vec![n, d])?)?;
        out.set_item("angular_velocity", f32s(self.angular_velocity, vec![n, w])?)?;
        out.set_item("mass", PyArray1::from_vec(py, self.mass))?;
        out.set_item(
            "force",
            PyArray1::from_vec(py, self.force).reshape(vec![n, d])?,
        )?;
        out.set_item(
            "torque",
            PyArray1::from_vec(py, self.torque).reshape(vec![n, w])?,
        )?;
        Ok(out)
    }
}

/// Checks a body (a dict) as a `dim`-D solver of `n_grid` cells and walls
/// `wall_cells` thick would when it is added as body `index` (its shape,
/// size, density or mass, rotation, and that it lies inside the walls),
/// without a solver. Raises `InvalidInputError` naming the field
/// (`bodies[index].density`, ...). Returns its mass [kg; per unit depth in 2D].
#[pyfunction]
fn check_body(
    py: Python<'_>,
    body: &Bound<'_, PyAny>,
    dim: usize,
    n_grid: usize,
    wall_cells: usize,
    index: usize,
) -> PyResult<f32> {
    let field = format!("bodies[{index}]");
    if index >= core::body::MAX_BODIES {
        return Err(invalid_input(
            py,
            "bodies",
            format!("at most {} bodies", core::body::MAX_BODIES),
        ));
    }
    let p = read(body, &field)?;
    let dx = 1.0 / n_grid.max(1) as f32;
    match dim {
        2 => {
            let b = build::<2>(py, &p, &field)?;
            b.validate(&field, dx, wall_cells)
                .map_err(|e| to_py(py, e))?;
            Ok(b.mass())
        }
        3 => {
            let b = build::<3>(py, &p, &field)?;
            b.validate(&field, dx, wall_cells)
                .map_err(|e| to_py(py, e))?;
            Ok(b.mass())
        }
        _ => Err(invalid_input(
            py,
            "dim",
            format!("must be 2 or 3, got {dim}"),
        )),
    }
}

/// The convex hull of `points` (a list of `[x, y, z]`, metres), the body
/// a `mesh` body of these points is (`hybridmpm_mpm::body::Hull`): a dict
/// of `points` float32 [V, 3] (the hull's vertices, in the points' frame:
/// what a body keeps), `vertices` float32 [V, 3] (the same, in the body's
/// frame: centre of mass at 0), `faces` uint32 [F, 3] (outward), `offset`
/// float32 [3] (the centre of mass in the points' frame) and `volume`
/// [m³]. Raises `InvalidInputError` naming `field` (fewer than 4 points,
/// a non-finite one, all on one plane, more than `MAX_HULL_POINTS`).
#[pyfunction]
fn body_hull<'py>(
    py: Python<'py>,
    points: Vec<Vec<f32>>,
    field: &str,
) -> PyResult<Bound<'py, PyDict>> {
    let (prefix, key) = match field.rsplit_once('.') {
        Some((a, "path")) => (a, "path"),
        Some((a, "vertices")) => (a, "vertices"),
        _ => (field, "vertices"),
    };
    if let Some(i) = points.iter().position(|p| p.len() != 3) {
        return Err(invalid_input(
            py,
            &format!("{prefix}.{key}"),
            format!("point {i}: expected 3 numbers, got {:?}", points[i]),
        ));
    }
    let pts: Vec<[f32; 3]> = points.iter().map(|p| [p[0], p[1], p[2]]).collect();
    let hull = core::body::Hull::new(&pts, prefix, key).map_err(|e| to_py(py, e))?;
    let flat = |v: &[[f32; 3]]| v.iter().flatten().copied().collect::<Vec<f32>>();
    let n = hull.vertices.len();
    let out = PyDict::new(py);
    out.set_item(
        "points",
        PyArray1::from_vec(py, flat(&hull.source)).reshape(vec![n, 3])?,
    )?;
    out.set_item(
        "vertices",
        PyArray1::from_vec(py, flat(&hull.vertices)).reshape(vec![n, 3])?,
    )?;
    let faces: Vec<u32> = hull.faces.iter().flatten().copied().collect();
    out.set_item(
        "faces",
        PyArray1::from_vec(py, faces).reshape(vec![hull.faces.len(), 3])?,
    )?;
    out.set_item("offset", PyArray1::from_vec(py, hull.offset.to_vec()))?;
    out.set_item("volume", hull.volume)?;
    Ok(out)
}

/// Whether bodies `a` and `b` (dicts, as given, in `dim` dimensions)
/// overlap where they are given (parry's intersection test on rapier's
/// shapes). Raises `InvalidInputError` naming a field of a bad body
/// (`bodies[ia]` / `bodies[ib]`).
#[pyfunction]
fn bodies_overlap(
    py: Python<'_>,
    a: &Bound<'_, PyAny>,
    b: &Bound<'_, PyAny>,
    dim: usize,
    ia: usize,
    ib: usize,
) -> PyResult<bool> {
    let (fa, fb) = (format!("bodies[{ia}]"), format!("bodies[{ib}]"));
    let (pa, pb) = (read(a, &fa)?, read(b, &fb)?);
    match dim {
        2 => {
            let (x, y) = (build::<2>(py, &pa, &fa)?, build::<2>(py, &pb, &fb)?);
            Ok(x.overlaps(&BodyState::of(&x), &y, &BodyState::of(&y)))
        }
        3 => {
            let (x, y) = (build::<3>(py, &pa, &fa)?, build::<3>(py, &pb, &fb)?);
            Ok(x.overlaps(&BodyState::of(&x), &y, &BodyState::of(&y)))
        }
        _ => Err(invalid_input(
            py,
            "dim",
            format!("must be 2 or 3, got {dim}"),
        )),
    }
}

/// Points per rayon task of [`body_sdf`]: a hull of 4,096 faces costs about
/// 2 ms a chunk, a box or a ball microseconds.
const SDF_CHUNK: usize = 1024;

/// The signed distance [m] of `points` (float64 [N, D], metres) to a body
/// (a dict, as given; D = 2 or 3), negative inside, as float64 [N]: the
/// solver's own distance (`BodyPose::sdf_normal`, in float32), with the
/// body's centre of mass at `center` (float [D]) and rotation `rotation`
/// (float [D, D], columns the body's axes), or where it is given. A hull's
/// is the largest of its face planes' (exact inside, a lower bound
/// outside). Memory: the N distances. Raises `InvalidInputError` naming
/// `points`, `center` or `rotation` (shape, a non-finite number) or a
/// field of the body (`body.density`, ...).
#[pyfunction]
#[pyo3(signature = (body, points, center=None, rotation=None))]
fn body_sdf<'py>(
    py: Python<'py>,
    body: &Bound<'_, PyAny>,
    points: PyReadonlyArray2<'py, f64>,
    center: Option<Vec<f64>>,
    rotation: Option<Vec<Vec<f64>>>,
) -> PyResult<Bound<'py, PyArray1<f64>>> {
    let [n, dim] = [points.shape()[0], points.shape()[1]];
    let p = read(body, "body")?;
    let pts = points
        .as_slice()
        .map_err(|_| invalid_input(py, "points", "expected a C-contiguous float64 [N, D] array"))?;
    if pts.iter().any(|v| !v.is_finite()) {
        return Err(invalid_input(py, "points", "expected finite numbers"));
    }
    let out = match dim {
        2 => sdf_of::<2>(py, &p, pts, center, rotation)?,
        3 => sdf_of::<3>(py, &p, pts, center, rotation)?,
        _ => {
            return Err(invalid_input(
                py,
                "points",
                format!("expected [N, 2] or [N, 3], got [{n}, {dim}]"),
            ));
        }
    };
    Ok(PyArray1::from_vec(py, out))
}

/// [`body_sdf`] in `D` dimensions.
fn sdf_of<const D: usize>(
    py: Python<'_>,
    p: &BodyParams,
    pts: &[f64],
    center: Option<Vec<f64>>,
    rotation: Option<Vec<Vec<f64>>>,
) -> PyResult<Vec<f64>>
where
    Dim<D>: DimOps<D>,
{
    let b: Body<D> = build::<D>(py, p, "body")?;
    let finite = |field: &str, v: &[f64]| {
        if v.iter().all(|x| x.is_finite()) {
            Ok(())
        } else {
            Err(invalid_input(py, field, "expected finite numbers"))
        }
    };
    let c = match center {
        None => b.center,
        Some(c) if c.len() == D => {
            finite("center", &c)?;
            SVector::from_fn(|d, _| c[d] as f32)
        }
        Some(c) => {
            let msg = format!("expected {D} numbers, got {}", c.len());
            return Err(invalid_input(py, "center", msg));
        }
    };
    let r = match rotation {
        None => b.rotation,
        Some(r) if r.len() == D && r.iter().all(|row| row.len() == D) => {
            finite("rotation", &r.concat())?;
            SMatrix::from_fn(|i, j| r[i][j] as f32)
        }
        Some(_) => {
            return Err(invalid_input(
                py,
                "rotation",
                format!("expected [{D}, {D}]"),
            ));
        }
    };
    let pose = BodyPose {
        shape: b.shape.clone(),
        center: c,
        rotation: r,
        velocity: SVector::zeros(),
        angular_velocity: [0.0; 3],
        friction: 0.0,
    };
    let one = |x: &[f64]| pose.sdf_normal(&SVector::from_fn(|d, _| x[d] as f32)).0 as f64;
    Ok(py.detach(|| {
        crate::pool::install(|| {
            pts.par_chunks(SDF_CHUNK * D)
                .flat_map_iter(|chunk| chunk.chunks_exact(D).map(one))
                .collect()
        })
    }))
}

pub fn register(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add("MAX_BODIES", core::body::MAX_BODIES)?;
    m.add("MIN_BODY_DENSITY", core::body::MIN_BODY_DENSITY)?;
    m.add("MAX_BODY_DENSITY", core::body::MAX_BODY_DENSITY)?;
    m.add("MAX_BODY_SPEED", core::body::MAX_BODY_SPEED)?;
    m.add("BODY_STATE_LEN", STATE_LEN)?;
    m.add("MAX_HULL_POINTS", core::body::MAX_HULL_POINTS)?;
    m.add_function(wrap_pyfunction!(check_body, m)?)?;
    m.add_function(wrap_pyfunction!(body_hull, m)?)?;
    m.add_function(wrap_pyfunction!(bodies_overlap, m)?)?;
    m.add_function(wrap_pyfunction!(body_sdf, m)?)?;
    Ok(())
}
