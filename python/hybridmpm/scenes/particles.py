"""The particle set of a scene: which particles are fluid and which are boundary.

Every array that holds *all* particles (what the network reads, what a
trajectory file stores, what a renderer draws) lists the ``N`` fluid particles
— the ones MPM moves, in solver order — and then the ``B`` static boundary /
obstacle particles (GNS type :data:`~hybridmpm.conventions.GNS_KINEMATIC`)
that only the network sees. :class:`ParticleSet` is the one place that pads
fluid arrays with the boundary and slices them back.
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
    """Fluid particles followed by static boundary particles.

    ``num_fluid`` N; ``boundary`` float32 [B, D] [m] (B may be 0);
    ``particle_type`` int64 [N + B] (GNS codes); ``material`` int32 [N]
    (solver codes); ``masses`` float32 [N] [kg] as the solver resolved them.
    """

    num_fluid: int
    boundary: np.ndarray
    particle_type: np.ndarray
    material: np.ndarray
    masses: np.ndarray

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

    def pad(self, fluid: Any) -> np.ndarray:
        """Fluid positions ``[..., N, D]`` → all particles ``[..., N + B, D]`` float32
        (the boundary appended, broadcast over leading axes). Raises
        :class:`InvalidInputError` (field ``positions``) for another particle count."""
        x = np.asarray(fluid, dtype=np.float32)
        if x.ndim < 2 or x.shape[-2] != self.num_fluid or x.shape[-1] != self.dim:
            raise InvalidInputError(f"positions: expected [..., {self.num_fluid}, {self.dim}] fluid positions, got {list(x.shape)}", "positions")
        return pad_boundary(x, self.boundary)

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
