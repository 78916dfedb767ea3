"""A scene's obstacles: reading and checking them, writing them back, and what they look like to the fluid.

A scene file's ``[[obstacles]]`` are boxes (``half_extents``, ``angle_deg``
in 2D or ``rotation``), spheres (``radius``) and, in 3D, triangle meshes
(``shape = "mesh"``, ``path``, ``scale``, ``rotation``;
:mod:`hybridmpm.scenes.obstacle_mesh`), all with ``center``, ``condition``,
``friction`` and ``project`` (the particle projection, default on), and optionally a keyframed path (``keyframes = [{t = 0.0,
center = [..]}, ...]``, :mod:`hybridmpm.mpm.motion`; the simulators move the
obstacle along it); docs/obstacles.md lists every key.

:class:`~hybridmpm.scenes.SceneSpec` reads them in two steps around the
solver parameters: :func:`read_obstacles` before (at most
:data:`MAX_OBSTACLES`; a path's keyframes checked, its first key being where
the obstacle starts; a mesh's entry checked and its file resolved against
the scene file's folder) and :func:`place_obstacles` once the grid is known
(a mesh sampled on the grid's nodes, the path attached, every box and sphere
checked). :func:`obstacles_on_grid` carries them to another grid,
:func:`obstacle_dict` writes one back as a scene file does. Every error names
the field as the scene file spells it (``obstacles[i].center``,
``obstacles[i].keyframes[k].t``, ...), also for the solver's own checks,
which call obstacles ``colliders`` (:func:`obstacles_error`).

:func:`collider_sdf` is the signed distance the solver sees and
:func:`sample_boundary` the network's static boundary particles (GNS
type 3) on a shell inside each surface, with the obstacle each belongs to.
:func:`obstacle_center` is an obstacle's centre as the scene places it and
:func:`obstacles_at` the obstacles translated to other centres (a recorded
frame's poses: the surfaces and the USD file of a run whose obstacles move).

:mod:`hybridmpm.scenes.spec` imports this module, never the reverse; the
small checks both use (:func:`check_vec`, :func:`is_number`) live here.
"""

from __future__ import annotations

import dataclasses
import math
import os
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from hybridmpm.errors import InvalidInputError
from hybridmpm.limits import check_allocation
from hybridmpm.mpm import Box, MpmParams, MpmSolver, Sphere
from hybridmpm.mpm.motion import Keyframe, check_keyframes
from hybridmpm.mpm.params import Collider, SampledSdf
from hybridmpm.scenes import obstacle_mesh
from hybridmpm.scenes.core import BYTES_PER_PARTICLE, lattice

#: Most obstacles a scene may have.
MAX_OBSTACLES = 256


@dataclass
class PendingObstacles:
    """What :func:`read_obstacles` sets aside until the grid is known, by
    obstacle index: the checked entries of mesh obstacles with their resolved
    files, and the keyframed paths."""

    meshes: dict[int, tuple[dict[str, Any], Path]] = field(default_factory=dict)
    paths: dict[int, tuple[Keyframe, ...]] = field(default_factory=dict)


