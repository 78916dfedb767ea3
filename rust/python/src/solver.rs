//! `MpmSolver`: the MLS-MPM solver (`hybridmpm_mpm::Solver`, 2D or 3D)
//! as a Python class behind a lock.

use hybridmpm_mpm as core;
use hybridmpm_mpm::{Body, Collider, Solver, SolverParams};
use nalgebra::SVector;
use numpy::{PyArray1, PyArrayMethods, PyUntypedArrayMethods};
use pyo3::prelude::*;
use pyo3::types::{PyBytes, PyDict};
use std::sync::Mutex;

use crate::args::{extract_budget, extract_count, f32_array, f32_vec};
use crate::errors::{invalid_input, to_py};
use crate::fields::{self, Column, read_column, write_column};
use crate::material::{expand_sets, material_codes, set_indices};
use crate::particles::{NewParticles, add_particles_impl};

/// The solver parameters, colliders and bodies of the dict `MpmSolver`
/// takes, read by the core's types (`crate::params`); errors name the field.
#[allow(clippy::type_complexity)]
fn parse_params<const D: usize>(
    d: &Bound<'_, PyDict>,
) -> PyResult<(SolverParams<D>, Vec<Collider<D>>, Vec<Body<D>>)> {
    let py = d.py();
    let (params, specs, body_specs) = crate::params::read_params::<D>(d)?;
    let colliders = specs
        .iter()
        .enumerate()
        .map(|(i, c)| c.build::<D>(&format!("colliders[{i}]")))
        .collect::<Result<Vec<_>, _>>()
        .map_err(|e| to_py(py, e))?;
    let bodies = body_specs
        .iter()
        .enumerate()
        .map(|(i, b)| crate::bodies::build::<D>(py, b, &format!("bodies[{i}]")))
        .collect::<PyResult<Vec<_>>>()?;
    Ok((params, colliders, bodies))
}

/// A new solver with its bodies added (each checked against the grid).
fn make_solver<const D: usize>(
    p: SolverParams<D>,
    c: Vec<Collider<D>>,
    bodies: Vec<Body<D>>,
    budget: Option<u64>,
) -> core::Result<Solver<D>>
where
    core::Dim<D>: core::DimOps<D>,
{
    let mut s = Solver::with_memory_budget(p, c, budget)?;
    for b in bodies {
        // as given: a checkpoint's bodies were checked for overlaps when added
        s.add_given_body(b)?;
    }
    Ok(s)
}

enum Inner {
    D2(Solver<2>),
    D3(Solver<3>),
}

macro_rules! dispatch {
    ($inner:expr, $s:ident => $body:expr) => {
        match $inner {
            Inner::D2($s) => $body,
            Inner::D3($s) => $body,
        }
    };
}

/// MLS-MPM solver (Hu et al. 2018; APIC, quadratic B-splines) for water,
/// Drucker–Prager sand (Klár et al. 2016) and their mixture, with static
/// SDF colliders, in 2D or 3D on the unit domain.
///
/// Use the typed wrapper `hybridmpm.MpmSolver`; this class takes the
/// parameters as one dict (see `hybridmpm.mpm.MpmParams.to_dict`) and an
/// optional `memory_budget` in bytes (refuses a grid or particle count that
/// would need more; None: no budget). Raises `InvalidInputError` naming the
/// bad parameter.
///
/// Thread safety: the solver sits behind a lock. Every call waits (with the
/// GIL released) for the call in progress on another thread, so calls are
/// serialised and a reader sees the state at a frame boundary, never a
/// frame in progress.
#[pyclass(module = "hybridmpm._core", frozen)]
pub struct MpmSolver {
    inner: Mutex<Inner>,
    dim: usize,
    n_grid: usize,
    dx: f32,
    bounds: (f32, f32),
    bytes_per_particle: usize,
}

