"""The paper's domains as seeded generators of random initial conditions.

Each generator maps a seed to a :class:`~hybridmpm.scenes.spec.SceneSpec`
in the spirit of GNS (Sanchez-Gonzalez et al. 2020): 1–3 blocks of random size
and position with random initial velocities and, where the domain has them,
obstacles (ramps) placed at random. Grids, particle budgets and rollout
lengths follow the paper's Table "Datasets" (App. B): 128² in 2D and 64³ in
3D, at most ~4k particles (3.3k with ramps), ``T`` frames of 2.5 ms:

=============== ====== ===== =========================================
domain          N_h    T     contents
=============== ====== ===== =========================================
water2d         4096   1000  1–3 water blocks
sand2d          4096   320   1–3 sand blocks, rough floor (μ = tan φ)
water_ramps2d   3300   600   1–3 water blocks above 1–3 ramps
sand_ramps2d    3300   400   1–3 sand blocks above 1–3 rough ramps
water_sand2d    4096   500   2–3 blocks, water and sand
water_columns2d 4608   400   1–2 water columns at rest, released (ours, not the paper's)
water3d         4096   800   1–3 water blocks
sand3d          4096   350   1–3 sand blocks
dam_break2d     —      300   Martin & Moyce (1952) column (deterministic)
dam_break3d     —      300   its 3D twin across the box (ours, deterministic)
paddle3d        —      300   dam_break3d with a paddle the surge hits (ours, deterministic)
=============== ====== ===== =========================================

and the scenes that show each solid with water
(:mod:`hybridmpm.scenes.material_scenes`: ``jelly_dam_break2d``,
``jelly_dam_break3d``, ``snowball2d``, ``mud_slump2d``) and the tanks of
rigid bodies (:mod:`hybridmpm.scenes.body_scenes`: ``crates2d``, ``crates3d``).
"""

from __future__ import annotations

import math
import zlib
from collections.abc import Callable
from typing import Any

import numpy as np

from hybridmpm.errors import InvalidInputError
from hybridmpm.limits import check_seed
from hybridmpm.mpm import Box, MpmParams, SandParams, WallParams
from hybridmpm.scenes.body_scenes import BODY_SCENE_DOMAINS, BODY_SCENE_FRAMES
from hybridmpm.scenes.core import Scene, wall_face
from hybridmpm.scenes.material_scenes import SOLID_SCENE_DOMAINS, SOLID_SCENE_FRAMES
from hybridmpm.scenes.spec import Block, SceneSpec, collider_sdf

#: Paper T (frames per trajectory) per domain, Table "Datasets".
PAPER_FRAMES = {
    "water2d": 1000,
    "sand2d": 320,
    "water_ramps2d": 600,
    "sand_ramps2d": 400,
    "water_sand2d": 500,
    "water3d": 800,
    "sand3d": 350,
    "dam_break2d": 300,
    # not in the paper: training data for column collapses, about 1 s
    "water_columns2d": 400,
    # not in the paper: the page's 3D scene, 0.75 s (the surge reaches the far wall at about 0.4 s)
    "dam_break3d": 300,
    # not in the paper: the page's default 3D scene, the same 0.75 s (the surge reaches the paddle at about 0.16 s)
    "paddle3d": 300,
    # not in the paper: each solid with water (hybridmpm.scenes.material_scenes)
    **SOLID_SCENE_FRAMES,
    # not in the paper: rigid bodies in a tank (hybridmpm.scenes.body_scenes)
    **BODY_SCENE_FRAMES,
}

#: Base of the dam-break column [grid cells] (Martin & Moyce's ``a``; height ``2a``).
DAM_BREAK_A_CELLS = 24
#: Columns of ``water_columns2d`` within this many cells of the dam break's base
#: and twice that of its height are redrawn: the dam break stays a held-out scene.
DAM_BREAK_HOLDOUT_CELLS = 3

#: Largest initial velocity component of a random block [m/s].
MAX_SPEED = 1.0


def _rng(name: str, seed: int) -> np.random.Generator:
    """Per-domain stream: the same seed gives unrelated layouts in different domains. Raises
    :class:`InvalidInputError` (``seed``) for a seed outside [0, 2^63)."""
    return np.random.default_rng([check_seed(seed), zlib.crc32(name.encode())])