def read_obstacles(raw: Any, dim: int, base_dir: str | os.PathLike[str] | None, confine: bool) -> tuple[Any, PendingObstacles]:
    """A scene file's ``obstacles`` as the solver parameters' ``colliders``,
    and what waits for the grid (:func:`place_obstacles`).

    An entry with ``keyframes`` loses them (they go to the pending paths) and
    starts at its first key's centre (``center`` may be left out, else must
    be that centre). A mesh entry is checked
    (:func:`~hybridmpm.scenes.obstacle_mesh.check_mesh_obstacle`), its
    ``path`` resolved against ``base_dir`` (``confine``:
    :func:`~hybridmpm.scenes.obstacle_mesh.resolve_mesh_path`), and a
    placeholder sphere stands in for it until it is sampled. Anything but a
    list is given back as it is, for the solver parameters to refuse.
    """
    pending = PendingObstacles()
    if isinstance(raw, list) and len(raw) > MAX_OBSTACLES:
        raise InvalidInputError(f"obstacles: {len(raw)} obstacles, more than the {MAX_OBSTACLES} a scene may have", "obstacles")
    if not isinstance(raw, list):
        return raw, pending
    cols = list(raw)
    for i, c in enumerate(cols):
        if isinstance(c, dict) and "keyframes" in c:  # a path: its first key is where the obstacle starts
            c = dict(c)
            keys = check_keyframes(f"obstacles[{i}].keyframes", c.pop("keyframes"), dim)
            first = list(keys[0].center)
            if "center" not in c:
                c["center"] = first
            elif not (isinstance(c["center"], (list, tuple)) and [float(v) if is_number(v) else v for v in c["center"]] == first):
                raise InvalidInputError(
                    f"obstacles[{i}].center: must be the first keyframe's centre {first} (where the path starts), or left out; got {c['center']!r}",
                    f"obstacles[{i}].center",
                )
            pending.paths[i] = keys
            cols[i] = c
        if isinstance(c, dict) and c.get("shape") == "mesh":
            f = f"obstacles[{i}]"
            checked = obstacle_mesh.check_mesh_obstacle(c, f, dim)
            pending.meshes[i] = (checked, obstacle_mesh.resolve_mesh_path(c.get("path"), f"{f}.path", base_dir, confine))
            cols[i] = {"shape": "sphere", "center": [0.5] * dim, "radius": 0.25}  # placeholder, replaced below
    return cols, pending


def place_obstacles(params: MpmParams, pending: PendingObstacles, n_grid: int, dim: int) -> None:
    """Finish the obstacles of ``params`` (made from :func:`read_obstacles`'
    colliders) in place: each mesh sampled on the ``n_grid`` grid's nodes
    (:func:`~hybridmpm.scenes.obstacle_mesh.mesh_obstacle`), each path
    attached, and every box and sphere checked (``center``,
    ``half_extents``, ``angle_deg``, ``rotation``, ``radius``)."""
    for i, (checked, resolved) in pending.meshes.items():
        params.colliders[i] = obstacle_mesh.mesh_obstacle(checked, f"obstacles[{i}]", n_grid, resolved)
    for i, keys in pending.paths.items():
        params.colliders[i].keyframes = keys
    for i, c in enumerate(params.colliders):
        if isinstance(c, SampledSdf):
            continue
        check_vec(f"obstacles[{i}].center", c.center, dim)
        if isinstance(c, Box):
            check_vec(f"obstacles[{i}].half_extents", c.half_extents, dim, positive=True)
            if c.angle_deg is not None and not (is_number(c.angle_deg) and math.isfinite(c.angle_deg)):
                raise InvalidInputError(f"obstacles[{i}].angle_deg: must be a finite number [°], got {c.angle_deg!r}", f"obstacles[{i}].angle_deg")
            if c.rotation is not None:
                rot = np.asarray(c.rotation, np.float64)
                if rot.shape != (dim, dim) or not np.isfinite(rot).all() or not np.allclose(rot @ rot.T, np.eye(dim), atol=1e-5):
                    raise InvalidInputError(f"obstacles[{i}].rotation: must be a finite orthonormal {dim}×{dim} matrix", f"obstacles[{i}].rotation")
        elif not (isinstance(c.radius, (int, float)) and math.isfinite(c.radius) and c.radius > 0):
            raise InvalidInputError(f"obstacles[{i}].radius: must be a finite number > 0", f"obstacles[{i}].radius")


def obstacles_on_grid(colliders: Sequence[Collider], params: MpmParams, n_grid: int) -> None:
    """Carry ``colliders`` to ``params``, whose grid has ``n_grid`` cells per
    side, in place: a mesh obstacle sampled again on the new grid's nodes,
    every path kept; then refuse an obstacle too thin for that grid
    (:func:`check_obstacles_hold`)."""
    for i, c in enumerate(colliders):  # a mesh obstacle is sampled again on the new grid's nodes
        if isinstance(c, SampledSdf) and c.source is not None:
            params.colliders[i] = obstacle_mesh.mesh_obstacle(c.source, f"obstacles[{i}]", n_grid, Path(c.source["path"]))
        params.colliders[i].keyframes = c.keyframes  # a path is no solver parameter: carried over here
    check_obstacles_hold(params)