impl MpmSolver {
    /// Runs `f` on the solver with the GIL released, once the lock is free:
    /// the lock is taken only here and `f` never calls into Python, so no
    /// thread ever waits for the lock while holding the GIL or the other way
    /// round (no deadlock), and a call on one thread never fails because
    /// another is using the solver.
    fn with<R: Send>(&self, py: Python<'_>, f: impl FnOnce(&mut Inner) -> R + Send) -> R {
        py.detach(|| {
            // A panic cannot happen while the lock is held (no code path
            // panics); if one did, the state is still a validated one.
            let mut guard = self.inner.lock().unwrap_or_else(|e| e.into_inner());
            f(&mut guard)
        })
    }
}

fn stats_dict<'py>(py: Python<'py>, st: core::FrameStats) -> PyResult<Bound<'py, PyDict>> {
    let d = PyDict::new(py);
    d.set_item("substeps", st.substeps)?;
    d.set_item("dt", st.dt)?;
    d.set_item("max_speed", st.max_speed)?;
    d.set_item("active_blocks", st.active_blocks)?;
    d.set_item("retries", st.retries)?;
    d.set_item("replans", st.replans)?;
    Ok(d)
}

#[pymethods]
impl MpmSolver {
    #[new]
    #[pyo3(signature = (params, memory_budget=None))]
    fn new(params: &Bound<'_, PyDict>, memory_budget: Option<&Bound<'_, PyAny>>) -> PyResult<Self> {
        let py = params.py();
        let budget = extract_budget(memory_budget)?;
        let dim = match params.get_item("dim")? {
            Some(v) if !v.is_none() => {
                crate::pyde::read::<usize>(&v, "dim").map_err(|e| e.into_py(py))?
            }
            _ => 2,
        };
        // parse with the GIL, build (allocations, the thread pool) without it
        let inner = match dim {
            2 => {
                let (p, c, b) = parse_params::<2>(params)?;
                py.detach(|| make_solver(p, c, b, budget).map(Inner::D2))
            }
            3 => {
                let (p, c, b) = parse_params::<3>(params)?;
                py.detach(|| make_solver(p, c, b, budget).map(Inner::D3))
            }
            _ => {
                return Err(invalid_input(
                    py,
                    "dim",
                    format!("must be 2 or 3, got {dim}"),
                ));
            }
        }
        .map_err(|e| to_py(py, e))?;
        let (n_grid, dx, bounds) =
            dispatch!(&inner, s => (s.params().n_grid, s.params().dx(), s.domain_bounds()));
        let bytes_per_particle = match dim {
            2 => Solver::<2>::bytes_per_particle(),
            _ => Solver::<3>::bytes_per_particle(),
        };
        Ok(MpmSolver {
            inner: Mutex::new(inner),
            dim,
            n_grid,
            dx,
            bounds,
            bytes_per_particle,
        })
    }

    /// Spatial dimension (2 or 3).
    #[getter]
    fn dim(&self) -> usize {
        self.dim
    }

    /// Grid cells per dimension.
    #[getter]
    fn n_grid(&self) -> usize {
        self.n_grid
    }

    /// Grid spacing dx = 1/n_grid [m].
    #[getter]
    fn dx(&self) -> f32 {
        self.dx
    }

    /// Estimated bytes the solver allocates per particle (the unit of the
    /// `positions` budget check).
    #[getter]
    fn bytes_per_particle(&self) -> usize {
        self.bytes_per_particle
    }

    /// The memory budget in bytes (None: unlimited).
    #[getter]
    fn memory_budget(&self, py: Python<'_>) -> Option<u64> {
        self.with(py, |inner| dispatch!(inner, s => s.memory_budget()))
    }

    #[getter]
    fn num_particles(&self, py: Python<'_>) -> usize {
        self.with(py, |inner| dispatch!(inner, s => s.num_particles()))
    }

    /// Simulated time [s].
    #[getter]
    fn time(&self, py: Python<'_>) -> f64 {
        self.with(py, |inner| dispatch!(inner, s => s.time()))
    }

