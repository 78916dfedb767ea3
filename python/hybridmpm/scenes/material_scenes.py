"""Registered scenes that show each solid with water (docs/materials.md "Scenes").

Seeded like the paper's domains: seed 0 is the layout the docs draw; another
seed moves and resizes the solid by a few cells and changes its speed a
little (a family of related initial conditions, not one picture). No shipped
default configuration exists for them (``defaults.json``), so the CLI and the
service run them with MPM; the learned simulators refuse them, naming the
material (:func:`hybridmpm.materials.refuse_untrained`).

================== ====== ===== ===============================================
scene              grid   T     contents
================== ====== ===== ===============================================
jelly_dam_break2d  128²   300   the dam break's column; a jelly cube falls into its surge
jelly_dam_break3d  34³    300   the 3D dam break's column; a jelly cube falls into its surge
snowball2d         128²   240   a square of snow thrown at the right wall above a pool
mud_slump2d        128²   400   a mud column slumps into a shallow pool of water
================== ====== ===== ===============================================
"""

from __future__ import annotations

from typing import Any

import numpy as np

from hybridmpm.limits import check_seed
from hybridmpm.mpm import MpmParams, WallParams
from hybridmpm.scenes.core import wall_face
from hybridmpm.scenes.spec import Block, SceneSpec

#: Frames per scene (2.5 ms each).
SOLID_SCENE_FRAMES = {"jelly_dam_break2d": 300, "jelly_dam_break3d": 300, "snowball2d": 240, "mud_slump2d": 400}

#: Throwing speed of ``snowball2d``'s snow toward the wall [m/s] (seed 0).
SNOWBALL_SPEED = 4.0


def _rng(name: str, seed: int) -> np.random.Generator:
    """Per-scene stream; :class:`~hybridmpm.errors.InvalidInputError` (``seed``) for a seed outside [0, 2^63)."""
    import zlib

    return np.random.default_rng([check_seed(seed), zlib.crc32(name.encode())])


def _jitter(rng: np.random.Generator, seed: int, cells: int) -> int:
    """A shift of at most ``cells`` grid cells (0 for seed 0, the canonical layout)."""
    return 0 if int(seed) == 0 else int(rng.integers(-cells, cells + 1))


def _spec(name: str, seed: int, params: MpmParams, blocks: list[Block], frames: int | None, **info: Any) -> SceneSpec:
    return SceneSpec(name, params, blocks, frames=frames if frames is not None else SOLID_SCENE_FRAMES[name], info={"seed": int(seed), **info}, registered=True)


def jelly_dam_break2d(seed: int = 0, frames: int | None = None, n_grid: int = 128) -> SceneSpec:
    """The dam break (:func:`~hybridmpm.scenes.registry.dam_break2d_spec`'s
    column of base ``a`` = 24 cells and height ``2a`` at hydrostatic rest
    against the left wall) with a jelly cube (preset ``jello``: E = 20 kPa,
    ν = 0.45, ρ = 1050 kg/m³) of 16 cells a side held at rest 0.45 m above
    the floor, its centre 0.55 m from the left wall: it lands in the surge
    about 0.3 s later and rides it, wobbling, to the far wall."""
    rng = _rng("jelly_dam_break2d", seed)
    params = MpmParams(dim=2, n_grid=n_grid)
    dx = 1.0 / n_grid
    wall = wall_face(params)
    a = 24 * dx
    side = (16 + _jitter(rng, seed, 3)) * dx
    x0 = 0.55 - side / 2 + _jitter(rng, seed, 6) * dx
    y0 = wall + 0.45 + _jitter(rng, seed, 4) * dx
    water = Block("water", [wall, wall], [wall + a, wall + 2 * a], hydrostatic=True)
    jelly = Block("jello", [x0, y0], [x0 + side, y0 + side])
    return _spec("jelly_dam_break2d", seed, params, [water, jelly], frames, a=a, x_wall=wall, y_floor=wall)


