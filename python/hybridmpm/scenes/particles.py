"""The particle set of a scene: which particles are fluid and which are boundary.

Every array that holds *all* particles (what the network reads, what a
trajectory file stores, what a renderer draws) lists the ``N`` fluid particles
— the ones MPM moves, in solver order — and then the ``B`` boundary /
obstacle particles (GNS type :data:`~hybridmpm.conventions.GNS_KINEMATIC`)
that only the network sees. :class:`ParticleSet` is the one place that pads
fluid arrays with the boundary and slices them back. The network always sees
the boundary where the scene put it; a frame of a simulator whose obstacles
moved pads with each obstacle's particles translated with it
(:meth:`ParticleSet.pad`'s ``offsets``).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from hybridmpm.conventions import GNS_KINEMATIC
from hybridmpm.errors import InvalidInputError


def pad_boundary(fluid: np.ndarray, boundary: np.ndarray | None) -> np.ndarray:
    """``fluid`` ``[..., N, D]`` with ``boundary`` ``[B, D]`` appended along the
    particle axis (broadcast over leading axes), float32 ``[..., N + B, D]``."""
    x = np.asarray(fluid, dtype=np.float32)
    if boundary is None or len(boundary) == 0:
        return x
    b = np.broadcast_to(np.asarray(boundary, np.float32), x.shape[:-2] + tuple(np.shape(boundary)))
    return np.concatenate([x, b], axis=-2)


@dataclass(frozen=True)
class ParticleSet:
    """Fluid particles followed by boundary particles (on the obstacles, not simulated).

    ``num_fluid`` N; ``boundary`` float32 [B, D] [m] (B may be 0) where the
    scene put the obstacles; ``particle_type`` int64 [N + B] (GNS codes);
    ``material`` int32 [N] (solver codes); ``masses`` float32 [N] [kg] as the
    solver resolved them; ``boundary_obstacle`` int32 [B]: the obstacle each
    boundary particle lies on (its index in the scene's colliders; -1: none),
    or None when not known (the boundary then never moves). Raises
    :class:`InvalidInputError` (field ``boundary_obstacle``) for another shape
    or an index below -1.
    """

    num_fluid: int
    boundary: np.ndarray
    particle_type: np.ndarray
    material: np.ndarray
    masses: np.ndarray
    boundary_obstacle: np.ndarray | None = None

    def __post_init__(self) -> None:
        owner = self.boundary_obstacle
        if owner is not None and (
            np.shape(owner) != (self.num_boundary,) or not np.issubdtype(np.asarray(owner).dtype, np.integer) or np.any(np.asarray(owner) < -1)
        ):
            raise InvalidInputError(
                f"boundary_obstacle: expected {self.num_boundary} obstacle indices >= -1, got {np.asarray(owner).dtype} {list(np.shape(owner))}",
                "boundary_obstacle",
            )

    @property
    def num_boundary(self) -> int:
        return int(self.boundary.shape[0])

    @property
    def num_total(self) -> int:
        """N + B."""
        return self.num_fluid + self.num_boundary

    @property
    def dim(self) -> int:
        return int(self.boundary.shape[1])

    @property
    def fluid_mask(self) -> np.ndarray:
        """bool [N + B]: True for fluid particles."""
        return np.asarray(self.particle_type != GNS_KINEMATIC)

    def pad(self, fluid: Any, offsets: Any = None) -> np.ndarray:
        """Fluid positions ``[..., N, D]`` → all particles ``[..., N + B, D]`` float32
        (the boundary appended, broadcast over leading axes), with the
        boundary of :meth:`boundary_at` ``offsets``. Raises
        :class:`InvalidInputError` (field ``positions``) for another particle
        count, or what :meth:`boundary_at` raises."""
        x = np.asarray(fluid, dtype=np.float32)
        if x.ndim < 2 or x.shape[-2] != self.num_fluid or x.shape[-1] != self.dim:
            raise InvalidInputError(f"positions: expected [..., {self.num_fluid}, {self.dim}] fluid positions, got {list(x.shape)}", "positions")
        return pad_boundary(x, self.boundary_at(offsets))

    def boundary_at(self, offsets: Any = None) -> np.ndarray:
        """The boundary particles with each obstacle moved: float32 [B, D] [m].

        ``offsets`` float [C, D] [m]: each obstacle's displacement from where
        the scene put it (current centre − scene centre; obstacles translate,
        they do not rotate). A particle of obstacle ``i`` moves by
        ``offsets[i]`` (added in float64); particles of no obstacle, and all of
        them when ``boundary_obstacle`` is None, stay put. None or all zeros
        returns :attr:`boundary` itself (no copy). Raises
        :class:`InvalidInputError` (field ``offsets``) for a shape other than
        [C, D] with C above every obstacle index, or a non-finite offset."""
        owner = self.boundary_obstacle
        if offsets is None or owner is None or self.num_boundary == 0:
            return self.boundary
        off = np.asarray(offsets, np.float64)
        if off.ndim != 2 or off.shape[1] != self.dim or len(off) <= int(owner.max()) or not np.all(np.isfinite(off)):
            raise InvalidInputError(f"offsets: expected finite [C, {self.dim}] displacements with C > {int(owner.max())}, got {list(off.shape)}", "offsets")
        if not np.any(off):
            return self.boundary
        shift = np.where((owner >= 0)[:, None], off[np.maximum(owner, 0)], 0.0)
        return (self.boundary.astype(np.float64) + shift).astype(np.float32)

    def fluid(self, positions: Any) -> np.ndarray:
        """All particles ``[..., N + B, D]`` (or already fluid-only ``[..., N, D]``)
        → the fluid particles ``[..., N, D]`` (a view when possible)."""
        x = np.asarray(positions)
        if x.ndim < 2 or x.shape[-2] not in (self.num_fluid, self.num_total):
            raise InvalidInputError(f"positions: expected [..., {self.num_total}, D] positions, got {list(x.shape)}", "positions")
        return x[..., : self.num_fluid, :]

    def full_masses(self) -> np.ndarray:
        """float32 [N + B]: the fluid masses, then 0 for boundary particles."""
        return np.concatenate([np.asarray(self.masses, np.float32), np.zeros(self.num_boundary, np.float32)])

    def full_material(self) -> np.ndarray:
        """int32 [N + B]: the solver material codes, then -1 for boundary particles."""
        return np.concatenate([np.asarray(self.material, np.int32), np.full(self.num_boundary, -1, np.int32)])


__all__ = ["ParticleSet", "pad_boundary"]
