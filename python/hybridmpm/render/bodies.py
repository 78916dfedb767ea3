"""Rigid bodies in pictures and exports (docs/bodies.md "Pictures and exports").

A body's shape (a :class:`~hybridmpm.mpm.bodies.Body`: box, sphere/circle,
capsule, or a mesh's convex hull) as geometry in its own frame, placed at a pose (``center`` [D], ``rotation``
[D, D], columns its axes: a trajectory's ``body_center`` / ``body_rotation``)
as ``x = center + rotation @ local``:

- 3D: a box as its 8 corners and 12 triangles, a sphere as an icosphere
  (:data:`ICO_LEVEL` subdivisions: 162 vertices, 320 triangles), a capsule
  as that icosphere cut at its equator and its halves moved to ±``half_height``
  along y (joined by the cylinder between them), a mesh body as its hull;
- 2D: a closed outline (a box's 4 corners, a circle as :data:`CIRCLE_SEGMENTS`
  points, a capsule as two half circles of ``CIRCLE_SEGMENTS / 2 + 1`` points
  each), written as the fluid's 2D outlines are (edges, z = 0);
  :func:`body_prism` extrudes it along z for USD, as the 2D obstacles are.

:func:`export_bodies` writes ``body_<i>_<t>.<fmt>`` per body per frame.
"""

from __future__ import annotations

from collections.abc import Sequence
from functools import cache
from pathlib import Path
from typing import Any, cast

import numpy as np

from hybridmpm.mpm.bodies import BodyTrack, as_body_track, check_poses
from hybridmpm.render.surface import SurfaceContours, SurfaceMesh, write_surface

#: Points of a circle's outline (2D).
CIRCLE_SEGMENTS = 48
#: Points around a capsule's mesh (3D), and its rings of latitude on each half ball.
CAPSULE_SEGMENTS = 32
CAPSULE_RINGS = 8
#: Subdivisions of a sphere's icosahedron (3D).
ICO_LEVEL = 2
#: GNS-like code and name the body surfaces carry (not a particle type: bodies have no particles).
BODY_TAG = -1


@cache
def icosphere(level: int = ICO_LEVEL) -> tuple[np.ndarray, np.ndarray]:
    """A unit icosphere: vertices float64 [V, 3] on the unit sphere, faces int32 [F, 3] counter-clockwise seen from outside."""
    g = (1.0 + 5.0**0.5) / 2.0
    v = [[-1, g, 0], [1, g, 0], [-1, -g, 0], [1, -g, 0], [0, -1, g], [0, 1, g], [0, -1, -g], [0, 1, -g], [g, 0, -1], [g, 0, 1], [-g, 0, -1], [-g, 0, 1]]
    f = [[0, 11, 5], [0, 5, 1], [0, 1, 7], [0, 7, 10], [0, 10, 11], [1, 5, 9], [5, 11, 4], [11, 10, 2], [10, 7, 6], [7, 1, 8]]
    f += [[3, 9, 4], [3, 4, 2], [3, 2, 6], [3, 6, 8], [3, 8, 9], [4, 9, 5], [2, 4, 11], [6, 2, 10], [8, 6, 7], [9, 8, 1]]
    verts = [np.asarray(p, np.float64) / np.linalg.norm(p) for p in v]
    faces = f
    for _ in range(level):
        mid: dict[tuple[int, int], int] = {}
        nxt = []
        for a, b, c in faces:
            ab, bc, ca = (_middle(verts, mid, p, q) for p, q in ((a, b), (b, c), (c, a)))
            nxt += [[a, ab, ca], [b, bc, ab], [c, ca, bc], [ab, bc, ca]]
        faces = nxt
    out_v, out_f = np.array(verts), np.array(faces, np.int32)
    out_v.flags.writeable = out_f.flags.writeable = False
    return out_v, out_f


def _middle(verts: list[np.ndarray], mid: dict[tuple[int, int], int], a: int, b: int) -> int:
    """The index of the unit vector half way between vertices ``a`` and ``b``, added to ``verts`` once."""
    key = (min(a, b), max(a, b))
    if key not in mid:
        m = verts[a] + verts[b]
        verts.append(m / np.linalg.norm(m))
        mid[key] = len(verts) - 1
    return mid[key]


