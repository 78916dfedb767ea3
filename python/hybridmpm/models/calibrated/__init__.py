"""Calibrated coarse materials: constitutive parameters fitted so that plain MPM
on a coarser grid follows full-resolution MPM more closely, at no run-time cost
(docs/correction.md "Rung 1").

Each fit is ``<scene>_g<n>.json`` beside this file (the scene's registered
domain on an ``n`` grid, 2 particles per cell per axis) with its card
``<scene>_g<n>.md`` (seeds, objective, the fit's curve, held-out error) and
the curve ``<scene>_g<n>.png``; ``benchmarks/coarse_ladder.py rung1-fit``
writes them. A fit's ``params`` are keys of
:data:`hybridmpm.mpm.params.CALIBRATION_BOUNDS` (dotted paths into the solver
parameters) with their fitted values.
"""

from __future__ import annotations

import json
from importlib import resources
from typing import Any

from hybridmpm.errors import InvalidInputError


def fit_name(scene: str, n_grid: int) -> str:
    """The file stem of ``scene``'s fit on an ``n_grid`` grid: ``<scene>_g<n>``."""
    return f"{scene}_g{int(n_grid)}"


def shipped_calibrations() -> list[str]:
    """The stems (``<scene>_g<n>``) of the shipped fits, sorted."""
    root = resources.files(__name__)
    return sorted(p.name[: -len(".json")] for p in root.iterdir() if p.name.endswith(".json"))


def calibration(scene: str, n_grid: int, base_n_grid: int, particles_per_cell: int | float) -> dict[str, Any]:
    """The shipped fit of registered scene ``scene`` (made for a
    ``base_n_grid`` grid) on an ``n_grid`` grid at ``particles_per_cell``
    particles per cell per axis: its JSON as a dict (``params`` the fitted
    values, ``defaults`` the values it replaces, ``bounds``, ``fit_seeds``,
    ``held_out``, ...). Raises :class:`InvalidInputError` (field
    ``calibrated``, the message naming ``--calibrated``) where no fit exists
    for that scene, grid and lattice: no silent fallback to the defaults."""
    name = fit_name(scene, n_grid)
    shipped = shipped_calibrations()
    path = resources.files(__name__).joinpath(name + ".json")
    if name not in shipped:
        where = ", ".join(shipped) or "none"
        raise InvalidInputError(
            f"calibrated: no calibrated coarse material for {scene} on a {int(n_grid)} grid (--calibrated has fits for: {where}); drop --calibrated",
            "calibrated",
        )
    fit = json.loads(path.read_text())
    if int(fit["base_n_grid"]) != int(base_n_grid) or float(fit["particles_per_cell"]) != float(particles_per_cell):
        raise InvalidInputError(
            f"calibrated: the --calibrated fit {name} was made for a scene on a {fit['base_n_grid']} grid at {fit['particles_per_cell']} particles per "
            f"cell per axis, not {int(base_n_grid)} at {particles_per_cell:g}; drop --calibrated",
            "calibrated",
        )
    return dict(fit)


__all__ = ["calibration", "fit_name", "shipped_calibrations"]
