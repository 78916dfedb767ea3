"""Velocity and acceleration statistics of a GNS dataset (``vel_mean``, ``vel_std``, ``acc_mean``, ``acc_std``),
taken in chunks of frames."""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

from hybridmpm.conventions import GNS_KINEMATIC
from hybridmpm.data.gns.io import TrajectoryLike, check_trajectory
from hybridmpm.errors import InvalidInputError

_STATS_CHUNK_FRAMES = 256


@dataclass
class _Moments:
    """Streaming per-axis count, mean and centred sum of squares (Chan et al. merge)."""

    count: int
    mean: np.ndarray
    m2: np.ndarray

    def add(self, x: np.ndarray) -> None:
        flat = x.reshape(-1, x.shape[-1])
        nb = flat.shape[0]
        if nb == 0:
            return
        mean_b = flat.mean(axis=0)
        m2_b = ((flat - mean_b) ** 2).sum(axis=0)
        n = self.count + nb
        delta = mean_b - self.mean
        self.mean = self.mean + delta * (nb / n)
        self.m2 = self.m2 + m2_b + delta**2 * (self.count * nb / n)
        self.count = n


def compute_statistics(
    trajectories: Mapping[str, TrajectoryLike] | Iterable[TrajectoryLike],
    *,
    exclude_types: Iterable[int] = (GNS_KINEMATIC,),
) -> dict[str, list[float]]:
    """Velocity and acceleration mean / std per axis, as GNS metadata wants them.

    Velocity is ``x[t+1] − x[t]`` and acceleration ``x[t+1] − 2 x[t] + x[t−1]``
    between stored frames, in GNS per-step units (position units per frame,
    NOT divided by ``dt``). The statistics run over every frame and every
    particle whose type is not in ``exclude_types`` (default: kinematic
    particles, type 3) of all trajectories. The std is the population one
    (``ddof=0``, as ``np.std``). Computed in float64 streaming (per-chunk mean
    and centred sum of squares, merged as in Chan, Golub & LeVeque 1979), so
    trajectories are never concatenated.

    Parameters
    ----------
    trajectories:
        A mapping id → trajectory (as :func:`read_split` returns) or an
        iterable of trajectories; each ``(positions [T, N, D],
        particle_type [N])`` as in :func:`write_split`. All share one D.
    exclude_types:
        GNS particle types left out.

    Returns
    -------
    dict
        ``{"vel_mean", "vel_std", "acc_mean", "acc_std"}``, each a list of D
        floats, ready for ``metadata.json``.

    Raises
    ------
    InvalidInputError
        A malformed trajectory (field ``"<id>.positions"``, ...), dimensions
        that differ between trajectories, or too little data: no counted
        particle, or fewer than 3 frames in all (``field="trajectories"``).
    """
    pairs: Iterable[tuple[str, Any]]
    if isinstance(trajectories, Mapping):
        pairs = trajectories.items()
    else:
        pairs = ((f"#{i}", t) for i, t in enumerate(trajectories))
    excluded = np.asarray(sorted({int(t) for t in exclude_types}), dtype=np.int64)
    dim: int | None = None
    vel: _Moments | None = None
    acc: _Moments | None = None
    for tid, value in pairs:
        traj = check_trajectory(str(tid), value, source=None, lenient=True)
        t_count, _, d = traj.positions.shape
        if dim is None:
            dim = d
            vel = _Moments(0, np.zeros(d), np.zeros(d))
            acc = _Moments(0, np.zeros(d), np.zeros(d))
        elif d != dim:
            raise InvalidInputError(f"trajectory {tid!r}: positions have D = {d}, earlier trajectories D = {dim}", f"{tid}.positions")
        assert vel is not None and acc is not None
        keep = ~np.isin(traj.particle_type, excluded)
        if not keep.any() or t_count < 2:
            continue
        for start in range(0, t_count - 1, _STATS_CHUNK_FRAMES):
            window = traj.positions[start : start + _STATS_CHUNK_FRAMES + 2][:, keep].astype(np.float64)
            d1 = np.diff(window, axis=0)
            vel.add(d1[:_STATS_CHUNK_FRAMES])
            acc.add(np.diff(d1, axis=0)[:_STATS_CHUNK_FRAMES])
    if vel is None or acc is None or acc.count == 0:
        raise InvalidInputError(
            f"statistics need at least one trajectory with 3 or more frames and one particle whose type is not excluded (excluded types: {excluded.tolist()})",
            "trajectories",
        )
    return {
        "vel_mean": [float(v) for v in vel.mean],
        "vel_std": [float(v) for v in np.sqrt(vel.m2 / vel.count)],
        "acc_mean": [float(v) for v in acc.mean],
        "acc_std": [float(v) for v in np.sqrt(acc.m2 / acc.count)],
    }


# --------------------------------------------------------------------------- metadata