#: A unit box's corners (bit k of the index: the sign of axis k) and its 12 triangles, outward.
_BOX_CORNERS = np.array([[1.0 if (k >> a) & 1 else -1.0 for a in range(3)] for k in range(8)])
_BOX_FACES = np.array(
    [[0, 2, 3], [0, 3, 1], [4, 5, 7], [4, 7, 6], [0, 1, 5], [0, 5, 4], [2, 6, 7], [2, 7, 3], [0, 4, 6], [0, 6, 2], [1, 3, 7], [1, 7, 5]], np.int32
)


def local_mesh(body: Any) -> tuple[np.ndarray, np.ndarray]:
    """A 3D body's mesh in its own frame (centre of mass at 0, its axes): vertices float64 [V, 3] [m], faces int32 [F, 3]."""
    if body.shape == "box":
        return _BOX_CORNERS * np.asarray(body.half_extents, np.float64), _BOX_FACES
    if body.shape == "mesh":
        h = body.hull()
        return np.asarray(h["vertices"], np.float64), np.asarray(h["faces"], np.int32)
    if body.shape == "capsule":
        return capsule_mesh(float(body.radius), float(body.half_height))
    v, f = icosphere()
    return v * float(body.radius), f


def capsule_mesh(radius: float, half_height: float) -> tuple[np.ndarray, np.ndarray]:
    """A capsule along y in its own frame: :data:`CAPSULE_SEGMENTS` points around, rings of latitude
    every 90° / :data:`CAPSULE_RINGS` on each half ball (centred at ±``half_height``) and a pole at
    each end; vertices float64 [V, 3] [m], faces int32 [F, 3] counter-clockwise seen from outside."""
    k = CAPSULE_SEGMENTS
    lon = np.linspace(0.0, 2.0 * np.pi, k, endpoint=False)
    rings = []  # (latitude, centre height) from the bottom up, poles excluded
    for i in range(1, CAPSULE_RINGS + 1):
        rings.append((-np.pi / 2 + np.pi / 2 * i / CAPSULE_RINGS, -half_height))
    for i in range(CAPSULE_RINGS):
        rings.append((np.pi / 2 * i / CAPSULE_RINGS, half_height))
    pts = [[0.0, -half_height - radius, 0.0]]
    for lat, y0 in rings:
        c = radius * np.cos(lat)
        pts += np.stack([c * np.cos(lon), np.full(k, y0 + radius * np.sin(lat)), -c * np.sin(lon)], axis=1).tolist()
    pts.append([0.0, half_height + radius, 0.0])
    top, n = len(pts) - 1, len(rings)
    j = np.arange(k)
    nxt = (j + 1) % k
    faces = [np.stack([np.zeros(k, int), 1 + nxt, 1 + j], 1)]
    for r in range(n - 1):
        a, b = 1 + r * k, 1 + (r + 1) * k
        faces += [np.stack([a + j, a + nxt, b + nxt], 1), np.stack([a + j, b + nxt, b + j], 1)]
    last = 1 + (n - 1) * k
    faces.append(np.stack([np.full(k, top), last + j, last + nxt], 1))
    return np.asarray(pts, np.float64), np.concatenate(faces).astype(np.int32)


