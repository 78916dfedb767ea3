"""Pour a block into a running MPM simulator between frames (the service's
``POST /v1/sessions/{id}/blocks``; docs/materials.md "Pouring").

A block has the keys of a scene file's block (``material``, a model or a
preset, and its parameters; ``lo``, ``hi``, optional ``velocity``). It is
seeded on the scene's lattice and appended to the solver, in its own
parameter set where its parameters are new to the run. A block naming a model
starts from the scene's table of it (as a scene file's blocks do), a preset
from the preset; the block's keys override either. Everything is checked
before anything changes: a refused block leaves the simulator bit for bit as
it was.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from hybridmpm.errors import InvalidInputError, SimulationError
from hybridmpm.materials import material_from_block, scene_bases
from hybridmpm.scenes.core import lattice, wall_face
from hybridmpm.scenes.obstacles import collider_sdf
from hybridmpm.scenes.spec import BYTES_PER_PARTICLE, MAX_BLOCK_SPEED

#: Most particles one pour adds.
MAX_POUR_PARTICLES = 16_384
#: Most particles a session holds after pours (its scene's own count, if larger, is kept).
MAX_POURED_TOTAL = 131_072
#: Share of a block's lattice particles that may lie within half a lattice
#: spacing of a particle already there (or inside an obstacle); those are
#: dropped, a block with more is refused (field ``lo``).
MAX_OVERLAP_FRACTION = 0.1
#: The keys of a block besides its material's parameters.
_PLACE_KEYS = ("material", "lo", "hi", "velocity")


def _vec(name: str, v: Any, dim: int) -> np.ndarray:
    if not isinstance(v, (list, tuple)) or len(v) != dim or not all(isinstance(x, (int, float)) and not isinstance(x, bool) for x in v):
        raise InvalidInputError(f"{name}: expected {dim} numbers, got {v!r}", name)
    a = np.asarray(v, np.float64)
    if not np.isfinite(a).all():
        raise InvalidInputError(f"{name}: must be finite, got {v!r}", name)
    return a


def pour_block(sim: Any, block: dict[str, Any]) -> int:
    """Append ``block`` to the :class:`~hybridmpm.sim.MpmSimulator` ``sim``
    (its particles, on the scene's lattice, at rest or at ``velocity``) and
    return the new particle count. Raises :class:`InvalidInputError` naming
    the field (``material``, a parameter such as ``E``, ``lo``, ``hi``,
    ``velocity``) and leaves ``sim`` unchanged when the block is outside the
    walls' faces, overlaps the particles there (or obstacles) beyond
    :data:`MAX_OVERLAP_FRACTION`, exceeds :data:`MAX_POUR_PARTICLES`, the
    session's :data:`MAX_POURED_TOTAL` or the solver's memory budget, or has a
    bad parameter."""
    if not isinstance(block, dict):
        raise InvalidInputError("block: expected an object", "block")
    dim = sim.particles.dim
    keys = {k: v for k, v in block.items() if k not in _PLACE_KEYS and v is not None}
    try:
        m = material_from_block(block.get("material"), keys, "block", scene_bases(sim.solver.params))
    except InvalidInputError as e:  # "block.E" -> "E": the body's own key
        field = str(e.field or "material").removeprefix("block.")
        raise InvalidInputError(str(e).removeprefix("block."), field) from None
    lo, hi = _vec("lo", block.get("lo"), dim), _vec("hi", block.get("hi"), dim)
    if np.any(hi <= lo):
        raise InvalidInputError("hi: must exceed lo on every axis", "hi")
    params = sim.solver.params
    face = wall_face(params)
    if lo.min() < face - 1e-9 or hi.max() > 1.0 - face + 1e-9:
        raise InvalidInputError(
            f"lo: the block must lie inside the walls' faces [{face:.4g}, {1 - face:.4g}] m on every axis", "lo" if lo.min() < face else "hi"
        )
    vel = np.zeros(dim)
    if block.get("velocity") is not None:
        vel = _vec("velocity", block["velocity"], dim)
        if np.any(np.abs(vel) > MAX_BLOCK_SPEED):
            raise InvalidInputError(f"velocity: at most {MAX_BLOCK_SPEED:g} m/s per axis", "velocity")
    spacing = sim.scene.spec.spacing if sim.scene.spec is not None else 1.0 / (2 * params.resolved_n_grid())
    counts = np.maximum(np.round((hi - lo) / spacing), 1)
    lattice_n = int(np.prod(counts))
    n0 = int(sim.solver.num_particles)
    if lattice_n > MAX_POUR_PARTICLES:
        raise InvalidInputError(f"hi: the block holds {lattice_n} particles, more than the {MAX_POUR_PARTICLES} one pour may add", "hi")
    most = max(MAX_POURED_TOTAL, sim.particles.num_fluid if n0 > MAX_POURED_TOTAL else 0)
    if n0 + lattice_n > most:
        raise InvalidInputError(f"hi: {n0} + {lattice_n} particles exceed the {most} a session may hold", "hi")
    budget = sim.solver.memory_budget
    if budget is not None and (n0 + lattice_n) * BYTES_PER_PARTICLE > budget:
        raise InvalidInputError(f"hi: {n0 + lattice_n} particles exceed the session's memory budget of {budget} bytes", "hi")
    p = lattice(lo, hi, spacing)
    from scipy.spatial import cKDTree

    near = cKDTree(np.asarray(sim.solver.positions, np.float64)).query(p, k=1, distance_upper_bound=0.5 * spacing)[0] < np.inf
    for c in params.colliders:
        near |= collider_sdf(c, p) < 0.0
    if params.bodies:  # counted as obstacles, each where it is now
        now = sim.solver.bodies
        for k, b in enumerate(params.bodies):
            near |= b.sdf(p, now.center[k], now.rotation[k]) < 0.0
    if near.sum() > MAX_OVERLAP_FRACTION * len(p) or near.all():
        raise InvalidInputError(
            f"lo: {int(near.sum())} of the block's {len(p)} particles fall within half a lattice spacing of particles already there "
            f"or inside an obstacle; at most {MAX_OVERLAP_FRACTION:.0%} may: move or shrink it",
            "lo",
        )
    p = p[~near].astype(np.float32)
    v = np.tile(vel.astype(np.float32), (len(p), 1))
    steppable = _steppable(sim.solver, sim.dt_frame)
    solver, reason = _poured(sim, m, p, v, steppable)
    if reason is not None:
        key = _culprit(sim, block, keys, p, v)
        raise InvalidInputError(f"{key}: {block.get(key)!r} leaves a block the session cannot step: {reason}", key)
    sim.adopt(solver, [*sim.pours, len(p)])
    return int(solver.num_particles)


def _steppable(solver: Any, dt_frame: float) -> str | None:
    """None when the next frame of ``solver`` needs at most ``max_substeps`` substeps, else the reason."""
    try:
        solver.substeps_for(dt_frame)
    except SimulationError as e:
        return str(e)
    return None


def _poured(sim: Any, m: Any, p: np.ndarray, v: np.ndarray, before: str | None) -> tuple[Any, str | None]:
    """A solver holding ``sim``'s state and the particles ``p`` [N, D] of material ``m`` at velocities ``v``
    (``sim``'s own, changed in place, when its state could not be stepped before either and the block's set is
    already in its table; else a copy, so that ``sim`` is unchanged when the pour fails), and the reason the pour
    cannot run: its next frame would need more than ``max_substeps`` substeps where it did not before (``before``
    is None)."""
    # a state that could be stepped must stay one: the pour goes into a copy, checked; so does a pour that adds a
    # parameter set, so that a refused block leaves no set behind
    checked = before is None
    solver = _copy(sim.solver) if checked or sim.solver.params.set_index(m.to_params()) is None else sim.solver
    solver.add_particles(p, m.code, velocities=v, material_set=_set_for(solver, m))
    if checked and (reason := _steppable(solver, sim.dt_frame)) is not None:
        return sim.solver, reason
    return solver, None


def _culprit(sim: Any, block: dict[str, Any], keys: dict[str, Any], p: np.ndarray, v: np.ndarray) -> str:
    """The key of a refused pour to name: the first of the block's own material parameters whose default (the scene's
    table or the preset) lets the pour run; ``velocity`` when the material's defaults alone do not."""
    bases = scene_bases(sim.solver.params)
    for k in keys:
        if k == "material":
            continue
        m = material_from_block(block.get("material"), {q: x for q, x in keys.items() if q != k}, "block", bases)
        if _poured(sim, m, p, v, None)[1] is None:
            return k
    return "velocity" if block.get("velocity") is not None else "material"


def _set_for(solver: Any, m: Any) -> int:
    """The parameter-set index of material ``m`` in ``solver``'s table (:meth:`~hybridmpm.mpm.MpmParams.set_index`),
    ``m``'s set appended in place where the table lacks it (:meth:`~hybridmpm.mpm.MpmSolver.add_parameter_set`)."""
    ps = m.to_params()
    index = solver.params.set_index(ps)
    return int(solver.add_parameter_set(ps)) if index is None else index


def _copy(solver: Any) -> Any:
    """A new solver of ``solver``'s parameters holding its whole state (particles, clock, the colliders' poses
    and pending moves, the bodies)."""
    out = type(solver)(solver.params, memory_budget=solver.memory_budget)
    out.restore(solver.checkpoint())
    return out


__all__ = ["MAX_OVERLAP_FRACTION", "MAX_POURED_TOTAL", "MAX_POUR_PARTICLES", "pour_block"]
