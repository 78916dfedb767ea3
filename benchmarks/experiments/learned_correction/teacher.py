"""The teacher of the learned correction: what MPM on the scene's grid makes
of a coarse state in one frame.

A coarse particle (spacing ``s`` = half a coarse cell) stands for the
``2^D`` particles of the scene's grid it covers. :func:`split_state` makes
them: children at ``±s/4`` per axis around it, velocity ``v + C·offset``
(its APIC affine field), the same ``C``, ``F``, ``J`` and log-volume
correction, a ``2^-D`` share of its mass and rest volume. On the scene's grid
they are the full-resolution lattice the coarse scene was seeded from, so
one frame of them is the fine solver's answer to the coarse state; the mean
of a particle's children after the frame is its target
(:func:`teacher_frame`). DAgger (Ross et al. 2011) asks this teacher at the
states the corrected coarse MPM itself visits.
"""

from __future__ import annotations

import itertools

import numpy as np

from hybridmpm.mpm import MpmParams, MpmSolver
from hybridmpm.sim.mpm import probe_frame


def split_state(coarse: MpmSolver, fine_params: MpmParams, *, num_threads: int = 1) -> MpmSolver:
    """A fine solver on ``fine_params``' grid holding ``2^D`` children of
    every particle of ``coarse``, children of particle ``i`` at rows
    ``i·2^D … (i+1)·2^D − 1``."""
    pos = np.asarray(coarse.positions, np.float64)
    n, d = pos.shape
    k = 2**d
    s = 0.5 / coarse.n_grid  # coarse particle spacing: half a coarse cell
    offs = np.asarray(list(itertools.product((-0.25, 0.25), repeat=d))) * s  # [k, D]
    aff = np.asarray(coarse.affine, np.float64)
    lo, hi = 1.0 / fine_params.resolved_n_grid(), 1.0 - 1.0 / fine_params.resolved_n_grid()
    cpos = np.clip(pos[:, None, :] + offs[None], lo, hi).reshape(n * k, d)
    cvel = (np.asarray(coarse.velocities, np.float64)[:, None, :] + np.einsum("nij,kj->nki", aff, offs)).reshape(n * k, d)
    rep = lambda a: np.repeat(np.asarray(a), k, axis=0)  # noqa: E731
    p = MpmParams.from_dict({**fine_params.to_dict(), "num_threads": int(num_threads)})
    fine = MpmSolver(p)
    fine.add_particles(
        cpos.astype(np.float32),
        rep(coarse.material).astype(np.int32),
        velocities=cvel.astype(np.float32),
        masses=rep(coarse.masses) / k,
        volumes=rep(coarse.volumes) / k,
    )
    fine.affine = rep(coarse.affine)
    fine.deformation_gradient = rep(coarse.deformation_gradient)
    fine.volume_ratio = rep(coarse.volume_ratio)
    fine.set_field("volume_correction", rep(coarse.field("volume_correction")))
    return fine


def teacher_frame(coarse: MpmSolver, fine_params: MpmParams, dt_frame: float, *, num_threads: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """One frame of the split state on the fine grid: the mean position [m]
    and velocity [m/s] of every coarse particle's children, float64 [N, D]
    each. ``coarse`` is unchanged. Raises
    :class:`~hybridmpm.errors.SimulationError` if the fine frame fails."""
    fine = split_state(coarse, fine_params, num_threads=num_threads)
    probe_frame(fine, dt_frame)
    n, d = np.shape(coarse.positions)
    k = 2**d
    x = np.asarray(fine.positions, np.float64).reshape(n, k, d).mean(axis=1)
    v = np.asarray(fine.velocities, np.float64).reshape(n, k, d).mean(axis=1)
    return x, v


__all__ = ["split_state", "teacher_frame"]