def obstacles_error(e: InvalidInputError) -> InvalidInputError:
    """The solver's error about ``colliders...`` as a scene names it: ``obstacles...``
    (the message and the field; any other error unchanged)."""
    f = (e.field or "").replace("colliders", "obstacles", 1)
    return InvalidInputError(str(e).replace("colliders", "obstacles", 1), f)


def check_obstacles_hold(params: MpmParams) -> None:
    """Refuse obstacles too thin for ``params``' grid, as the solver does at
    construction (an empty solver: its grid only), naming ``obstacles[i]...``."""
    try:
        MpmSolver(params)
    except InvalidInputError as e:
        raise obstacles_error(e) from e


def guess_obstacle_field(colliders: Any) -> str | None:
    """The first field of a scene's ``obstacles`` that is not a plain value of
    its expected kind (``obstacles``, ``obstacles[i]``, ``obstacles[i].radius``,
    ...), or ``None``; for an error that a bare ``float()`` raised."""
    if not isinstance(colliders, list):
        return "obstacles"
    for i, c in enumerate(colliders):
        if not isinstance(c, dict):
            return f"obstacles[{i}]"
        for key, val in c.items():
            if key in ("center", "half_extents", "rotation") and not (isinstance(val, list) and all(is_number(x) for x in val)):
                return f"obstacles[{i}].{key}"
            if key in ("radius", "angle_deg", "friction") and not is_number(val):
                return f"obstacles[{i}].{key}"
    return None


def obstacle_dict(c: Collider, raw: dict[str, Any]) -> dict[str, Any]:
    """An obstacle as a scene file writes it: a mesh by its ``source`` (path,
    center, scale, rotation), not by its samples; other shapes by ``raw``;
    with its ``keyframes`` when it follows a path."""
    d = (
        {**c.source, "condition": c.condition, "friction": float(c.friction), "project": c.project}
        if isinstance(c, SampledSdf) and c.source is not None
        else dict(raw)
    )
    if c.keyframes:
        d["keyframes"] = [k.to_dict() for k in c.keyframes]
    return d


def mesh_paths_relative_to(obstacles: list[dict[str, Any]], folder: Path) -> None:
    """Make the ``path`` of each mesh obstacle in ``obstacles`` (as
    :func:`obstacle_dict` writes them) relative to ``folder``, in place, when
    the mesh lies under it."""
    for ob in obstacles:
        if ob.get("shape") == "mesh":
            rel = os.path.relpath(ob["path"], os.path.abspath(folder))
            if not rel.startswith(".."):
                ob["path"] = rel


def is_number(x: Any) -> bool:
    """A plain int or float (not a bool)."""
    return isinstance(x, (int, float)) and not isinstance(x, bool)


def check_vec(name: str, v: Any, dim: int, positive: bool = False) -> np.ndarray:
    """``v`` as ``dim`` finite float64 numbers (> 0 with ``positive``), or an
    :class:`InvalidInputError` naming ``name``."""
    try:
        a = np.asarray(v, dtype=np.float64)
    except (TypeError, ValueError) as e:
        raise InvalidInputError(f"{name}: expected {dim} numbers, got {v!r}", name) from e
    if a.shape != (dim,) or not np.all(np.isfinite(a)):
        raise InvalidInputError(f"{name}: expected {dim} finite numbers, got {v!r}", name)
    if positive and np.any(a <= 0):
        raise InvalidInputError(f"{name}: must be > 0 on every axis, got {v!r}", name)
    return a