def _params(dim: int, n_grid: int, rough: bool, friction_angle_deg: float = 30.0) -> MpmParams:
    mu = math.tan(math.radians(friction_angle_deg)) if rough else 0.0
    return MpmParams(dim=dim, n_grid=n_grid, sand=SandParams(friction_angle_deg=friction_angle_deg), walls=WallParams(friction=mu))


def _random_blocks(
    rng: np.random.Generator,
    params: MpmParams,
    materials: list[str],
    size_cells: tuple[int, int],
    max_particles: int,
    ppc: int = 2,
    y_min: float = 0.0,
) -> list[Block]:
    """Draw ``len(materials)`` non-overlapping blocks (1-cell gap) within the
    particle budget; shrinks the draw on repeated failure. Deterministic in ``rng``."""
    dim = params.dim
    n = params.resolved_n_grid()
    dx = 1.0 / n
    margin = (params.walls.cells + 2) * dx
    for attempt in range(400):
        hi_cells = size_cells[1] if attempt < 200 else max(size_cells[0], size_cells[1] // 2)
        blocks: list[Block] = []
        boxes: list[tuple[np.ndarray, np.ndarray]] = []
        total = 0
        ok = True
        for mat in materials:
            size = rng.integers(size_cells[0], hi_cells + 1, size=dim) * dx
            lo_min = np.full(dim, margin)
            lo_min[1] = max(margin, y_min)
            lo_max = 1.0 - margin - size
            if np.any(lo_max <= lo_min):
                ok = False
                break
            lo = np.round(rng.uniform(lo_min, lo_max) / dx) * dx  # cell-aligned corners
            hi = lo + size
            count = int(np.prod(np.round(size / dx).astype(int) * ppc))
            if total + count > max_particles or any(np.all((lo < bhi + dx) & (hi > blo - dx)) for blo, bhi in boxes):
                ok = False
                break
            total += count
            boxes.append((lo, hi))
            vel = rng.uniform(-MAX_SPEED, MAX_SPEED, size=dim)
            blocks.append(Block(mat, [float(v) for v in lo], [float(v) for v in hi], [float(v) for v in vel]))
        if ok:
            return blocks
    raise InvalidInputError("blocks: could not place the blocks within the particle budget", "blocks")


def _random_ramps(rng: np.random.Generator, params: MpmParams, count: int, friction: float) -> list[Box]:
    """1–3 thin rotated boxes (2 cells thick, 0.16–0.4 m long, 10–40° either way)
    in the lower part of the domain, apart from each other by ≥ 4 cells,
    without the particle projection (``project=False``, as their models and
    datasets were made)."""
    dx = 1.0 / params.resolved_n_grid()
    ramps: list[Box] = []
    for _ in range(400):
        if len(ramps) == count:
            break
        half_len = rng.uniform(0.08, 0.2)
        angle = float(rng.uniform(10.0, 40.0) * rng.choice([-1.0, 1.0]))
        center = [float(rng.uniform(0.2, 0.8)), float(rng.uniform(0.12, 0.55))]
        # project=False: the shipped models and datasets of the ramps scenes were
        # made without the particle projection; on, their bits would change
        box = Box(center=center, half_extents=[float(half_len), 1.0 * dx], angle_deg=angle, friction=friction, project=False)
        # keep the ramp inside the domain's free region and away from other ramps
        ends = np.array(center) + half_len * np.array([[math.cos(math.radians(angle)), math.sin(math.radians(angle))]]) * np.array([[1.0], [-1.0]])
        lim = (params.walls.cells + 2) * dx
        if np.any(ends < lim) or np.any(ends > 1.0 - lim):
            continue
        probe = np.array(center) + np.linspace(-1.0, 1.0, 33)[:, None] * (ends[0] - np.array(center))
        if any(collider_sdf(r, probe).min() < 4 * dx for r in ramps):
            continue
        ramps.append(box)
    if len(ramps) < count:
        raise InvalidInputError("obstacles: could not place the ramps", "obstacles")
    return ramps


#: Obstacle clearance of the ramp domains [grid cells]: their blocks may reach
#: into a ramp, and the particles within half a cell of it have always been
#: dropped; kept so that every seed gives the initial condition it always gave.
RAMP_CLEARANCE_CELLS = 0.5


def _spec(name: str, seed: int, params: MpmParams, blocks: list[Block], frames: int | None, clearance_cells: float = 0.0, **info: Any) -> SceneSpec:
    return SceneSpec(
        name,
        params,
        blocks,
        frames=frames if frames is not None else PAPER_FRAMES[name],
        info={"seed": int(seed), **info},
        obstacle_clearance_cells=clearance_cells,
        registered=True,
    )


def water2d(seed: int = 0, frames: int | None = None, n_grid: int = 128, max_particles: int = 4096) -> SceneSpec:
    """1–3 water blocks (8–40 cells a side) with random velocities (|v_d| ≤ 1 m/s)."""
    rng = _rng("water2d", seed)
    params = _params(2, n_grid, rough=False)
    k = int(rng.integers(1, 4))
    return _spec("water2d", seed, params, _random_blocks(rng, params, ["water"] * k, (8, 40), max_particles), frames)


def sand2d(seed: int = 0, frames: int | None = None, n_grid: int = 128, max_particles: int = 4096, friction_angle_deg: float = 30.0) -> SceneSpec:
    """1–3 sand blocks (8–40 cells) with random velocities on a rough floor
    (Coulomb μ = tan φ: on a frictionless floor a sand pile spreads like a fluid)."""
    rng = _rng("sand2d", seed)
    params = _params(2, n_grid, rough=True, friction_angle_deg=friction_angle_deg)
    k = int(rng.integers(1, 4))
    return _spec("sand2d", seed, params, _random_blocks(rng, params, ["sand"] * k, (8, 40), max_particles), frames)


def _ramps_scene(name: str, material: str, seed: int, frames: int | None, n_grid: int, max_particles: int) -> SceneSpec:
    """1–3 blocks of ``material`` above y = 0.6 m falling onto 1–3 ramps
    (frictionless for water, μ = tan φ for sand, like the floor)."""
    rng = _rng(name, seed)
    params = _params(2, n_grid, rough=material == "sand")
    params.colliders = list(_random_ramps(rng, params, int(rng.integers(1, 4)), friction=params.walls.friction))
    k = int(rng.integers(1, 4))
    blocks = _random_blocks(rng, params, [material] * k, (8, 36), max_particles, y_min=0.6)
    return _spec(name, seed, params, blocks, frames, clearance_cells=RAMP_CLEARANCE_CELLS)


def water_ramps2d(seed: int = 0, frames: int | None = None, n_grid: int = 128, max_particles: int = 3300) -> SceneSpec:
    """1–3 water blocks in the upper part falling onto 1–3 frictionless ramps."""
    return _ramps_scene("water_ramps2d", "water", seed, frames, n_grid, max_particles)


def sand_ramps2d(seed: int = 0, frames: int | None = None, n_grid: int = 128, max_particles: int = 3300) -> SceneSpec:
    """1–3 sand blocks in the upper part falling onto 1–3 rough ramps (μ = tan φ)."""
    return _ramps_scene("sand_ramps2d", "sand", seed, frames, n_grid, max_particles)


def water_sand2d(seed: int = 0, frames: int | None = None, n_grid: int = 128, max_particles: int = 4096) -> SceneSpec:
    """2–3 blocks: one water, one sand, a third of either; rough floor."""
    rng = _rng("water_sand2d", seed)
    params = _params(2, n_grid, rough=True)
    mats = ["water", "sand"] + ([str(rng.choice(["water", "sand"]))] if rng.integers(2, 4) == 3 else [])
    return _spec("water_sand2d", seed, params, _random_blocks(rng, params, mats, (8, 32), max_particles), frames)


def water_columns2d(seed: int = 0, frames: int | None = None, n_grid: int = 128, max_particles: int = 4608) -> SceneSpec:
    """1–2 water columns at hydrostatic rest on the floor, released at t = 0:
    column collapses of random base (8–36 cells) and height (0.75–3 × the base,
    at most 96 cells), the first against the left or the right wall, a second
    (half the seeds) against the other wall or standing free, 4+ cells apart.

    Not one of the paper's domains: training data for the pressure-driven
    collapse of a column at rest, which the thrown blocks of ``water2d`` rarely
    show. The dam break stays held out: a column whose base is within
    :data:`DAM_BREAK_HOLDOUT_CELLS` cells of :data:`DAM_BREAK_A_CELLS` and whose
    height is within twice that of ``2a`` is redrawn, whatever its wall.
    """
    rng = _rng("water_columns2d", seed)
    params = _params(2, n_grid, rough=False)
    n = params.resolved_n_grid()
    dx = 1.0 / n
    wall = wall_face(params)
    top = 1.0 - wall
    k = int(rng.integers(1, 3))
    a0, h0, tol = DAM_BREAK_A_CELLS, 2 * DAM_BREAK_A_CELLS, DAM_BREAK_HOLDOUT_CELLS
    for _ in range(400):
        sizes = []
        for _ in range(k):
            a = int(rng.integers(8, 37))
            h = int(rng.integers(max(8, (3 * a) // 4), min(3 * a, 96) + 1))
            sizes.append((a, h))
        if any(abs(a - a0) <= tol and abs(h - h0) <= 2 * tol for a, h in sizes):
            continue
        if sum(a * h * 4 for a, h in sizes) > max_particles:
            continue
        left = bool(rng.integers(0, 2))
        a1 = sizes[0][0] * dx
        spans = [(wall, wall + a1) if left else (top - a1, top)]
        if k == 2:
            a2 = sizes[1][0] * dx
            if rng.integers(0, 2):  # against the other wall
                spans.append((top - a2, top) if left else (wall, wall + a2))
            else:  # free-standing, cell-aligned, 4+ cells from the first column and the walls
                lo_min, lo_max = (spans[0][1] + 4 * dx, top - 4 * dx - a2) if left else (wall + 4 * dx, spans[0][0] - 4 * dx - a2)
                if lo_max < lo_min:
                    continue
                x0 = wall + round((rng.uniform(lo_min, lo_max) - wall) / dx) * dx
                spans.append((x0, x0 + a2))
            (_, first_hi), (second_lo, _) = sorted(spans)
            if second_lo < first_hi + 4 * dx:
                continue
        blocks = [Block("water", [float(lo), wall], [float(hi), wall + hc * dx], hydrostatic=True) for (lo, hi), (_, hc) in zip(spans, sizes)]
        return _spec("water_columns2d", seed, params, blocks, frames)
    raise InvalidInputError("blocks: could not place the columns within the particle budget", "blocks")


def water3d(seed: int = 0, frames: int | None = None, n_grid: int = 64, max_particles: int = 4096) -> SceneSpec:
    """1–3 water blocks (4–12 cells a side, 8 particles per cell) in a 64³ box."""
    rng = _rng("water3d", seed)
    params = _params(3, n_grid, rough=False)
    k = int(rng.integers(1, 4))
    return _spec("water3d", seed, params, _random_blocks(rng, params, ["water"] * k, (4, 12), max_particles), frames)


def sand3d(seed: int = 0, frames: int | None = None, n_grid: int = 64, max_particles: int = 4096) -> SceneSpec:
    """1–3 sand blocks (4–12 cells a side) in a 64³ box, rough floor."""
    rng = _rng("sand3d", seed)
    params = _params(3, n_grid, rough=True)
    k = int(rng.integers(1, 4))
    return _spec("sand3d", seed, params, _random_blocks(rng, params, ["sand"] * k, (4, 12), max_particles), frames)


def dam_break2d_spec(seed: int = 0, frames: int | None = None, n_grid: int = 128, a_cells: int = DAM_BREAK_A_CELLS) -> SceneSpec:
    """Martin & Moyce (1952) water column: base ``a``, height ``2a``, against the
    left wall, at hydrostatic rest, released at t = 0 (``a = a_cells·dx``, at
    least 24 cells). ``seed`` is unused (the scene is deterministic).

    ``info`` holds ``a`` [m], ``x_wall`` and ``y_floor`` [m] (the wall faces
    the fluid rests against, see :func:`~hybridmpm.scenes.wall_face`: the
    origin of the experiment's x and h) and the lattice ``spacing``.
    """
    if a_cells < 24:
        raise InvalidInputError(f"a_cells: must be >= 24 grid cells, got {a_cells}", "a_cells")
    params = MpmParams(dim=2, n_grid=n_grid)
    dx = 1.0 / n_grid
    wall = wall_face(params)
    a = a_cells * dx
    if wall + 4.2 * a > 1.0 - wall:
        raise InvalidInputError(f"a_cells: the surge would leave the domain; use a_cells <= {int((1 - 2 * params.walls.cells * dx) / 4.2 / dx)}", "a_cells")
    block = Block("water", [wall, wall], [wall + a, wall + 2 * a], hydrostatic=True)
    return _spec("dam_break2d", seed, params, [block], frames, a=a, x_wall=wall, y_floor=wall, spacing=dx / 2)


#: Grid of ``dam_break3d`` [cells per side] and its column's base ``a`` [cells]: the
#: largest column that fits the surge (``4.2a``) on the grid chosen for speed
#: (docs/page.md "The default 3D scene": ms per frame per grid).
DAM_BREAK3D_N_GRID = 34
DAM_BREAK3D_A_CELLS = 7


def dam_break3d_spec(seed: int = 0, frames: int | None = None, n_grid: int = DAM_BREAK3D_N_GRID, a_cells: int = DAM_BREAK3D_A_CELLS) -> SceneSpec:
    """Martin & Moyce's water column in 3D: base ``a = a_cells·dx`` along x,
    height ``2a``, spanning the box across z (wall to wall, as the
    experiment's column spanned its channel), against the x- wall, at
    hydrostatic rest, released at t = 0. The walls are frictionless, so every
    x–y slice collapses as the 2D dam break does (it meets Martin & Moyce's
    tolerances as the 2D scene does: tests/test_scenes.py). Default: a 34³
    grid, ``a`` = 7 cells = 0.206 m, 2 particles per cell per axis (spacing
    dx/2): 14 × 28 × 60 = 23,520 particles. The grid is the finest at which
    MPM advances it at about 100 frames/s on 2 cores (11 ms per frame; 17 ms
    on one thread, as a service session runs it: docs/page.md). ``seed`` is
    unused (the scene is deterministic).

    ``info`` holds ``a`` [m], ``x_wall``, ``y_floor`` and ``z_walls`` [m]
    (the wall faces the water rests against, :func:`~hybridmpm.scenes.wall_face`)
    and the lattice ``spacing`` [m].
    """
    params = MpmParams(dim=3, n_grid=n_grid)
    dx = 1.0 / n_grid
    wall = wall_face(params)
    if a_cells < 4:
        raise InvalidInputError(f"a_cells: must be >= 4 grid cells, got {a_cells}", "a_cells")
    a = a_cells * dx
    if wall + 4.2 * a > 1.0 - wall:
        raise InvalidInputError(f"a_cells: the surge would leave the domain; use a_cells <= {int((1 - 2 * wall) / 4.2 / dx)}", "a_cells")
    block = Block("water", [wall, wall, wall], [wall + a, wall + 2 * a, 1.0 - wall], hydrostatic=True)
    return _spec("dam_break3d", seed, params, [block], frames, a=a, x_wall=wall, y_floor=wall, z_walls=[wall, 1.0 - wall], spacing=dx / 2)


def paddle3d_spec(seed: int = 0, frames: int | None = None, n_grid: int = DAM_BREAK3D_N_GRID, a_cells: int = DAM_BREAK3D_A_CELLS) -> SceneSpec:
    """:func:`dam_break3d_spec`'s water column (the same grid, particles,
    hydrostatic release and frictionless walls) with one box obstacle
    downstream of it: a paddle standing on the floor, 2 cells thick in x, as
    tall as the column (``2a``) and ``2a`` wide across z, centred in z, its
    upstream face ``2a`` from the x- wall (``a`` clear of the column's face).
    The surge hits it about 0.16 s after the release and flows round both
    sides of it (and, in the page, a person drags it through the water:
    docs/page.md). The paddle is frictionless and ``separate`` like the
    walls, with the particle projection on. Default (34³ grid, ``a`` = 7
    cells = 0.206 m): the paddle is 0.059 × 0.412 × 0.412 m, centred at
    (0.5, 0.265, 0.5) m; 23,520 water particles and 1,784 boundary
    particles (GNS type 3) on it. ``seed`` is unused (the scene is
    deterministic).

    ``info`` holds :func:`dam_break3d_spec`'s (``a``, ``x_wall``,
    ``y_floor``, ``z_walls``, ``spacing``, all [m]). Raises
    :class:`InvalidInputError` naming ``a_cells`` as :func:`dam_break3d_spec`
    does (the paddle fits wherever the column's surge does: ``2a + 2dx < 4.2a``).
    """
    column = dam_break3d_spec(seed=seed, n_grid=n_grid, a_cells=a_cells)
    params, info = column.params, dict(column.info)
    dx = 1.0 / n_grid
    wall, a = info["x_wall"], info["a"]
    params.colliders = [Box(center=[wall + 2 * a + dx, wall + a, 0.5], half_extents=[dx, a, a], friction=params.walls.friction)]
    return _spec("paddle3d", seed, params, column.blocks, frames, **{k: v for k, v in info.items() if k != "seed"})


#: Registered domains: name → seeded spec generator ``f(seed, frames=None, **kw) -> SceneSpec``.
DOMAINS: dict[str, Callable[..., SceneSpec]] = {
    "water2d": water2d,
    "sand2d": sand2d,
    "water_ramps2d": water_ramps2d,
    "sand_ramps2d": sand_ramps2d,
    "water_sand2d": water_sand2d,
    "water_columns2d": water_columns2d,
    "water3d": water3d,
    "sand3d": sand3d,
    "dam_break2d": dam_break2d_spec,
    "dam_break3d": dam_break3d_spec,
    "paddle3d": paddle3d_spec,
    **SOLID_SCENE_DOMAINS,
    **BODY_SCENE_DOMAINS,
}


def scene_spec(
    name: str, seed: int = 0, frames: int | None = None, *, n_grid: int | None = None, particles_per_cell: int | None = None, **kwargs: Any
) -> SceneSpec:
    """The spec of a registered domain for ``seed``; with ``n_grid`` and/or
    ``particles_per_cell``, the same initial condition on another grid of the
    same domain (:meth:`SceneSpec.on_grid`). Raises :class:`InvalidInputError`
    for an unknown name (the message lists the available ones) or a grid too
    coarse for the scene (naming the field), ``seed`` outside [0, 2^63)."""
    if name not in DOMAINS:
        raise InvalidInputError(f"scene: unknown scene {name!r} (available: {', '.join(sorted(DOMAINS))})", "scene")
    check_seed(seed)
    if frames is not None and (not isinstance(frames, int) or frames < 1):
        raise InvalidInputError(f"frames: must be an integer >= 1, got {frames!r}", "frames")
    spec = DOMAINS[name](seed=seed, frames=frames, **kwargs)
    return _regrid(spec, n_grid, particles_per_cell)


def registered_name(scene: Scene | SceneSpec | str) -> str | None:
    """The name of the registered scene (:data:`DOMAINS`) that ``scene`` is, else None.

    A name is one when :data:`DOMAINS` holds it (a path to a scene file is not); a
    :class:`Scene` or :class:`SceneSpec` when the registry made it (:func:`scene_spec`,
    :func:`make_scene` by name: ``SceneSpec.registered``) and its name is registered. A scene
    file, a spec of your own or one moved to another grid is none, whatever its ``name``: what
    belongs to a registered scene (its shipped default configuration) is looked up by this."""
    if isinstance(scene, str):
        return scene if scene in DOMAINS else None
    spec = scene.spec if isinstance(scene, Scene) else scene
    if isinstance(spec, SceneSpec) and spec.registered and spec.name == scene.name and scene.name in DOMAINS:
        return scene.name
    return None


def _regrid(spec: SceneSpec, n_grid: int | None, particles_per_cell: int | None) -> SceneSpec:
    if n_grid is None and particles_per_cell is None:
        return spec
    return spec.on_grid(spec.params.resolved_n_grid() if n_grid is None else n_grid, particles_per_cell)


def make_scene(
    name: str, seed: int = 0, frames: int | None = None, *, n_grid: int | None = None, particles_per_cell: int | None = None, **kwargs: Any
) -> Scene:
    """Build a registered scene by name (see :data:`DOMAINS`), or load a scene
    file if ``name`` ends in ``.toml`` or ``.json``; ``n_grid`` and
    ``particles_per_cell`` put it on another grid of the same domain (the
    same blocks, obstacles and wall faces: :meth:`SceneSpec.on_grid`).
    Raises :class:`InvalidInputError`."""
    if name.endswith((".toml", ".json")):
        spec = SceneSpec.load(name)
        if frames is not None:
            spec.frames = frames
        return _regrid(spec, n_grid, particles_per_cell).build()
    return scene_spec(name, seed=seed, frames=frames, n_grid=n_grid, particles_per_cell=particles_per_cell, **kwargs).build()


def dam_break2d(seed: int = 0, n_grid: int = 128, a_cells: int = DAM_BREAK_A_CELLS) -> Scene:
    """The dam-break scene (see :func:`dam_break2d_spec`)."""
    return dam_break2d_spec(seed=seed, n_grid=n_grid, a_cells=a_cells).build()
