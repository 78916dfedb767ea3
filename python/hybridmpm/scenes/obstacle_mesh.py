"""Mesh obstacles: a scene's obstacle given as a triangle mesh file (3D).

A scene file's ``[[obstacles]]`` entry with ``shape = "mesh"`` names a
triangle mesh (OBJ, STL, PLY or GLB, read by trimesh) and places it::

    [[obstacles]]
    shape = "mesh"
    path = "meshes/rock.stl"   # relative to the scene file's folder
    center = [0.5, 0.3, 0.5]   # where the mesh's origin goes [m]
    scale = 0.2                # mesh units -> m (> 0; default 1)
    rotation = [[1, 0, 0], [0, 1, 0], [0, 0, 1]]   # optional, orthonormal
    condition = "separate"
    friction = 0.3
    project = true             # particles inside go back onto the surface (default)

A vertex ``v`` of the file goes to ``center + rotation · (scale · v)``.
:func:`mesh_obstacle` reads and checks the mesh, then samples its signed
distance once on the scene's grid nodes (``i · dx``) over the mesh's
bounding box plus :data:`MARGIN_CELLS` cells, and returns a
:class:`~hybridmpm.mpm.params.SampledSdf` collider; the solver interpolates
those samples (Rust ``Shape::Sampled``), and so does
:func:`~hybridmpm.scenes.collider_sdf`.

Sampling (:func:`sample_mesh_sdf`), without trimesh's optional spatial index
(rtree): the unsigned distance of each node is the exact point-triangle
distance (Ericson, *Real-Time Collision Detection*, 2005, §5.1.5) to the
triangles of the :data:`_NEAREST` surface samples nearest to it (a lattice
on every triangle at spacing ``dx/4``, found with a k-d tree), so it is the
exact distance to the mesh or exceeds it by at most that lattice's covering
radius (< ``dx/4``). The sign is the parity of crossings of a ray along +x
from the node (a scanline voxelisation as in Bridson's SDFGen), with edge
tests made consistent between the two triangles that share an edge and the
rays moved off the nodes by ~1e-5 cells so that no ray meets an edge or a
vertex exactly; a watertight mesh is therefore signed without holes or
leaks. Each node also gets its outward normal, which the solver
interpolates: the central difference of the sampled distance where its
length is near 1 (:data:`_SMOOTH_GRADIENT`; smooth across the facets of a
curved mesh), else the direction between the node and its nearest surface
point (a central difference fails on the ridge inside a part a few cells
thin, where the two faces' slopes cancel, and near edges).

Mesh obstacles are 3D only: a 2D scene refuses ``shape = "mesh"``
(``obstacles[i].shape``).
"""

from __future__ import annotations

import collections
import io
import math
import os
import re
import struct
from pathlib import Path
from typing import Any

import numpy as np

from hybridmpm.errors import InvalidInputError
from hybridmpm.files import loads_json, read_regular_file
from hybridmpm.limits import check_allocation, human
from hybridmpm.mpm.params import COLLIDER_DEFAULTS, SampledSdf

#: File kinds a mesh obstacle may be (by suffix, case-insensitive).
MESH_SUFFIXES = (".obj", ".stl", ".ply", ".glb")
#: Largest mesh file read [bytes].
MAX_MESH_FILE_BYTES = 128 * 2**20
#: Most triangles a mesh obstacle may have.
MAX_MESH_TRIANGLES = 200_000
#: Memory a mesh takes per triangle while it is loaded and checked [bytes]: the file's arrays in trimesh, the
#: merged copy, the triangles' corners and areas (measured with tracemalloc, benchmarks/bench_mesh_memory.py:
#: at most 886 B for an 81,920-triangle sphere in STL, whose vertices are not shared; 494-552 B in OBJ, PLY, GLB).
MESH_BYTES_PER_TRIANGLE = 1024
#: Cells of margin around the mesh's bounding box in the sampled grid.
MARGIN_CELLS = 3
#: The deepest sample must lie at least this many grid cells inside (the Rust
#: core's ``MIN_SAMPLED_DEPTH_CELLS``: half the 2-cell thinnest box that holds).
MIN_DEPTH_CELLS = 1.0
#: Keys of a mesh obstacle in a scene file.
MESH_KEYS = ("shape", "path", "center", "scale", "rotation", "angle_deg", "condition", "friction", "project")
#: Surface samples per node whose triangles are tested exactly.
_NEAREST = 8
#: Surface sample spacing, in grid cells.
_SAMPLE_CELLS = 0.25
#: A node's normal is the central difference of the distance where its length is at least this (a distance has
#: gradient 1), else the direction to the nearest surface point (measured: 0.9 let a mesh ramp drift from the
#: analytic one by a grid-mass error of 0.22 at 64³, 0.98 by 0.0008; see docs/obstacles.md).
_SMOOTH_GRADIENT = 0.98
#: glTF accessor types and component types: values per element, bytes per value.
_GLTF_COMPONENTS = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4, "MAT2": 4, "MAT3": 9, "MAT4": 16}
_GLTF_COMPONENT_BYTES = {5120: 1, 5121: 1, 5122: 2, 5123: 2, 5125: 4, 5126: 4}
#: An OBJ face line (its corners in group 1) and a corner.
_OBJ_FACE = re.compile(rb"(?m)^f[ \t]+([^\r\n]*)")
_TOKEN = re.compile(rb"\S+")
#: Ray offsets off the node lines, in cells (irrational multiples of 1e-5).
_RAY_OFFSET = (math.sqrt(2.0) * 1e-5, math.sqrt(3.0) * 1e-5)


