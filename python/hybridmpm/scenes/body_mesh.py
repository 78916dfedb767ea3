"""Mesh bodies' files (docs/bodies.md "Shapes"): a ``[[bodies]]`` table
with ``shape = "mesh"`` names a triangle mesh (OBJ, STL, PLY or GLB) read
by the mesh obstacles' loader (:mod:`hybridmpm.scenes.obstacle_mesh`); the
body keeps its convex hull's vertices (:func:`resolve_mesh_body`).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from hybridmpm import _core
from hybridmpm.errors import InvalidInputError
from hybridmpm.scenes.obstacle_mesh import load_mesh, resolve_mesh_path


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


__all__ = ["resolve_mesh_body"]