def jelly_dam_break3d(seed: int = 0, frames: int | None = None, n_grid: int = 34) -> SceneSpec:
    """The 3D dam break (:func:`~hybridmpm.scenes.registry.dam_break3d_spec`:
    the column of base ``a`` = 7 cells across the box on a 34³ grid) with a
    jelly cube (``jello``) of 6 cells a side, centred in z, 0.35 m above the
    floor, its centre 0.55 m from the x- wall."""
    rng = _rng("jelly_dam_break3d", seed)
    params = MpmParams(dim=3, n_grid=n_grid)
    dx = 1.0 / n_grid
    wall = wall_face(params)
    a = 7 * dx
    side = (6 + _jitter(rng, seed, 1)) * dx
    x0 = 0.55 - side / 2 + _jitter(rng, seed, 2) * dx
    y0 = wall + 0.35 + _jitter(rng, seed, 2) * dx
    z0 = 0.5 - side / 2 + _jitter(rng, seed, 2) * dx
    water = Block("water", [wall, wall, wall], [wall + a, wall + 2 * a, 1.0 - wall], hydrostatic=True)
    jelly = Block("jello", [x0, y0, z0], [x0 + side, y0 + side, z0 + side])
    return _spec("jelly_dam_break3d", seed, params, [water, jelly], frames, a=a, x_wall=wall, y_floor=wall)


def snowball2d(seed: int = 0, frames: int | None = None, n_grid: int = 128) -> SceneSpec:
    """A square of snow (preset ``snow``: Stomakhin et al. 2013's parameters,
    ρ = 400 kg/m³; scene blocks are boxes, so the "ball" is 14 cells square)
    thrown at :data:`SNOWBALL_SPEED` m/s toward the right wall, 0.45 m above a
    pool of water 12 cells deep across the floor. It hits the wall about
    0.1 s later, keeps a dent (snow's plastic compaction) and falls into the
    pool. Walls with friction (μ = 0.3) so the snow sticks a moment."""
    rng = _rng("snowball2d", seed)
    params = MpmParams(dim=2, n_grid=n_grid, walls=WallParams(friction=0.3))
    dx = 1.0 / n_grid
    wall = wall_face(params)
    side = (14 + _jitter(rng, seed, 2)) * dx
    x0 = 0.5 + _jitter(rng, seed, 6) * dx
    y0 = wall + 0.45 + _jitter(rng, seed, 6) * dx
    speed = SNOWBALL_SPEED * (1.0 if int(seed) == 0 else float(rng.uniform(0.8, 1.2)))
    pool = Block("water", [wall, wall], [1.0 - wall, wall + 12 * dx], hydrostatic=True)
    snow = Block("snow", [x0, y0], [x0 + side, y0 + side], velocity=[speed, 0.0])
    return _spec("snowball2d", seed, params, [pool, snow], frames, x_wall=1.0 - wall, y_floor=wall)


def mud_slump2d(seed: int = 0, frames: int | None = None, n_grid: int = 128) -> SceneSpec:
    """A mud column (preset ``mud``: Bingham, τ_y = 100 Pa, η = 10 Pa·s,
    ρ = 1800 kg/m³) 20 cells wide and 40 tall against the left wall, released
    at rest beside a pool of water 8 cells deep filling the rest of the floor
    (one cell apart). The mud slumps until its stress falls under the yield
    stress (it stops; the water keeps flowing) and the pool rises against it.
    No-slip floor for the mud's stopping shape (wall friction μ = 1)."""
    rng = _rng("mud_slump2d", seed)
    params = MpmParams(dim=2, n_grid=n_grid, walls=WallParams(friction=1.0))
    dx = 1.0 / n_grid
    wall = wall_face(params)
    w = (20 + _jitter(rng, seed, 3)) * dx
    h = (40 + _jitter(rng, seed, 6)) * dx
    mud = Block("mud", [wall, wall], [wall + w, wall + h])
    pool = Block("water", [wall + w + dx, wall], [1.0 - wall, wall + 8 * dx], hydrostatic=True)
    return _spec("mud_slump2d", seed, params, [mud, pool], frames, x_wall=wall, y_floor=wall, width=w, height=h)


#: The scenes of this module: name → seeded spec generator.
SOLID_SCENE_DOMAINS = {
    "jelly_dam_break2d": jelly_dam_break2d,
    "jelly_dam_break3d": jelly_dam_break3d,
    "snowball2d": snowball2d,
    "mud_slump2d": mud_slump2d,
}

__all__ = ["SOLID_SCENE_DOMAINS", "SOLID_SCENE_FRAMES", "SNOWBALL_SPEED", "jelly_dam_break2d", "jelly_dam_break3d", "mud_slump2d", "snowball2d"]