def _trimesh() -> Any:
    try:
        import trimesh
    except ModuleNotFoundError as e:  # pragma: no cover - the 'mesh' extra
        raise InvalidInputError("obstacles: mesh obstacles need trimesh (pip install 'hybridmpm[mesh]')", "obstacles") from e
    return trimesh


def _is_number(x: Any) -> bool:
    return isinstance(x, (int, float, np.integer, np.floating)) and not isinstance(x, bool)


def resolve_mesh_path(path: Any, field: str, base_dir: str | os.PathLike[str] | None, confine: bool) -> Path:
    """The file a mesh obstacle's ``path`` names: relative to ``base_dir``
    (the scene file's folder; the working directory when ``None``).

    With ``confine=True`` (a scene from an untrusted source, e.g. a served
    request) the path must stay inside ``base_dir``: an absolute path, a
    ``..`` component, or a link that resolves outside the folder is refused.
    Raises :class:`InvalidInputError` naming ``field``."""
    if not isinstance(path, str) or not path.strip():
        raise InvalidInputError(f"{field}: expected a non-empty string (a mesh file), got {path!r}", field)
    if "\x00" in path:
        raise InvalidInputError(f"{field}: contains a NUL character", field)
    p = Path(path)
    base = Path(base_dir) if base_dir is not None else Path.cwd()
    if confine:
        if p.is_absolute() or p.drive:
            raise InvalidInputError(f"{field}: must be relative to the scene file's folder, got the absolute path {path!r}", field)
        if ".." in p.parts:
            raise InvalidInputError(f"{field}: must not leave the scene file's folder ('..' in {path!r})", field)
    full = p if p.is_absolute() else base / p
    if confine:
        root = os.path.realpath(base)
        real = os.path.realpath(full)
        if os.path.commonpath([root, real]) != root:
            raise InvalidInputError(f"{field}: {path!r} resolves outside the scene file's folder (through a link)", field)
    if full.suffix.lower() not in MESH_SUFFIXES:
        raise InvalidInputError(f"{field}: must be a {', '.join(MESH_SUFFIXES)} file, got {path!r}", field)
    return Path(os.path.abspath(full))


