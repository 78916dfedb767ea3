"""The nodes of a learned model's grid (numpy): their geometry, the wall mask, the mass floor.

Shared by the grid model's runtime (:mod:`hybridmpm.neural.grid`) and the GNS's
grid branch (:mod:`hybridmpm.neural.grid_branch`); kept apart from both so that
neither imports the other's runtime (the branch is loaded by
:class:`~hybridmpm.neural.runtime.GnsRuntime`, which the grid model's runtime
imports). The torch side is :func:`hybridmpm.train.grid.grid_geometry`.
"""

from __future__ import annotations

import numpy as np

#: Smallest node mass (in particle counts) a grid velocity is divided by: a
#: node of less weighs less than this in every particle's g2p, so the floor
#: biases nothing a particle reads (a rigid translation is reproduced exactly).
MASS_FLOOR = 1e-6


def grid_geometry(bounds: np.ndarray, grid: int) -> tuple[np.ndarray, np.ndarray]:
    """``(origin [D], spacing [D])`` float32 of a model's grid: nodes at
    ``origin + i·spacing``, ``spacing = (hi − lo)/(G − 3)``, ``origin = lo − spacing``
    (:func:`hybridmpm.train.grid.grid_geometry`, in float32 as torch computes it)."""
    b = np.asarray(bounds, np.float32)
    spacing = ((b[:, 1] - b[:, 0]) / np.float32(grid - 3)).astype(np.float32)
    return (b[:, 0] - spacing).astype(np.float32), spacing


def wall_mask(bounds: np.ndarray, grid: int) -> np.ndarray:
    """The mask channel of the nodes beyond the walls, float32 [1, 1, G^D...]
    (1 outside ``bounds`` [[lo, hi]] * D, 0 inside), on :func:`grid_geometry`'s nodes."""
    b = np.asarray(bounds, np.float32)
    d = b.shape[0]
    origin, spacing = grid_geometry(b, grid)
    axes = [origin[k] + spacing[k] * np.arange(grid, dtype=np.float32) for k in range(d)]
    mesh = np.stack(np.meshgrid(*axes, indexing="ij"))
    outside = np.any((mesh < b[:, 0].reshape(d, *[1] * d)) | (mesh > b[:, 1].reshape(d, *[1] * d)), axis=0)
    return np.asarray(outside, np.float32)[None, None]


__all__ = ["MASS_FLOOR", "grid_geometry", "wall_mask"]
