"""What a run's exported files hold, read on the host for benchmarks/blender_import.py: the figures of each frame
(vertex and face counts, distinct faces, centroid) of the binary PLY files hybridmpm writes and of the OBJ sequence,
the frames to check, and ``run.usd`` read back with ``pxr`` against them (the check that needs no Blender). Only the
host process imports it: the figures go to Blender in the plan file."""

from __future__ import annotations

import argparse
import os
import re
from pathlib import Path
from typing import Any

import numpy as np

_PLY_TYPES = {
    "char": "i1",
    "int8": "i1",
    "uchar": "u1",
    "uint8": "u1",
    "short": "i2",
    "int16": "i2",
    "ushort": "u2",
    "uint16": "u2",
    "int": "i4",
    "int32": "i4",
    "uint": "u4",
    "uint32": "u4",
    "float": "f4",
    "float32": "f4",
    "double": "f8",
    "float64": "f8",
}


def _figures(xyz: Any, faces: Any) -> dict[str, Any]:
    """Vertex and face counts, faces with distinct vertex sets (Blender merges faces on the same vertices), centroid."""
    distinct = len(np.unique(np.sort(faces, axis=1), axis=0)) if len(faces) else 0
    return {"vertices": len(xyz), "faces": len(faces), "faces_distinct": distinct, "centroid": xyz.mean(axis=0).tolist() if len(xyz) else None}


def read_ply(path: Path) -> dict[str, Any]:
    """Figures of a binary little-endian PLY as hybridmpm writes it: the vertex element, then triangles (or none)."""
    data = path.read_bytes()
    end = data.index(b"end_header\n") + len(b"end_header\n")
    counts: dict[str, int] = {}
    props: list[tuple[str, str]] = []
    face_types: tuple[str, str] = ("u1", "i4")
    element = ""
    for line in data[:end].decode("ascii").splitlines():
        w = line.split()
        if w and w[0] == "format" and w[1] != "binary_little_endian":
            raise ValueError(f"{path}: not binary little-endian PLY")
        if w and w[0] == "element":
            element, counts[w[1]] = w[1], int(w[2])
        elif w and w[0] == "property" and element == "vertex":
            props.append((w[-1], "<" + _PLY_TYPES[w[1]]))
        elif w[:2] == ["property", "list"] and element == "face":
            face_types = (_PLY_TYPES[w[2]], _PLY_TYPES[w[3]])
    n, m = counts.get("vertex", 0), counts.get("face", 0)
    vdt = np.dtype(props)
    v = np.frombuffer(data, vdt, count=n, offset=end)
    xyz = np.stack([v["x"], v["y"], v["z"]], axis=1).astype(np.float64)
    faces = np.zeros((0, 3), np.int64)
    start = end + n * vdt.itemsize
    if m and data[start] == 3:  # triangles (a surface); the point clouds' faces are single vertices
        f = np.frombuffer(data, np.dtype([("n", face_types[0]), ("v", "<" + face_types[1], 3)]), count=m, offset=start)
        if not (f["n"] == 3).all():
            raise ValueError(f"{path}: faces other than triangles")
        faces = f["v"].astype(np.int64)
    out = _figures(xyz, faces)
    out["faces"] = m
    return out


def read_obj(path: Path) -> dict[str, Any]:
    v, f = [], []
    for line in path.read_text().splitlines():
        if line.startswith("v "):
            v.append([float(x) for x in line.split()[1:4]])
        elif line.startswith("f "):
            f.append([int(x.split("/")[0]) - 1 for x in line.split()[1:]])
    return _figures(np.array(v, np.float64).reshape(-1, 3), np.array(f, np.int64).reshape(-1, 3))


def _frames(pattern: re.Pattern[str], folder: Path) -> dict[int, Path]:
    out = {}
    for p in folder.iterdir():
        m = pattern.fullmatch(p.name)
        if m:
            out[int(m.group(1))] = p
    return dict(sorted(out.items()))


def spread(frames: list[int], count: int) -> list[int]:
    """``count`` frames evenly across ``frames``, first and last included."""
    if len(frames) <= count:
        return list(frames)
    return sorted({frames[round(i * (len(frames) - 1) / (count - 1))] for i in range(count)})