def _glb_declared(raw: bytes, path: Path, field: str) -> tuple[int, int]:
    """A GLB's triangles (each mesh's triangle primitives, times the nodes
    that place it) and the bytes of all its accessors, from its JSON chunk
    (:func:`~hybridmpm.files.loads_json`), without reading its buffers."""

    def bad(why: str) -> InvalidInputError:
        return InvalidInputError(f"{field}: {path} is not a readable GLB mesh ({why})", field)

    if len(raw) < 20 or raw[:4] != b"glTF":
        raise bad("no glTF header")
    (n, kind) = struct.unpack_from("<I4s", raw, 12)
    if kind != b"JSON" or 20 + n > len(raw):
        raise bad("its first chunk is not the JSON of its length")
    doc = loads_json(raw[20 : 20 + n], field)
    try:
        accessors = doc.get("accessors", [])
        counts = []
        nbytes = 0
        for a in accessors:
            c = a["count"]
            if isinstance(c, bool) or not isinstance(c, int) or c < 0:
                raise ValueError(f"accessor count {c!r}")
            counts.append(c)
            nbytes += c * _GLTF_COMPONENTS[a["type"]] * _GLTF_COMPONENT_BYTES[a["componentType"]]
        uses = collections.Counter(node["mesh"] for node in doc.get("nodes", []) if isinstance(node, dict) and "mesh" in node)
        triangles = 0
        for i, mesh in enumerate(doc.get("meshes", [])):
            per = 0
            for prim in mesh.get("primitives", []):
                mode = prim.get("mode", 4)
                k = counts[prim["indices"]] if "indices" in prim else counts[prim["attributes"]["POSITION"]]
                per += k // 3 if mode == 4 else max(k - 2, 0) if mode in (5, 6) else 0
            triangles += per * max(1, uses.get(i, 0))
    except (AttributeError, KeyError, IndexError, TypeError, ValueError) as e:
        raise bad(f"malformed accessors or meshes: {type(e).__name__} {str(e)[:80]}") from None
    return triangles, nbytes


def _obj_triangles(raw: bytes, most: int) -> int:
    """An OBJ's triangles once its faces are split in fans (corners − 2 per
    ``f`` line), counted up to just past ``most`` (no list of the lines or
    their corners is made)."""
    total = 0
    for m in _OBJ_FACE.finditer(raw):
        corners = 0
        for _ in _TOKEN.finditer(raw, m.start(1), m.end(1)):
            corners += 1
            if total + corners - 2 > most:
                return total + corners - 2
        total += max(corners - 2, 0)
    return total


def declared_size(raw: bytes, kind: str, path: Path, field: str) -> tuple[int, int]:
    """``(triangles, bytes)`` a mesh file declares, read without loading it:
    a binary STL's count (its ASCII ``endfacet`` lines otherwise), a PLY
    header's ``element face`` count, an OBJ's faces split in fans, a GLB's
    triangle primitives (:func:`_glb_declared`; ``bytes``: its accessors,
    which trimesh allocates even when no buffer backs them). Raises
    :class:`InvalidInputError` naming ``field`` for a GLB whose JSON is
    malformed or too deep."""
    if kind == "stl":
        ascii_count = raw.count(b"endfacet") + raw.count(b"ENDFACET")
        binary = struct.unpack_from("<I", raw, 80)[0] if len(raw) >= 84 else 0
        return max(ascii_count, binary if 84 + 50 * binary <= len(raw) else 0), 0
    if kind == "ply":
        end = raw.find(b"end_header", 0, 1 << 16)
        faces = re.search(rb"(?m)^element[ \t]+face[ \t]+(\d{1,18})", raw[: end if end >= 0 else 1 << 16])
        return (int(faces.group(1)) if faces else 0), 0
    if kind == "obj":
        return _obj_triangles(raw, MAX_MESH_TRIANGLES), 0
    if kind == "glb":
        return _glb_declared(raw, path, field)
    return 0, 0


