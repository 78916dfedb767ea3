"""``hybridmpm export``: surface meshes and USD from a saved trajectory, and the
export step ``hybridmpm simulate --export`` shares with it."""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

import numpy as np

from hybridmpm.cli.common import out_dir, parse_seed
from hybridmpm.errors import InvalidInputError
from hybridmpm.files import loads_json

#: What ``--export`` takes: point clouds (``ply``, ``vtu``), surface meshes (``mesh``), one USD file (``usd``).
EXPORTS = ("ply", "vtu", "mesh", "usd")
#: Extras key of trajectory.npz holding the scene's MpmParams as JSON (written by ``simulate``).
PARAMS_KEY = "scene_params"


#: Key of a sampled (mesh) obstacle's entry in ``scene_params`` holding its scene centre (its mesh's ``center``).
CENTER_KEY = "scene_center"


def params_json(params: Any) -> np.ndarray:
    """The scene's :class:`~hybridmpm.mpm.MpmParams` as a 0-d unicode array
    (a trajectory extra, no pickle); a sampled (mesh) obstacle's entry also
    holds its centre as :data:`CENTER_KEY` (the reference of the
    trajectory's ``obstacle_centers``: its mesh's, not its samples' corner)."""
    from hybridmpm.mpm import SampledSdf  # import time: loaded by the commands that export only
    from hybridmpm.scenes.obstacles import obstacle_center

    d = params.to_dict()
    for entry, c in zip(d["colliders"], params.colliders):
        if isinstance(c, SampledSdf):
            entry[CENTER_KEY] = obstacle_center(c).tolist()
    return np.asarray(json.dumps(d))


def params_of(traj: Any, scene: str | None = None, seed: int = 0) -> tuple[Any, str]:
    """The :class:`~hybridmpm.mpm.MpmParams` a trajectory was run with and where
    they came from: its ``scene_params`` extra (written by ``simulate``);
    else the registered or file scene ``scene`` rebuilt with ``seed`` on the
    trajectory's grid; else the unit box with default walls on the
    trajectory's grid and no obstacles. Obstacles stand where the scene put
    them (a trajectory's ``obstacle_centers`` places them per frame:
    :func:`write_exports`)."""
    from hybridmpm.mpm import MpmParams, SampledSdf  # import time: loaded by this command only

    raw = traj.extras.get(PARAMS_KEY)
    if raw is not None:
        arr = np.asarray(raw)
        if arr.ndim != 0 or arr.dtype.kind != "U":
            raise InvalidInputError(f"{PARAMS_KEY}: expected one JSON string in the trajectory, got {arr.dtype} {list(arr.shape)}", PARAMS_KEY)
        d = loads_json(str(arr), PARAMS_KEY)  # nesting checked before parsing
        try:
            cols = d.get("colliders") if isinstance(d, dict) else None
            centers = [c.pop(CENTER_KEY, None) if isinstance(c, dict) else None for c in cols] if isinstance(cols, list) else []
            params = MpmParams.from_dict(d)
        except (ValueError, TypeError, AttributeError) as e:
            raise InvalidInputError(f"{PARAMS_KEY}: unreadable in the trajectory ({e})", PARAMS_KEY) from e
        for c, center in zip(params.colliders, centers):
            if center is not None and isinstance(c, SampledSdf):  # a mesh obstacle: where its centre is (its only source key here)
                c.source = {"center": [float(v) for v in center]}
        return params, "the trajectory's scene_params"
    n_grid = traj.n_grid
    if scene is not None:
        from hybridmpm.scenes import make_scene  # import time: loaded by this command only

        return make_scene(scene, seed=seed, n_grid=n_grid).params, f"scene {scene} (seed {seed}) rebuilt"
    return MpmParams(dim=traj.dim, n_grid=n_grid), "default walls, no obstacles (no scene_params in the file; pass --scene)"


