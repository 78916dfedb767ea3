"""Registered scenes with rigid bodies in a water tank (docs/bodies.md "Scenes").

Seeded like the material scenes: seed 0 is the layout the docs draw; another
seed shifts each body by a few cells and tilts it a little. No shipped default
configuration exists for them (``defaults.json``), so the CLI and the service
run them with MPM; the learned simulators refuse them, naming ``bodies``
(:func:`hybridmpm.mpm.bodies.refuse_bodies`).

========== ====== ===== ================================================================
scene      grid   T     contents
========== ====== ===== ================================================================
crates2d   128²   400   a tank 0.4 m deep; boxes of 250, 500, 750 kg/m³ float, 2000 sinks
crates3d   32³    240   a tank 0.25 m deep; a cube of 500 kg/m³ floats, a ball of 2000 sinks
========== ====== ===== ================================================================
"""

from __future__ import annotations

import zlib
from typing import Any

import numpy as np

from hybridmpm.limits import check_seed
from hybridmpm.mpm import MpmParams
from hybridmpm.mpm.bodies import Body
from hybridmpm.scenes.core import wall_face
from hybridmpm.scenes.spec import Block, SceneSpec

#: Frames per scene (2.5 ms each).
BODY_SCENE_FRAMES = {"crates2d": 400, "crates3d": 240}

#: Densities [kg/m³] of ``crates2d``'s boxes, left to right: three float, the last sinks.
CRATE_DENSITIES = (250.0, 500.0, 750.0, 2000.0)
#: Half extents [m] of ``crates2d``'s boxes (0.12 × 0.08 m).
CRATE_HALF = (0.06, 0.04)
#: Depth of ``crates2d``'s water [m].
CRATES2D_DEPTH = 0.4
#: Depth of ``crates3d``'s water [m].
CRATES3D_DEPTH = 0.25


def _rng(name: str, seed: int) -> np.random.Generator:
    """Per-scene stream; :class:`~hybridmpm.errors.InvalidInputError` (``seed``) for a seed outside [0, 2^63)."""
    return np.random.default_rng([check_seed(seed), zlib.crc32(name.encode())])


def _jitter(rng: np.random.Generator, seed: int, cells: int) -> int:
    """A shift of at most ``cells`` grid cells (0 for seed 0, the canonical layout)."""
    return 0 if int(seed) == 0 else int(rng.integers(-cells, cells + 1))


def _spec(name: str, seed: int, params: MpmParams, blocks: list[Block], frames: int | None, **info: Any) -> SceneSpec:
    return SceneSpec(name, params, blocks, frames=frames if frames is not None else BODY_SCENE_FRAMES[name], info={"seed": int(seed), **info}, registered=True)


def crates2d(seed: int = 0, frames: int | None = None, n_grid: int = 128) -> SceneSpec:
    """A tank of water :data:`CRATES2D_DEPTH` deep at hydrostatic rest, wall
    to wall, with four boxes of :data:`CRATE_HALF` (0.12 × 0.08 m) at
    x = 0.2, 0.4, 0.6, 0.8 m: boxes of 250, 500 and 750 kg/m³ released with
    their centre at the surface (each settles at its Archimedes draft,
    ρ_b/ρ_w of its height under the level), one of 2000 kg/m³ released half
    way down, which sinks to the floor. Another seed shifts each box by up
    to 4 cells in x and 2 in y and tilts it by up to 10°."""
    rng = _rng("crates2d", seed)
    params = MpmParams(dim=2, n_grid=n_grid)
    dx = 1.0 / n_grid
    wall = wall_face(params)
    level = wall + CRATES2D_DEPTH
    bodies = []
    for k, rho in enumerate(CRATE_DENSITIES):
        y = level if rho < 1000.0 else wall + CRATES2D_DEPTH / 2
        x = 0.2 + 0.2 * k + _jitter(rng, seed, 4) * dx
        y += _jitter(rng, seed, 2) * dx
        angle = 0.0 if int(seed) == 0 else float(rng.uniform(-10.0, 10.0))
        bodies.append(Body(shape="box", center=[x, y], half_extents=list(CRATE_HALF), angle_deg=angle, density=rho))
    params.bodies = bodies
    water = Block("water", [wall, wall], [1.0 - wall, level], hydrostatic=True)
    return _spec("crates2d", seed, params, [water], frames, x_wall=wall, y_floor=wall, level=level, densities=list(CRATE_DENSITIES))


def crates3d(seed: int = 0, frames: int | None = None, n_grid: int = 32) -> SceneSpec:
    """A small tank (32³ grid) of water :data:`CRATES3D_DEPTH` deep at
    hydrostatic rest, wall to wall, with a cube of 500 kg/m³ (0.14 m a side)
    released with its centre at the surface (x = 0.33 m) and a ball of
    2000 kg/m³ (radius 0.07 m) released just above it (x = 0.67 m), which
    sinks to the floor. Another seed shifts each body by up to 2 cells in x
    and z."""
    rng = _rng("crates3d", seed)
    params = MpmParams(dim=3, n_grid=n_grid)
    dx = 1.0 / n_grid
    wall = wall_face(params)
    level = wall + CRATES3D_DEPTH

    def at(x: float, y: float) -> list[float]:
        return [x + _jitter(rng, seed, 2) * dx, y, 0.5 + _jitter(rng, seed, 2) * dx]

    params.bodies = [
        Body(shape="box", center=at(0.33, level), half_extents=[0.07, 0.07, 0.07], density=500.0),
        Body(shape="sphere", center=at(0.67, level + 0.1), radius=0.07, density=2000.0),
    ]
    water = Block("water", [wall, wall, wall], [1.0 - wall, level, 1.0 - wall], hydrostatic=True)
    return _spec("crates3d", seed, params, [water], frames, x_wall=wall, y_floor=wall, level=level)


#: The scenes of this module: name → seeded spec generator.
BODY_SCENE_DOMAINS = {"crates2d": crates2d, "crates3d": crates3d}

__all__ = ["BODY_SCENE_DOMAINS", "BODY_SCENE_FRAMES", "CRATES2D_DEPTH", "CRATES3D_DEPTH", "CRATE_DENSITIES", "CRATE_HALF", "crates2d", "crates3d"]