def load_mesh(path: Path, field: str) -> tuple[np.ndarray, np.ndarray]:
    """Read and check a mesh file for its geometry: vertices float64 [V, 3]
    (file units) and triangles int64 [F, 3]. Before trimesh reads it, what
    the file declares (:func:`declared_size`) is held to
    :data:`MAX_MESH_TRIANGLES` and, at :data:`MESH_BYTES_PER_TRIANGLE` per
    triangle plus a GLB's accessors, to the memory budget; a GLB's
    materials and their image textures are skipped (never decoded: the
    collider reads no colour). Raises :class:`InvalidInputError` naming
    ``field`` for a file that is missing, not a regular file, over
    :data:`MAX_MESH_FILE_BYTES`, not a triangle mesh trimesh can read, with
    more than :data:`MAX_MESH_TRIANGLES` triangles (declared or loaded),
    over the memory budget, with non-finite vertices, degenerate
    (zero-area) triangles, or not watertight (a closed surface is needed to
    tell inside from outside)."""
    trimesh = _trimesh()
    raw = read_regular_file(path, MAX_MESH_FILE_BYTES, field, "mesh file")
    kind = path.suffix.lower().lstrip(".")
    triangles, accessor_bytes = declared_size(raw, kind, path, field)
    if triangles > MAX_MESH_TRIANGLES:
        raise InvalidInputError(f"{field}: {path} declares {triangles} triangles, more than the {MAX_MESH_TRIANGLES} allowed; simplify it", field)
    declared = f"{triangles} triangles" + (f", accessors of {human(accessor_bytes)}" if accessor_bytes else "")
    check_allocation(field, MESH_BYTES_PER_TRIANGLE * triangles + accessor_bytes, f"loading the mesh {path.name} ({declared})")
    extra = {"skip_materials": True} if kind == "glb" else {}
    try:
        mesh = trimesh.load(io.BytesIO(raw), file_type=kind, force="mesh", process=False, **extra)
    except Exception as e:  # trimesh raises many kinds (ValueError, KeyError, struct.error, ...) for a bad file
        raise InvalidInputError(f"{field}: {path} is not a readable {kind.upper()} mesh ({type(e).__name__}: {e})", field) from e
    if not isinstance(mesh, trimesh.Trimesh) or len(mesh.faces) == 0:
        raise InvalidInputError(f"{field}: {path} holds no triangles", field)
    faces = np.asarray(mesh.faces, np.int64)
    if len(faces) > MAX_MESH_TRIANGLES:
        raise InvalidInputError(f"{field}: {path} has {len(faces)} triangles, more than the {MAX_MESH_TRIANGLES} allowed; simplify it", field)
    vertices = np.asarray(mesh.vertices, np.float64)
    if not np.isfinite(vertices).all():
        raise InvalidInputError(f"{field}: {path} has non-finite (NaN or infinite) vertex coordinates", field)
    tri = vertices[faces]
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    diag = float(np.linalg.norm(vertices.max(axis=0) - vertices.min(axis=0)))
    bad = np.flatnonzero(area <= 1e-12 * diag * diag)
    if len(bad):
        raise InvalidInputError(f"{field}: {path} has {len(bad)} degenerate (zero-area) triangles, the first is triangle {int(bad[0])}", field)
    merged = trimesh.Trimesh(vertices, faces, process=True)  # merges the duplicated vertices of STL and similar files
    if not merged.is_watertight:
        raise InvalidInputError(f"{field}: {path} is not watertight (a closed surface is needed to tell its inside from its outside)", field)
    return np.asarray(merged.vertices, np.float64), np.asarray(merged.faces, np.int64)


def rotation_matrix(raw: dict[str, Any], field: str, dim: int) -> np.ndarray:
    """The obstacle's rotation: its ``rotation`` (a finite orthonormal
    ``dim``×``dim`` matrix; columns: the mesh's axes in world coordinates),
    identity when absent. ``angle_deg`` is refused in 3D as for boxes."""
    if raw.get("angle_deg") is not None:
        raise InvalidInputError(f"{field}.angle_deg: only in 2D; give 'rotation' in 3D", f"{field}.angle_deg")
    rot = raw.get("rotation")
    if rot is None:
        return np.eye(dim)
    try:
        r = np.asarray(rot, np.float64)
    except (TypeError, ValueError) as e:
        raise InvalidInputError(f"{field}.rotation: must be a finite orthonormal {dim}×{dim} matrix", f"{field}.rotation") from e
    if r.shape != (dim, dim) or not np.isfinite(r).all() or not np.allclose(r @ r.T, np.eye(dim), atol=1e-5):
        raise InvalidInputError(f"{field}.rotation: must be a finite orthonormal {dim}×{dim} matrix", f"{field}.rotation")
    return r


