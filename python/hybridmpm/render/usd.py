"""One USD file per run: particles, fluid surfaces, obstacles and the domain, time-sampled.

Written with Pixar's ``pxr`` (the ``usd`` extra: ``pip install 'hybridmpm[usd]'``,
PyPI ``usd-core``). Layout (``/Run`` is the default prim):

==========================  ====================  ==================================================
prim                        type                  contents
==========================  ====================  ==================================================
``/Run/Particles``          ``Points``            ``points`` [m] and ``velocities`` [m/s] per frame;
                                                  ``ids`` (particle index), ``widths`` (particle
                                                  spacing), ``primvars:material`` (GNS type per
                                                  point: water 5, sand 6, boundary 3),
                                                  ``primvars:solver`` (per frame, constant
                                                  interpolation: 0 MPM, 1 neural)
``/Run/Surfaces/<material>`` ``Mesh`` (3D) or      surface per frame (:mod:`hybridmpm.render.surface`):
                            ``BasisCurves`` (2D)  ``points``, ``faceVertexCounts``,
                                                  ``faceVertexIndices`` (2D: ``curveVertexCounts``,
                                                  closed linear curves)
``/Run/Obstacles/obstacle_<i>``  ``Cube``/``Sphere``/``Mesh``  boxes as unit cubes scaled to the half extents and
                                                  rotated (``xformOp:transform``), spheres as
                                                  spheres, sampled-SDF (mesh) obstacles as their
                                                  zero level set; an obstacle that moves has an
                                                  ``xformOp:translate`` sampled per frame (its
                                                  centre; a mesh: its displacement)
``/Run/Bodies/body_<i>``    ``Xform``             a rigid body: ``xformOp:translate`` (its centre of
                                                  mass) and ``xformOp:orient`` (its rotation, a
                                                  quaternion) sampled per frame; its child
                                                  ``shape`` (``Mesh``) the body in its own frame: a
                                                  box's 8 corners, a sphere's icosphere, a 2D
                                                  body's outline extruded to z = ±``DEPTH_2D``
``/Run/Domain``             ``BasisCurves``       the edges of the fluid domain (the wall faces),
                                                  purpose ``guide``
==========================  ====================  ==================================================

Units and axes: metres (``metersPerUnit = 1``), y up (``upAxis = "Y"``, the
solver's gravity axis), 2D runs at z = 0. Time: frame ``t`` of the trajectory
is time code ``t``; ``timeCodesPerSecond = framesPerSecond = 1/dt_frame``, so
one second of simulated time plays in one second.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from hybridmpm.errors import InvalidInputError
from hybridmpm.mpm import Sphere
from hybridmpm.mpm.bodies import BodyTrack, as_body_track
from hybridmpm.render.bodies import body_prism, local_mesh
from hybridmpm.render.surface import SurfaceContours, SurfaceMesh
from hybridmpm.render.surface_field import is_sampled
from hybridmpm.scenes.obstacles import box_rotation, obstacle_center
from hybridmpm.trajectory import check_frame_velocities

#: Suffixes :func:`write_usd` writes (``.usd`` is the binary crate format).
USD_SUFFIXES = (".usd", ".usda", ".usdc")
#: Half thickness [m] along z of a 2D box obstacle in the file.
DEPTH_2D = 0.05


def require_pxr(field: str = "usd") -> Any:
    """Import ``pxr`` or raise :class:`InvalidInputError` naming ``field``."""
    try:
        from pxr import Usd
    except ImportError as e:
        what = "--export usd" if field == "export" else "USD export"
        raise InvalidInputError(f"{field}: {what} needs the usd extra: pip install 'hybridmpm[usd]' (usd-core) ({e})", field) from e
    return Usd


def _vec3(a: np.ndarray) -> np.ndarray:
    a = np.asarray(a, np.float32)
    return a if a.shape[-1] == 3 else np.concatenate([a, np.zeros(a.shape[:-1] + (1,), np.float32)], axis=-1)


def write_usd(
    path: str | os.PathLike[str],
    positions: Any,
    particle_type: Any,
    dt_frame: float,
    *,
    solver: Any = None,
    surfaces: Sequence[Sequence[SurfaceMesh | SurfaceContours]] | None = None,
    obstacles: Sequence[Any] = (),
    obstacle_centers: Any = None,
    domain: tuple[Sequence[float], Sequence[float]] | None = None,
    width: float | None = None,
    bodies: BodyTrack | Sequence[Any] | None = (),
    body_center: Any = None,
    body_rotation: Any = None,
) -> Path:
    """Write a run as one USD stage at ``path`` (see the module doc for the prims).

    ``positions`` float [T, N, D] [m] (D 2 or 3, finite); ``particle_type``
    int [N]; ``dt_frame`` [s] between stored frames (> 0); ``solver`` int [T]
    (0 MPM, 1 neural) or None (all 0); ``surfaces`` one list per frame of
    :class:`SurfaceMesh` (3D) / :class:`SurfaceContours` (2D), or None for
    none; ``obstacles`` the scene's colliders (where the scene puts them);
    ``obstacle_centers`` float [T, C, D] [m] each obstacle's centre per frame
    (a trajectory's :attr:`~hybridmpm.trajectory.Trajectory.obstacle_centers`)
    or None (they stand still): an obstacle whose centre differs from the
    scene's in float32 in some frame gets a translate op sampled at every
    frame, the others are written once; ``domain`` ``(lo, hi)`` [m] or
    None (no domain prim); ``width`` the points' display width [m] (default:
    none written); ``bodies`` the rigid bodies over the T frames: a
    :class:`~hybridmpm.mpm.bodies.BodyTrack` (a rollout's
    :attr:`~hybridmpm.sim.Rollout.bodies`), or the scene's
    :class:`~hybridmpm.mpm.bodies.Body` list at ``body_center`` float
    [T, B, D] [m] and ``body_rotation`` [T, B, D, D] (a trajectory's arrays,
    made into a track once here: :func:`~hybridmpm.mpm.bodies.as_body_track`;
    without them no body is written). Returns the path.

    Raises :class:`InvalidInputError` naming ``path`` (suffix not one of
    :data:`USD_SUFFIXES`, folder missing or not writable), ``positions``,
    ``particle_type``, ``dt_frame`` (also when it makes a particle's velocity
    between frames overflow float32: :func:`~hybridmpm.trajectory.check_frame_velocities`),
    ``solver``, ``surfaces``, ``obstacle_centers``, ``body_center``, ``body_rotation`` or ``usd``
    (``pxr`` not installed).
    """
    require_pxr()
    from pxr import Gf, Sdf, Usd, UsdGeom, Vt

    path = Path(path)
    if path.suffix.lower() not in USD_SUFFIXES:
        raise InvalidInputError(f"path: a USD file must end in {', '.join(USD_SUFFIXES)}, got {path.name!r}", "path")
    if not path.parent.is_dir() or not os.access(path.parent, os.W_OK):
        raise InvalidInputError(f"path: folder {path.parent} does not exist or is not writable", "path")
    p = np.asarray(positions)
    if p.dtype.kind not in "fiu" or p.ndim != 3 or p.shape[2] not in (2, 3) or p.shape[0] < 1:
        raise InvalidInputError(f"positions: expected a real array [T, N, 2|3], got {list(p.shape)}", "positions")
    if not np.isfinite(p).all():
        raise InvalidInputError("positions: non-finite coordinates", "positions")
    t_count, n, dim = p.shape
    pt = np.asarray(particle_type)
    if pt.dtype.kind not in "iu" or pt.shape != (n,):
        raise InvalidInputError(f"particle_type: expected an integer array [{n}], got {list(pt.shape)}", "particle_type")
    if not (isinstance(dt_frame, (int, float, np.integer, np.floating)) and np.isfinite(dt_frame) and dt_frame > 0):
        raise InvalidInputError(f"dt_frame: must be a finite number > 0 [s], got {dt_frame!r}", "dt_frame")
    check_frame_velocities(p, float(dt_frame))  # the velocities written below stay finite float32
    tags = np.zeros(t_count, np.int32) if solver is None else np.asarray(solver)
    if tags.shape != (t_count,):
        raise InvalidInputError(f"solver: expected [{t_count}] tags, got {list(tags.shape)}", "solver")
    if surfaces is not None and len(surfaces) != t_count:
        raise InvalidInputError(f"surfaces: expected one list per frame ({t_count}), got {len(surfaces)}", "surfaces")
    oc = None if obstacle_centers is None else np.asarray(obstacle_centers)
    if oc is not None:
        if oc.dtype.kind not in "fiu" or oc.shape != (t_count, len(obstacles), dim) or not np.isfinite(oc).all():
            raise InvalidInputError(
                f"obstacle_centers: expected finite numbers [{t_count}, {len(obstacles)}, {dim}], got {oc.dtype} {list(oc.shape)}", "obstacle_centers"
            )
        oc = oc.astype(np.float64)
    track = as_body_track(bodies, body_center, body_rotation, t_count=t_count)

    tmp = path.with_name(path.name + ".tmp" + path.suffix)
    stage = Usd.Stage.CreateNew(str(tmp))
    fps = 1.0 / float(dt_frame)
    stage.SetTimeCodesPerSecond(fps)
    stage.SetFramesPerSecond(fps)
    stage.SetStartTimeCode(0)
    stage.SetEndTimeCode(t_count - 1)
    UsdGeom.SetStageMetersPerUnit(stage, 1.0)
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.y)
    root = UsdGeom.Xform.Define(stage, "/Run")
    stage.SetDefaultPrim(root.GetPrim())
    root.GetPrim().SetCustomDataByKey("hybridmpm:dt_frame", float(dt_frame))

    # particles
    pts = UsdGeom.Points.Define(stage, "/Run/Particles")
    pts.CreateIdsAttr(Vt.Int64Array.FromNumpy(np.arange(n, dtype=np.int64)))
    if width is not None:
        pts.CreateWidthsAttr(Vt.FloatArray([float(width)]))
        pts.SetWidthsInterpolation(UsdGeom.Tokens.constant)
    pv = UsdGeom.PrimvarsAPI(pts)
    pv.CreatePrimvar("material", Sdf.ValueTypeNames.IntArray, UsdGeom.Tokens.vertex).Set(Vt.IntArray.FromNumpy(pt.astype(np.int32)))
    solver_pv = pv.CreatePrimvar("solver", Sdf.ValueTypeNames.IntArray, UsdGeom.Tokens.constant)
    pa, va, ea = pts.CreatePointsAttr(), pts.CreateVelocitiesAttr(), pts.CreateExtentAttr()
    p3 = _vec3(p)
    for t in range(t_count):
        vel = (p3[t] - p3[t - 1]) / float(dt_frame) if t > 0 else np.zeros_like(p3[t])
        pa.Set(Vt.Vec3fArray.FromNumpy(p3[t]), t)
        va.Set(Vt.Vec3fArray.FromNumpy(vel.astype(np.float32)), t)
        ea.Set(Vt.Vec3fArray.FromNumpy(np.stack([p3[t].min(axis=0), p3[t].max(axis=0)])), t)
        solver_pv.Set(Vt.IntArray([int(tags[t])]), t)

    # surfaces
    if surfaces is not None:
        _write_surfaces(stage, surfaces)

    # obstacles and domain
    UsdGeom.Scope.Define(stage, "/Run/Obstacles")
    for i, c in enumerate(obstacles):
        moved = oc is not None and not (oc[:, i].astype(np.float32) == obstacle_center(c).astype(np.float32)).all()
        _write_obstacle(stage, f"/Run/Obstacles/obstacle_{i}", c, dim, Gf, oc[:, i] if moved and oc is not None else None)
    if track is not None:
        UsdGeom.Scope.Define(stage, "/Run/Bodies")
        for i, b in enumerate(track.shapes):
            _write_body(stage, f"/Run/Bodies/body_{i}", b, track.center[:, i], track.rotation[:, i])
    if domain is not None:
        lo, hi = (_vec3(np.asarray(b, np.float32)) for b in domain)
        _write_domain(stage, lo, hi, dim)
    stage.GetRootLayer().Save()
    del stage
    os.replace(tmp, path)
    return path


def _write_surfaces(stage: Any, surfaces: Sequence[Sequence[SurfaceMesh | SurfaceContours]]) -> None:
    from pxr import UsdGeom, Vt

    UsdGeom.Scope.Define(stage, "/Run/Surfaces")
    prims: dict[str, Any] = {}
    for t, frame in enumerate(surfaces):
        for s in frame:
            prim = prims.get(s.material)
            if isinstance(s, SurfaceMesh):
                if prim is None:
                    prim = prims[s.material] = UsdGeom.Mesh.Define(stage, f"/Run/Surfaces/{s.material}")
                    prim.CreateSubdivisionSchemeAttr(UsdGeom.Tokens.none)
                    prim.CreateOrientationAttr(UsdGeom.Tokens.rightHanded)
                v = np.asarray(s.vertices, np.float32).reshape(-1, 3)
                prim.CreatePointsAttr().Set(Vt.Vec3fArray.FromNumpy(v), t)
                prim.CreateFaceVertexCountsAttr().Set(Vt.IntArray.FromNumpy(np.full(len(s.faces), 3, np.int32)), t)
                prim.CreateFaceVertexIndicesAttr().Set(Vt.IntArray.FromNumpy(np.asarray(s.faces, np.int32).ravel()), t)
            else:
                if prim is None:
                    prim = prims[s.material] = UsdGeom.BasisCurves.Define(stage, f"/Run/Surfaces/{s.material}")
                    prim.CreateTypeAttr(UsdGeom.Tokens.linear)
                    prim.CreateWrapAttr(UsdGeom.Tokens.periodic)
                loops = [lp[:-1] for lp in s.loops]  # periodic curves: the closing point is implied
                v = _vec3(np.concatenate(loops)) if loops else np.zeros((0, 3), np.float32)
                prim.CreatePointsAttr().Set(Vt.Vec3fArray.FromNumpy(v), t)
                prim.CreateCurveVertexCountsAttr().Set(Vt.IntArray([len(lp) for lp in loops]), t)
            if len(v):
                prim.CreateExtentAttr().Set(Vt.Vec3fArray.FromNumpy(np.stack([v.min(axis=0), v.max(axis=0)])), t)


def _translate(prim: Any, centers: np.ndarray, gf: Any) -> None:
    """A translate op on ``prim`` sampled at every frame: ``centers`` float64 [T, D] (z = 0 in 2D)."""
    c3 = np.zeros((len(centers), 3))
    c3[:, : centers.shape[1]] = centers
    op = prim.AddTranslateOp()
    for t, c in enumerate(c3):
        op.Set(gf.Vec3d(*c.tolist()), t)


def _write_obstacle(stage: Any, where: str, c: Any, dim: int, gf: Any, centers: np.ndarray | None) -> None:
    """Obstacle ``c`` at ``where``; ``centers`` float64 [T, D] its centre per frame when it moves (None: it stands where the scene put it)."""
    from pxr import UsdGeom, Vt

    if is_sampled(c):  # a mesh obstacle: its zero level set
        from skimage.measure import marching_cubes

        vals = np.asarray(c.values, np.float32)
        mesh = UsdGeom.Mesh.Define(stage, where)
        if dim == 3 and vals.min() < 0 < vals.max():
            vs, fs, _, _ = marching_cubes(np.pad(vals, 1, constant_values=max(float(vals.max()), 1e-3)), 0.0)
            v = (vs - 1) * float(c.cell) + np.asarray(c.origin, np.float64)
            mesh.CreatePointsAttr(Vt.Vec3fArray.FromNumpy(v.astype(np.float32)))
            mesh.CreateFaceVertexCountsAttr(Vt.IntArray.FromNumpy(np.full(len(fs), 3, np.int32)))
            mesh.CreateFaceVertexIndicesAttr(Vt.IntArray.FromNumpy(fs[:, ::-1].astype(np.int32).ravel()))
            mesh.CreateSubdivisionSchemeAttr(UsdGeom.Tokens.none)
        if centers is not None:  # the level set stays at the scene's pose, moved by the displacement
            _translate(mesh, centers - obstacle_center(c), gf)
        return
    center = np.zeros(3)
    center[:dim] = np.asarray(c.center, np.float64)
    if isinstance(c, Sphere):
        s = UsdGeom.Sphere.Define(stage, where)
        s.CreateRadiusAttr(float(c.radius))
        s.CreateExtentAttr(Vt.Vec3fArray([gf.Vec3f(-float(c.radius)), gf.Vec3f(float(c.radius))]))
        if centers is not None:
            _translate(s, centers, gf)
        else:
            s.AddTranslateOp().Set(gf.Vec3d(*center))
        return
    half = np.full(3, DEPTH_2D)
    half[:dim] = np.asarray(c.half_extents, np.float64)
    rot = np.eye(3)
    rot[:dim, :dim] = box_rotation(c, dim)
    m = np.eye(4)
    m[:3, :3] = (rot * half[None, :]).T  # row-vector convention: p' = p · M, columns of rot scaled by the half extents
    cube = UsdGeom.Cube.Define(stage, where)
    cube.CreateSizeAttr(2.0)
    if centers is not None:  # moving: translate (sampled) ∘ the rotation and scale
        _translate(cube, centers, gf)
    else:
        m[3, :3] = center
    cube.AddTransformOp().Set(gf.Matrix4d(*m.ravel().tolist()))


def quaternion(r: np.ndarray) -> list[float]:
    """The unit quaternion (w, x, y, z) of rotation ``r`` [3, 3] (``x' = r x``), in float64
    (Shepperd's method: Gf's matrix-to-rotation conversion rounds a rotation of 1e-5 rad to none)."""
    tr = float(np.trace(r))
    k = int(np.argmax([tr, r[0, 0], r[1, 1], r[2, 2]]))
    if k == 0:
        s = 2.0 * np.sqrt(1.0 + tr)
        q = [s / 4, (r[2, 1] - r[1, 2]) / s, (r[0, 2] - r[2, 0]) / s, (r[1, 0] - r[0, 1]) / s]
    else:
        i, j, m = k - 1, k % 3, (k + 1) % 3
        s = 2.0 * np.sqrt(max(1.0 + r[i, i] - r[j, j] - r[m, m], 1e-300))
        q = [0.0, 0.0, 0.0, 0.0]
        q[0] = (r[m, j] - r[j, m]) / s
        q[1 + i] = s / 4
        q[1 + j] = (r[j, i] + r[i, j]) / s
        q[1 + m] = (r[m, i] + r[i, m]) / s
    q = np.asarray(q) / np.linalg.norm(q)
    return [float(v) for v in q]


def _write_body(stage: Any, where: str, body: Any, centers: np.ndarray, rotations: np.ndarray) -> None:
    """Body ``body`` at ``where``: an Xform whose translate and orient are sampled at every frame
    (``centers`` float64 [T, D], ``rotations`` [T, D, D]), its mesh in its own frame as child ``shape``."""
    from pxr import Gf, UsdGeom, Vt

    dim = centers.shape[1]
    xf = UsdGeom.Xform.Define(stage, where)
    move = xf.AddTranslateOp(precision=UsdGeom.XformOp.PrecisionDouble)
    turn = xf.AddOrientOp(precision=UsdGeom.XformOp.PrecisionDouble)
    for t in range(len(centers)):
        c3, r3 = np.zeros(3), np.eye(3)
        c3[:dim], r3[:dim, :dim] = centers[t], rotations[t]
        move.Set(Gf.Vec3d(*c3.tolist()), t)
        w, *xyz = quaternion(r3)
        turn.Set(Gf.Quatd(w, Gf.Vec3d(*xyz)), t)
    v, f = local_mesh(body) if dim == 3 else body_prism(body, DEPTH_2D)
    mesh = UsdGeom.Mesh.Define(stage, where + "/shape")
    mesh.CreatePointsAttr(Vt.Vec3fArray.FromNumpy(np.asarray(v, np.float32)))
    mesh.CreateFaceVertexCountsAttr(Vt.IntArray.FromNumpy(np.full(len(f), 3, np.int32)))
    mesh.CreateFaceVertexIndicesAttr(Vt.IntArray.FromNumpy(np.asarray(f, np.int32).ravel()))
    mesh.CreateSubdivisionSchemeAttr(UsdGeom.Tokens.none)
    mesh.CreateExtentAttr(Vt.Vec3fArray.FromNumpy(np.stack([v.min(axis=0), v.max(axis=0)]).astype(np.float32)))


def _write_domain(stage: Any, lo: np.ndarray, hi: np.ndarray, dim: int) -> None:
    from pxr import UsdGeom, Vt

    curves = UsdGeom.BasisCurves.Define(stage, "/Run/Domain")
    curves.CreateTypeAttr(UsdGeom.Tokens.linear)
    curves.CreatePurposeAttr(UsdGeom.Tokens.guide)
    if dim == 2:
        pts = np.array([[lo[0], lo[1], 0], [hi[0], lo[1], 0], [hi[0], hi[1], 0], [lo[0], hi[1], 0]], np.float32)
        curves.CreateWrapAttr(UsdGeom.Tokens.periodic)
        counts = [4]
    else:
        corner = np.array([[(hi if (k >> a) & 1 else lo)[a] for a in range(3)] for k in range(8)], np.float32)
        edges = [(k, k | (1 << a)) for k in range(8) for a in range(3) if not (k >> a) & 1]
        pts = np.concatenate([corner[list(e)] for e in edges])
        counts = [2] * len(edges)
    curves.CreatePointsAttr(Vt.Vec3fArray.FromNumpy(pts))
    curves.CreateCurveVertexCountsAttr(Vt.IntArray(counts))
    curves.CreateWidthsAttr(Vt.FloatArray([0.002]))
    curves.SetWidthsInterpolation(UsdGeom.Tokens.constant)


__all__ = ["DEPTH_2D", "USD_SUFFIXES", "quaternion", "require_pxr", "write_usd"]