def expected_figures(export: Path, a: argparse.Namespace) -> dict[str, Any]:
    """What Blender should find, read from the exported files."""
    points = _frames(re.compile(r"frame_(\d+)\.ply"), export)
    water = _frames(re.compile(r"water_(\d+)\.ply"), export)
    obj_dir = export.parent / "export_obj"
    water_obj = _frames(re.compile(r"water_(\d+)\.obj"), obj_dir) if obj_dir.is_dir() else {}
    if not water:
        raise SystemExit(f"blender_import: no water_#####.ply in {export} (export with --export mesh)")
    frames = list(water)
    water_ply = {str(k): read_ply(p) for k, p in water.items()}
    # frames spread over the run, and up to 3 whose surface has two faces on the same vertices
    dup = [k for k in frames if water_ply[str(k)]["faces"] != water_ply[str(k)]["faces_distinct"]]
    check = sorted(set(spread(frames, a.check_frames)) | set(dup[:3]))
    exp: dict[str, Any] = {
        "export_dir": str(export),
        "usd": str(export / "run.usd") if (export / "run.usd").is_file() else None,
        "frames": frames,
        "check_frames": check,
        "water_ply": water_ply,
        "frames_with_duplicate_faces": dup,
        "water_obj": {str(k): read_obj(p) for k, p in water_obj.items()},
        "obj_dir": str(obj_dir) if water_obj else None,
        "points_ply": {str(k): read_ply(points[k]) for k in check if k in points},
        "points_files": {str(k): str(points[k]) for k in check if k in points},
    }
    if exp["points_ply"]:
        exp["particles"] = next(iter(exp["points_ply"].values()))["vertices"]
    return exp


def pxr_check(exp: dict[str, Any]) -> dict[str, Any]:
    """``run.usd`` read back with pxr against the exported files: the check without Blender's USD."""
    try:
        from pxr import Usd, UsdGeom
    except ImportError as e:
        return {"ran": False, "reason": f"pxr not installed ({e}): pip install 'hybridmpm[usd]'"}
    if not exp["usd"]:
        return {"ran": False, "reason": "no run.usd in the export (export with --export usd)"}
    stage = Usd.Stage.Open(exp["usd"])
    out: dict[str, Any] = {"ran": True, "file_mib": os.path.getsize(exp["usd"]) / 2**20}
    out["prims"] = {str(p.GetPath()): p.GetTypeName() for p in stage.Traverse()}
    out["fps"] = stage.GetFramesPerSecond()
    out["time_codes_per_second"] = stage.GetTimeCodesPerSecond()
    out["start"], out["end"] = stage.GetStartTimeCode(), stage.GetEndTimeCode()
    out["meters_per_unit"] = UsdGeom.GetStageMetersPerUnit(stage)
    out["up_axis"] = str(UsdGeom.GetStageUpAxis(stage))
    dom = UsdGeom.BasisCurves(stage.GetPrimAtPath("/Run/Domain"))
    if dom:
        pts = np.array(dom.GetPointsAttr().Get())
        out["domain"] = [pts.min(axis=0).tolist(), pts.max(axis=0).tolist()]
        out["domain_purpose"] = str(dom.GetPurposeAttr().Get())
    pa = UsdGeom.Points(stage.GetPrimAtPath("/Run/Particles")).GetPointsAttr()
    mesh = UsdGeom.Mesh(stage.GetPrimAtPath("/Run/Surfaces/water"))
    out["points_time_samples"] = len(pa.GetTimeSamples())
    out["mesh_time_samples"] = len(mesh.GetPointsAttr().GetTimeSamples())
    frames: dict[str, Any] = {}
    ok = out["points_time_samples"] == out["mesh_time_samples"] == len(exp["frames"]) and (out["start"], out["end"]) == (exp["frames"][0], exp["frames"][-1])
    for k in exp["check_frames"]:
        w = exp["water_ply"][str(k)]
        mp = np.array(mesh.GetPointsAttr().Get(k), np.float64).reshape(-1, 3)
        faces = len(mesh.GetFaceVertexCountsAttr().Get(k) or [])
        row: dict[str, Any] = {"mesh_vertices": len(mp), "mesh_faces": faces, "file_vertices": w["vertices"], "file_faces": w["faces"]}
        good = len(mp) == w["vertices"] and faces == w["faces"] and (not len(mp) or np.allclose(mp.mean(axis=0), w["centroid"], atol=1e-5))
        if str(k) in exp["points_ply"]:
            pp = np.array(pa.Get(k), np.float64)
            f = exp["points_ply"][str(k)]
            row.update(points=len(pp), file_points=f["vertices"])
            good = good and len(pp) == f["vertices"] and np.allclose(pp.mean(axis=0), f["centroid"], atol=1e-5)
        row["ok"] = bool(good)
        ok = ok and good
        frames[str(k)] = row
    out["frames"] = frames
    out["ok"] = bool(ok)
    return out
