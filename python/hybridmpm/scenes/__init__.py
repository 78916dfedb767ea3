"""Built-in scenes: particle blocks + solver parameters.

This module holds the scenes the engine ships with (``dam_break2d``,
``sand2d``, ``water3d``); every builder takes a ``seed`` so random scenes are
reproducible. Particles sit on a lattice at spacing ``dx/2`` (2 particles per
cell per dimension), cell-centred, the usual MPM seeding.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, Callable

import numpy as np

from hybridmpm.errors import InvalidInputError
from hybridmpm.mpm import DT_FRAME, SAND, WATER, MpmParams, MpmSolver, SandParams, WallParams

#: GNS particle-type codes (DeepMind learning_to_simulate): kinematic
#: obstacles 3, water 5, sand 6.
GNS_TYPE = {WATER: 5, SAND: 6}
GNS_KINEMATIC = 3


@dataclass
class Scene:
    """A scene: parameters and initial particles.

    ``positions`` float32 [N, D] [m], ``material`` int32 [N], ``velocities``
    float32 [N, D] [m/s]; ``frames`` the default rollout length; ``info``
    scene-specific facts (e.g. the dam-break column size).
    """

    name: str
    params: MpmParams
    positions: np.ndarray
    material: np.ndarray
    velocities: np.ndarray
    dt_frame: float = DT_FRAME
    frames: int = 300
    info: dict[str, Any] = field(default_factory=dict)
    #: initial volume ratio J [N] (water at hydrostatic rest), or None for J = 1
    volume_ratio: np.ndarray | None = None

    @property
    def dim(self) -> int:
        return int(self.positions.shape[1])

    @property
    def num_particles(self) -> int:
        return int(self.positions.shape[0])

    def particle_type(self) -> np.ndarray:
        """GNS particle types [N] int64 (water 5, sand 6)."""
        return np.vectorize(GNS_TYPE.__getitem__, otypes=[np.int64])(self.material)

    def make_solver(self, num_threads: int | None = None) -> MpmSolver:
        """A fresh :class:`MpmSolver` holding this scene's particles."""
        params = self.params
        if num_threads is not None:
            params = MpmParams.from_dict({**params.to_dict(), "num_threads": int(num_threads)})
        sim = MpmSolver(params)
        sim.add_particles(self.positions, self.material, velocities=self.velocities)
        if self.volume_ratio is not None:
            sim.volume_ratio = self.volume_ratio
        return sim


def lattice(lo: np.ndarray | list[float], hi: np.ndarray | list[float], spacing: float) -> np.ndarray:
    """Cell-centred lattice points filling the box ``[lo, hi]`` at ``spacing``: float32 [N, D]."""
    lo_a = np.asarray(lo, dtype=np.float64)
    hi_a = np.asarray(hi, dtype=np.float64)
    counts = np.maximum(np.round((hi_a - lo_a) / spacing).astype(int), 1)
    axes = [lo_a[d] + (np.arange(counts[d]) + 0.5) * spacing for d in range(len(lo_a))]
    grid = np.meshgrid(*axes, indexing="ij")
    return np.stack([g.ravel() for g in grid], axis=1).astype(np.float32)


def wall_face(params: MpmParams) -> float:
    """Where fluid rests against the lower domain walls [m]: ``(cells − 1)·dx``.

    With a wall band of ``cells`` nodes whose velocity may not point outwards,
    particles come to rest about one cell inside the band; blocks placed
    against a wall start there so that they start at rest.
    """
    return (params.walls.cells - 1) / params.resolved_n_grid()


def hydrostatic_volume_ratio(positions: np.ndarray, surface: float, params: MpmParams) -> np.ndarray:
    """Volume ratio ``J = 1 − ρ·|g|·(surface − y)/K`` of water at hydrostatic rest
    (Cauchy pressure ``K(1 − J) = ρ|g|·depth``), float32 [N]. ``surface`` is the
    free-surface height [m]; ``y`` is the vertical (second) coordinate."""
    g = abs(params.to_dict()["gravity"][1])
    depth = np.clip(surface - positions[:, 1], 0.0, None)
    return np.clip(1.0 - params.water.density * g * depth / params.water.bulk_modulus, 0.5, 1.0).astype(np.float32)


