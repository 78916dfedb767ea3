"""The free-motion prior of the planned controllers: a cheap MLS-MPM rollout
of the uncontrolled motion, at a coarser grid on a subset of the particles,
carried back to every particle.

Why: in a control case the start is ``X_T`` with its motion reversed (paper
Sec. 3.2), so wherever the fluid was in free flight the uncontrolled motion
already retraces ``X_T … X_1``; what a controller must add is what pressure,
friction and the walls did not give back. Measured on validation seeds
4000–4011 (``docs/control.md``, "the free-motion prior"): the true free path
plus the sketch's geometric correction lands 20% (water2d) and 13% (sand2d)
below the constant-force baseline with no learning at all, and the free path
alone is closer to the target path than the first diffusion models' plans.
The model then learns only the correction (:data:`PRIOR_FREE_SKETCH`).

The rollout: every ``stride``-th particle (in the solver's order) on a grid
``coarsen`` times coarser, one thread, default volumes and masses (the
acceleration of a particle does not depend on its mass when mass = density ×
volume), the deformation gradient and ``J`` reset (the start is stress-free:
the same function serves training and serving, from positions, velocities
and materials alone), started at least one coarse cell inside the walls'
band (so the bottom layer starts up to a cell above the floor: a known
approximation, kept because the shipped models were trained with it); run by
:class:`~hybridmpm.sim.MpmSimulator` and
:func:`~hybridmpm.sim.rollout`. Every particle then moves with the displacement of its
nearest sampled particle at the start, so sampled particles follow their own
rollout exactly.
"""

from __future__ import annotations

import math

import numpy as np

from hybridmpm.control.sketch import Sketch
from hybridmpm.control.targets import pd_targets, smoothstep
from hybridmpm.conventions import GNS_TYPE_OF_MATERIAL
from hybridmpm.errors import InvalidInputError
from hybridmpm.mpm import MpmParams
from hybridmpm.scenes.core import Scene
from hybridmpm.sim import MpmSimulator, Simulator, rollout

#: The sketch-ramp prior (first format): the plan minus every particle moved to its sketch target along a smoothstep.
PRIOR_SKETCH_RAMP = "sketch_ramp"
#: The free-motion prior: the coarse free rollout (:func:`free_motion`) plus the sketch ramp applied to its end.
PRIOR_FREE_SKETCH = "free_sketch"
#: Every ``STRIDE``-th particle is simulated.
STRIDE = 4
#: The grid is ``COARSEN`` times coarser.
COARSEN = 2
#: The rollout's CFL number (the scenes use 0.4). 0.8 needs ~40% fewer substeps; on validation seeds 4000–4015 the
#: controllers tracked as well with it (sand2d 1.023 against 1.026, water2d 0.997 against 1.005) although the shipped
#: models were trained on priors at 0.4: the prior's error is its coarse grid, not its time step. None: the scene's.
CFL: float | None = 0.8
#: Largest deviation [m] of the free-motion rollout from every particle's parabola for which the fluid counts as in free
#: flight (:func:`in_free_flight`). Chosen on the training cases (seeds < 4000, ``docs/control.md``): of 439 sand2d and 558
#: water2d cases, 34 and 40 stay within 0.5 cm of the parabola, and in every one of them the true path does too (within
#: 0.02 cm); no case lies between 0.5 and 2 cm, and above 2 cm the true path leaves the parabola by up to 11 cm.
BALLISTIC_TOL = 0.01


