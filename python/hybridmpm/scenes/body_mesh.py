"""A scene's bodies against its files and its obstacles (docs/bodies.md
"Shapes"): a ``[[bodies]]`` table with ``shape = "mesh"`` names a triangle
mesh (OBJ, STL, PLY or GLB) read by the mesh obstacles' loader
(:mod:`hybridmpm.scenes.obstacle_mesh`), and the body keeps its convex
hull's vertices (:func:`resolve_mesh_body`); bodies that overlap each other
or an obstacle are refused (:func:`check_overlaps`).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from hybridmpm import _core
from hybridmpm.errors import InvalidInputError
from hybridmpm.mpm.bodies import Body
from hybridmpm.mpm.params import Collider
from hybridmpm.scenes.obstacle_mesh import load_mesh, resolve_mesh_path
from hybridmpm.scenes.obstacles import collider_sdf


def resolve_mesh_body(d: dict[str, Any], field: str, dim: int | None = None, base_dir: Any = None, confine: bool = False) -> dict[str, Any]:
    """A body's dict with a mesh read: for ``shape = "mesh"`` with a ``path``
    and no ``vertices``, the file (OBJ, STL, PLY or GLB, relative to
    ``base_dir``, the working directory when None; ``confine`` as for mesh
    obstacles, :func:`~hybridmpm.scenes.obstacle_mesh.resolve_mesh_path`)
    is read by the mesh obstacles' loader, its vertices times ``scale``
    (default 1) taken, and the dict returned with ``vertices`` the hull's
    (float lists [V, 3], m, the mesh's frame) and ``scale`` dropped (it is
    in the vertices). Anything else comes back as given. Raises
    :class:`InvalidInputError` naming ``field.shape`` (a mesh with
    ``dim`` = 2), ``field.scale`` (not a finite number > 0) or
    ``field.path`` (a missing, unreadable or broken file, fewer than 4
    points not on one plane, non-finite vertices)."""
    if d.get("shape") != "mesh":
        return d
    if dim == 2:
        raise InvalidInputError(f"{field}.shape: 'mesh' bodies are 3D only (dim = 3); this scene has dim = 2", f"{field}.shape")
    if d.get("vertices") is not None or d.get("path") is None:
        return d
    scale = d.get("scale", 1.0)
    if not (isinstance(scale, (int, float, np.integer, np.floating)) and not isinstance(scale, bool) and np.isfinite(scale) and scale > 0):
        raise InvalidInputError(f"{field}.scale: must be a finite number > 0, got {scale!r}", f"{field}.scale")
    path = resolve_mesh_path(d["path"], f"{field}.path", base_dir, confine)
    verts, _ = load_mesh(path, f"{field}.path")
    hull = _core.body_hull((verts * float(scale)).astype(np.float32).tolist(), f"{field}.path")
    out = {k: v for k, v in d.items() if k != "scale"}
    out["vertices"] = np.asarray(hull["points"], np.float64).tolist()
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


__all__ = ["bounding_radius", "check_overlaps", "resolve_mesh_body"]
