"""A session's recent trajectory for download: ``GET /v1/sessions/{sid}/trajectory``,
its last recorded coarse steps as a trajectory ``.npz`` (what ``hybridmpm
evaluate`` and :class:`hybridmpm.trajectory.Trajectory` read) or as a zip of
PLY point clouds (:func:`hybridmpm.render.export_points`, for Blender)."""

from __future__ import annotations

import io
import tempfile
import zipfile
from pathlib import Path
from typing import Annotated, Literal

import numpy as np
from fastapi import APIRouter, Query
from fastapi.responses import Response

from hybridmpm.render import export_points
from hybridmpm.service.deps import ManagerDep, SessionDep
from hybridmpm.service.errors import ApiError
from hybridmpm.service.sessions import RECORD_STEPS
from hybridmpm.trajectory import Trajectory

NPZ = "application/x-npz"
ZIP = "application/zip"
#: Copies of the trajectory alive while its file is made (the stacked positions, the file, its buffer).
FILE_COPIES = 3
#: Bytes per position value of the PLY zip while it is made (the float64 copy, the velocities, the files, the zip).
PLY_BYTES_PER_VALUE = 40

router = APIRouter()


def trajectory_npz(traj: Trajectory) -> bytes:
    buf = io.BytesIO()
    np.savez(buf, allow_pickle=False, **traj.to_arrays())
    return buf.getvalue()


def trajectory_ply_zip(traj: Trajectory, solver: np.ndarray) -> bytes:
    """One binary PLY per frame (``frame_00000.ply`` …, x y z, the velocity, the particle type, the solver), zipped."""
    buf = io.BytesIO()
    with tempfile.TemporaryDirectory(prefix="hybridmpm-ply-") as tmp:
        paths = export_points(traj.positions, traj.particle_type, tmp, fmt="ply", dt=traj.dt_frame, solver=solver)
        with zipfile.ZipFile(buf, "w", zipfile.ZIP_DEFLATED, compresslevel=1) as z:
            for p in paths:
                z.write(p, Path(p).name)
    return buf.getvalue()


@router.get(
    "/v1/sessions/{sid}/trajectory",
    responses={
        200: {
            "content": {NPZ: {}, ZIP: {}},
            "description": "npz: positions [T, N, D], particle_type, dt_frame (between stored frames), n_grid, masses, material, "
            "frame_index [T], solver [T] (0 MPM, 1 network), controlled [T]; or a zip of one PLY point cloud per frame",
        },
        404: {"description": "no such session"},
        409: {"description": "no frame recorded (the memory budget was full)"},
    },
)
async def get_session_trajectory(
    s: SessionDep,
    manager: ManagerDep,
    frames: Annotated[int, Query(ge=1, le=RECORD_STEPS, description="the latest coarse steps wanted (fewer if fewer are recorded)")] = RECORD_STEPS,
    format: Annotated[Literal["npz", "ply"], Query(description="npz (a hybridmpm trajectory) or ply (a zip of PLY frames)")] = "npz",  # noqa: A002 - the query's name
) -> Response:
    """The session's latest ``frames`` coarse steps, consecutive (a reset or
    a restored checkpoint starts the recording again; controls and steps are
    recorded as they run)."""
    held = await manager.recorded(s, frames)  # in the session's actor with --backend ray
    if not held:
        raise ApiError(409, "no frame of this session is recorded (the memory budget was full); step it and retry")
    f = s.facts
    values = len(held) * f.num_total * f.dim
    dt, n_grid = f.step_dt, f.n_grid
    ptype, masses, material = f.particle_type, f.masses, f.material
    with manager.budget.hold(values * (PLY_BYTES_PER_VALUE if format == "ply" else 4 * FILE_COPIES), "the trajectory's file"):

        def make() -> Trajectory:
            return Trajectory(
                positions=np.stack([h[1] for h in held]),
                particle_type=ptype,
                dt_frame=dt,
                n_grid=n_grid,
                masses=masses,
                material=material,
                extras={
                    "frame_index": np.array([h[0] for h in held], np.int64),
                    "solver": np.array([h[2] == "neural" for h in held], np.int8),
                    "controlled": np.array([h[3] for h in held], bool),
                },
            )

        traj = await manager.compute(make)
        first, last = held[0][0], held[-1][0]
        name = f"{s.scene}-seed{s.seed}-frames{first}-{last}"
        if format == "ply":
            data = await manager.compute(trajectory_ply_zip, traj, traj.extras["solver"])
            media, name = ZIP, name + "-ply.zip"
        else:
            data = await manager.compute(trajectory_npz, traj)
            media, name = NPZ, name + ".npz"
        del traj
    s.touch()
    return Response(data, media_type=media, headers={"Content-Disposition": f'attachment; filename="{name}"', "X-Frames": f"{first},{last}"})
