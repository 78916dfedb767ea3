"""The real-time ladder (docs/realtime.md): the configurations real-time mode
(:class:`~hybridmpm.sim.realtime.RealtimeSimulator`) moves between, and their order.

A *rung* is one configuration of the scene's MPM: a grid (the scene's, or ¾ or ½ of it where the walls' faces
stay where they are), an integrator (the explicit MLS-MPM substeps, or the incompressible projection where the
scene is water round free-slip obstacles; docs/large-step.md) and its particles: the scene's own, or on a coarser
grid as many as the scene has per cell of its own grid (``r_p`` = the grids' ratio to the power D: the scene's
particles merged by parameter set in cubes of the coarser lattice's spacing, :func:`~hybridmpm.sim.convert.bin_groups`). The ladder orders the rungs by their error against the scene's
full-resolution reference, measured once by ``benchmarks/realtime_chart.py`` and shipped in
``models/realtime.json`` with each rung's time relative to the first; a rung that is slower and no more accurate
than another is dropped. A scene without a chart (a scene file of your own) gets the rungs by their time priors,
costliest first, and the measured times correct the priors.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from functools import cache
from importlib import resources
from typing import Any

import numpy as np

from hybridmpm.conventions import MATERIAL_WATER
from hybridmpm.errors import InvalidInputError
from hybridmpm.files import loads_json
from hybridmpm.mpm import MpmSolver
from hybridmpm.mpm.params import INTEGRATORS
from hybridmpm.scenes.core import Scene, wall_face
from hybridmpm.scenes.registry import registered_name

#: The grids of the ladder, as fractions of the scene's grid (those that keep the walls' faces: :func:`grid_holds`).
GRID_FRACTIONS = (1.0, 0.75, 0.5)
#: The smallest grid a rung runs on (the solver's own lower bound).
MIN_GRID = 16
#: The shipped real-time charts (``benchmarks/realtime_chart.py``), in the package's ``models``.
CHART_FILE = "realtime.json"
#: Time priors for a scene without a chart: the projection's time as a fraction of the explicit step's on its grid.
PROJECTION_PRIOR = 0.6


@dataclass(frozen=True)
class Rung:
    """One configuration of the ladder: MPM on ``n_grid`` (cells per axis) stepped by ``integrator``, on the
    simulator's own particles (``r_p`` 1) or those merged to the scene's density per cell of ``n_grid`` (``r_p``
    < 1: the nominal share of particles kept, ``(n_grid / n_scene)^D``). ``error`` its chart error (grid-mass
    error against the full-resolution reference, mean over the chart's frames; None without a chart) and
    ``time_ratio`` its chart time per frame relative to the ladder's first rung."""

    n_grid: int
    integrator: str
    error: float | None
    time_ratio: float
    r_p: float = 1.0

    @property
    def key(self) -> str:
        """``g{n_grid}-{integrator}``, e.g. ``g96-explicit``, with ``-rp{r_p}`` for merged particles
        (``g64-explicit-rp0.25``): the name the chart, the state and the service use."""
        return rung_key(self.n_grid, self.integrator, self.r_p)


def rung_key(n_grid: int, integrator: str, r_p: float = 1.0) -> str:
    """The key of the rung on ``n_grid`` stepped by ``integrator`` with particles ``r_p`` (:class:`Rung`)."""
    return f"g{int(n_grid)}-{integrator}" + (f"-rp{r_p:.3g}" if r_p < 1.0 else "")


def rung_label(key: str, dim: int) -> str:
    """A rung's key for people: ``g96-explicit`` in 2D is "MPM 96² explicit", ``g64-explicit-rp0.25``
    "MPM 64² explicit, r_p 0.25"."""
    grid, integrator, *rp = key[1:].split("-")
    return f"MPM {grid}{'²' if dim == 2 else '³'} {integrator}" + (f", r_p {rp[0][2:]}" if rp else "")


def ladder_grids(n_grid: int) -> list[int]:
    """The grids of the ladder for a scene on ``n_grid``: :data:`GRID_FRACTIONS` of it, at least
    :data:`MIN_GRID`, without repeats, finest first."""
    out: list[int] = []
    for f in GRID_FRACTIONS:
        n = max(MIN_GRID, int(round(n_grid * f)))
        if n not in out and n <= n_grid:
            out.append(n)
    return out


def projection_allowed(scene: Scene) -> bool:
    """Whether the projection steps ``scene``: water only, in the box walls, round free-slip obstacles and rigid
    bodies (the solver's own checks, :func:`~hybridmpm.scenes.resolution.with_integrator`)."""
    if np.any(np.asarray(scene.material) != MATERIAL_WATER):
        return False
    try:
        MpmSolver(replace(scene.params, integrator=INTEGRATORS[1]))
    except InvalidInputError:
        return False
    return True


def grid_holds(scene: Scene, n_grid: int) -> bool:
    """Whether ``scene`` moves onto ``n_grid`` as it is: the walls' faces exactly where they are (``face ·
    n_grid`` a whole number of cells, :func:`~hybridmpm.scenes.core.wall_cells_for`; elsewhere the box would
    shrink under the particles) and its spec's checks (obstacles at least two cells thick); a scene without a
    spec stays on its own grid."""
    if scene.spec is None:
        return n_grid == scene.params.resolved_n_grid()
    cells = wall_face(scene.params) * n_grid
    if abs(cells - round(cells)) > 1e-6 or round(cells) < 1:
        return False
    try:
        scene.spec.on_grid(n_grid)
    except InvalidInputError:
        return False
    return True


@cache
def _charts() -> dict[str, Any]:
    try:
        text = resources.files("hybridmpm.models").joinpath(CHART_FILE).read_text()
    except FileNotFoundError:
        return {}
    try:
        doc = loads_json(text, "realtime")
    except InvalidInputError as e:
        raise InvalidInputError(f"realtime: the package's models/{CHART_FILE} is corrupt ({e}); reinstall hybridmpm", "realtime") from None
    return doc.get("scenes", {}) if isinstance(doc, dict) else {}


def realtime_chart(scene: Scene | str) -> dict[str, Any] | None:
    """The shipped real-time chart of a registered scene (``models/realtime.json``): ``{"rungs": [{"key",
    "n_grid", "integrator", "error", "ms", "time_ratio"}...], "frames", ...}``, or None (a scene of your own)."""
    name = registered_name(scene)
    return _charts().get(name) if name is not None else None


def pareto(rungs: list[Rung]) -> list[Rung]:
    """``rungs`` ordered most accurate first (by chart error, then time), keeping only those faster than every
    more accurate one: each step down the ladder buys time."""
    ordered = sorted(rungs, key=lambda r: (math.inf if r.error is None else r.error, r.time_ratio))
    out: list[Rung] = []
    for r in ordered:
        if not out or r.time_ratio < min(o.time_ratio for o in out):
            out.append(r)
    return out


def candidate_rungs(scene: Scene) -> list[Rung]:
    """Every rung ``scene`` can run (its grid, ¾ and ½ of it where its walls and obstacles stay as they are,
    :func:`grid_holds`; explicit, and projection where allowed; on a coarser grid the scene's particles and
    those merged to its density, ``r_p = (n / n_scene)^D``; where the scene's grid is the only one, its particles
    and those merged to half its density per axis, ``r_p = 2^−D``; on the coarsest grid the merged particles also
    at half that density per axis, a further ``2^−D``: the ladder's last resort), finer grids first, explicit
    before projection, the scene's particles before merged ones, with time priors (explicit: the grid's share of
    the substeps, ``n / n_scene``; projection: :data:`PROJECTION_PRIOR` of that; merged: times ``r_p``) and no
    error."""
    n0 = scene.params.resolved_n_grid()
    integrators = [INTEGRATORS[0]] + ([INTEGRATORS[1]] if projection_allowed(scene) else [])
    grids = [n for n in ladder_grids(n0) if grid_holds(scene, n)]
    out = []
    for n in grids:
        # merged: the scene's density on a coarser grid, or half of it per axis where the scene's grid is the
        # only one; on the coarsest grid half that per axis too (the last resort)
        r_p = (n / n0) ** scene.dim if n < n0 else (0.5**scene.dim if len(grids) == 1 else 1.0)
        merged = [r_p] if r_p < 1.0 else []
        if merged and n == grids[-1]:
            merged.append(r_p * 0.5**scene.dim)
        for i in integrators:
            prior = n / n0 * (1.0 if i == INTEGRATORS[0] else PROJECTION_PRIOR)
            out += [Rung(n, i, None, prior)] + [Rung(n, i, None, prior * m, m) for m in merged]
    return out


def charted_rungs(scene: Scene) -> list[Rung]:
    """Every :func:`candidate_rungs` of ``scene`` with its chart error and time ratio where the shipped chart
    (:func:`realtime_chart`) has the rung, else its priors (error None), in the candidates' order."""
    chart = realtime_chart(scene) or {}
    charted = {r.get("key"): r for r in chart.get("rungs", []) if r.get("error") is not None and r.get("time_ratio")}
    out = []
    for r in candidate_rungs(scene):
        c = charted.get(r.key)
        out.append(r if c is None else replace(r, error=float(c["error"]), time_ratio=float(c["time_ratio"])))
    return out


def make_ladder(scene: Scene, integrators: tuple[str, ...] | None = None) -> list[Rung]:
    """The ladder of ``scene``, most accurate first: its :func:`charted_rungs` Pareto-ordered by :func:`pareto`
    where the chart has them all, else by their time priors, costliest first (a finer grid, the explicit step:
    the more accurate, as a rule). ``integrators``: of the rungs stepped by these only (None: all), e.g. the
    explicit ones a scene falls back on when another material is poured into its water (a projection rung that
    dominates an explicit one drops it from the whole ladder, not from this one)."""
    rungs = [r for r in charted_rungs(scene) if integrators is None or r.integrator in integrators]
    if all(r.error is not None for r in rungs):
        return pareto(rungs)
    return sorted(rungs, key=lambda r: -r.time_ratio)


__all__ = [
    "CHART_FILE",
    "GRID_FRACTIONS",
    "MIN_GRID",
    "PROJECTION_PRIOR",
    "Rung",
    "candidate_rungs",
    "charted_rungs",
    "grid_holds",
    "ladder_grids",
    "make_ladder",
    "pareto",
    "projection_allowed",
    "realtime_chart",
    "rung_key",
    "rung_label",
]