def box_rotation(c: Box, dim: int) -> np.ndarray:
    """A box's rotation matrix, float64 [D, D]: its ``rotation`` as given, a
    2D box's ``angle_deg`` (counter-clockwise), or the identity. Columns are
    the box's local axes in world coordinates, as the Rust colliders take them."""
    if c.rotation is not None:
        return np.asarray(c.rotation, np.float64)
    r = np.eye(dim)
    if c.angle_deg is not None and dim == 2:
        a = math.radians(c.angle_deg)
        r[:2, :2] = [[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]]
    return r


def collider_sdf(c: Collider, points: np.ndarray) -> np.ndarray:
    """Signed distance [m] from ``points`` [N, D] to an obstacle (negative inside),
    float64 [N]; the same shapes and rotation convention as the Rust colliders
    (a :class:`~hybridmpm.mpm.params.SampledSdf` by the same multilinear
    interpolation of its samples)."""
    p = np.asarray(points, np.float64)
    if isinstance(c, SampledSdf):
        return obstacle_mesh.sampled_sdf(c, p)
    center = np.asarray(c.center, np.float64)
    if isinstance(c, Sphere):
        return np.asarray(np.linalg.norm(p - center, axis=1) - float(c.radius))
    local = (p - center) @ box_rotation(c, p.shape[1])
    q = np.abs(local) - np.asarray(c.half_extents, np.float64)
    outside = np.linalg.norm(np.maximum(q, 0.0), axis=1)
    return np.asarray(outside + np.minimum(q.max(axis=1), 0.0))


def obstacle_center(c: Collider) -> np.ndarray:
    """An obstacle's centre as the scene places it [m], float64 [D]: a box's
    or sphere's ``center``; a mesh's ``center`` (its ``source``), else its
    sampled ``origin``. The centre :attr:`~hybridmpm.sim.MpmSimulator.obstacle_centers`
    reports for an obstacle that stands where the scene put it."""
    if isinstance(c, SampledSdf):
        ref = c.source["center"] if c.source is not None and "center" in c.source else c.origin
        return np.asarray([float(v) for v in ref], np.float64)
    return np.asarray([float(v) for v in c.center], np.float64)


def obstacles_at(colliders: Sequence[Collider], centers: Any) -> list[Collider]:
    """``colliders`` translated so that obstacle ``i``'s centre
    (:func:`obstacle_center`) is ``centers[i]`` [m] (float [C, D]): a box's
    or sphere's ``center`` replaced, a sampled (mesh) obstacle's ``origin``
    and ``source`` centre shifted by the displacement; shape, rotation and
    everything else kept (obstacles translate only). An obstacle whose
    centre is its own in float32 (where the solver keeps it: one that did not
    move) is given back as it is, a moved one is a copy: a new list, and
    ``colliders`` is not changed.

    Raises :class:`InvalidInputError` naming ``obstacle_centers`` for an
    array that is not finite float [C, D]."""
    cols = list(colliders)
    d = len(obstacle_center(cols[0])) if cols else 0
    a = np.asarray(centers)
    if a.dtype.kind not in "fiu" or a.ndim != 2 or a.shape[0] != len(cols) or (cols and a.shape[1] != d):
        raise InvalidInputError(f"obstacle_centers: expected a real array [{len(cols)}, {d}] [m], got {a.dtype} {list(a.shape)}", "obstacle_centers")
    a = np.asarray(a, np.float64)
    if not np.isfinite(a).all():
        raise InvalidInputError("obstacle_centers: contains NaN or inf", "obstacle_centers")
    out: list[Collider] = []
    for c, new in zip(cols, a):
        ref = obstacle_center(c)
        if np.array_equal(ref.astype(np.float32), new.astype(np.float32)):
            out.append(c)
        elif isinstance(c, SampledSdf):
            shift = new - ref
            origin = [float(v) for v in np.asarray(c.origin, np.float64) + shift]
            source = None if c.source is None else {**c.source, "center": [float(v) for v in new]}
            out.append(dataclasses.replace(c, origin=origin, source=source))
        else:
            out.append(dataclasses.replace(c, center=[float(v) for v in new]))
    return out