def local_outline(body: Any) -> np.ndarray:
    """A 2D body's outline in its own frame, counter-clockwise, float64 [K, 2] [m] (not closed)."""
    if body.shape == "box":
        hx, hy = (float(h) for h in body.half_extents)
        return np.array([[-hx, -hy], [hx, -hy], [hx, hy], [-hx, hy]])
    r = float(body.radius)
    if body.shape == "capsule":
        h = float(body.half_height)
        a = np.linspace(0.0, np.pi, CIRCLE_SEGMENTS // 2 + 1)
        top = np.stack([r * np.cos(a), h + r * np.sin(a)], axis=1)
        return np.concatenate([top, -top])
    a = np.linspace(0.0, 2.0 * np.pi, CIRCLE_SEGMENTS, endpoint=False)
    return r * np.stack([np.cos(a), np.sin(a)], axis=1)


def place(local: np.ndarray, center: Any, rotation: Any) -> np.ndarray:
    """Points of a body's frame at its pose: ``center + rotation @ p`` for each row ``p``, float64."""
    return np.asarray(local, np.float64) @ np.asarray(rotation, np.float64).T + np.asarray(center, np.float64)


def body_prism(body: Any, half_depth: float) -> tuple[np.ndarray, np.ndarray]:
    """A 2D body's outline extruded to z = ±``half_depth``, in its own frame: vertices [2K, 3], faces int32 [F, 3] (outward)."""
    o = local_outline(body)
    k = len(o)
    v = np.concatenate([np.c_[o, np.full(k, -half_depth)], np.c_[o, np.full(k, half_depth)]])
    i = np.arange(k)
    j = (i + 1) % k
    sides = np.concatenate([np.stack([i, j, j + k], 1), np.stack([i, j + k, i + k], 1)])
    fan = np.arange(1, k - 1)
    caps = np.concatenate([np.stack([np.zeros_like(fan), fan + 1, fan], 1), np.stack([np.full_like(fan, k), fan + k, fan + 1 + k], 1)])
    return v, np.concatenate([sides, caps]).astype(np.int32)


def body_surface(body: Any, center: Any, rotation: Any) -> SurfaceMesh | SurfaceContours:
    """The body at a pose as :func:`~hybridmpm.render.surface.write_surface` writes it: a
    :class:`SurfaceMesh` in 3D, a :class:`SurfaceContours` (one closed loop) in 2D."""
    if len(center) == 2:
        loop = place(local_outline(body), center, rotation)
        return SurfaceContours((np.concatenate([loop, loop[:1]]),), "body", BODY_TAG, 0.0)
    v, f = local_mesh(body)
    return SurfaceMesh(place(v, center, rotation), np.asarray(f, np.int32), "body", BODY_TAG, 0.0)


def export_bodies(
    out_dir: str | Path, bodies: BodyTrack | Sequence[Any], center: Any = None, rotation: Any = None, fmt: str = "ply", every: int = 1
) -> list[Path]:
    """Write each body at each ``every``-th frame as ``out_dir/body_<i>_<t>.<fmt>`` (``ply`` or
    ``obj``; ``glb`` for 3D): :func:`body_surface` at the pose ``center[t, i]``,
    ``rotation[t, i]``. ``bodies`` a :class:`~hybridmpm.mpm.bodies.BodyTrack` (then
    ``center`` and ``rotation`` stay None), or the bodies as given with ``center``
    float [T, B, D] [m] and ``rotation`` [T, B, D, D], made into one once here
    (:meth:`~hybridmpm.mpm.bodies.BodyTrack.make`). Returns the paths. Raises
    :class:`InvalidInputError` naming ``body_center`` (also: a track with arrays
    beside it), ``body_rotation`` or ``fmt``."""
    made = as_body_track(bodies, center, rotation)  # a track as it is (no arrays beside it), or made of the arrays
    # none made (no bodies, or no centres): the arrays as they are, for their errors (or no body)
    track = made if made is not None else BodyTrack.make(cast(Sequence[Any], bodies), center, rotation)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    paths = []
    for t in range(0, track.num_frames, every):
        for i, body in enumerate(track.shapes):
            paths.append(write_surface(body_surface(body, track.center[t, i], track.rotation[t, i]), out / f"body_{i}_{t:05d}.{fmt}", fmt))
    return paths


__all__ = [
    "BODY_TAG",
    "CAPSULE_RINGS",
    "CAPSULE_SEGMENTS",
    "CIRCLE_SEGMENTS",
    "ICO_LEVEL",
    "body_prism",
    "body_surface",
    "capsule_mesh",
    "check_poses",  # re-exported: hybridmpm.mpm.bodies.check_poses, a thin wrapper of BodyTrack.make
    "export_bodies",
    "icosphere",
    "local_mesh",
    "local_outline",
    "place",
]