def check_mesh_obstacle(raw: Any, field: str, dim: int) -> dict[str, Any]:
    """Check a scene file's mesh obstacle entry (keys :data:`MESH_KEYS`) and
    return it normalised (``scale`` and ``condition``/``friction``/``project`` filled
    in); does not read the file. Raises :class:`InvalidInputError` naming the
    field (``obstacles[i].scale``, ...)."""
    if not isinstance(raw, dict):
        raise InvalidInputError(f"{field}: expected a table/object", field)
    if dim != 3:
        raise InvalidInputError(f"{field}.shape: 'mesh' obstacles are 3D only (dim = 3); this scene has dim = {dim}", f"{field}.shape")
    unknown = sorted(set(raw) - set(MESH_KEYS), key=str)
    if unknown:
        raise InvalidInputError(f"{field}.{unknown[0]}: unknown mesh obstacle field (allowed: {', '.join(MESH_KEYS)})", f"{field}.{unknown[0]}")
    center = raw.get("center")
    try:
        c = np.asarray(center, np.float64)
    except (TypeError, ValueError) as e:
        raise InvalidInputError(f"{field}.center: expected {dim} finite numbers, got {center!r}", f"{field}.center") from e
    if c.shape != (dim,) or not np.isfinite(c).all():
        raise InvalidInputError(f"{field}.center: expected {dim} finite numbers, got {center!r}", f"{field}.center")
    scale = raw.get("scale", 1.0)
    if not (_is_number(scale) and math.isfinite(scale) and scale > 0):
        raise InvalidInputError(f"{field}.scale: must be a finite number > 0, got {scale!r}", f"{field}.scale")
    rot = rotation_matrix(raw, field, dim)
    condition = raw.get("condition", COLLIDER_DEFAULTS["condition"])
    if condition not in ("sticky", "slip", "separate"):
        raise InvalidInputError(f"{field}.condition: must be one of 'sticky', 'slip', 'separate', got {condition!r}", f"{field}.condition")
    friction = raw.get("friction", COLLIDER_DEFAULTS["friction"])
    if not (_is_number(friction) and math.isfinite(friction) and friction >= 0):
        raise InvalidInputError(f"{field}.friction: must be a finite number >= 0, got {friction!r}", f"{field}.friction")
    project = raw.get("project", COLLIDER_DEFAULTS["project"])
    if not isinstance(project, bool):
        raise InvalidInputError(f"{field}.project: must be true or false, got {project!r}", f"{field}.project")
    out: dict[str, Any] = {"shape": "mesh", "path": raw.get("path"), "center": [float(v) for v in c], "scale": float(scale)}
    if raw.get("rotation") is not None:
        out["rotation"] = [[float(v) for v in row] for row in rot]
    out["condition"] = condition
    out["friction"] = float(friction)
    out["project"] = project
    return out


def _closest_point_on_triangle(p: np.ndarray, a: np.ndarray, b: np.ndarray, c: np.ndarray) -> np.ndarray:
    """Closest point to each of ``p`` on its triangle ``(a, b, c)``, all float64
    [M, 3], row by row: float64 [M, 3] (Ericson 2005, §5.1.5, by Voronoi region)."""
    ab, ac, ap = b - a, c - a, p - a
    d1 = np.einsum("ij,ij->i", ab, ap)
    d2 = np.einsum("ij,ij->i", ac, ap)
    bp = p - b
    d3 = np.einsum("ij,ij->i", ab, bp)
    d4 = np.einsum("ij,ij->i", ac, bp)
    cp = p - c
    d5 = np.einsum("ij,ij->i", ab, cp)
    d6 = np.einsum("ij,ij->i", ac, cp)
    va = d3 * d6 - d5 * d4
    vb = d5 * d2 - d1 * d6
    vc = d1 * d4 - d3 * d2
    with np.errstate(divide="ignore", invalid="ignore"):
        v_ab = d1 / (d1 - d3)
        w_ac = d2 / (d2 - d6)
        w_bc = (d4 - d3) / ((d4 - d3) + (d5 - d6))
        denom = 1.0 / (va + vb + vc)
    v_in = vb * denom
    w_in = vc * denom
    conds = [
        (d1 <= 0) & (d2 <= 0),
        (d3 >= 0) & (d4 <= d3),
        (vc <= 0) & (d1 >= 0) & (d3 <= 0),
        (d6 >= 0) & (d5 <= d6),
        (vb <= 0) & (d2 >= 0) & (d6 <= 0),
        (va <= 0) & ((d4 - d3) >= 0) & ((d5 - d6) >= 0),
    ]
    choices = [a, b, a + ab * v_ab[:, None], c, a + ac * w_ac[:, None], b + (c - b) * w_bc[:, None]]
    q = a + ab * v_in[:, None] + ac * w_in[:, None]
    for cond, choice in zip(reversed(conds), reversed(choices)):
        q = np.where(cond[:, None], choice, q)
    return np.asarray(q)