def dam_break2d(seed: int = 0, n_grid: int = 128, a_cells: int = 24) -> Scene:
    """Martin & Moyce (1952) water column: base ``a``, height ``2a``, against the
    left wall, at hydrostatic rest, released at t = 0 (``a = a_cells·dx``, at
    least 24 cells).

    ``info`` holds ``a`` [m], ``x_wall`` and ``y_floor`` [m] (the wall faces
    the fluid rests against, see :func:`wall_face`: the origin of the
    experiment's x and h). ``seed`` is unused (the scene is deterministic) and
    accepted for a uniform signature.
    """
    del seed
    if a_cells < 24:
        raise InvalidInputError(f"a_cells: must be >= 24 grid cells, got {a_cells}", "a_cells")
    params = MpmParams(dim=2, n_grid=n_grid)
    dx = 1.0 / n_grid
    wall = wall_face(params)
    a = a_cells * dx
    if wall + 4.2 * a > 1.0 - wall:
        raise InvalidInputError(f"a_cells: the surge would leave the domain; use a_cells <= {int((1 - 2 * params.walls.cells * dx) / 4.2 / dx)}", "a_cells")
    pos = lattice([wall, wall], [wall + a, wall + 2 * a], dx / 2)
    n = len(pos)
    return Scene(
        name="dam_break2d",
        params=params,
        positions=pos,
        material=np.full(n, WATER, dtype=np.int32),
        velocities=np.zeros_like(pos),
        frames=300,
        info={"a": a, "x_wall": wall, "y_floor": wall, "spacing": dx / 2},
        volume_ratio=hydrostatic_volume_ratio(pos, wall + 2 * a, params),
    )


def _random_block(rng: np.random.Generator, dim: int, n_grid: int, size_cells: tuple[int, int], wall_cells: int) -> tuple[np.ndarray, np.ndarray]:
    dx = 1.0 / n_grid
    size = rng.integers(size_cells[0], size_cells[1] + 1, size=dim) * dx
    margin = (wall_cells + 2) * dx
    lo = np.array([rng.uniform(margin, 1.0 - margin - size[d]) for d in range(dim)])
    return lo, lo + size


def sand2d(seed: int = 0, n_grid: int = 128, friction_angle_deg: float = 30.0) -> Scene:
    """A random block of sand (16–32 cells a side, ≤ 4096 particles) with a random
    initial velocity, on a frictional floor (Coulomb μ = tan φ: on a frictionless
    floor a sand pile spreads like a fluid)."""
    rng = np.random.default_rng(seed)
    params = MpmParams(
        dim=2,
        n_grid=n_grid,
        sand=SandParams(friction_angle_deg=friction_angle_deg),
        walls=WallParams(friction=math.tan(math.radians(friction_angle_deg))),
    )
    lo, hi = _random_block(rng, 2, n_grid, (16, 32), params.walls.cells)
    pos = lattice(lo, hi, 0.5 / n_grid)
    vel = np.tile(rng.uniform(-1.0, 1.0, size=(1, 2)), (len(pos), 1)).astype(np.float32)
    return Scene("sand2d", params, pos, np.full(len(pos), SAND, np.int32), vel, frames=320, info={"seed": seed})


def water3d(seed: int = 0, n_grid: int = 64) -> Scene:
    """A random block of water in a 64³ box (6–9 cells a side, ≤ ~5.8k particles)
    with a random initial velocity."""
    rng = np.random.default_rng(seed)
    params = MpmParams(dim=3, n_grid=n_grid)
    lo, hi = _random_block(rng, 3, n_grid, (6, 9), params.walls.cells)
    pos = lattice(lo, hi, 0.5 / n_grid)
    vel = np.tile(rng.uniform(-1.0, 1.0, size=(1, 3)), (len(pos), 1)).astype(np.float32)
    return Scene("water3d", params, pos, np.full(len(pos), WATER, np.int32), vel, frames=800, info={"seed": seed})


SCENES: dict[str, Callable[..., Scene]] = {
    "dam_break2d": dam_break2d,
    "sand2d": sand2d,
    "water3d": water3d,
}


def make_scene(name: str, seed: int = 0, **kwargs: Any) -> Scene:
    """Build a registered scene by name. Raises :class:`InvalidInputError` for an unknown name."""
    if name not in SCENES:
        raise InvalidInputError(f"scene: unknown scene {name!r} (available: {', '.join(sorted(SCENES))})", "scene")
    return SCENES[name](seed=seed, **kwargs)


__all__ = [
    "GNS_KINEMATIC",
    "GNS_TYPE",
    "SCENES",
    "Scene",
    "dam_break2d",
    "hydrostatic_volume_ratio",
    "lattice",
    "make_scene",
    "sand2d",
    "wall_face",
    "water3d",
]
