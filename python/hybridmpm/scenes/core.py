"""The :class:`Scene` type and the seeding helpers every scene shares.

Particles sit on a lattice at spacing ``dx/2`` (2 particles per cell per
dimension), cell-centred, the usual MPM seeding. Obstacles are MPM colliders
(:class:`~hybridmpm.mpm.Box`, :class:`~hybridmpm.mpm.Sphere`) and, for the
network, static boundary particles of GNS type 3 sampled on their surface
(as in the GNS WaterRamps dataset).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np

from hybridmpm.conventions import CONNECTIVITY_RADIUS, DT_FRAME, GNS_KINEMATIC, GNS_TYPE_OF_MATERIAL, MATERIAL_WATER
from hybridmpm.mpm import MpmParams, MpmSolver
from hybridmpm.mpm.bodies import Body
from hybridmpm.scenes.particles import ParticleSet, pad_boundary

#: Memory a particle costs while a scene is built and simulated [bytes], an
#: upper bound of the lattice and selection arrays (float64 temporaries), the
#: Scene's arrays and the solver's particle state (~40 floats in 3D); a
#: rollout's stored positions are budgeted separately.
BYTES_PER_PARTICLE = 512


@dataclass(frozen=True)
class Clusters:
    """Which particles of a full-resolution scene a downsampled one merged
    (paper Sec. 3.1.1): ``labels`` int32 [N_h], the cluster (low-resolution
    particle) of each solver particle, and ``boundary_labels`` int32 [B_h],
    that of each boundary particle. Given back to
    :func:`~hybridmpm.scenes.downsample_scene` they rebuild the same
    low-resolution scene without clustering again (a restored session)."""

    labels: np.ndarray
    boundary_labels: np.ndarray


class SceneSource(Protocol):
    """What a scene was built from, as the scene keeps it to rebuild itself on another grid:
    :class:`hybridmpm.scenes.spec.SceneSpec`, the one implementation (named here by what the scene uses of it,
    so that this module imports nothing of the spec's, which imports this one)."""

    name: str
    params: MpmParams
    particles_per_cell: int
    info: dict[str, Any]

    @property
    def spacing(self) -> float:
        """The particles' initial spacing [m]."""
        ...

    def on_grid(self, n_grid: int, particles_per_cell: int | None = None) -> SceneSource:
        """The same scene on an ``n_grid`` grid (and ``particles_per_cell``)."""
        ...

    def build(self) -> Scene:
        """The scene: its solver parameters and particles."""
        ...


@dataclass
class Scene:
    """A scene: parameters, initial particles and static boundary particles.

    ``positions`` float32 [N, D] [m], ``material`` int32 [N] (0 water, 1 sand,
    2 elastic, 3 snow, 4 viscoplastic; ``material_set`` int32 [N], each
    particle's parameter set in ``params``' table, or None for each
    material's default set),
    ``velocities`` float32 [N, D] [m/s]: the particles the MPM solver moves.
    ``boundary_positions`` float32 [B, D] [m]: static obstacle particles (GNS
    type 3) that only the network sees; MPM sees the colliders in ``params``.
    ``boundary_obstacle`` int32 [B]: the obstacle (index in
    ``params.colliders``) each boundary particle was sampled on, so that it
    follows a moved obstacle in the frames; -1 for a particle of no obstacle,
    which stays put (None: not known, and none moves).
    ``masses`` [N] kg and ``volumes`` [N] m^D override the solver defaults
    (density × (dx/2)^D) for downsampled scenes; ``volume_ratio`` [N] is the
    initial J (water at hydrostatic rest), or None for J = 1. ``frames`` is
    the default rollout length; ``info`` holds scene-specific facts;
    ``spec`` is the declarative spec the scene was built from (if any);
    ``clusters`` the particles of the full-resolution scene each particle of
    a downsampled one merged (None for a scene at full resolution).
    """

    name: str
    params: MpmParams
    positions: np.ndarray
    material: np.ndarray
    velocities: np.ndarray
    dt_frame: float = DT_FRAME
    frames: int = 300
    info: dict[str, Any] = field(default_factory=dict)
    volume_ratio: np.ndarray | None = None
    boundary_positions: np.ndarray | None = None
    masses: np.ndarray | None = None
    volumes: np.ndarray | None = None
    connectivity_radius: float = CONNECTIVITY_RADIUS
    spec: SceneSource | None = None
    clusters: Clusters | None = None
    boundary_obstacle: np.ndarray | None = None
    material_set: np.ndarray | None = None

    @property
    def dim(self) -> int:
        return int(self.positions.shape[1])

    @property
    def bodies(self) -> list[Body]:
        """The rigid bodies the solver starts with (``params.bodies``; docs/bodies.md)."""
        return list(self.params.bodies)

    @property
    def num_particles(self) -> int:
        """Particles the solver moves (boundary particles not counted)."""
        return int(self.positions.shape[0])

    @property
    def num_boundary(self) -> int:
        return 0 if self.boundary_positions is None else int(self.boundary_positions.shape[0])

    def particle_type(self) -> np.ndarray:
        """GNS particle types int64 [N + B]: water 5, sand 6, viscoplastic 7,
        elastic 8, snow 9 (:data:`~hybridmpm.conventions.GNS_TYPE_OF_MATERIAL`), then boundary 3."""
        lookup = np.full(max(GNS_TYPE_OF_MATERIAL) + 1, GNS_TYPE_OF_MATERIAL[MATERIAL_WATER], np.int64)
        for code, gns in GNS_TYPE_OF_MATERIAL.items():
            lookup[code] = gns
        fluid = lookup[np.asarray(self.material, np.int64)]
        return np.concatenate([fluid, np.full(self.num_boundary, GNS_KINEMATIC, np.int64)])

    def with_boundary(self, positions: np.ndarray) -> np.ndarray:
        """Append the static boundary particles to solver positions: [..., N, D] → [..., N + B, D] float32."""
        return pad_boundary(positions, self.boundary_positions)

    def particles(self, masses: np.ndarray | None = None) -> ParticleSet:
        """The scene's :class:`ParticleSet` (fluid, then boundary). ``masses``
        float [N] [kg]: the solver's resolved masses (default: resolved by a
        throwaway solver, exactly as :meth:`make_solver` would)."""
        if masses is None:
            masses = self.make_solver(num_threads=1).masses
        boundary = self.boundary_positions if self.boundary_positions is not None else np.zeros((0, self.dim), np.float32)
        return ParticleSet(
            self.num_particles,
            np.asarray(boundary, np.float32),
            self.particle_type(),
            np.asarray(self.material, np.int32),
            np.asarray(masses, np.float32),
            None if self.boundary_obstacle is None else np.asarray(self.boundary_obstacle, np.int32),
        )

    def make_solver(self, num_threads: int | None = None) -> MpmSolver:
        """A fresh :class:`MpmSolver` holding this scene's particles."""
        params = self.params
        if num_threads is not None:
            params = MpmParams.from_dict({**params.to_dict(), "num_threads": int(num_threads)})
        sim = MpmSolver(params)
        sim.add_particles(self.positions, self.material, velocities=self.velocities, masses=self.masses, volumes=self.volumes, material_set=self.material_set)
        if self.volume_ratio is not None:
            sim.volume_ratio = self.volume_ratio
        return sim


def lattice(lo: np.ndarray | list[float], hi: np.ndarray | list[float], spacing: float | np.ndarray) -> np.ndarray:
    """Cell-centred lattice points filling the box ``[lo, hi]`` at ``spacing``
    [m] (one number, or one per axis): float32 [N, D]."""
    lo_a = np.asarray(lo, dtype=np.float64)
    hi_a = np.asarray(hi, dtype=np.float64)
    sp = np.broadcast_to(np.asarray(spacing, np.float64), lo_a.shape)
    counts = np.maximum(np.round((hi_a - lo_a) / sp).astype(int), 1)
    axes = [lo_a[d] + (np.arange(counts[d]) + 0.5) * sp[d] for d in range(len(lo_a))]
    grid = np.meshgrid(*axes, indexing="ij")
    return np.stack([g.ravel() for g in grid], axis=1).astype(np.float32)


def wall_face(params: MpmParams) -> float:
    """Where fluid rests against the lower domain walls [m]: ``(cells − 1)·dx``.

    With a wall band of ``cells`` nodes whose velocity may not point outwards,
    particles come to rest about one cell inside the band; blocks placed
    against a wall start there so that they start at rest.
    """
    return (params.walls.cells - 1) / params.resolved_n_grid()


def wall_cells_for(face: float, n_grid: int) -> int:
    """The wall band [cells] of a grid of ``n_grid`` cells whose face
    ``(cells − 1)·dx`` (:func:`wall_face`) is the grid node nearest ``face``
    [m] at or inside it, at least 2 cells (the quadratic stencil's reach).

    The face is exactly ``face`` when ``face·n_grid`` is an integer (128² with
    3 cells and 64² with 2 cells both rest fluid at 1/64 m); otherwise it lies
    less than one cell further in.
    """
    return max(2, math.ceil(face * n_grid - 1e-6) + 1)


def hydrostatic_volume_ratio(positions: np.ndarray, surface: float, params: MpmParams) -> np.ndarray:
    """Volume ratio ``J = 1 − ρ·|g|·(surface − y)/K`` of water at hydrostatic rest
    (Cauchy pressure ``K(1 − J) = ρ|g|·depth``), float32 [N]. ``surface`` is the
    free-surface height [m]; ``y`` is the vertical (second) coordinate."""
    g = abs(float(params.resolved_gravity()[1]))
    depth = np.clip(surface - positions[:, 1], 0.0, None)
    return np.clip(1.0 - params.water.density * g * depth / params.water.bulk_modulus, 0.5, 1.0).astype(np.float32)
