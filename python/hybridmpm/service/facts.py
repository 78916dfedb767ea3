"""What the routes read of a session: plain values, the same on both backends.

What it was created with (:class:`SessionSettings`: scene, seed, solver,
``r_c``, grid) and its fixed facts (:class:`SessionFacts`: its scene, grid, particle
counts and types, masses, frame step) are taken once from its simulator —
in this process for the local backend, in the session's actor for the Ray
one, which sends them to the front end — so a route never reaches into a
simulator, and the Ray front end needs no stand-in for one.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from hybridmpm.errors import InvalidInputError
from hybridmpm.mpm import INTEGRATORS, SampledSdf
from hybridmpm.render.surface_scene import surface_settings
from hybridmpm.scenes import scene_spec
from hybridmpm.sim import RealtimeSimulator, Simulator

#: The solver of a session in real-time mode (one of :data:`hybridmpm.sim.SOLVERS`).
REALTIME = "realtime"


@dataclass(frozen=True)
class SessionSettings:
    """What a session was created with, and what rebuilds it: ``scene``
    (its registered name), ``seed``, ``solver`` (``default``, ``mpm``, ``hybrid``,
    ``neural`` or ``realtime``: :data:`hybridmpm.sim.SOLVERS`), ``r_c`` (the coarsening ratio of a learned solver) and
    ``n_grid`` (MPM on a coarser grid of the scene; None: the scene's own)
    and ``integrator`` (what MPM steps with, one of
    :data:`hybridmpm.mpm.INTEGRATORS`; None: the scene's own)."""

    scene: str
    seed: int
    solver: str
    r_c: float
    n_grid: int | None = None
    integrator: str | None = None

    def meta(self) -> dict[str, Any]:
        """What a checkpoint of the session is written for (its ``meta``): scene, seed, solver, ``r_c``, and ``n_grid`` and ``integrator`` when asked."""
        d: dict[str, Any] = {"scene": self.scene, "seed": self.seed, "solver": self.solver, "r_c": self.r_c}
        if self.n_grid is not None:
            d["n_grid"] = self.n_grid
        if self.integrator is not None:
            d["integrator"] = self.integrator
        return d


@dataclass(frozen=True)
class SessionFacts:
    """A session's fixed facts: ``scene_name`` (the scene's own name),
    ``kind`` (the simulator's: ``mpm``, ``hybrid``, ``neural``), ``n_grid``
    (the grid it runs on), ``dim``, ``num_fluid`` and ``num_total``
    particles (fluid, and with the boundary particles), ``particle_type``
    int [num_total] (GNS codes), ``masses`` float32 [num_total] [kg] and
    ``material`` int [num_total] (the trajectory file's), ``r_t`` frames per
    coarse step, ``dt_frame`` [s] between frames, and ``surface`` the
    settings of its fluid surfaces (:func:`~hybridmpm.render.surface_scene.surface_settings`:
    the wall faces, the grid, the obstacles, each particle's volume)."""

    scene_name: str
    kind: str
    n_grid: int
    dim: int
    num_fluid: int
    num_total: int
    particle_type: np.ndarray
    masses: np.ndarray
    material: np.ndarray
    r_t: int
    dt_frame: float
    surface: dict[str, Any]

    @classmethod
    def of(cls, sim: Simulator) -> SessionFacts:
        """The facts of ``sim`` (copies: they outlive any change to it)."""
        p = sim.particles
        return cls(
            scene_name=str(sim.scene.name),
            kind=str(sim.kind),
            n_grid=int(sim.scene.params.resolved_n_grid()),
            dim=int(p.dim),
            num_fluid=int(p.num_fluid),
            num_total=int(p.num_total),
            particle_type=np.asarray(p.particle_type).copy(),
            masses=np.asarray(p.full_masses()).copy(),
            material=np.asarray(p.full_material()).copy(),
            r_t=int(sim.r_t),
            dt_frame=float(sim.dt_frame),
            surface=surface_settings(sim.scene.params, p.particle_type, p.full_masses()),
        )

    @property
    def frame_bytes(self) -> int:
        """Bytes of one frame's positions (float32)."""
        return self.num_total * self.dim * 4

    @property
    def step_dt(self) -> float:
        """Seconds between stored frames of a trajectory (one coarse step: ``r_t`` frames)."""
        return self.dt_frame * self.r_t

    def to_dict(self) -> dict[str, Any]:
        return {k: getattr(self, k) for k in self.__dataclass_fields__}

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> SessionFacts:
        return cls(**{k: d[k] for k in cls.__dataclass_fields__})


def checked_n_grid(scene: str, solver: str, n_grid: int | None) -> int | None:
    """A session's ``n_grid`` as asked: None, or for the ``mpm`` solver a grid
    no finer than the registered scene's own (a coarser grid of the same
    domain costs less; a finer one could ask for any memory). Raises
    :class:`InvalidInputError` naming ``n_grid``."""
    if n_grid is None:
        return None
    if solver == "default":
        raise InvalidInputError("n_grid: applies to the mpm solver; the default solver runs the grid the chart chose for the scene", "n_grid")
    if solver == REALTIME:
        raise InvalidInputError("n_grid: applies to the mpm solver; the realtime solver picks its grid from its real-time ladder as it runs", "n_grid")
    if solver != "mpm":
        raise InvalidInputError(f"n_grid: applies to the mpm solver; the {solver} solver runs at its model's resolution", "n_grid")
    own = scene_spec(scene).params.resolved_n_grid()
    if n_grid > own:
        raise InvalidInputError(f"n_grid: at most the scene's own grid, {own}, got {n_grid}", "n_grid")
    return int(n_grid)


def checked_integrator(solver: str, integrator: str | None) -> str | None:
    """A session's ``integrator`` as asked: None, or one of
    :data:`hybridmpm.mpm.INTEGRATORS` for the ``mpm`` solver (whether the
    scene takes it — water only, free-slip obstacles — the simulator checks when
    it is built). Raises :class:`InvalidInputError` naming ``integrator``."""
    if integrator is None:
        return None
    if integrator not in INTEGRATORS:
        raise InvalidInputError(f"integrator: must be one of {', '.join(map(repr, INTEGRATORS))}, got {integrator!r}", "integrator")
    if solver == "default":
        raise InvalidInputError("integrator: applies to the mpm solver; the default solver runs the configuration the chart chose for the scene", "integrator")
    if solver == REALTIME:
        raise InvalidInputError("integrator: applies to the mpm solver; the realtime solver picks its integrator from its real-time ladder", "integrator")
    if solver != "mpm":
        raise InvalidInputError(f"integrator: applies to the mpm solver; the {solver} solver's MPM part runs its scene's integrator", "integrator")
    return str(integrator)


def checked_realtime(solver: str, realtime: bool | None, n_grid: int | None, integrator: str | None, default: bool = False) -> str:
    """The solver a session of ``solver`` runs given ``realtime`` (the request's; None: ``default``, the server's
    ``serve --realtime``): :data:`REALTIME` for ``realtime`` true (with the ``default`` solver, or ``realtime``
    itself, and no ``n_grid`` or ``integrator``: real-time mode picks its own grid and integrator), ``solver``
    for false. With None the server's default applies to a session of the ``default`` solver with neither
    ``n_grid`` nor ``integrator`` (a solver named, or a grid or integrator asked, runs as asked). Raises
    :class:`InvalidInputError` naming ``realtime`` for true with another solver, ``n_grid`` or ``integrator``,
    and for false with the ``realtime`` solver."""
    if realtime is None:
        return REALTIME if default and solver == "default" and n_grid is None and integrator is None else solver
    if not realtime:
        if solver == REALTIME:
            raise InvalidInputError("realtime: false contradicts solver 'realtime'; name another solver, or leave realtime out", "realtime")
        return solver
    if solver not in ("default", REALTIME):
        raise InvalidInputError(
            f"realtime: real-time mode is a solver of its own (MPM on the scene's default particles); it does not apply to the {solver} "
            "solver: leave solver out (or 'default')",
            "realtime",
        )
    for name, value in (("n_grid", n_grid), ("integrator", integrator)):
        if value is not None:
            raise InvalidInputError(f"realtime: real-time mode picks its own grid and integrator from its ladder; leave {name} out", "realtime")
    return REALTIME


def session_realtime(sim: Simulator) -> dict[str, Any] | None:
    """What a real-time session's simulator is doing (:meth:`hybridmpm.sim.RealtimeSimulator.realtime_info`,
    plain JSON values); None for any other simulator."""
    return dict(sim.realtime_info()) if isinstance(sim, RealtimeSimulator) else None


def session_integrator(sim: Simulator) -> str:
    """What ``sim``'s MPM steps with (:data:`hybridmpm.mpm.INTEGRATORS`): an
    MPM session's own, a hybrid or neural one's MPM part's (its scene's)."""
    return str(getattr(sim.scene.params, "integrator", INTEGRATORS[0]))


def scene_geometry(sim: Simulator) -> dict[str, Any]:
    """What a viewer draws besides the particles: the grid size, the walls'
    thickness [m] and the obstacles (the MPM colliders, as their ``to_dict``;
    a mesh obstacle as ``{"shape": "mesh", "lo", "hi"}``, the box its sampled
    distance covers, never its samples or its file's path)."""
    params = sim.scene.params
    n_grid = int(params.resolved_n_grid())
    return {
        "n_grid": n_grid,
        "wall_thickness": float(params.walls.cells) / n_grid,
        "obstacles": [_drawn(c) for c in params.colliders],
    }


def _drawn(c: Any) -> dict[str, Any]:
    if isinstance(c, SampledSdf):
        lo = np.asarray(c.origin, np.float64)
        hi = lo + float(c.cell) * (np.asarray(np.shape(c.values), np.float64) - 1)
        return {"shape": "mesh", "lo": lo.tolist(), "hi": hi.tolist(), "condition": c.condition}
    return dict(c.to_dict())


__all__ = [
    "REALTIME",
    "SessionFacts",
    "SessionSettings",
    "checked_integrator",
    "checked_n_grid",
    "checked_realtime",
    "scene_geometry",
    "session_integrator",
    "session_realtime",
]