def sample_boundary(colliders: Sequence[Collider], dim: int, spacing: float, dx: float) -> tuple[np.ndarray, np.ndarray]:
    """Static boundary particles (GNS type 3) for the obstacles and the
    obstacle each lies on: float32 [B, D] [m] and int32 [B] (the index in
    ``colliders``, which follow in order: obstacle 0's particles first).

    A lattice at ``spacing`` [m] in each obstacle's own frame, kept where it lies
    within one spacing inside the surface (a shell one particle thick; a thin
    ramp is filled); for a mesh (:class:`~hybridmpm.mpm.params.SampledSdf`) a
    lattice over its sampled box, kept where ``-spacing < sdf <= 0``. Points outside ``[dx, 1 − dx]^D`` are dropped (they are in
    the walls, which the network sees through its wall-distance features).
    The one place that knows which obstacle a boundary particle belongs to
    (a moved obstacle's particles follow it: :meth:`~hybridmpm.scenes.ParticleSet.pad`).
    Raises :class:`InvalidInputError` (field ``colliders[i]``) for a lattice over the memory limit.
    """
    out = [np.zeros((0, dim), np.float32)]
    owner = [np.zeros(0, np.int32)]
    for i, c in enumerate(colliders):
        if isinstance(c, SampledSdf):  # the same shell, found by the sampled signed distance
            lo = np.asarray(c.origin, np.float64)
            hi = lo + float(c.cell) * (np.asarray(np.shape(c.values)) - 1)
            n = float(np.prod(np.maximum(np.round((hi - lo) / spacing), 1)))
            check_allocation(f"colliders[{i}]", n * BYTES_PER_PARTICLE, f"sampling its boundary particles ({n:.3g} lattice points at spacing {spacing:.3g} m)")
            p = lattice(lo, hi, spacing).astype(np.float64)
            sdf = obstacle_mesh.sampled_sdf(c, p)
            p = p[(sdf <= 0) & (sdf > -spacing)]
        else:
            extent = 2.0 * np.full(dim, float(c.radius)) if isinstance(c, Sphere) else 2.0 * np.abs(np.asarray(c.half_extents, np.float64))
            n = float(np.prod(np.maximum(np.round(extent / spacing), 1)))
            check_allocation(f"colliders[{i}]", n * BYTES_PER_PARTICLE, f"sampling its boundary particles ({n:.3g} lattice points at spacing {spacing:.3g} m)")
            center = np.asarray(c.center, np.float64)
            if isinstance(c, Sphere):
                r = float(c.radius)
                p = lattice(center - r, center + r, spacing).astype(np.float64)
                d = np.linalg.norm(p - center, axis=1)
                p = p[(d <= r) & (d > r - spacing)]
            else:
                h = np.asarray(c.half_extents, np.float64)
                local = lattice(-h, h, spacing).astype(np.float64)
                shell = np.any(np.abs(local) > h - spacing, axis=1)
                p = center + local[shell] @ box_rotation(c, dim).T
        inside = np.all((p >= dx) & (p <= 1.0 - dx), axis=1)
        out.append(p[inside].astype(np.float32))
        owner.append(np.full(int(inside.sum()), i, np.int32))
    return np.concatenate(out), np.concatenate(owner)


def boundary_particles(colliders: Sequence[Collider], dim: int, spacing: float, dx: float) -> np.ndarray:
    """The positions of :func:`sample_boundary`: float32 [B, D] [m]."""
    return sample_boundary(colliders, dim, spacing, dx)[0]


__all__ = [
    "MAX_OBSTACLES",
    "PendingObstacles",
    "boundary_particles",
    "box_rotation",
    "check_obstacles_hold",
    "check_vec",
    "collider_sdf",
    "guess_obstacle_field",
    "is_number",
    "mesh_paths_relative_to",
    "obstacle_center",
    "obstacle_dict",
    "obstacles_at",
    "obstacles_error",
    "obstacles_on_grid",
    "place_obstacles",
    "read_obstacles",
    "sample_boundary",
]