    /// Frame attempts so far `(alone, team)`: run by the calling thread alone
    /// or by the pool's team of threads, as the solver chose by measured cost
    /// (docs/engine.md, "A busy machine"; probes of the other way included).
    #[getter]
    fn mode_runs(&self, py: Python<'_>) -> (u64, u64) {
        self.with(py, |inner| dispatch!(inner, s => s.mode_runs()))
    }

    /// The compiled copy of the frame loop that runs: `"baseline"` (portable)
    /// or `"x86-64-v3"` (AVX2/FMA, chosen when the CPU has it); the same bits
    /// either way (docs/engine.md).
    #[getter]
    fn isa(&self, py: Python<'_>) -> &'static str {
        self.with(py, |inner| dispatch!(inner, s => s.isa().name()))
    }

    /// Run the frame loop's copy `name` (see `isa`) from the next frame on:
    /// for comparing them; `InvalidInputError` (field `isa`) for an unknown
    /// name or one this CPU cannot run.
    fn set_isa(&self, py: Python<'_>, name: &str) -> PyResult<()> {
        let isa = core::Isa::from_name(name).ok_or_else(|| {
            let known: Vec<&str> = core::Isa::ALL.iter().map(|i| i.name()).collect();
            invalid_input(
                py,
                "isa",
                format!("unknown instruction set {name:?}; expected one of {known:?}"),
            )
        })?;
        self.with(py, |inner| dispatch!(inner, s => s.set_isa(isa)))
            .map_err(|e| to_py(py, e))
    }

    /// Frames advanced so far.
    #[getter]
    fn frame(&self, py: Python<'_>) -> u64 {
        self.with(py, |inner| dispatch!(inner, s => s.frame()))
    }

    /// Valid particle coordinate range (lo, hi): one cell inside the unit domain.
    #[getter]
    fn domain_bounds(&self) -> (f32, f32) {
        self.bounds
    }

    /// Append a parameter set (a dict naming one material, as an entry of
    /// `params["sets"]`: `{"elastic": {"youngs_modulus": 5e4, ...}}`) to the
    /// table, in place: the particles, the clock and every other parameter
    /// are kept. Returns its index in the table (a particle's
    /// `material_set`). Raises `InvalidInputError` naming `sets[k]`'s key
    /// (k: the new set's place in `params["sets"]`); the solver is then
    /// unchanged.
    fn add_parameter_set(&self, py: Python<'_>, set: &Bound<'_, PyAny>) -> PyResult<u16> {
        let k = self.with(py, |inner| dispatch!(inner, s => s.params().sets.len()));
        let set: core::MaterialParams =
            crate::pyde::read(set, &format!("sets[{k}]")).map_err(|e| e.into_py(py))?;
        self.with(py, |inner| dispatch!(inner, s => s.add_parameter_set(set)))
            .map_err(|e| to_py(py, e))
    }

    /// Append particles. `positions` float32 [N, D] in [dx, 1 - dx]; `material`
    /// int code or int array [N] (0 = water, 1 = sand, 2 = elastic, 3 = snow,
    /// 4 = viscoplastic); optional `material_set` int or int array [N], the
    /// parameter set of each (an index into the table: each material's
    /// default at its code, then `params["sets"]`; default: the material's
    /// code), `velocities` float32 [N, D] [m/s], `masses` [N] [kg], `volumes`
    /// [N] [m^D] (default volume (dx/2)^D, mass = the set's density·volume).
    /// Returns the new count. Refused (field `positions`) beyond the memory
    /// budget.
    #[pyo3(signature = (positions, material, *, velocities=None, masses=None, volumes=None, material_set=None))]
    #[allow(clippy::too_many_arguments)] // pyo3's signature: the keyword arguments of Python's call
    fn add_particles(
        &self,
        py: Python<'_>,
        positions: &Bound<'_, PyAny>,
        material: &Bound<'_, PyAny>,
        velocities: Option<&Bound<'_, PyAny>>,
        masses: Option<&Bound<'_, PyAny>>,
        volumes: Option<&Bound<'_, PyAny>>,
        material_set: Option<&Bound<'_, PyAny>>,
    ) -> PyResult<usize> {
        let d = self.dim;
        let x = f32_array(positions, "positions", &[None, Some(d)])?;
        let n = x.shape()[0];
        // refuse a huge array before copying it (the total is checked under the lock)
        let per = self.bytes_per_particle;
        let budget = self.memory_budget(py);
        core::error::check_budget(
            "positions",
            &format!("{n} particles ({per} bytes each)"),
            (n as u128).checked_mul(per as u128),
            budget,
        )
        .map_err(|e| to_py(py, e))?;
        drop(x);
        let new = NewParticles {
            n,
            x: f32_vec(positions, "positions", &[Some(n), Some(d)])?,
            mats: material_codes(material)?,
            sets: match material_set {
                Some(v) => {
                    let scalar = v
                        .getattr("ndim")
                        .map_or(true, |d| d.extract::<usize>().ok() == Some(0));
                    Some((set_indices(v, "material_set")?, scalar))
                }
                None => None,
            },
            v: velocities
                .map(|v| f32_vec(v, "velocities", &[Some(n), Some(d)]))
                .transpose()?,
            m: masses
                .map(|v| f32_vec(v, "masses", &[Some(n)]))
                .transpose()?,
            vol: volumes
                .map(|v| f32_vec(v, "volumes", &[Some(n)]))
                .transpose()?,
        };
        self.with(
            py,
            |inner| dispatch!(inner, s => add_particles_impl(s, &new)),
        )
        .map_err(|e| to_py(py, e))
    }

    /// Remove the particles where `mask` (bool [N]) is True. Returns the new count.
    fn remove_particles(&self, py: Python<'_>, mask: &Bound<'_, PyAny>) -> PyResult<usize> {
        let np = py.import("numpy")?;
        let arr = np.call_method1("asarray", (mask,))?;
        let kind: String = arr.getattr("dtype")?.getattr("kind")?.extract()?;
        let shape: Vec<usize> = arr.getattr("shape")?.extract()?;
        if kind != "b" || shape.len() != 1 {
            return Err(invalid_input(
                py,
                "mask",
                format!(
                    "expected a bool array of shape [N], got dtype kind '{kind}' and shape {shape:?}"
                ),
            ));
        }
        let remove: Vec<bool> = arr.call_method0("tolist")?.extract()?;
        let keep: Vec<bool> = remove.iter().map(|r| !r).collect();
        self.with(py, |inner| dispatch!(inner, s => s.retain_particles(&keep)))
            .map_err(|e| to_py(py, e))
    }

    /// Copy of a per-particle array: positions/velocities/external_acceleration
    /// float32 [N, D]; affine/deformation_gradient/stress float32 [N, D, D];
    /// volume_ratio/volume_correction/masses/volumes float32 [N]; material and
    /// material_set (the parameter set of each particle) int32 [N].
    fn get(&self, py: Python<'_>, field: &str) -> PyResult<Py<PyAny>> {
        fields::check_name(py, field)?;
        let (n, col) = self.with(py, |inner| dispatch!(inner, s => read_column(s, field)));
        let shape = fields::shape(field, n, self.dim);
        Ok(match col {
            Column::I32(v) => PyArray1::from_vec(py, v)
                .reshape(shape)?
                .into_any()
                .unbind(),
            Column::F32(v) => PyArray1::from_vec(py, v)
                .reshape(shape)?
                .into_any()
                .unbind(),
        })
    }

    /// Overwrite a per-particle array (same shapes as `get`; `stress` is read-only).
    /// Validated as a whole: on error nothing changes.
    fn set(&self, py: Python<'_>, field: &str, value: &Bound<'_, PyAny>) -> PyResult<()> {
        fields::check_name(py, field)?;
        if field == "stress" {
            return Err(invalid_input(
                py,
                "stress",
                "is derived from the state and read-only",
            ));
        }
        if field == "material" {
            let codes = material_codes(value)?;
            return self
                .with(py, |inner| {
                    dispatch!(inner, s => {
                        let mats = codes.expand(s.num_particles())?;
                        // each particle takes its new material's default set
                        s.modify_particles(true, |i, p| {
                            p.material = mats[i];
                            p.set = mats[i] as u16;
                        })
                    })
                })
                .map_err(|e| to_py(py, e));
        }
        if field == "material_set" {
            let scalar = value
                .getattr("ndim")
                .map_or(true, |d| d.extract::<usize>().ok() == Some(0));
            let sets = set_indices(value, "material_set")?;
            return self
                .with(py, |inner| {
                    dispatch!(inner, s => {
                        let sets = expand_sets(&sets, s.num_particles(), scalar)?;
                        s.modify_particles(true, |i, p| p.set = sets[i])
                    })
                })
                .map_err(|e| to_py(py, e));
        }
        let n = self.num_particles(py);
        let shape: Vec<Option<usize>> = fields::shape(field, n, self.dim)
            .into_iter()
            .map(Some)
            .collect();
        let flat = f32_vec(value, field, &shape)?;
        self.with(
            py,
            |inner| dispatch!(inner, s => write_column(s, field, &flat)),
        )
        .map_err(|e| to_py(py, e))
    }

    /// Substeps the CFL condition asks for over a frame of `dt_frame` seconds
    /// (in (0, 1]): `ceil(dt_frame / dt_max)`, or the fixed `substeps`.
    /// Raises `SimulationError` (naming the particles' speed) if more than
    /// `max_substeps` would be needed, as `step_frame` would.
    #[pyo3(signature = (dt_frame=2.5e-3))]
    fn substeps_for(&self, py: Python<'_>, dt_frame: f32) -> PyResult<usize> {
        self.with(py, |inner| dispatch!(inner, s => s.substeps_for(dt_frame)))
            .map_err(|e| to_py(py, e))
    }

    /// Advance one frame (default 2.5 ms). Returns {substeps, dt, max_speed,
    /// active_blocks, retries, replans}. A substep that leaves a non-finite state,
    /// inverts a sand particle (det F <= 0) or violates the CFL condition
    /// restarts the frame with the substep halved (`retries` counts them);
    /// a projection step stopped before its particles moved, too fast for
    /// its length, shortens the frame's remaining steps (`replans`).
    /// Raises `SimulationError` (with `.substep`) if even `max_substeps`
    /// fail, and (naming the particles' speed) if the CFL condition asks for
    /// more than `max_substeps`: the state is then that of the frame's start.
    /// The GIL is released while stepping; other threads' calls wait.
    #[pyo3(signature = (dt_frame=2.5e-3))]
    fn step_frame<'py>(&self, py: Python<'py>, dt_frame: f32) -> PyResult<Bound<'py, PyDict>> {
        let r = self.with(py, |inner| dispatch!(inner, s => s.step_frame(dt_frame)));
        stats_dict(py, r.map_err(|e| to_py(py, e))?)
    }

    /// Each collider's anchor now [m]: float32 [C, D], a box's or sphere's
    /// centre, a sampled shape's origin (moved by `move_collider` /
    /// `place_collider`).
    #[getter]
    fn collider_positions<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyAny>> {
        let (n, flat) = self.with(py, |inner| {
            dispatch!(inner, s => {
                let flat: Vec<f32> = s
                    .colliders()
                    .iter()
                    .flat_map(|c| c.shape.anchor().iter().copied().collect::<Vec<f32>>())
                    .collect();
                (s.colliders().len(), flat)
            })
        });
        Ok(PyArray1::from_vec(py, flat)
            .reshape(vec![n, self.dim])?
            .into_any())
    }

    /// Pending moves for the next frame: a list of `(index, position,
    /// velocity)`, `position` the anchor at the frame's end and `velocity`
    /// the boundary velocity [m/s] or None (derived from the move), both
    /// lists of D floats.
    #[getter]
    #[allow(clippy::type_complexity)]
    fn collider_moves(&self, py: Python<'_>) -> Vec<(usize, Vec<f32>, Option<Vec<f32>>)> {
        self.with(py, |inner| {
            dispatch!(inner, s => (0..s.colliders().len())
                .filter_map(|i| {
                    s.collider_move(i).map(|m| {
                        (i, m.end.as_slice().to_vec(), m.velocity.map(|v| v.as_slice().to_vec()))
                    })
                })
                .collect())
        })
    }

    /// Put collider `index` at anchor `position` (float32 [D], m) now, at
    /// rest, dropping its pending move. `InvalidInputError` names `index`
    /// or `position`.
    fn place_collider(
        &self,
        py: Python<'_>,
        index: &Bound<'_, PyAny>,
        position: &Bound<'_, PyAny>,
    ) -> PyResult<()> {
        let i = extract_count(index, "index", "a collider index (an integer >= 0)")?;
        let x = f32_vec(position, "position", &[Some(self.dim)])?;
        self.with(
            py,
            |inner| dispatch!(inner, s => s.place_collider(i, SVector::from_column_slice(&x))),
        )
        .map_err(|e| to_py(py, e))
    }

    /// Move collider `index` over the next frame to anchor `position`
    /// (float32 [D], m), its boundary condition relative to `velocity`
    /// (float32 [D], m/s; None: the move's distance over the frame's
    /// duration). Used once (see the core's `Solver::move_collider`).
    /// `InvalidInputError` names `index`, `position` or `velocity`.
    #[pyo3(signature = (index, position, velocity=None))]
    fn move_collider(
        &self,
        py: Python<'_>,
        index: &Bound<'_, PyAny>,
        position: &Bound<'_, PyAny>,
        velocity: Option<&Bound<'_, PyAny>>,
    ) -> PyResult<()> {
        let i = extract_count(index, "index", "a collider index (an integer >= 0)")?;
        let x = f32_vec(position, "position", &[Some(self.dim)])?;
        let v = velocity
            .filter(|v| !v.is_none())
            .map(|v| f32_vec(v, "velocity", &[Some(self.dim)]))
            .transpose()?;
        self.with(py, |inner| {
            dispatch!(inner, s => s.move_collider(
                i,
                SVector::from_column_slice(&x),
                v.as_ref().map(|v| SVector::from_column_slice(v)),
            ))
        })
        .map_err(|e| to_py(py, e))
    }

    /// The rigid bodies now (docs/bodies.md), a dict of arrays over the B
    /// bodies in order: `center` float32 [B, D] [m], `rotation` [B, D, D]
    /// (columns: the body's axes), `velocity` [B, D] [m/s],
    /// `angular_velocity` [B, 1] in 2D (about z) or [B, 3] [rad/s], `mass`
    /// [B] [kg; per unit depth in 2D], the fluid's mean `force` float64
    /// [B, D] [N] and `torque` [B, 1 or 3] [N·m] over the last frame, and
    /// `state` float32 [B, 13], each body's exact state (`set_body_state`).
    fn bodies<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyDict>> {
        let snap = self.with(
            py,
            |inner| dispatch!(inner, s => crate::bodies::snapshot(s)),
        );
        snap.into_dict(py)
    }

    /// Add a rigid body between frames from its dict (`shape` 'box' or
    /// 'sphere'/'circle', `center`, `half_extents` or `radius`, `rotation`
    /// or `angle_deg`, `density` or `mass`, `velocity`, `angular_velocity`,
    /// `friction`); returns its index. `InvalidInputError` names the field
    /// (`bodies[i].density`, or `bodies` past `MAX_BODIES`); nothing changes then.
    fn add_body(&self, py: Python<'_>, body: &Bound<'_, PyAny>) -> PyResult<usize> {
        let i = self.with(py, |inner| dispatch!(inner, s => s.bodies().len()));
        let field = format!("bodies[{i}]");
        let p = crate::bodies::read(body, &field)?;
        self.with(py, |inner| match inner {
            Inner::D2(s) => p.build::<2>(&field).and_then(|b| s.add_body(b)),
            Inner::D3(s) => p.build::<3>(&field).and_then(|b| s.add_body(b)),
        })
        .map_err(|e| to_py(py, e))
    }

    /// Remove body `index` (the later ones move down one). `InvalidInputError`
    /// names `index`.
    fn remove_body(&self, py: Python<'_>, index: &Bound<'_, PyAny>) -> PyResult<()> {
        let i = extract_count(index, "index", "a body index (an integer >= 0)")?;
        self.with(py, |inner| dispatch!(inner, s => s.remove_body(i)))
            .map_err(|e| to_py(py, e))
    }

    /// Set body `index`'s exact state (float32 [13], a row of `bodies()["state"]`).
    /// `InvalidInputError` names `index`, `state` or `bodies[i].state`.
    fn set_body_state(
        &self,
        py: Python<'_>,
        index: &Bound<'_, PyAny>,
        state: &Bound<'_, PyAny>,
    ) -> PyResult<()> {
        let (i, st) = body_state_args(index, state)?;
        self.with(py, |inner| dispatch!(inner, s => s.set_body_state(i, st)))
            .map_err(|e| to_py(py, e))
    }

    /// Check a checkpoint's state for body `index` without setting it
    /// (float32 [13]: finite, a unit rotation, the body inside the walls
    /// within a cell, its points no faster than `MAX_BODY_SPEED`).
    /// `InvalidInputError` names `index`, `state` or `body_state[i]`.
    fn check_body_state(
        &self,
        py: Python<'_>,
        index: &Bound<'_, PyAny>,
        state: &Bound<'_, PyAny>,
    ) -> PyResult<()> {
        let (i, st) = body_state_args(index, state)?;
        self.with(
            py,
            |inner| dispatch!(inner, s => s.check_body_state(i, &st)),
        )
        .map_err(|e| to_py(py, e))
    }

    /// Sets the fluid's last force and torque on body `index` (6 float64
    /// lanes: force x, y, z, torque x, y, z; a 2D body's torque in lane 5),
    /// as a checkpoint holds them. Raises `InvalidInputError` naming
    /// `index`, `force` (not 6 numbers) or `bodies[i].force` (not finite).
    fn set_body_force(
        &self,
        py: Python<'_>,
        index: &Bound<'_, PyAny>,
        force: Vec<f64>,
    ) -> PyResult<()> {
        let i = extract_count(index, "index", "a body index (an integer >= 0)")?;
        let f: [f64; 6] = force.try_into().map_err(|_| {
            invalid_input(
                py,
                "force",
                "expected 6 numbers (force x, y, z, torque x, y, z)",
            )
        })?;
        self.with(py, |inner| dispatch!(inner, s => s.set_body_force(i, f)))
            .map_err(|e| to_py(py, e))
    }

    /// Particle state and clock as bytes (parameters not included).
    fn checkpoint<'py>(&self, py: Python<'py>) -> Bound<'py, PyBytes> {
        let blob = self.with(py, |inner| dispatch!(inner, s => s.checkpoint()));
        PyBytes::new(py, &blob)
    }

    /// Restore a `checkpoint()` blob. Raises `CheckpointError`; on error nothing changes.
    fn restore(&self, py: Python<'_>, blob: &[u8]) -> PyResult<()> {
        self.with(py, |inner| dispatch!(inner, s => s.restore(blob)))
            .map_err(|e| to_py(py, e))
    }
}

pub fn register(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add_class::<MpmSolver>()?;
    Ok(())
}

/// A body's index and exact state as `set_body_state` and
/// `check_body_state` take them (an integer >= 0; float32 [13]).
fn body_state_args(
    index: &Bound<'_, PyAny>,
    state: &Bound<'_, PyAny>,
) -> PyResult<(usize, core::BodyState)> {
    let i = extract_count(index, "index", "a body index (an integer >= 0)")?;
    let v = f32_vec(state, "state", &[Some(crate::bodies::STATE_LEN)])?;
    Ok((i, crate::bodies::unflat(&v)))
}