def coarse_model(
    positions: np.ndarray,
    velocities: np.ndarray,
    material: np.ndarray,
    params: MpmParams,
    *,
    dt_frame: float,
    frames: int = 1,
    stride: int = STRIDE,
    coarsen: int = COARSEN,
    cfl: float | None = None,
) -> tuple[MpmSimulator, np.ndarray, np.ndarray]:
    """The cheap model of a fluid (module doc): an :class:`~hybridmpm.sim.MpmSimulator`
    of every ``stride``-th particle of ``positions`` [N, D] m (``velocities``
    [N, D] m/s, solver ``material`` codes int [N]) on a grid ``coarsen`` times
    coarser than ``params``' at CFL number ``cfl`` (None: :data:`CFL`), one
    thread, started one coarse cell inside the walls' band. Returns ``(sim,
    idx int [M] the simulated particles' indices, start float64 [M, D] their
    start positions)``. Used by the free-motion prior and by model-predictive
    control (:mod:`~hybridmpm.control.mpc`). Raises :class:`InvalidInputError`
    naming a bad argument."""
    x = np.asarray(positions, np.float64)
    v = np.asarray(velocities, np.float64)
    if x.ndim != 2 or v.shape != x.shape:
        raise InvalidInputError(f"positions: expected [N, D] with velocities of the same shape, got {list(x.shape)} and {list(v.shape)}", "positions")
    if isinstance(frames, bool) or not isinstance(frames, int) or not 1 <= frames <= 10_000:
        raise InvalidInputError(f"frames: must be an integer in [1, 10000], got {frames!r}", "frames")
    d = params.to_dict()
    cfl = CFL if cfl is None else cfl
    if cfl is not None:
        d["cfl"] = float(cfl)
    idx = np.arange(0, len(x), max(1, int(stride)))
    coarse_grid = max(16, int(math.ceil(params.resolved_n_grid() / coarsen)))
    sim = None
    for n_grid in (coarse_grid, params.resolved_n_grid()):  # a collider too thin for the coarse grid: keep the grid, subsample only
        pad = 1.01 / n_grid
        xs = np.clip(x[idx], pad, 1.0 - pad)
        scene = Scene(
            "free-motion prior", MpmParams.from_dict({**d, "n_grid": n_grid, "num_threads": 1, "substeps": None}),
            xs.astype(np.float32), np.asarray(material)[idx].astype(np.int32), v[idx].astype(np.float32), dt_frame=dt_frame, frames=frames,
        )  # fmt: skip
        try:
            sim = MpmSimulator(scene, threads=1)
            break
        except InvalidInputError:
            continue
    if sim is None:
        raise InvalidInputError("params: the scene's colliders refuse the free-motion rollout's grid", "params")
    # start one coarse cell inside the walls' band (what the shipped free-sketch models were trained with)
    lo, hi = sim.solver.domain_bounds
    pad = 1.01 / sim.solver.n_grid
    xs = np.clip(x[idx], lo + pad, hi - pad)
    sim.solver.positions = xs.astype(np.float32)
    return sim, idx, xs


def free_motion(
    positions: np.ndarray,
    velocities: np.ndarray,
    material: np.ndarray,
    params: MpmParams,
    frames: int,
    *,
    dt_frame: float,
    stride: int = STRIDE,
    coarsen: int = COARSEN,
    cfl: float | None = None,
) -> np.ndarray:
    """The uncontrolled motion of the fluid ``positions`` [N, D] m with
    ``velocities`` [N, D] m/s and solver ``material`` codes int [N], under
    :class:`~hybridmpm.mpm.MpmParams` ``params`` (gravity, walls, colliders,
    grid), for ``frames`` frames of ``dt_frame`` s at CFL number ``cfl``
    (None: :data:`CFL`): float64 [frames + 1, N, D] (row 0 the start). Approximate by design (module doc); deterministic.
    Raises :class:`InvalidInputError` naming a bad argument, and
    :class:`~hybridmpm.errors.SimulationError` if the coarse rollout fails."""
    from scipy.spatial import cKDTree

    x = np.asarray(positions, np.float64)
    sim, _, xs = coarse_model(positions, velocities, material, params, dt_frame=dt_frame, frames=frames, stride=stride, coarsen=coarsen, cfl=cfl)
    out = rollout(sim, frames).fluid_positions.astype(np.float64)  # the start, then ``frames`` frames
    out[0] = xs  # (the simulator's first frame predates the clipping above)
    nearest = cKDTree(xs).query(x, k=1)[1]
    return x[None] + (out - out[:1])[:, nearest]


def free_motion_of(sim: Simulator, frames: int) -> np.ndarray:
    """:func:`free_motion` of a simulator's fluid (any
    :class:`~hybridmpm.sim.Simulator`: its positions, velocities, particle
    types, scene parameters and frame length), float64 [frames + 1, N, D]."""
    p = sim.particles
    x = p.fluid(sim.positions)
    return free_motion(x, sim.velocities, material_of(p.particle_type[: p.num_fluid]), sim.scene.params, frames, dt_frame=sim.dt_frame)