def _surface_samples(tri: np.ndarray, spacing: float, field: str) -> tuple[np.ndarray, np.ndarray]:
    """A barycentric lattice on every triangle with edges of at most
    ``spacing`` [m]: points float64 [S, 3] and their triangle ids int64 [S]."""
    edges = np.stack(
        [np.linalg.norm(tri[:, 1] - tri[:, 0], axis=1), np.linalg.norm(tri[:, 2] - tri[:, 1], axis=1), np.linalg.norm(tri[:, 0] - tri[:, 2], axis=1)], axis=1
    )
    n_sub = np.maximum(np.ceil(edges.max(axis=1) / spacing), 1).astype(np.int64)
    total = float(np.sum((n_sub + 1) * (n_sub + 2) // 2))
    check_allocation(field, 64.0 * total, f"sampling the mesh surface ({total:.3g} points at {spacing:.3g} m)")
    pts, ids = [], []
    for n in np.unique(n_sub):
        sel = np.flatnonzero(n_sub == n)
        i, j = np.meshgrid(np.arange(n + 1), np.arange(n + 1), indexing="ij")
        keep = i + j <= n
        w1, w2 = i[keep] / n, j[keep] / n
        w0 = 1.0 - w1 - w2
        t = tri[sel]
        p = w0[None, :, None] * t[:, None, 0] + w1[None, :, None] * t[:, None, 1] + w2[None, :, None] * t[:, None, 2]
        pts.append(p.reshape(-1, 3))
        ids.append(np.repeat(sel, len(w0)))
    return np.concatenate(pts), np.concatenate(ids)


def _inside_by_parity(tri: np.ndarray, faces: np.ndarray, origin: np.ndarray, h: float, dims: tuple[int, int, int]) -> np.ndarray:
    """Whether each node ``origin + h·(i, j, k)`` lies inside the closed
    surface: bool [nx, ny, nz], by the parity of the triangles a ray along +x
    from the node (moved by :data:`_RAY_OFFSET` cells in y, z) crosses."""
    nx, ny, nz = dims
    oy = origin[1] + _RAY_OFFSET[0] * h
    oz = origin[2] + _RAY_OFFSET[1] * h
    y, z = tri[:, :, 1], tri[:, :, 2]
    jlo = np.maximum(np.ceil((y.min(axis=1) - oy) / h), 0).astype(np.int64)
    jhi = np.minimum(np.floor((y.max(axis=1) - oy) / h), ny - 1).astype(np.int64)
    klo = np.maximum(np.ceil((z.min(axis=1) - oz) / h), 0).astype(np.int64)
    khi = np.minimum(np.floor((z.max(axis=1) - oz) / h), nz - 1).astype(np.int64)
    nj = np.maximum(jhi - jlo + 1, 0)
    nk = np.maximum(khi - klo + 1, 0)
    count = nj * nk
    check_allocation("obstacles", 200.0 * float(count.sum()), "testing the mesh against the grid's rays")
    t = np.repeat(np.arange(len(tri)), count)
    off = np.arange(len(t)) - np.repeat(np.cumsum(count) - count, count)
    jj = jlo[t] + off // nk[t]
    kk = klo[t] + off % nk[t]
    py = oy + jj * h
    pz = oz + kk * h

    def edge(u: int, v: int) -> np.ndarray:
        """Orientation of the ray's point against edge (u, v) of each triangle,
        evaluated from the lower vertex id so that a shared edge gives the two
        triangles exactly opposite values."""
        iu, iv = faces[t, u], faces[t, v]
        flip = iu > iv
        a = np.where(flip[:, None], tri[t, v], tri[t, u])
        b = np.where(flip[:, None], tri[t, u], tri[t, v])
        o = (b[:, 1] - a[:, 1]) * (pz - a[:, 2]) - (b[:, 2] - a[:, 2]) * (py - a[:, 1])
        return np.asarray(np.where(flip, -o, o))

    e0, e1, e2 = edge(1, 2), edge(2, 0), edge(0, 1)  # e0 weighs vertex 0, ...
    hit = ((e0 > 0) & (e1 > 0) & (e2 > 0)) | ((e0 < 0) & (e1 < 0) & (e2 < 0))
    t, e0, e1, e2, jj, kk = t[hit], e0[hit], e1[hit], e2[hit], jj[hit], kk[hit]
    s = e0 + e1 + e2
    x = (e0 * tri[t, 0, 0] + e1 * tri[t, 1, 0] + e2 * tri[t, 2, 0]) / s
    ic = np.clip(np.ceil((x - origin[0]) / h), 0, nx).astype(np.int64)  # nodes i >= ic lie beyond the crossing
    crossings = np.bincount((ic * ny + jj) * nz + kk, minlength=(nx + 1) * ny * nz).reshape(nx + 1, ny, nz)
    return np.asarray(np.cumsum(crossings, axis=0)[:nx] % 2 == 1)


def sample_mesh_sdf(vertices: np.ndarray, faces: np.ndarray, n_grid: int, field: str) -> tuple[list[float], float, np.ndarray, np.ndarray]:
    """Signed distance [m] of the closed triangle mesh ``vertices`` (world
    coordinates [m], float64 [V, 3]) / ``faces`` (int [F, 3]) at the nodes
    ``i/n_grid`` of the unit domain over its bounding box plus
    :data:`MARGIN_CELLS` cells (clipped to the domain): ``(origin, cell,
    values, normals)`` with ``origin`` [m] (3 float32-exact numbers), ``cell
    = dx``, ``values`` float32 [nx, ny, nz] (negative inside) and
    ``normals`` float32 [nx, ny, nz, 3], the outward unit normal at each
    node: the central difference of ``values`` where its length is at least
    :data:`_SMOOTH_GRADIENT`, else the direction from the node's nearest
    surface point to it (outside) or from it to that point (inside). See the module
    docstring for the method and its error bound. Raises
    :class:`InvalidInputError` naming ``field`` when the grid would exceed
    the memory budget."""
    from scipy.spatial import cKDTree

    n = int(n_grid)
    dx32 = np.float32(1.0) / np.float32(n)
    h = 1.0 / n
    lo, hi = vertices.min(axis=0), vertices.max(axis=0)
    i0 = np.maximum(np.floor(lo * n).astype(np.int64) - MARGIN_CELLS, 0)
    i1 = np.minimum(np.ceil(hi * n).astype(np.int64) + MARGIN_CELLS, n)
    dims = tuple(int(v) for v in i1 - i0 + 1)
    nodes_count = float(np.prod(dims))
    check_allocation(field, 120.0 * nodes_count, f"sampling its signed distance on {dims[0]}×{dims[1]}×{dims[2]} grid nodes")
    origin = i0 / n
    axes = [(i0[d] + np.arange(dims[d])) / n for d in range(3)]
    nodes = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
    tri = vertices[faces]
    samples, sample_tri = _surface_samples(tri, _SAMPLE_CELLS * h, field)
    k = min(_NEAREST, len(samples))
    dist = np.full(len(nodes), np.inf)
    nearest = np.zeros_like(nodes)
    tree = cKDTree(samples)
    chunk = 1 << 16
    for s0 in range(0, len(nodes), chunk):
        p = nodes[s0 : s0 + chunk]
        _, idx = tree.query(p, k=k)
        cand = sample_tri[np.asarray(idx).reshape(len(p), k)]
        pr = np.repeat(p, k, axis=0)
        t = tri[cand.ravel()]
        q = _closest_point_on_triangle(pr, t[:, 0], t[:, 1], t[:, 2])
        d = np.linalg.norm(pr - q, axis=1).reshape(len(p), k)
        best = d.argmin(axis=1)
        dist[s0 : s0 + chunk] = d[np.arange(len(p)), best]
        nearest[s0 : s0 + chunk] = q.reshape(len(p), k, 3)[np.arange(len(p)), best]
    inside = _inside_by_parity(tri, faces, origin, h, dims)  # type: ignore[arg-type]
    sign = np.where(inside.ravel(), -1.0, 1.0)
    values = (sign * dist).astype(np.float32).reshape(dims)
    normals = sign[:, None] * (nodes - nearest)
    grad = np.stack(np.gradient(values.astype(np.float64), h), axis=-1).reshape(-1, 3)
    # the distance's central difference where it is a distance's gradient (|∇φ| ≈ 1: smooth over the facets of a
    # curved mesh), the nearest-surface direction where it is not (a ridge inside a thin part, where the faces'
    # slopes cancel) or where the node is on the surface
    smooth = np.linalg.norm(grad, axis=1) >= _SMOOTH_GRADIENT
    normals = np.where(smooth[:, None] | (np.linalg.norm(normals, axis=1) < 1e-6 * h)[:, None], grad, normals)
    normals /= np.maximum(np.linalg.norm(normals, axis=1), 1e-30)[:, None]
    origin32 = [float(np.float32(int(i)) * dx32) for i in i0]
    return origin32, float(dx32), values, normals.astype(np.float32).reshape(*dims, 3)


def place(vertices: np.ndarray, obstacle: dict[str, Any]) -> np.ndarray:
    """World coordinates [m] of mesh ``vertices``: ``center + rotation · (scale · v)``."""
    rot = np.asarray(obstacle.get("rotation", np.eye(3)), np.float64)
    return np.asarray(np.asarray(obstacle["center"], np.float64) + (float(obstacle["scale"]) * vertices) @ rot.T)


def mesh_obstacle(obstacle: dict[str, Any], field: str, n_grid: int, resolved: Path) -> SampledSdf:
    """The collider of a checked mesh obstacle (:func:`check_mesh_obstacle`)
    on a grid of ``n_grid`` cells per side, its file at ``resolved``.

    Raises :class:`InvalidInputError` naming ``{field}.path`` for a bad mesh
    (:func:`load_mesh`) or one thinner than the solver holds (no node
    :data:`MIN_DEPTH_CELLS` cells inside: make it thicker, scale it up or
    use a finer grid), ``{field}.center`` for a mesh not inside the domain
    ``[0, 1]³`` once placed."""
    vertices, faces = load_mesh(resolved, f"{field}.path")
    with np.errstate(over="ignore", invalid="ignore"):
        world = place(vertices, obstacle)
    if not np.isfinite(world).all():
        reach = float(np.abs(vertices).max())
        raise InvalidInputError(
            f"{field}.scale: {obstacle['scale']:g} times the mesh's vertices (up to {reach:g} in file units) overflows once placed; "
            "give the scale from file units to metres",
            f"{field}.scale",
        )
    lo, hi = world.min(axis=0), world.max(axis=0)
    if lo.min() < 0.0 or hi.max() > 1.0:
        raise InvalidInputError(
            f"{field}.center: the placed mesh spans {np.round(lo, 4).tolist()} to {np.round(hi, 4).tolist()} m, not inside the domain [0, 1]³; move or scale it",
            f"{field}.center",
        )
    origin, cell, values, normals = sample_mesh_sdf(world, faces, n_grid, f"{field}.path")
    deepest = float(values.min())
    if not deepest <= -MIN_DEPTH_CELLS * cell:
        raise InvalidInputError(
            f"{field}.path: the mesh is thinner than the solver holds on a {n_grid}³ grid: its deepest grid node is "
            f"{max(-deepest, 0.0) / cell:.2f} cells inside, less than {MIN_DEPTH_CELLS:g} (about {2 * MIN_DEPTH_CELLS:g} cells thick); "
            "particles would fall through it. Make it thicker, scale it up or use a finer grid",
            f"{field}.path",
        )
    source = {**obstacle, "path": str(resolved)}
    return SampledSdf(
        origin=origin,
        cell=cell,
        values=values,
        normals=normals,
        condition=obstacle["condition"],
        friction=obstacle["friction"],
        project=obstacle["project"],
        source=source,
    )


def sampled_sdf(c: SampledSdf, points: np.ndarray) -> np.ndarray:
    """Signed distance [m] of a :class:`SampledSdf` at ``points`` [N, D]:
    float64 [N], the multilinear interpolant of its samples, plus the
    distance to the sampled box outside it (as the Rust ``Shape::Sampled``)."""
    p = np.asarray(points, np.float64)
    values = np.asarray(c.values, np.float64)
    dims = np.asarray(values.shape)
    d = p.shape[1]
    u = (p - np.asarray(c.origin, np.float64)) / float(c.cell)
    uc = np.clip(u, 0.0, dims - 1)
    outside = np.linalg.norm((u - uc) * float(c.cell), axis=1)
    idx = np.minimum(np.floor(uc).astype(np.int64), dims - 2)
    t = uc - idx
    acc = np.zeros(len(p))
    for corner in range(1 << d):
        bits = np.array([(corner >> a) & 1 for a in range(d)])
        w = np.prod(np.where(bits == 1, t, 1.0 - t), axis=1)
        acc += w * values[tuple((idx + bits).T)]
    return np.asarray(acc + outside)


__all__ = [
    "MARGIN_CELLS",
    "MAX_MESH_FILE_BYTES",
    "MAX_MESH_TRIANGLES",
    "MESH_BYTES_PER_TRIANGLE",
    "MESH_KEYS",
    "MESH_SUFFIXES",
    "MIN_DEPTH_CELLS",
    "check_mesh_obstacle",
    "declared_size",
    "load_mesh",
    "mesh_obstacle",
    "place",
    "resolve_mesh_path",
    "sample_mesh_sdf",
    "sampled_sdf",
]
