"""Local features of a coarse MPM state, per particle: what the learned
correction reads (arXiv 2505.18926's cheap half replaced by a corrected coarse
MPM; the correction follows solver-in-the-loop work, Um et al. 2020, arXiv
2007.00016, and INC, arXiv 2511.12764: a force inside the solver).

Every feature is dimensionless and local, so one network serves any seed and
any block layout of a scene:

* the particle's velocity in cells per frame (``v·Δt/dx``, D), its APIC
  affine matrix times the frame (``C·Δt``, D²), ``F − I`` (D², sand's elastic
  deformation; zero for water), ``J − 1`` scaled by 10 (water's volume ratio),
  its material (one-hot, 2) and its offset from its cell's centre (D, cells);
* p2g on the coarse cells of the 3^D neighbourhood of its cell (nearest-cell
  deposit): water mass and sand mass as fractions of a full cell (a cell holds
  ``ppc^D`` particles of the particle's mass), and the cell's mass-weighted
  velocity relative to the particle's, in cells per frame (3^D · (2 + D));
* the distance to each domain wall face in cells, clipped to
  [0, :data:`WALL_REACH`] and divided by it (2D), and the signed distance to
  the nearest collider in cells, clipped to [−1, :data:`WALL_REACH`] and
  divided by it, with the collider's outward normal (1 + D).

Width: 2D 58, 3D 172 (:func:`num_features`).
"""

from __future__ import annotations

import itertools

import numpy as np

from hybridmpm.conventions import MATERIAL_SAND
from hybridmpm.mpm import MpmParams, MpmSolver
from hybridmpm.mpm.params import Collider
from hybridmpm.scenes.spec import collider_sdf

#: Distances to walls and colliders are seen up to this many cells.
WALL_REACH = 4.0
#: Particles per cell per axis the features take as "a full cell".
PPC = 2


def num_features(dim: int) -> int:
    """Feature width for ``dim`` (2 or 3)."""
    own = dim + dim * dim + dim * dim + 1 + 2 + dim
    return own + 3**dim * (2 + dim) + 2 * dim + 1 + dim


def _collider_sdf(pos: np.ndarray, colliders: list[Collider]) -> tuple[np.ndarray, np.ndarray]:
    """Signed distance [m] to the nearest collider (inf without any,
    :func:`~hybridmpm.scenes.spec.collider_sdf`) and its outward unit normal
    [N, D] (the distance's central-difference gradient)."""
    n, d = pos.shape
    best = np.full(n, np.inf)
    normal = np.zeros((n, d))
    h = 1e-5  # [m], far below a cell
    for c in colliders:
        sdf = collider_sdf(c, pos)
        grad = np.stack([(collider_sdf(c, pos + h * e) - collider_sdf(c, pos - h * e)) / (2 * h) for e in np.eye(d)], axis=1)
        nrm = grad / np.maximum(np.linalg.norm(grad, axis=1, keepdims=True), 1e-12)
        closer = sdf < best
        best = np.where(closer, sdf, best)
        normal[closer] = nrm[closer]
    return best, normal


def particle_features(solver: MpmSolver, dt_frame: float, params: MpmParams | None = None) -> np.ndarray:
    """Features of every particle of ``solver`` (the coarse MPM), float32 [N, F].

    ``dt_frame`` [s] sets the velocity unit (cells per frame); ``params`` the
    walls and colliders (default the solver's). See the module docstring for
    the columns; F = :func:`num_features`.
    """
    params = solver.params if params is None else params
    pos = np.asarray(solver.positions, np.float64)
    vel = np.asarray(solver.velocities, np.float64)
    n, d = pos.shape
    ng = solver.n_grid
    dx = 1.0 / ng
    vs = dt_frame / dx  # m/s -> cells per frame
    mat = np.asarray(solver.material)
    sand = mat == MATERIAL_SAND
    mass = np.asarray(solver.masses, np.float64)
    cols: list[np.ndarray] = [vel * vs, np.asarray(solver.affine, np.float64).reshape(n, d * d) * dt_frame]
    f = np.asarray(solver.deformation_gradient, np.float64).reshape(n, d * d) - np.eye(d).ravel()
    cols += [f, (np.asarray(solver.volume_ratio, np.float64)[:, None] - 1.0) * 10.0]
    cols += [np.stack([~sand, sand], axis=1).astype(np.float64)]
    g = pos / dx
    cell = np.clip(np.floor(g).astype(np.int64), 0, ng - 1)
    cols.append(g - cell - 0.5)
    strides = ng ** np.arange(d - 1, -1, -1)
    flat = cell @ strides
    size = ng**d
    mw = np.bincount(flat, weights=mass * ~sand, minlength=size)
    ms = np.bincount(flat, weights=mass * sand, minlength=size)
    mom = np.stack([np.bincount(flat, weights=mass * vel[:, k], minlength=size) for k in range(d)], axis=1)
    mtot = mw + ms
    vcell = np.divide(mom, mtot[:, None], out=np.zeros_like(mom), where=mtot[:, None] > 0)
    full = mass * PPC**d
    for off in itertools.product((-1, 0, 1), repeat=d):
        nb = np.clip(cell + np.asarray(off), 0, ng - 1) @ strides
        occ = mtot[nb] > 0
        cols += [(mw[nb] / full)[:, None], (ms[nb] / full)[:, None], np.where(occ[:, None], (vcell[nb] - vel) * vs, 0.0)]
    lo = (params.walls.cells - 1) * dx
    cols += [np.clip((pos - lo) / dx, 0.0, WALL_REACH) / WALL_REACH, np.clip((1.0 - lo - pos) / dx, 0.0, WALL_REACH) / WALL_REACH]
    sdf, normal = _collider_sdf(pos, list(params.colliders))
    cols += [(np.clip(sdf / dx, -1.0, WALL_REACH) / WALL_REACH)[:, None], normal * (sdf < WALL_REACH * dx)[:, None]]
    out = np.concatenate(cols, axis=1).astype(np.float32)
    assert out.shape[1] == num_features(d)
    return out


__all__ = ["PPC", "WALL_REACH", "num_features", "particle_features"]