def prior_path(free: np.ndarray, positions: np.ndarray, sketch: Sketch | None) -> np.ndarray:
    """The plan an untrained free-sketch model makes: the free motion ``free``
    float [F, N, D] (row 0 the start ``positions`` [N, D]) plus, along a
    smoothstep, the correction that moves its last row onto the sketch — an
    arrow: the centroid shifted to the start centroid plus the arrow (x–y); an
    oval: the end cloud's ±2σ ellipse mapped onto the drawn one
    (:func:`~hybridmpm.control.targets.pd_targets`). ``sketch`` None: the
    free motion itself. float64 [F, N, D]."""
    y = np.asarray(free, np.float64)
    if sketch is None:
        return y.copy()
    end = y[-1]
    if sketch.kind == "arrow":
        x0 = np.asarray(positions, np.float64)
        target = end.copy()
        target[:, :2] += x0[:, :2].mean(0) + np.asarray(sketch.vector, np.float64) - end[:, :2].mean(0)
    else:
        target = pd_targets(end, sketch)
    return y + smoothstep(len(y))[:, None, None] * (target - end)[None]


def ballistic_path(positions: np.ndarray, velocities: np.ndarray, gravity: np.ndarray, frames: int, dt_frame: float) -> np.ndarray:
    """Free flight: every particle on its own parabola ``x + v t + g t²/2``,
    ``t = k·dt_frame`` for ``k = 0 … frames``; float64 [frames + 1, N, D]
    (``positions`` [N, D] m, ``velocities`` [N, D] m/s, ``gravity`` [D] m/s²)."""
    x = np.asarray(positions, np.float64)
    t = np.arange(int(frames) + 1, dtype=np.float64)[:, None, None] * float(dt_frame)
    return x[None] + np.asarray(velocities, np.float64)[None] * t + 0.5 * np.asarray(gravity, np.float64)[None, None] * t * t


def in_free_flight(free: np.ndarray, positions: np.ndarray, velocities: np.ndarray, gravity: np.ndarray, dt_frame: float, tol: float | None = None) -> bool:
    """Whether the free-motion rollout ``free`` float [F, N, D] of the fluid
    at ``positions``/``velocities`` stays within ``tol`` m (None:
    :data:`BALLISTIC_TOL`) of every particle's parabola
    (:func:`ballistic_path`) over the whole horizon: no wall, collider,
    pressure or friction acted on it. Then the reverse-simulation path is the
    parabola itself — time reversal of a free flight is a free flight — and
    the planned controllers plan it without the network (``docs/control.md``,
    "free flight")."""
    fm = np.asarray(free, np.float64)
    bal = ballistic_path(positions, velocities, gravity, len(fm) - 1, dt_frame)
    if bal.shape != fm.shape:
        raise InvalidInputError(f"free: expected {list(bal.shape)}, got {list(fm.shape)}", "free")
    if fm.size == 0:  # no fluid: nothing in flight
        return False
    dev = float(np.sqrt(((fm - bal) ** 2).sum(-1)).max())
    return dev < (BALLISTIC_TOL if tol is None else float(tol))


def material_of(particle_type: np.ndarray) -> np.ndarray:
    """Solver material codes int32 [N] of GNS particle-type codes [N]
    (:data:`~hybridmpm.conventions.GNS_TYPE_OF_MATERIAL` inverted). Raises
    :class:`InvalidInputError` naming ``particle_type`` for a code that is no fluid."""
    inverse = {v: k for k, v in GNS_TYPE_OF_MATERIAL.items()}
    pt = np.asarray(particle_type).astype(np.int64)
    bad = ~np.isin(pt, list(inverse))
    if bad.any():
        raise InvalidInputError(f"particle_type: code {int(pt[bad][0])} is not a fluid type ({sorted(inverse)})", "particle_type")
    out = np.zeros(len(pt), np.int32)
    for gns, mat in inverse.items():
        out[pt == gns] = mat
    return out


__all__ = [
    "BALLISTIC_TOL",
    "COARSEN",
    "PRIOR_FREE_SKETCH",
    "PRIOR_SKETCH_RAMP",
    "STRIDE",
    "ballistic_path",
    "coarse_model",
    "free_motion",
    "free_motion_of",
    "in_free_flight",
    "material_of",
    "prior_path",
]
