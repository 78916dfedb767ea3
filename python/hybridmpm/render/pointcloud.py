"""Trajectory export for artists: a PLY or VTU point-cloud sequence (via meshio).

Blender imports ``.ply`` point clouds (File → Import → Stanford PLY);
ParaView opens a ``frame_*.vtu`` series as one time-varying dataset. 2D
positions get z = 0. Point data: ``particle_type`` (GNS codes), ``velocity``
[m/s] (finite difference to the previous stored frame), and ``solver``
(0 MPM, 1 neural) when given.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from hybridmpm.errors import InvalidInputError
from hybridmpm.trajectory import check_frame_velocities

FORMATS = ("ply", "vtu")


def export_points(
    positions: np.ndarray,
    particle_type: np.ndarray,
    out_dir: str | Path,
    *,
    fmt: str = "ply",
    dt: float = 2.5e-3,
    solver: np.ndarray | None = None,
    every: int = 1,
) -> list[Path]:
    """Write ``positions`` float [T, N, D] (m) as one point-cloud file per stored
    frame, ``out_dir/frame_00000.<fmt>`` …, every ``every``-th frame. ``dt`` [s]
    between stored frames (for the velocity), ``solver`` int [T] (0 MPM, 1
    neural) or None. Returns the paths. Raises :class:`InvalidInputError`
    naming ``fmt``, ``positions`` (also non-finite), ``particle_type``, ``solver``,
    ``every`` or ``dt`` (not finite and > 0, or so small that a velocity
    overflows: :func:`~hybridmpm.trajectory.check_frame_velocities`)."""
    import meshio

    if fmt not in FORMATS:
        raise InvalidInputError(f"fmt: must be one of {', '.join(FORMATS)}, got {fmt!r}", "fmt")
    p = np.asarray(positions, np.float64)
    if p.ndim != 3 or p.shape[2] not in (2, 3) or p.shape[0] < 1:
        raise InvalidInputError(f"positions: expected [T, N, 2|3], got {list(p.shape)}", "positions")
    pt = np.asarray(particle_type)
    if pt.shape != (p.shape[1],):
        raise InvalidInputError(f"particle_type: expected [{p.shape[1]}], got {list(pt.shape)}", "particle_type")
    if solver is not None and np.asarray(solver).shape != (p.shape[0],):
        raise InvalidInputError(f"solver: expected [{p.shape[0]}] tags, got {list(np.asarray(solver).shape)}", "solver")
    if not isinstance(every, int) or every < 1:
        raise InvalidInputError(f"every: must be an integer >= 1, got {every!r}", "every")
    if not np.isfinite(p).all():
        raise InvalidInputError("positions: non-finite coordinates", "positions")
    if not (isinstance(dt, (int, float, np.integer, np.floating)) and np.isfinite(dt) and dt > 0):
        raise InvalidInputError(f"dt: must be a finite number > 0 [s], got {dt!r}", "dt")
    check_frame_velocities(p, float(dt), "dt")  # the velocities written below stay finite
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    n = p.shape[1]
    cells = [("vertex", np.arange(n, dtype=np.int32).reshape(-1, 1))]
    paths = []
    for t in range(0, p.shape[0], every):
        pts = p[t] if p.shape[2] == 3 else np.concatenate([p[t], np.zeros((n, 1))], axis=1)
        vel = (p[t] - p[t - 1]) / dt if t > 0 else np.zeros_like(p[t])
        if vel.shape[1] == 2:
            vel = np.concatenate([vel, np.zeros((n, 1))], axis=1)
        data: dict[str, np.ndarray] = {"particle_type": pt.astype(np.int32)}
        if fmt == "vtu":
            data["velocity"] = vel.astype(np.float32)
        else:  # PLY holds scalar properties
            for k, ax in enumerate("xyz"):
                data[f"v{ax}"] = vel[:, k].astype(np.float32)
        if solver is not None:
            data["solver"] = np.full(n, int(np.asarray(solver)[t]), np.int32)
        path = out / f"frame_{t:05d}.{fmt}"
        meshio.Mesh(pts.astype(np.float32), cells, point_data=data).write(path)
        paths.append(path)
    return paths


__all__ = ["FORMATS", "export_points"]