def write_exports(
    out: Path,
    kinds: list[str],
    traj: Any,
    params: Any,
    *,
    mesh_format: str = "ply",
    solver: Any = None,
) -> dict[str, Any]:
    """Write every export of ``kinds`` (:data:`EXPORTS`) for trajectory
    ``traj`` into ``out``: ``frame_#####.ply|vtu`` point clouds,
    ``<material>_#####.<mesh_format>`` surface sequences (and
    ``body_<i>_#####.<mesh_format>``, each rigid body at its pose, when
    ``params`` has bodies and ``traj`` their ``body_center`` /
    ``body_rotation``), ``run.usd``.
    Surfaces are computed once for ``mesh`` and ``usd``; the obstacles of
    ``params`` stand in each frame where the trajectory's
    ``obstacle_centers`` put them (surfaces end on them there, the USD file
    samples their translation), or where ``params`` put them when it has
    none. Returns a summary
    {kind: file count or path}. Raises :class:`InvalidInputError` naming
    ``export`` (unknown kind, or ``usd`` without ``pxr``), ``mesh_format``, or
    ``body_center`` / ``body_rotation`` (for ``mesh`` and ``usd``: the
    trajectory's poses are not those of ``params``' bodies,
    :func:`~hybridmpm.mpm.bodies.as_body_track`)."""
    # import time: loaded by the commands that export only
    from hybridmpm.mpm.bodies import as_body_track
    from hybridmpm.render import export_points
    from hybridmpm.render.surface import MESH_FORMATS, frame_surfaces, write_surface
    from hybridmpm.render.surface_scene import posed_settings, surface_settings

    bad = [k for k in kinds if k not in EXPORTS]
    if bad:
        raise InvalidInputError(f"export: unknown export {bad[0]!r} (choose from {', '.join(EXPORTS)})", "export")
    if mesh_format not in MESH_FORMATS:
        raise InvalidInputError(f"mesh_format: must be one of {', '.join(MESH_FORMATS)}, got {mesh_format!r}", "mesh_format")
    if "usd" in kinds:
        from hybridmpm.render.usd import require_pxr  # import time: loaded by the commands that export only

        require_pxr("export")
    if "mesh" in kinds and traj.dim == 2 and mesh_format == "glb":
        raise InvalidInputError("mesh_format: 2D outlines are written as ply or obj (glb holds triangle meshes)", "mesh_format")
    out.mkdir(parents=True, exist_ok=True)
    done: dict[str, Any] = {}
    tags = solver if solver is not None else traj.extras.get("solver")
    for fmt in ("ply", "vtu"):
        if fmt in kinds:
            done[fmt] = len(export_points(traj.positions, traj.particle_type, out, fmt=fmt, dt=traj.dt_frame, solver=tags))
    if "mesh" in kinds or "usd" in kinds:
        settings = surface_settings(params, traj.particle_type, traj.masses)
        centers = traj.obstacle_centers
        if centers is not None and centers.shape[1] != len(settings["obstacles"]):
            raise InvalidInputError(
                f"obstacle_centers: the trajectory places {centers.shape[1]} obstacles, its scene has {len(settings['obstacles'])}", "obstacle_centers"
            )
        # the scene's bodies at the trajectory's poses as one track, checked once here (None: no bodies to draw)
        track = as_body_track(params.bodies, traj.body_center, traj.body_rotation, mass=traj.body_mass, t_count=traj.num_frames)
        surfaces = [frame_surfaces(traj.positions[t], traj.particle_type, **posed_settings(settings, centers, t, track)) for t in range(traj.num_frames)]
        if "mesh" in kinds:
            count = 0
            for t, frame in enumerate(surfaces):
                for s in frame:
                    write_surface(s, out / f"{s.material}_{t:05d}.{mesh_format}", mesh_format)
                    count += 1
            done["mesh"] = count
            if track is not None:
                from hybridmpm.render.bodies import export_bodies  # import time: loaded by the commands that export only

                done["body"] = len(export_bodies(out, track, fmt=mesh_format))
        if "usd" in kinds:
            from hybridmpm.render.usd import write_usd  # import time: loaded by the commands that export only

            path = write_usd(
                out / "run.usd", traj.positions, traj.particle_type, traj.dt_frame, solver=tags, surfaces=surfaces,
                obstacles=settings["obstacles"], obstacle_centers=centers, domain=settings["domain"], width=settings["dx"] / 2, bodies=track,
            )  # fmt: skip
            done["usd"] = str(path)
    return done


def _export(args: argparse.Namespace) -> int:
    from hybridmpm.trajectory import Trajectory  # import time: loaded by this command only

    traj = Trajectory.load(args.trajectory)
    kinds = (["mesh"] if args.mesh else []) + (["usd"] if args.usd else []) + ([args.points] if args.points else [])
    if not kinds:
        raise InvalidInputError("export: nothing to write; give --mesh, --usd and/or --points ply|vtu", "export")
    out = out_dir(args.out)
    params, source = params_of(traj, args.scene, args.seed)
    if params.dim != traj.dim:
        raise InvalidInputError(f"scene: a {params.dim}D scene for a {traj.dim}D trajectory", "scene")
    done = write_exports(out, kinds, traj, params, mesh_format=args.mesh_format)
    if not args.quiet:
        parts = [f"{v} {k} files" if isinstance(v, int) else f"{v}" for k, v in done.items()]
        print(f"{traj.num_frames} frames; domain and obstacles from {source}: " + ", ".join(parts) + f" -> {out}/")
    return 0


def add_parsers(sub: Any) -> None:
    """Register ``export`` on the subparsers ``sub``."""
    ex = sub.add_parser("export", help="write surface meshes and/or a USD file from a saved trajectory.npz")
    ex.add_argument("trajectory", help="trajectory.npz as written by hybridmpm simulate")
    ex.add_argument("--mesh", action="store_true", help="surface mesh sequence <material>_#####.<fmt> (docs/mesh.md)")
    ex.add_argument("--usd", action="store_true", help="one USD file run.usd: particles, surfaces, obstacles (docs/usd.md; needs the usd extra)")
    ex.add_argument("--points", default=None, choices=["ply", "vtu"], help="also the point-cloud sequence frame_#####.ply|vtu")
    ex.add_argument("--mesh-format", default="ply", choices=["ply", "obj", "glb"], help="format of the mesh sequence (default ply)")
    ex.add_argument(
        "--scene", default=None, help="for a trajectory without scene_params (older files): the scene (name or file) whose walls and obstacles to use"
    )
    ex.add_argument("--seed", type=parse_seed, default=0, help="--scene: its seed (default 0)")
    ex.add_argument("--out", required=True, help="output directory")
    ex.add_argument("--quiet", action="store_true", help="no summary line")
    ex.set_defaults(func=_export)


__all__ = ["CENTER_KEY", "EXPORTS", "PARAMS_KEY", "add_parsers", "params_json", "params_of", "write_exports"]
