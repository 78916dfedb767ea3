"""A scene's bodies against its files and its obstacles (docs/bodies.md
"Shapes"): a ``[[bodies]]`` table with ``shape = "mesh"`` names a triangle
mesh (OBJ, STL, PLY or GLB) read by the mesh obstacles' loader
(:mod:`hybridmpm.scenes.obstacle_mesh`), and the body keeps its convex
hull's vertices (:func:`resolve_mesh_body`), a hull of more than
:data:`MAX_HULL_FACES` triangles simplified first (:func:`simplify_hull`);
bodies that overlap each other or an obstacle are refused
(:func:`check_overlaps`).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from hybridmpm import _core
from hybridmpm.errors import InvalidInputError
from hybridmpm.mpm.bodies import MAX_HULL_POINTS, Body
from hybridmpm.mpm.params import Collider
from hybridmpm.scenes.obstacle_mesh import load_mesh, resolve_mesh_path
from hybridmpm.scenes.obstacles import collider_sdf

#: Most triangles a mesh body's convex hull keeps. The coupling evaluates a hull's signed distance at every grid
#: node with mass within reach of the body, every substep, as the largest of its face planes' (Rust
#: ``Hull::sdf_normal``, a loop over the planes), and :meth:`~hybridmpm.mpm.bodies.Body.sdf` does the same at
#: each particle a scene seeds, so their cost grows linearly with the faces. Measured on one thread, a 40³ tank
#: of 97,000 particles with a floating hull 0.12 m in radius: 0.14-0.16 s a frame with 12 faces, 0.15-0.17 s
#: with 1,024, 0.20-0.21 s with 2,048 and 0.40-0.42 s with 8,192. 1,024 faces (a hull of ~500 vertices) hold
#: a sphere's volume within about 1.5 % (an icosphere of 1,280 faces is within 0.9 %). A hull with more faces
#: is simplified (:func:`simplify_hull`).
MAX_HULL_FACES: int = 1024
#: The simplification's first lattice spacing, in grid cells of the scene (``dx = 1 / n_grid``): a quarter
#: cell, finer than the coupling resolves (it reads the distance at nodes ``dx`` apart).
HULL_LATTICE_CELLS: float = 0.25
#: Factor the lattice spacing grows by while the hull still has more than :data:`MAX_HULL_FACES` faces:
#: each step about halves the lattice cubes the surface meets, so a hull coarsened past the first spacing
#: keeps between about half the cap and the cap.
HULL_LATTICE_GROWTH: float = math.sqrt(2.0)
#: The grid the first spacing is taken from when the scene's is not known (``MpmSimulator.add_body``): the
#: finest a solver takes, so that spacing is never coarser than a quarter of any scene's cell.
FINEST_N_GRID: int = 4096


def _numeric_points(v: Any) -> np.ndarray | None:
    """``v`` as float32 [V, 3] (what the core reads) when it is a list of V >= 4 triples of real numbers, finite
    in float32, at most :data:`~hybridmpm.mpm.bodies.MAX_HULL_POINTS` of them; None otherwise (the core names
    what is wrong)."""
    try:
        a = np.asarray(v)
    except (TypeError, ValueError):
        return None
    if a.dtype.kind not in "iuf" or a.ndim != 2 or a.shape[1] != 3 or not 4 <= len(a) <= MAX_HULL_POINTS:
        return None
    with np.errstate(over="ignore"):
        p = a.astype(np.float32)
    return p if np.isfinite(p).all() else None


def simplify_hull(points: np.ndarray, field: str, n_grid: int | None = None) -> tuple[np.ndarray, dict[str, Any]] | None:
    """A mesh body's points with its convex hull cut to at most :data:`MAX_HULL_FACES` triangles, or None when
    its hull (scipy's Qhull) has no more than that, or when ``points`` are not V >= 4 finite float32 triples
    (at most :data:`~hybridmpm.mpm.bodies.MAX_HULL_POINTS`) spanning a volume: the core then reads them as
    given and names what is wrong.

    ``points`` float32 [V, 3] [m] (the mesh's frame); ``n_grid`` the scene's grid (None: unknown, taken as
    :data:`FINEST_N_GRID`); ``field`` (``bodies[0].path``) what an error names. The hull's vertices are cut
    by a lattice of spacing ``tol`` (cubes about the points ``k·tol``, ``k`` integer), each cube keeping the
    one vertex nearest the mean of the vertices in it (the first in coordinate order on a tie), so the result
    is a subset of ``points`` and depends only on them, not on their order. ``tol`` starts at
    :data:`HULL_LATTICE_CELLS` of a cell (``0.25 / n_grid`` m) and grows by :data:`HULL_LATTICE_GROWTH`
    until the core's hull of the kept vertices (:func:`hybridmpm._core.body_hull`) has at most
    :data:`MAX_HULL_FACES` triangles. Every vertex dropped lies in a cube with one kept, within ``tol·√3`` of
    it, so the simplified hull lies inside the original and every point of the original lies within
    ``tol·√3`` of it: the surface moves inward by at most ``tol·√3`` (0.43 of a cell at the first spacing),
    never outward, and the body's volume, mass and inertia are the smaller hull's. An icosphere of 81,920
    triangles, radius 0.15 m, on a 24³ grid: 960 triangles, ``tol`` 0.71 of a cell (so within 1.22 cells),
    1.3 % less volume than the sphere.

    Returns ``(kept, report)``: ``kept`` float64 [K, 3] [m], the core's hull points of the kept vertices
    (what a body's ``vertices`` hold), and ``report`` ``{"field", "faces_given", "faces", "tolerance_m",
    "n_grid"}``: Qhull's triangles of the given hull, the core's of the kept one, ``tol·√3`` (the bound on
    the surface's move [m]) and the grid ``tol`` started from (left out when unknown). Raises
    :class:`InvalidInputError` naming ``field`` when the kept vertices span no volume (a mesh far thinner
    than it is wide: one thinner than 2 cells is refused anyway)."""
    p = _numeric_points(points)
    if p is None or 2 * len(p) - 4 <= MAX_HULL_FACES:  # a hull of V points has at most 2V - 4 triangles
        return None
    from scipy.spatial import ConvexHull, QhullError  # imported only for a mesh this big

    try:
        given = ConvexHull(p.astype(np.float64))
    except (QhullError, ValueError):
        return None  # on one plane: the core names it
    faces_given = len(given.simplices)
    if faces_given <= MAX_HULL_FACES:
        return None
    return _cut_hull(p[given.vertices].astype(np.float64), faces_given, field, n_grid)


def _lattice_cubes(v: np.ndarray, tol: float) -> tuple[np.ndarray, np.ndarray]:
    """Which cube of a lattice of spacing ``tol`` [m] (the points ``k·tol`` nearest) each of ``v`` [V, 3] lies
    in, as indices int64 [V] into the distinct cubes in lexicographic order of ``k``, and each cube's count [C]."""
    k = np.floor(v / tol + 0.5).astype(np.int64)
    lo = k.min(axis=0)
    span = [int(x) for x in k.max(axis=0) - lo + 1]
    if span[0] * span[1] * span[2] < 2**62:  # one integer a cube (8 times faster than unique rows)
        k = k - lo
        _, cube, count = np.unique((k[:, 0] * span[1] + k[:, 1]) * span[2] + k[:, 2], return_inverse=True, return_counts=True)
    else:
        _, cube, count = np.unique(k, axis=0, return_inverse=True, return_counts=True)
    return cube.reshape(-1), count


def _cut_hull(v: np.ndarray, faces_given: int, field: str, n_grid: int | None) -> tuple[np.ndarray, dict[str, Any]]:
    """:func:`simplify_hull` on a hull's vertices ``v`` float64 [V, 3] (float32 values), in any order."""
    tol = HULL_LATTICE_CELLS / float(n_grid or FINEST_N_GRID)
    v = np.unique(v, axis=0)  # sorted by coordinates: the result depends on the points, not their order
    index = np.arange(len(v))
    while True:
        cube, count = _lattice_cubes(v, tol)
        if 2 * len(count) - 4 <= MAX_HULL_FACES:
            mean = np.stack([np.bincount(cube, weights=v[:, k], minlength=len(count)) for k in range(3)], axis=1) / count[:, None]
            near = ((v - mean[cube]) ** 2).sum(axis=1)
            order = np.lexsort((index, near, cube))  # by cube, then distance to its mean, then index
            first = order[np.r_[True, cube[order][1:] != cube[order][:-1]]]
            kept = v[np.sort(first)].astype(np.float32)
            try:
                hull = _core.body_hull(kept.tolist(), field)
            except InvalidInputError as e:
                raise InvalidInputError(
                    f"{e} (its hull of {faces_given} triangles, more than the {MAX_HULL_FACES} a body keeps, cut to one vertex per {tol:.3g} m lattice cube)",
                    e.field,
                ) from e
            if len(hull["faces"]) <= MAX_HULL_FACES:
                report = {"field": field, "faces_given": int(faces_given), "faces": int(len(hull["faces"])), "tolerance_m": tol * math.sqrt(3.0)}
                return np.asarray(hull["points"], np.float64), report if n_grid is None else {**report, "n_grid": int(n_grid)}
        tol *= HULL_LATTICE_GROWTH


def resolve_mesh_body(
    d: dict[str, Any],
    field: str,
    dim: int | None = None,
    base_dir: Any = None,
    confine: bool = False,
    n_grid: int | None = None,
    simplified: list[dict[str, Any]] | None = None,
) -> dict[str, Any]:
    """A body's dict with a mesh read: for ``shape = "mesh"`` with a ``path``
    and no ``vertices``, the file (OBJ, STL, PLY or GLB, relative to
    ``base_dir``, the working directory when None; ``confine`` as for mesh
    obstacles, :func:`~hybridmpm.scenes.obstacle_mesh.resolve_mesh_path`)
    is read by the mesh obstacles' loader, its vertices times ``scale``
    (default 1) taken, and the dict returned with ``vertices`` the hull's
    (float lists [V, 3], m, the mesh's frame) and ``scale`` dropped (it is
    in the vertices). A hull of more than :data:`MAX_HULL_FACES` triangles,
    read from a file or given inline as ``vertices``, is simplified first
    (:func:`simplify_hull`, from a quarter of a cell of ``n_grid``, the
    scene's grid; None: :data:`FINEST_N_GRID`'s) and its report appended to
    ``simplified`` when given; a hull within the cap is kept as it was.
    Anything else comes back as given. Raises
    :class:`InvalidInputError` naming ``field.shape`` (a mesh with
    ``dim`` = 2), ``field.scale`` (not a finite number > 0) or
    ``field.path`` (a missing, unreadable or broken file, fewer than 4
    points not on one plane, non-finite vertices) or ``field.path`` /
    ``field.vertices`` (a simplified hull that spans no volume)."""
    if d.get("shape") != "mesh":
        return d
    if dim == 2:
        raise InvalidInputError(f"{field}.shape: 'mesh' bodies are 3D only (dim = 3); this scene has dim = 2", f"{field}.shape")
    if d.get("vertices") is not None:
        cut = simplify_hull(d["vertices"], f"{field}.vertices", n_grid)
        if cut is None:
            return d
        if simplified is not None:
            simplified.append(cut[1])
        return {**d, "vertices": cut[0].tolist()}
    if d.get("path") is None:
        return d
    scale = d.get("scale", 1.0)
    if not (isinstance(scale, (int, float, np.integer, np.floating)) and not isinstance(scale, bool) and np.isfinite(scale) and scale > 0):
        raise InvalidInputError(f"{field}.scale: must be a finite number > 0, got {scale!r}", f"{field}.scale")
    path = resolve_mesh_path(d["path"], f"{field}.path", base_dir, confine)
    verts, _ = load_mesh(path, f"{field}.path")
    points = (verts * float(scale)).astype(np.float32)
    out = {k: v for k, v in d.items() if k != "scale"}
    cut = simplify_hull(points, f"{field}.path", n_grid)
    if cut is None:
        hull = _core.body_hull(points.tolist(), f"{field}.path")
        if len(hull["faces"]) <= MAX_HULL_FACES:
            out["vertices"] = np.asarray(hull["points"], np.float64).tolist()
            return out
        cut = _cut_hull(np.asarray(hull["points"], np.float64), len(hull["faces"]), f"{field}.path", n_grid)  # parry kept more than Qhull
    if simplified is not None:
        simplified.append(cut[1])
    out["vertices"] = cut[0].tolist()
    return out


def bounding_radius(body: Body, dim: int) -> float:
    """Radius [m] of the smallest ball about the body's centre of mass that holds it."""
    if body.shape == "box":
        return float(np.linalg.norm(np.asarray(body.half_extents, np.float64)))
    if body.shape == "capsule":
        return float(body.radius or 0.0) + float(body.half_height or 0.0)  # both given for a capsule (Body.from_dict)
    if body.shape == "mesh":
        return float(np.linalg.norm(np.asarray(body.hull()["vertices"], np.float64), axis=1).max())
    return float(body.radius or 0.0)  # a sphere's (Body.from_dict requires it)


def check_overlaps(bodies: list[Body], colliders: list[Collider], dim: int, n_grid: int) -> None:
    """Refuse a scene whose bodies overlap each other where they are given
    (parry's intersection test on rapier's shapes, the Rust core's
    ``Body::overlaps``) or an obstacle (a grid node, spacing ``1 / n_grid``,
    inside both). Raises :class:`InvalidInputError` naming
    ``bodies[i].center`` (the later body of a pair)."""
    dx = 1.0 / n_grid
    for i, b in enumerate(bodies):
        for j in range(i):
            if _core.bodies_overlap(b.to_dict(), bodies[j].to_dict(), dim, i, j):
                raise InvalidInputError(f"bodies[{i}].center: the body overlaps body {j}", f"bodies[{i}].center")
        if not colliders:
            continue
        c, r = b.center_of_mass(dim), bounding_radius(b, dim)
        axes = [np.arange(max(0, int(np.floor((c[d] - r) / dx))), int(np.ceil((c[d] + r) / dx)) + 1) * dx for d in range(dim)]
        nodes = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, dim)
        nodes = nodes[b.sdf(nodes) < 0.0]
        for k, col in enumerate(colliders):
            if len(nodes) and (collider_sdf(col, nodes) < 0.0).any():
                raise InvalidInputError(f"bodies[{i}].center: the body overlaps obstacle {k}", f"bodies[{i}].center")


__all__ = [
    "FINEST_N_GRID",
    "HULL_LATTICE_CELLS",
    "HULL_LATTICE_GROWTH",
    "MAX_HULL_FACES",
    "bounding_radius",
    "check_overlaps",
    "resolve_mesh_body",
    "simplify_hull",
]
