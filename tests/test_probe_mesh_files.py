"""Mesh obstacle files are read for their geometry only, within bounds known
before they are loaded: a GLB's image textures are never decoded (a 12000²
texture in a small file loads in bounded memory); the triangle cap and the
memory budget are applied to what the file declares (a binary STL's count,
a PLY's header, an OBJ's faces, a GLB's accessors) before trimesh reads it;
and placed vertices must be finite (a ``scale`` that overflows is refused
naming ``scale``)."""

from __future__ import annotations

import json
import os
import struct
import subprocess
import sys
import zlib
from pathlib import Path
from typing import Any

import numpy as np
import pytest

trimesh = pytest.importorskip("trimesh")

from hybridmpm.errors import InvalidInputError  # noqa: E402
from hybridmpm.scenes import SceneSpec, obstacle_mesh  # noqa: E402

CENTER = [0.5, 0.4, 0.5]


def _png_zeros(side: int) -> bytes:
    """A ``side``² RGB PNG of black pixels, deflated row by row (a few hundred kB; ``3·side²`` bytes decoded)."""

    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF)

    z = zlib.compressobj(9)
    row = bytes(1 + 3 * side)
    body = b"".join(z.compress(row) for _ in range(side)) + z.flush()
    return b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", side, side, 8, 2, 0, 0, 0)) + chunk(b"IDAT", body) + chunk(b"IEND", b"")


def _glb(path: Path, images: list[bytes] = (), index_count: int | None = None) -> Path:
    """A GLB of a closed cube (2 units a side, 12 triangles) with texture coordinates and, per image, a
    material whose base colour texture is that PNG (stored in the binary chunk). ``index_count`` overrides
    the indices accessor's declared count."""
    box = trimesh.creation.box(extents=(2.0, 2.0, 2.0))
    pos = np.asarray(box.vertices, np.float32)
    idx = np.asarray(box.faces, np.uint16).ravel()
    uv = (pos[:, :2] * 0.25 + 0.5).astype(np.float32)
    parts = [pos.tobytes(), idx.tobytes() + b"\0" * (-idx.nbytes % 4), uv.tobytes(), *(im + b"\0" * (-len(im) % 4) for im in images)]
    views, offset = [], 0
    for p in parts:
        views.append({"buffer": 0, "byteOffset": offset, "byteLength": len(p)})
        offset += len(p)
    views[1]["byteLength"] = idx.nbytes
    for k, im in enumerate(images):
        views[3 + k]["byteLength"] = len(im)
    doc: dict[str, Any] = {
        "asset": {"version": "2.0"},
        "scene": 0,
        "scenes": [{"nodes": [0]}],
        "nodes": [{"mesh": 0}],
        "buffers": [{"byteLength": offset}],
        "bufferViews": views,
        "accessors": [
            {"bufferView": 0, "componentType": 5126, "count": len(pos), "type": "VEC3", "min": pos.min(0).tolist(), "max": pos.max(0).tolist()},
            {"bufferView": 1, "componentType": 5123, "count": int(index_count if index_count is not None else len(idx)), "type": "SCALAR"},
            {"bufferView": 2, "componentType": 5126, "count": len(uv), "type": "VEC2"},
        ],
        "meshes": [{"primitives": [{"attributes": {"POSITION": 0, "TEXCOORD_0": 2}, "indices": 1, **({"material": 0} if images else {})}]}],
    }
    if images:
        doc["images"] = [{"bufferView": 3 + k, "mimeType": "image/png"} for k in range(len(images))]
        doc["textures"] = [{"source": k} for k in range(len(images))]
        doc["materials"] = [{"pbrMetallicRoughness": {"baseColorTexture": {"index": k}}} for k in range(len(images))]
    js = json.dumps(doc).encode()
    js += b" " * (-len(js) % 4)
    binary = b"".join(parts)
    body = struct.pack("<I4s", len(js), b"JSON") + js + struct.pack("<I4s", len(binary), b"BIN\0") + binary
    path.write_bytes(struct.pack("<4sII", b"glTF", 2, 12 + len(body)) + body)
    return path


def _scene(path: str, **kw: Any) -> dict[str, Any]:
    return {
        "name": "mesh_probe",
        "dim": 3,
        "n_grid": 32,
        "frames": 10,
        "blocks": [{"material": "water", "lo": [0.38, 0.7, 0.38], "hi": [0.62, 0.8, 0.62]}],
        "obstacles": [{"shape": "mesh", "path": path, "center": CENTER, "scale": 0.1, **kw}],
    }


def _err(d: dict[str, Any], base: Path) -> InvalidInputError:
    with pytest.raises(InvalidInputError) as e:
        SceneSpec.from_dict(d, base_dir=base)
    return e.value


