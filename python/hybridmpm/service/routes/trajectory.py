"""A session's recent trajectory for download: ``GET /v1/sessions/{sid}/trajectory``,
its last recorded coarse steps as a trajectory ``.npz`` (what ``hybridmpm
evaluate`` and :class:`hybridmpm.trajectory.Trajectory` read), as a zip of
PLY point clouds (:func:`hybridmpm.render.export_points`, for Blender) or as
a zip of the fluid's surface meshes per frame and material
(:func:`hybridmpm.render.export_surfaces`, each frame's surface ending on
the obstacles where they are in it; needs the ``mesh`` extra)."""

from __future__ import annotations

import importlib.util
import io
import tempfile
import zipfile
from pathlib import Path
from typing import Annotated, Any, Literal

import numpy as np
from fastapi import APIRouter, Query
from fastapi.responses import Response

from hybridmpm.mpm.bodies import BodyTrack
from hybridmpm.render import export_points, export_surfaces
from hybridmpm.render.bodies import export_bodies
from hybridmpm.service.budget import RecordedFrame, mesh_download_bytes
from hybridmpm.service.core import RECORD_STEPS
from hybridmpm.service.deps import ManagerDep, SessionDep
from hybridmpm.service.errors import ApiError, FieldError
from hybridmpm.trajectory import Trajectory

NPZ = "application/x-npz"
ZIP = "application/zip"
#: Copies of the trajectory alive while its file is made (the stacked positions, the file, its buffer).
FILE_COPIES = 3
#: Bytes per position value of the PLY zip while it is made (the float64 copy, the velocities, the files, the zip).
PLY_BYTES_PER_VALUE = 40

router = APIRouter()


def trajectory_mesh_zip(traj: Trajectory, settings: dict[str, Any], bodies: BodyTrack | None = None) -> bytes:
    """One binary PLY surface per frame and material (``water_00000.ply``, ``sand_00000.ply`` …; 2D: outlines), zipped;
    the obstacles of ``settings`` placed in each frame at the trajectory's ``obstacle_centers`` (when it has them); with
    ``bodies`` (the frames' :class:`~hybridmpm.mpm.bodies.BodyTrack`: :func:`recorded_bodies`), each body at each frame
    (``body_<i>_<t>.ply``, :func:`hybridmpm.render.bodies.export_bodies`) and the surfaces ending on it."""
    buf = io.BytesIO()
    with tempfile.TemporaryDirectory(prefix="hybridmpm-mesh-") as tmp:
        paths = export_surfaces(traj.positions, traj.particle_type, tmp, fmt="ply", obstacle_centers=traj.obstacle_centers, bodies=bodies, **settings)
        if bodies is not None:
            paths += export_bodies(tmp, bodies, fmt="ply")
        with zipfile.ZipFile(buf, "w", zipfile.ZIP_DEFLATED, compresslevel=1) as z:
            for p in paths:
                z.write(p, Path(p).name)
    return buf.getvalue()


def recorded_bodies(held: list[RecordedFrame]) -> BodyTrack | None:
    """The bodies of a session's recorded frames (oldest first) as one track, when every frame has the same ones
    (none added or removed meanwhile): :meth:`~hybridmpm.mpm.bodies.BodyTrack.stack`, the rule a rollout keeps
    its bodies by; else None."""
    return BodyTrack.stack([h[5] for h in held])


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
            "frame_index [T], solver [T] (0 MPM, 1 network), controlled [T], obstacle_centers [T, C, D] (a scene with obstacles), "
            "body_center [T, B, D], body_rotation [T, B, D, D] and body_mass [B] (bodies, none added or removed in these frames); "
            "or a zip of one PLY point cloud per frame, or of the surface meshes (and each body's)",
        },
        404: {"description": "no such session"},
        409: {"description": "no frame recorded (the memory budget was full)"},
    },
)
async def get_session_trajectory(
    s: SessionDep,
    manager: ManagerDep,
    frames: Annotated[int, Query(ge=1, le=RECORD_STEPS, description="the latest coarse steps wanted (fewer if fewer are recorded)")] = RECORD_STEPS,
    format: Annotated[
        Literal["npz", "ply", "mesh"], Query(description="npz (a hybridmpm trajectory), ply (a zip of PLY point clouds) or mesh (a zip of surface meshes)")
    ] = "npz",  # noqa: A002 - the query's name
) -> Response:
    """The session's latest ``frames`` coarse steps, consecutive (a reset or
    a restored checkpoint starts the recording again; controls and steps are
    recorded as they run)."""
    if format == "mesh" and importlib.util.find_spec("skimage") is None:
        raise FieldError(("query", "format"), "format: mesh needs scikit-image on the server (pip install 'hybridmpm[mesh]')")
    held = await manager.recorded(s, frames)  # in the session's actor with --backend ray
    if not held:
        raise ApiError(409, "no frame of this session is recorded (the memory budget was full); step it and retry")
    f = s.facts
    values = len(held) * f.num_total * f.dim
    dt, n_grid = f.step_dt, f.n_grid
    ptype, masses, material = f.particle_type, f.masses, f.material
    if format == "mesh":
        reserve = mesh_download_bytes(len(held), f.num_total, f.dim, f.n_grid)  # measured: benchmarks/bench_mesh_memory.py
    else:
        reserve = values * (PLY_BYTES_PER_VALUE if format == "ply" else 4 * FILE_COPIES)
    with manager.budget.hold(reserve, "the trajectory's file"):
        track = recorded_bodies(held)  # the bodies when every frame held has the same ones

        def make() -> Trajectory:
            centers = [h[4] for h in held if h[4] is not None]
            return Trajectory(
                obstacle_centers=np.stack(centers) if centers and len(centers) == len(held) else None,
                body_center=None if track is None else track.center,
                body_rotation=None if track is None else track.rotation,
                body_mass=None if track is None else track.mass,
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
        name = f"{s.settings.scene}-seed{s.settings.seed}-frames{first}-{last}"
        if format == "ply":
            data = await manager.compute(trajectory_ply_zip, traj, traj.extras["solver"])
            media, name = ZIP, name + "-ply.zip"
        elif format == "mesh":
            data = await manager.compute(trajectory_mesh_zip, traj, f.surface, track)
            media, name = ZIP, name + "-mesh.zip"
        else:
            data = await manager.compute(trajectory_npz, traj)
            media, name = NPZ, name + ".npz"
        del traj
    s.touch()
    return Response(data, media_type=media, headers={"Content-Disposition": f'attachment; filename="{name}"', "X-Frames": f"{first},{last}"})
