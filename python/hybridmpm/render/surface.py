"""Fluid surfaces from particles: triangle meshes (3D) and closed contours (2D).

The surface of one material (water, sand) in one frame is built in four steps:

1. **Volume fraction.** Every particle's volume ``v_p`` [m^D] is spread onto a
   grid of spacing ``h = dx / refine`` with the quadratic B-spline of MLS-MPM
   (Hu et al. 2018, "A moving least squares material point method";
   the weights of the solver's p2g): ``φ_i = Σ_p v_p·w_ip / h^D``, the
   fraction of node ``i``'s cell the material fills (1 in the bulk of a block
   seeded on the scene's lattice).
2. **Smoothing.** ``smooth`` passes of the binomial filter ``[1, 2, 1]/4`` per
   axis (the linear B-spline; it keeps ``Σ φ``).
3. **Closure.** A wall face of the fluid domain that lies on a node layer
   (every scene's: ``(cells − 1)·dx``) folds the field (the particles'
   mirror images across it are added, so fluid resting on the wall fills the
   face and none of its volume is lost into the wall) and sets it to
   ``-1e15`` beyond: the iso-surface ends exactly on the face, at any
   thickness of the fluid there. Obstacles (and walls between node layers)
   clip it, ``φ ← min(φ, c + sdf/(2h))`` with ``sdf`` the signed distance [m]
   (:func:`~hybridmpm.scenes.collider_sdf`, positive outside the obstacle):
   the surface ends on their faces and never passes through them. The field
   is zero outside the particles' bounding box plus 3 nodes, so every
   surface closes.
4. **Iso-surface** at level ``c``: Lewiner marching cubes
   (:func:`skimage.measure.marching_cubes`) in 3D,
   :func:`skimage.measure.find_contours` in 2D. The kernels are symmetric, so a
   flat face of a filled region crosses ``φ = 1/2`` exactly at its boundary,
   but edges and corners are rounded inwards. ``iso="volume"`` (the default)
   therefore matches the enclosed volume to the particles' volume per body
   (a 26-connected component of ``φ > BODY_MIN``; a film on the floor and a
   falling block are two): each body at the level in
   [:data:`~hybridmpm.render.surface_field.ISO_MIN`,
   :data:`~hybridmpm.render.surface_field.ISO_MAX`] whose volume, estimated
   from the field cell by cell
   (:class:`~hybridmpm.render.surface_field.VolumeEstimate`, no surface
   drawn), is its particles' volume; marching cubes there, and once more (the
   level moved by the estimate's error) if the body's surface is off by more
   than :data:`VOLUME_TOL` (docs/mesh.md;
   :func:`~hybridmpm.render.surface_levels.material_surface`); a number
   fixes ``c`` for all. Vertices that marching
   cubes puts on one node (at an edge of the domain) are merged, so no face
   is degenerate or doubled.

**Determinism.** The p2g runs in the compiled core
(:func:`hybridmpm._core.surface_p2g`, serial); nothing else is threaded. The
per-axis kernel weights are rounded to multiples of 2^-10 and the volume
fractions to multiples of 2^-14, so every product and every partial sum of
the p2g is exact in float64 (while a node's value stays below 2^8, i.e.
unless the fluid is compressed 256-fold): the field, and so the mesh and the
files, have the same bits whatever the order of the particles. Output is
sorted by particle type.

**Modules.** The field and its closure (steps 1-3) are
:mod:`hybridmpm.render.surface_field`'s, the volume matching
:mod:`hybridmpm.render.surface_levels`', a scene's settings
(:func:`surface_settings`, :func:`posed_settings`)
:mod:`hybridmpm.render.surface_scene`'s; this module checks the input, draws
the iso-surfaces and writes the files.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from hybridmpm.conventions import GNS_KINEMATIC, NAME_OF_GNS_TYPE
from hybridmpm.errors import InvalidInputError
from hybridmpm.mpm import Box, Sphere
from hybridmpm.render.surface_field import MARGIN, Field, PosedBody, is_sampled
from hybridmpm.render.surface_levels import VOLUME_TOL as VOLUME_TOL
from hybridmpm.render.surface_levels import material_surface
from hybridmpm.render.surface_scene import pose_track, posed_settings, rest_densities, surface_settings

#: Largest surface grid: nodes of the domain at spacing ``dx / refine`` (512³).
MAX_GRID_NODES = 512**3
#: Formats of :func:`export_surfaces`.
MESH_FORMATS = ("ply", "obj", "glb")
#: Finest surface grid per simulation cell.
MAX_REFINE = 8
#: Field values within this of the level are moved this far from it before marching cubes (:func:`_off_level`).
_LEVEL_GAP = 2.0**-16


def material_name(ptype: int) -> str:
    """``"water"`` (GNS 5), ``"sand"`` (GNS 6) or ``"type<code>"``."""
    return NAME_OF_GNS_TYPE.get(int(ptype), f"type{int(ptype)}")


@dataclass(frozen=True)
class SurfaceMesh:
    """The closed surface of one material in one frame (3D).

    ``vertices`` float64 [V, 3] [m]; ``faces`` int32 [F, 3], indices into
    ``vertices``, counter-clockwise seen from outside (outward normals);
    ``material`` ``"water"``/``"sand"``; ``particle_type`` its GNS code;
    ``iso`` the volume-fraction level it was drawn at (with
    ``iso="volume"``: the level of the body with the most volume).
    """

    vertices: np.ndarray
    faces: np.ndarray
    material: str
    particle_type: int
    iso: float = 0.5

    @property
    def volume(self) -> float:
        """Enclosed volume [m³] (divergence theorem over the faces; exact for a closed mesh)."""
        return mesh_volume(self.vertices, self.faces)


@dataclass(frozen=True)
class SurfaceContours:
    """The closed outline of one material in one frame (2D).

    ``loops`` tuple of float64 [K, 2] [m] polylines, each closed (last point =
    first), outer boundaries counter-clockwise, holes clockwise; ``material``,
    ``particle_type`` and ``iso`` as for :class:`SurfaceMesh`.
    """

    loops: tuple[np.ndarray, ...]
    material: str
    particle_type: int
    iso: float = 0.5

    @property
    def area(self) -> float:
        """Enclosed area [m²]: the signed shoelace areas of the loops summed (holes count negative)."""
        return float(sum(_signed_area(p) for p in self.loops))


def _signed_area(p: np.ndarray) -> float:
    x, y = p[:, 0], p[:, 1]
    return float(0.5 * (np.dot(x[:-1], y[1:]) - np.dot(x[1:], y[:-1])))


# ---------------------------------------------------------------------- input checks
def _check_common(
    positions: Any, particle_type: Any, domain: Any, dx: Any, refine: Any, iso: Any, smooth: Any, volumes: Any, dim: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, float, np.ndarray]:
    p = np.asarray(positions)
    if p.dtype.kind not in "fiu" or p.ndim != 2 or p.shape[1] != dim:
        raise InvalidInputError(f"positions: expected a real array [N, {dim}], got {p.dtype} {list(p.shape)}", "positions")
    p = np.asarray(p, np.float64)
    if not np.isfinite(p).all():
        raise InvalidInputError(f"positions: particle {int(np.argwhere(~np.isfinite(p).all(axis=1))[0, 0])} has a non-finite coordinate", "positions")
    n = p.shape[0]
    pt = np.asarray(particle_type)
    if pt.dtype.kind not in "iu" or pt.shape != (n,):
        raise InvalidInputError(f"particle_type: expected an integer array [{n}], got {pt.dtype} {list(pt.shape)}", "particle_type")
    if isinstance(dx, bool) or not isinstance(dx, (int, float, np.integer, np.floating)) or not math.isfinite(dx) or dx <= 0:
        raise InvalidInputError(f"dx: must be a finite number > 0 [m], got {dx!r}", "dx")
    if isinstance(refine, bool) or not isinstance(refine, (int, np.integer)) or not 1 <= refine <= MAX_REFINE:
        raise InvalidInputError(f"refine: must be an integer in [1, {MAX_REFINE}], got {refine!r}", "refine")
    if iso != "volume" and (isinstance(iso, bool) or not isinstance(iso, (int, float, np.integer, np.floating)) or not 0.0 < iso < 1.0):
        raise InvalidInputError(f"iso: must be 'volume' or a volume fraction in (0, 1), got {iso!r}", "iso")
    if isinstance(smooth, bool) or not isinstance(smooth, (int, np.integer)) or not 0 <= smooth <= 4:
        raise InvalidInputError(f"smooth: must be an integer in [0, 4], got {smooth!r}", "smooth")
    try:
        lo, hi = (np.asarray(b, np.float64) for b in domain)
    except (TypeError, ValueError):
        raise InvalidInputError(f"domain: expected (lo, hi), each {dim} numbers [m], got {domain!r}", "domain") from None
    if lo.shape != (dim,) or hi.shape != (dim,) or not (np.isfinite(lo).all() and np.isfinite(hi).all()) or not (hi > lo).all():
        raise InvalidInputError(f"domain: expected (lo, hi), each {dim} finite numbers [m] with lo < hi, got {domain!r}", "domain")
    h = float(dx) / int(refine)
    nodes = float(np.prod((hi - lo) / h + 2 * MARGIN + 1))
    if nodes > MAX_GRID_NODES:
        raise InvalidInputError(
            f"dx: a surface grid of spacing {h:.3g} m over the domain has {nodes:.3g} nodes, more than the cap of {MAX_GRID_NODES} (512³); "
            "use a larger dx or a smaller refine",
            "dx",
        )
    if volumes is None:
        v = np.full(n, (float(dx) / 2) ** dim)
    else:
        v = np.asarray(volumes)
        if v.dtype.kind not in "fiu" or v.shape != (n,):
            raise InvalidInputError(f"volumes: expected a real array [{n}] [m^{dim}], got {v.dtype} {list(v.shape)}", "volumes")
        v = np.asarray(v, np.float64)
        if not (np.isfinite(v) & (v >= 0)).all():
            raise InvalidInputError("volumes: must be finite and >= 0", "volumes")
    return p, np.asarray(pt, np.int64), lo, hi, h, v


def _check_obstacles(obstacles: Any) -> list[Any]:
    obs = list(obstacles or ())
    for i, c in enumerate(obs):
        if not (isinstance(c, (Box, Sphere, PosedBody)) or is_sampled(c)):
            raise InvalidInputError(
                f"obstacles[{i}]: must be a collider of hybridmpm.mpm (Box, Sphere, sampled SDF) or a PosedBody, got {c!r}", f"obstacles[{i}]"
            )
    return obs


# ---------------------------------------------------------------------- public API
def surface_mesh(
    positions: Any,
    particle_type: Any,
    *,
    domain: tuple[Sequence[float], Sequence[float]],
    dx: float,
    volumes: Any = None,
    obstacles: Sequence[Any] = (),
    refine: int = 1,
    iso: float | str = "volume",
    smooth: int = 1,
) -> list[SurfaceMesh]:
    """Closed triangle meshes of the fluid in one 3D frame, one per material.

    Parameters
    ----------
    positions:
        float [N, 3] [m], finite; kinematic particles (GNS type 3) are skipped.
    particle_type:
        int [N], GNS codes (water 5, sand 6, boundary 3).
    domain:
        ``(lo, hi)``, 3 numbers each [m]: the box the fluid is held in (the
        wall faces: :func:`surface_settings` gives them for a scene).
    dx:
        The simulation's cell size [m]; the surface grid has spacing ``dx / refine``.
    volumes:
        float [N] [m³], each particle's volume; default ``(dx/2)³`` (the
        scenes' lattice of 2 particles per cell per axis).
    obstacles:
        :class:`~hybridmpm.mpm.Box` / :class:`~hybridmpm.mpm.Sphere`
        colliders; the surface ends on their faces.
    refine:
        Surface grid nodes per simulation cell per axis, 1 … 8.
    iso:
        ``"volume"`` (default): each body of fluid (a connected part of the
        field) at the level ``c`` in [0.02, 0.7] whose surface encloses its
        particles' volume: marching cubes at the level where an estimate
        from the field gives that volume and, if the surface is off by more
        than 0.5 %, once more at a corrected level (docs/mesh.md); or a
        fixed volume fraction in (0, 1) for all.
    smooth:
        Passes of the ``[1, 2, 1]/4`` filter, 0 … 4.

    Returns
    -------
    A :class:`SurfaceMesh` per fluid particle type present, sorted by type
    (water before sand); a material with no surface (e.g. only lone
    particles, whose field stays below 0.02) gets an empty mesh.

    Raises
    ------
    InvalidInputError
        naming ``positions`` (not [N, 3], non-finite), ``particle_type``,
        ``domain``, ``dx`` (<= 0, or a grid over :data:`MAX_GRID_NODES`),
        ``volumes``, ``obstacles[i]``, ``refine``, ``iso`` or ``smooth``.
    """
    out = []
    for code, level, geom in _per_material(3, _mc_measure, positions, particle_type, domain, dx, volumes, obstacles, refine, iso, smooth):
        verts, faces = geom if geom is not None else (np.zeros((0, 3)), np.zeros((0, 3), np.int32))
        out.append(SurfaceMesh(verts, faces, material_name(code), code, level))
    return out


def surface_contours(
    positions: Any,
    particle_type: Any,
    *,
    domain: tuple[Sequence[float], Sequence[float]],
    dx: float,
    volumes: Any = None,
    obstacles: Sequence[Any] = (),
    refine: int = 1,
    iso: float | str = "volume",
    smooth: int = 1,
) -> list[SurfaceContours]:
    """Closed outlines of the fluid in one 2D frame, one :class:`SurfaceContours`
    per material (sorted by type). The same field as :func:`surface_mesh`
    (``positions`` float [N, 2] [m], ``volumes`` [m²], default ``(dx/2)²``),
    the level set by :func:`skimage.measure.find_contours`. Raises
    :class:`InvalidInputError` naming the field, as :func:`surface_mesh`."""
    out = []
    for code, level, loops in _per_material(2, _contour_measure, positions, particle_type, domain, dx, volumes, obstacles, refine, iso, smooth):
        out.append(SurfaceContours(loops if loops is not None else (), material_name(code), code, level))
    return out


def _per_material(
    dim: int, measure: Any, positions: Any, particle_type: Any, domain: Any, dx: Any, volumes: Any, obstacles: Any, refine: Any, iso: Any, smooth: Any
) -> list[tuple[int, float, Any]]:
    """The arguments of :func:`surface_mesh` (``dim`` 3, ``measure``
    :func:`_mc_measure`) or :func:`surface_contours` (2, :func:`_contour_measure`)
    checked, then ``(type, level, geometry or None)`` of each fluid type
    present, sorted by type (:func:`~hybridmpm.render.surface_levels.material_surface`)."""
    p, pt, lo, hi, h, v = _check_common(positions, particle_type, domain, dx, refine, iso, smooth, volumes, dim)
    obs = _check_obstacles(obstacles)
    out = []
    for code in _fluid_types(pt):
        sel = pt == code
        level, geom = material_surface(_select(p, sel), _select(v, sel), lo, hi, h, smooth, obs, iso, measure)
        out.append((int(code), level, geom))
    return out


def _fluid_types(pt: np.ndarray) -> list[int]:
    lo = int(pt.min()) if len(pt) else 0
    if len(pt) and lo == int(pt.max()):
        return [] if lo == GNS_KINEMATIC else [lo]
    return [int(c) + lo for c in np.flatnonzero(np.bincount(pt - lo)) if int(c) + lo != GNS_KINEMATIC]


def _select(a: np.ndarray, mask: np.ndarray) -> np.ndarray:
    return a if mask.all() else a[mask]


def _mc_measure(phi: np.ndarray, level: float, origin: np.ndarray, f: Field) -> tuple[tuple[np.ndarray, np.ndarray], float]:
    """The closed triangle mesh of ``phi`` at ``level`` (vertices [m], faces
    int32 with outward normals) and its volume."""
    from skimage.measure import marching_cubes

    vs, fs, _, _ = marching_cubes(_off_level(phi, level), level=level, allow_degenerate=True)
    # on the wall faces (on node layers) the vertices sit on the face nodes; clamped there exactly
    vs = np.clip(vs, (f.faces_lo - origin).astype(np.float32), (f.faces_hi - origin).astype(np.float32))
    vs, fs = _weld(vs, fs)
    verts = (vs.astype(np.float64) + origin) * f.h
    # skimage's faces are clockwise seen from the low side (outside here): reverse them for outward normals
    faces = np.ascontiguousarray(fs[:, ::-1], dtype=np.int32)
    return (verts, faces), mesh_volume(verts, faces)


def _off_level(phi: np.ndarray, level: float) -> np.ndarray:
    """``phi`` as float32 (what marching cubes works on) with no node at or
    next to the level: the values within :data:`_LEVEL_GAP` of it are moved
    to ``level ± _LEVEL_GAP`` (those at the level, on an obstacle face, below
    it). A node at the level would give a vertex on it from each of its
    edges that cross, and zero-area triangles between them; this way every
    vertex lies at least ``_LEVEL_GAP`` / (the field's change along its edge)
    of a cell from the nodes, except on the wall faces."""
    g = np.asarray(phi, np.float32)
    lv = np.float32(level)
    near = np.abs(g - lv) < _LEVEL_GAP
    if near.any():
        g = g.copy() if g is phi else g
        g[near] = np.where(g[near] > lv, lv + np.float32(_LEVEL_GAP), lv - np.float32(_LEVEL_GAP))
    return g


def _weld(vs: np.ndarray, fs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Merge the vertices on one grid node (marching cubes puts one on a wall
    face node from each wall face it closes: two or three at an edge or
    corner of the domain), then drop the faces this collapses and the
    back-to-back pairs of coincident faces it leaves: the mesh stays closed,
    with no zero-area or duplicate face."""
    on = np.flatnonzero((vs == np.rint(vs)).all(axis=1))
    if len(on) < 2:
        return vs, fs
    q = vs[on].astype(np.int64)
    order = np.lexsort(q.T[::-1])
    qs = q[order]
    first = np.r_[True, (qs[1:] != qs[:-1]).any(axis=1)]
    if first.all():
        return vs, fs
    remap = np.arange(len(vs))
    remap[on[order]] = on[order][np.maximum.accumulate(np.where(first, np.arange(len(qs)), 0))]
    fs = remap[fs]
    fs = fs[(fs[:, 0] != fs[:, 1]) & (fs[:, 1] != fs[:, 2]) & (fs[:, 0] != fs[:, 2])]
    s = np.sort(fs, axis=1)
    order = np.lexsort(s.T[::-1])
    same = (s[order][1:] == s[order][:-1]).all(axis=1)
    twice = np.zeros(len(fs), bool)
    twice[order[1:][same]] = twice[order[:-1][same]] = True
    fs = fs[~twice]
    used = np.zeros(len(vs), bool)
    used[fs.ravel()] = True
    return vs[used], (np.cumsum(used) - 1)[fs]


def mesh_volume(verts: np.ndarray, faces: np.ndarray) -> float:
    """Enclosed volume [m³] of a closed mesh, ``verts`` [V, 3] [m] and ``faces`` [F, 3] (vertex indices, outward
    counter-clockwise): the divergence theorem over the faces, float64. 0 for no face."""
    if len(faces) == 0:
        return 0.0
    a, b, c = (verts[faces[:, k]] for k in range(3))
    return float(np.einsum("ij,ij->i", a, np.cross(b, c)).sum() / 6.0)


def _contour_measure(phi: np.ndarray, level: float, origin: np.ndarray, f: Field) -> tuple[tuple[np.ndarray, ...], float]:
    """The closed outlines of ``phi`` at ``level`` ([m], outer loops
    counter-clockwise) and their area."""
    from skimage.measure import find_contours

    loops = []
    for c in find_contours(phi, level):
        # on the wall faces (on node layers) clamped onto the face; a face node met from two edges once
        c = np.clip(c, f.faces_lo - origin, f.faces_hi - origin)
        c = c[np.r_[True, (c[1:] != c[:-1]).any(axis=1)]]
        if len(c) >= 4:
            # find_contours leaves high values on the right; reversed, outer loops run counter-clockwise
            loops.append(np.ascontiguousarray(((c + origin) * f.h)[::-1]))
    return tuple(loops), float(sum(_signed_area(lp) for lp in loops))


# ---------------------------------------------------------------------- trajectories and files
def export_surfaces(
    positions: Any,
    particle_type: Any,
    out_dir: str | Path,
    *,
    fmt: str = "ply",
    every: int = 1,
    obstacle_centers: Any = None,
    bodies: Any = None,
    **settings: Any,
) -> list[Path]:
    """Write the surface of every ``every``-th frame of ``positions`` float
    [T, N, D] [m] as a file sequence per material:
    ``out_dir/water_00000.<fmt>``, ``sand_00000.<fmt>``, … (a common prefix
    and a zero-padded frame number, what Blender's sequence importers look
    for). 3D: triangle meshes in ``ply`` (binary), ``obj`` or ``glb``; 2D:
    the closed outlines at z = 0 as line segments in ``ply`` (``edge``
    elements) or ``obj`` (``l`` lines). ``settings`` are passed to
    :func:`surface_mesh` / :func:`surface_contours` (``domain``, ``dx``, ...);
    ``obstacle_centers`` float [T, C, D] [m] places the obstacles in each
    frame (:func:`posed_settings`; None: where ``settings`` put them), and
    ``bodies`` the rigid bodies the surfaces end on: a
    :class:`~hybridmpm.mpm.bodies.BodyTrack`, or ``(bodies as given,
    body_center, body_rotation)`` made into one once here
    (:func:`~hybridmpm.render.surface_scene.pose_track`).
    Returns the paths in frame order, materials sorted by type within a
    frame. Raises :class:`InvalidInputError` naming ``fmt`` (unknown, or
    ``glb`` in 2D), ``positions``, ``every``, ``obstacle_centers``, ``bodies``,
    ``body_center`` (also: not one pose per frame), ``body_rotation`` or a setting."""
    if fmt not in MESH_FORMATS:
        raise InvalidInputError(f"fmt: must be one of {', '.join(MESH_FORMATS)}, got {fmt!r}", "fmt")
    p = np.asarray(positions)
    if p.ndim != 3 or p.shape[2] not in (2, 3) or p.shape[0] < 1:
        raise InvalidInputError(f"positions: expected [T, N, 2|3], got {list(p.shape)}", "positions")
    if p.shape[2] == 2 and fmt == "glb":
        raise InvalidInputError("fmt: 2D outlines are written as ply or obj (glb holds triangle meshes)", "fmt")
    if isinstance(every, bool) or not isinstance(every, int) or every < 1:
        raise InvalidInputError(f"every: must be an integer >= 1, got {every!r}", "every")
    if obstacle_centers is not None and np.shape(obstacle_centers)[:1] != p.shape[:1]:
        raise InvalidInputError(f"obstacle_centers: expected one row per frame ({p.shape[0]}), got {list(np.shape(obstacle_centers))}", "obstacle_centers")
    track = pose_track(bodies)  # checked once, not per frame
    if track is not None and track.num_frames != p.shape[0]:
        raise InvalidInputError(f"body_center: expected one pose per frame ({p.shape[0]}), got {list(track.center.shape)}", "body_center")
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    paths = []
    for t in range(0, p.shape[0], every):
        surfaces = frame_surfaces(p[t], particle_type, **posed_settings(settings, obstacle_centers, t, track))
        for s in surfaces:
            path = out / f"{s.material}_{t:05d}.{fmt}"
            write_surface(s, path, fmt)
            paths.append(path)
    return paths


def frame_surfaces(positions: Any, particle_type: Any, **settings: Any) -> list[SurfaceMesh] | list[SurfaceContours]:
    """:func:`surface_mesh` for a 3D frame, :func:`surface_contours` for a 2D one."""
    p = np.asarray(positions)
    if p.ndim == 2 and p.shape[1] == 2:
        return surface_contours(p, particle_type, **settings)
    return surface_mesh(p, particle_type, **settings)


def write_surface(surface: SurfaceMesh | SurfaceContours, path: str | Path, fmt: str | None = None) -> Path:
    """Write one surface; ``fmt`` (default: the file's suffix) ``ply``,
    ``obj`` or ``glb`` (meshes only). PLY is binary little-endian with float32
    ``x y z`` and an int32 ``vertex_indices`` list per face (or ``edge``
    elements for outlines); OBJ is text with 9 significant digits. Neither
    holds a time stamp, so the same surface gives the same bytes. Raises
    :class:`InvalidInputError` naming ``fmt``."""
    path = Path(path)
    fmt = fmt or path.suffix.lstrip(".").lower()
    if fmt not in MESH_FORMATS or (fmt == "glb" and isinstance(surface, SurfaceContours)):
        raise InvalidInputError(f"fmt: cannot write a {type(surface).__name__} as {fmt!r}", "fmt")
    if isinstance(surface, SurfaceMesh):
        verts, cells, kind = surface.vertices, surface.faces, "face"
    else:
        verts, cells = _loops_to_edges(surface.loops)
        kind = "edge"
    if fmt == "glb":
        import trimesh

        data = trimesh.Trimesh(verts, cells, process=False).export(file_type="glb")
        path.write_bytes(bytes(data))  # type: ignore[arg-type]
    elif fmt == "ply":
        path.write_bytes(_ply_bytes(verts, cells, kind))
    else:
        path.write_bytes(_obj_bytes(verts, cells, kind))
    return path


def _loops_to_edges(loops: tuple[np.ndarray, ...]) -> tuple[np.ndarray, np.ndarray]:
    """Closed loops → vertices [V, 3] (z = 0; the repeated last point dropped) and edges int32 [E, 2]."""
    verts, edges, n = [np.zeros((0, 3))], [np.zeros((0, 2), np.int32)], 0
    for loop in loops:
        k = len(loop) - 1
        verts.append(np.concatenate([loop[:-1], np.zeros((k, 1))], axis=1))
        i = np.arange(k, dtype=np.int32) + n
        edges.append(np.stack([i, np.roll(i, -1)], axis=1))
        n += k
    return np.concatenate(verts), np.concatenate(edges)


def _ply_bytes(verts: np.ndarray, cells: np.ndarray, kind: str) -> bytes:
    v = np.ascontiguousarray(verts, "<f4")
    if kind == "face":
        rec = np.empty(len(cells), dtype=[("n", "u1"), ("i", "<i4", (3,))])
        rec["n"] = 3
        rec["i"] = cells
        elem = "element face {}\nproperty list uchar int vertex_indices\n"
    else:
        rec = np.ascontiguousarray(cells, "<i4")
        elem = "element edge {}\nproperty int vertex1\nproperty int vertex2\n"
    header = (
        "ply\nformat binary_little_endian 1.0\ncomment hybridmpm fluid surface, metres, y up\n"
        f"element vertex {len(v)}\nproperty float x\nproperty float y\nproperty float z\n" + elem.format(len(cells)) + "end_header\n"
    )
    return header.encode() + v.tobytes() + rec.tobytes()


def _obj_bytes(verts: np.ndarray, cells: np.ndarray, kind: str) -> bytes:
    v = np.asarray(verts, np.float64)
    c = np.asarray(cells, np.int64) + 1
    tag = "f" if kind == "face" else "l"
    row = " %d" * c.shape[1]
    text = "# hybridmpm fluid surface, metres, y up\n"
    text += ("v %.9g %.9g %.9g\n" * len(v)) % tuple(v.ravel())
    text += ((tag + row + "\n") * len(c)) % tuple(c.ravel())
    return text.encode()


__all__ = [
    "MAX_GRID_NODES",
    "MESH_FORMATS",
    "SurfaceContours",
    "mesh_volume",
    "SurfaceMesh",
    "export_surfaces",
    "frame_surfaces",
    "material_name",
    "rest_densities",
    "posed_settings",
    "surface_contours",
    "surface_mesh",
    "surface_settings",
    "write_surface",
]