def test_a_glb_s_image_textures_are_not_decoded(tmp_path):
    """Three 12000² textures (432 MB each decoded as RGB) in a file of under 2 MB: the collider
    is built from the cube's geometry alone, its samples equal to the untextured cube's, in a process whose
    peak memory stays far below one decoded texture."""
    side = 12000
    png = _png_zeros(side)
    textured = _glb(tmp_path / "textured.glb", [png, png, png])
    _glb(tmp_path / "plain.glb")
    assert textured.stat().st_size < 2 * 2**20
    code = (
        "import sys, numpy as np\n"
        "from hybridmpm.scenes import obstacle_mesh\n"
        "from pathlib import Path\n"
        "v, f = obstacle_mesh.load_mesh(Path(sys.argv[1]), 'obstacles[0].path')\n"
        # VmHWM, the peak of this process's own memory: ru_maxrss carries the parent's peak across a (v)fork and exec
        "print(len(f), next(int(l.split()[1]) * 1024 for l in open('/proc/self/status') if l.startswith('VmHWM')))\n"
    )
    r = subprocess.run([sys.executable, "-c", code, str(textured)], capture_output=True, text=True, timeout=300, env=dict(os.environ))
    assert r.returncode == 0, r.stderr[-2000:]
    triangles, peak = (int(x) for x in r.stdout.split())
    assert triangles == 12
    assert peak < 3 * side * side, f"peak RSS {peak / 2**20:.0f} MiB: a texture was decoded"
    a = SceneSpec.from_dict(_scene("textured.glb"), base_dir=tmp_path).build().params.colliders[0]
    b = SceneSpec.from_dict(_scene("plain.glb"), base_dir=tmp_path).build().params.colliders[0]
    assert np.array_equal(np.asarray(a.values), np.asarray(b.values))


def _no_trimesh_load(monkeypatch):
    def refuse(*a, **k):
        raise AssertionError("trimesh read a file whose declared size is over the caps")

    monkeypatch.setattr(trimesh, "load", refuse)
    monkeypatch.setattr(trimesh, "load_mesh", refuse)


def test_the_triangle_cap_applies_to_what_the_file_declares_before_it_is_loaded(tmp_path, monkeypatch):
    cap = obstacle_mesh.MAX_MESH_TRIANGLES
    many = cap + 1
    # a binary STL of cap + 1 triangles (its header's count)
    tri = np.zeros((many, 12), np.float32)
    tri[:, 3:6] = [0, 0, 0]
    tri[:, 6:9] = [1, 0, 0]
    tri[:, 9:12] = [0, 1, 0]
    rec = np.zeros(many, np.dtype([("t", "<f4", (12,)), ("attr", "<u2")]))
    rec["t"] = tri
    (tmp_path / "many.stl").write_bytes(b"\0" * 80 + struct.pack("<I", many) + rec.tobytes())
    # an ASCII PLY whose header declares cap + 1 faces (the body never read)
    (tmp_path / "many.ply").write_text(
        f"ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\nproperty float z\nelement face {many}\nproperty list uchar int vertex_indices\nend_header\n0 0 0\n1 0 0\n0 1 0\n"
    )
    # an OBJ of one polygon of cap + 3 corners (cap + 1 triangles once split)
    (tmp_path / "fan.obj").write_text(
        "".join(f"v {np.cos(a):.6f} {np.sin(a):.6f} 0\n" for a in np.linspace(0, 6, many + 2)) + "f " + " ".join(str(i + 1) for i in range(many + 2)) + "\n"
    )
    # a GLB whose indices accessor declares 3e9 indices (a billion triangles) over a 72-byte view
    _glb(tmp_path / "declared.glb", index_count=3_000_000_000)
    _no_trimesh_load(monkeypatch)
    for name in ("many.stl", "many.ply", "fan.obj", "declared.glb"):
        e = _err(_scene(name), tmp_path)
        assert e.field == "obstacles[0].path" and "triangles" in str(e) and "\n" not in str(e), (name, str(e))


def test_a_glb_accessor_declaring_more_than_the_budget_is_refused_before_loading(tmp_path, monkeypatch):
    """A vertex accessor without a buffer view (trimesh would allocate its zeros) declaring 10¹⁰ vertices (112 GiB)."""
    p = _glb(tmp_path / "cube.glb")
    raw = p.read_bytes()
    (jlen,) = struct.unpack("<I", raw[12:16])
    doc = json.loads(raw[20 : 20 + jlen])
    doc["accessors"].append({"componentType": 5126, "count": 10_000_000_000, "type": "VEC3"})
    js = json.dumps(doc).encode()
    js += b" " * (-len(js) % 4)
    rest = raw[20 + jlen :]
    body = struct.pack("<I4s", len(js), b"JSON") + js + rest
    (tmp_path / "zeros.glb").write_bytes(struct.pack("<4sII", b"glTF", 2, 12 + len(body)) + body)
    _no_trimesh_load(monkeypatch)
    e = _err(_scene("zeros.glb"), tmp_path)
    assert e.field == "obstacles[0].path" and "memory budget" in str(e) and "accessor" in str(e), str(e)


def test_a_scale_that_overflows_once_placed_is_refused_naming_scale(tmp_path):
    trimesh.creation.box(extents=(4.0, 4.0, 4.0)).export(tmp_path / "cube.stl")  # vertices at ±2: 2e308 is inf, and inf·0 NaN
    rot = [[0.6, -0.8, 0.0], [0.8, 0.6, 0.0], [0.0, 0.0, 1.0]]
    for kw in ({"scale": 1e308}, {"scale": 1e308, "rotation": rot}):
        e = _err(_scene("cube.stl", **kw), tmp_path)
        assert e.field == "obstacles[0].scale" and "\n" not in str(e), (kw, str(e))
