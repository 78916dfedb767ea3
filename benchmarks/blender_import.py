"""Open a run's exports in Blender, headless: the USD file, the mesh sequences, one rendered still.

Not part of CI: it needs Blender (``apt-get install blender`` on Debian, or an
official build) and the ``mesh`` and ``usd`` extras. Three parts:

1. **Export.** ``hybridmpm simulate SCENE --solver mpm --frames N --export ply usd mesh``
   (or ``--export-dir DIR``: an existing ``OUT/export``), then
   ``hybridmpm export TRAJ --mesh --mesh-format obj`` for the OBJ sequence. The
   expected figures per frame come from the files themselves: vertex and face
   counts and the vertex centroid of ``water_#####.ply``, the particle count and
   centroid of ``frame_#####.ply``. ``pxr`` (usd-core) reads ``run.usd`` back
   against them: the check that does not need Blender's USD support.
2. **Blender** (``blender -b --factory-startup --python THIS -- --inside PLAN``; or a
   Python with the PyPI ``bpy`` module, ``--bpy-python``): (a) if the build has USD
   (``bpy.app.build_options.usd``), ``bpy.ops.wm.usd_import`` of ``run.usd``, then
   for frames across the range the evaluated surface mesh and point cloud against
   the files (counts, centroid in the object's own coordinates), the frame range
   and frame rate the import leaves; (b) the mesh sequences ``water_#####.ply``
   and ``.obj`` through :data:`LOADER` (the script of docs/blender.md: one object
   per file, its visibility keyed to its frame), every frame checked; the
   point-cloud PLY of some frames; (c) a Cycles still of a mid-run frame (surface,
   floor, domain edges, sun, camera) to ``--image``.
3. A JSON summary (``--summary``) and Blender's log beside it.

    python benchmarks/blender_import.py --image docs/img/blender_water3d.png \\
        --summary benchmarks/results/blender/summary.json

Exit status 1 if a check fails, 2 if Blender is missing.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import re
import shutil
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]

#: The sequence loader of docs/blender.md, run inside Blender as it stands there
#: (the host checks that the page holds this exact text).
LOADER = '''\
import math
import re
from pathlib import Path

import bpy


def load_sequence(folder, prefix="water_"):
    """Import FOLDER/PREFIX#####.ply (or .obj), one object per file, each visible on its frame only."""
    pattern = re.compile(re.escape(prefix) + r"(\\d+)\\.(ply|obj)")
    files = sorted(p for p in Path(folder).iterdir() if pattern.fullmatch(p.name))
    if not files:
        raise FileNotFoundError(f"no {prefix}#####.ply or .obj in {folder}")
    scene = bpy.context.scene
    coll = bpy.data.collections.new(prefix.rstrip("_") or "sequence")
    scene.collection.children.link(coll)
    root = bpy.data.objects.new(coll.name + "_root", None)
    root.rotation_euler = (math.pi / 2, 0, 0)  # the files are y up, Blender is z up
    coll.objects.link(root)
    ops = dir(bpy.ops.wm)
    frames = []
    for path in files:
        k = int(pattern.fullmatch(path.name).group(1))
        before = set(bpy.data.objects)
        try:  # no axis conversion in the importer: the root turns the whole sequence
            if path.suffix == ".obj" and "obj_import" in ops:  # Blender 3.2+
                bpy.ops.wm.obj_import(filepath=str(path), forward_axis="Y", up_axis="Z")
            elif path.suffix == ".obj":
                bpy.ops.import_scene.obj(filepath=str(path), axis_forward="Y", axis_up="Z")
            elif "ply_import" in ops:  # Blender 4.0+
                bpy.ops.wm.ply_import(filepath=str(path))
            else:
                bpy.ops.import_mesh.ply(filepath=str(path))
        except RuntimeError:  # an empty frame (no surface): keep an empty mesh
            pass
        new = [o for o in bpy.data.objects if o not in before]
        obj = new[0] if new else bpy.data.objects.new(path.stem, bpy.data.meshes.new(path.stem))
        for c in list(obj.users_collection):
            c.objects.unlink(obj)
        coll.objects.link(obj)
        obj.name = path.stem
        obj.parent = root
        for f, hide in ((k - 1, True), (k, False), (k + 1, True)):
            obj.hide_viewport = obj.hide_render = hide
            obj.keyframe_insert("hide_viewport", frame=f)
            obj.keyframe_insert("hide_render", frame=f)
        frames.append(k)
    scene.frame_start, scene.frame_end = min(frames), max(frames)
    return coll
'''

# --------------------------------------------------------------------- host side


def run_cli(args: list[str], log: list[str]) -> float:
    cmd = [sys.executable, "-m", "hybridmpm", *args]
    log.append("$ hybridmpm " + " ".join(args))
    t = time.perf_counter()
    subprocess.run(cmd, check=True, cwd=ROOT)
    return time.perf_counter() - t


def make_export(a: argparse.Namespace, log: list[str]) -> tuple[Path, dict[str, Any]]:
    info: dict[str, Any] = {}
    if a.export_dir:
        export = Path(a.export_dir).resolve()
        info["source"] = f"existing export {export}"
    else:
        out = Path(a.out).resolve()
        cmd = [
            "simulate",
            a.scene,
            "--solver",
            "mpm",
            "--frames",
            str(a.frames),
            "--seed",
            str(a.seed),
            "--export",
            "ply",
            "usd",
            "mesh",
            "--out",
            str(out),
            "--no-render",
            "--quiet",
        ]
        info["simulate_s"] = run_cli(cmd, log)
        export = out / "export"
        info["source"] = "hybridmpm " + " ".join(cmd)
    traj = export.parent / "trajectory.npz"
    if a.obj and traj.is_file():
        obj_dir = export.parent / "export_obj"
        info["obj_export_s"] = run_cli(["export", str(traj), "--mesh", "--mesh-format", "obj", "--out", str(obj_dir), "--quiet"], log)
    return export, info


def find_blender(name: str) -> str:
    path = shutil.which(name)
    if path is None:
        sys.stderr.write(
            f"blender_import: Blender not found ('{name}' is not on PATH). Install it (Debian: apt-get install blender; "
            "or an official build, or `pip install bpy` and pass --bpy-python) or pass --blender PATH.\n"
        )
        raise SystemExit(2)
    return path


def _clean_env() -> dict[str, str]:
    """The environment without this virtual environment: Debian's Blender finds its Python home through
    ``python3`` on PATH, so an activated venv would hand it the venv's packages (numpy, hybridmpm)."""
    env = {k: v for k, v in os.environ.items() if k not in ("VIRTUAL_ENV", "PYTHONPATH", "PYTHONHOME")}
    if sys.prefix != sys.base_prefix:
        venv_bin = str(Path(sys.prefix) / "bin")
        env["PATH"] = os.pathsep.join(d for d in env.get("PATH", "").split(os.pathsep) if d != venv_bin)
    return env


def _squeeze(text: str, keep: int = 3) -> str:
    """Runs of lines that differ only in their numbers: the first ``keep`` and a count (4.5's PLY importer warns once per point)."""
    out: list[str] = []
    run: list[str] = []

    def flush() -> None:
        out.extend(run[:keep])
        if len(run) > keep:
            out.append(f"... {len(run) - keep} more lines like the one above")

    for line in text.splitlines():
        if run and re.sub(r"\d+", "#", line) != re.sub(r"\d+", "#", run[0]):
            flush()
            run = []
        run.append(line)
    flush()
    return "\n".join(out) + "\n"


def run_blender(cmd: list[str], plan: dict[str, Any], tag: str, results: Path, timeout: float) -> dict[str, Any]:
    from hybridmpm.bench.harness import write_file, write_json  # here, not at the top: Blender's Python runs this file too, without hybridmpm

    plan_path = results / f"plan_{tag}.json"
    out_path = results / f"blender_{tag}.json"
    plan = {**plan, "result": str(out_path)}
    write_json(plan_path, plan, indent=None)
    if out_path.exists():
        out_path.unlink()
    t = time.perf_counter()
    proc = subprocess.run([*cmd, str(plan_path)], capture_output=True, text=True, timeout=timeout, env=_clean_env())
    wall = time.perf_counter() - t
    log = results / f"blender_{tag}.log"
    write_file(log, f"$ {' '.join(cmd)} {plan_path}\n(exit {proc.returncode}, {wall:.1f} s)\n" + _squeeze(proc.stdout + proc.stderr))
    plan_path.unlink()
    if not out_path.exists():
        return {"ok": False, "error": f"Blender exited {proc.returncode} without a result; see {log}", "wall_s": wall}
    res = json.loads(out_path.read_text())
    out_path.unlink()
    res["wall_s"] = wall
    res["log"] = str(log.relative_to(ROOT) if log.is_relative_to(ROOT) else log)
    return res


def doc_has_loader(doc: Path) -> bool | None:
    if not doc.is_file():
        return None
    return "```python\n" + LOADER + "```" in doc.read_text()


def main(argv: list[str] | None = None) -> int:
    # here, not at the top: Blender's Python runs this file too, without hybridmpm; only the host reads the exported files
    from blender_files import expected_figures, pxr_check

    from hybridmpm.bench.harness import script_argv, write_results

    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--export-dir", help="an existing OUT/export (default: simulate one)")
    ap.add_argument("--scene", default="water3d")
    ap.add_argument("--frames", type=int, default=60)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", default=str(ROOT / "runs" / "blender_water3d"), help="run directory of the simulation")
    ap.add_argument("--no-obj", dest="obj", action="store_false", help="skip the OBJ sequence")
    ap.add_argument("--check-frames", type=int, default=7, help="frames checked across the range (USD, points); the sequences check every frame")
    ap.add_argument("--blender", default="blender", help="Blender executable (default: blender on PATH)")
    ap.add_argument("--bpy-python", help="also run the checks with this Python, which has the PyPI bpy module")
    ap.add_argument("--no-debian", dest="binary", action="store_false", help="skip the blender executable (with --bpy-python)")
    ap.add_argument("--image", default=str(ROOT / "docs" / "img" / "blender_water3d.png"), help="the still, rendered by the blender executable ('' for none)")
    ap.add_argument("--bpy-image", default="", help="the still rendered by --bpy-python (default none)")
    ap.add_argument("--render-frame", type=int, help="frame of the still (default the middle one)")
    ap.add_argument("--resolution", type=int, nargs=2, default=[480, 270])
    ap.add_argument("--samples", type=int, default=32, help="Cycles samples")
    ap.add_argument("--summary", default=str(ROOT / "benchmarks" / "results" / "blender" / "summary.json"))
    ap.add_argument("--timeout", type=float, default=1800)
    a = ap.parse_args(argv)

    runners: list[tuple[str, list[str], str]] = []
    if a.binary:
        runners.append(
            ("blender", [find_blender(a.blender), "-b", "--factory-startup", "--python-exit-code", "1", "--python", __file__, "--", "--inside"], a.image)
        )
    if a.bpy_python:
        runners.append(("bpy", [a.bpy_python, __file__, "--inside"], a.bpy_image))
    if not runners:
        ap.error("nothing to run: --no-debian without --bpy-python")

    log: list[str] = []
    t0 = time.perf_counter()
    export, info = make_export(a, log)
    exp = expected_figures(export, a)
    results = Path(a.summary).resolve().parent
    results.mkdir(parents=True, exist_ok=True)
    summary: dict[str, Any] = {
        "export": {
            **info,
            "commands": log,
            "dir": str(export),
            "frames": len(exp["frames"]),
            "first_last": [exp["frames"][0], exp["frames"][-1]],
            "particles": exp.get("particles"),
            "frames_with_duplicate_faces": exp["frames_with_duplicate_faces"],
            "water_vertices_min_max": [min(w["vertices"] for w in exp["water_ply"].values()), max(w["vertices"] for w in exp["water_ply"].values())],
        },
        "check_frames": exp["check_frames"],
    }
    t = time.perf_counter()
    summary["usd_pxr"] = {**pxr_check(exp), "seconds": time.perf_counter() - t}
    plan = {
        **exp,
        "loader": LOADER,
        "fps_file": summary["usd_pxr"].get("fps"),
        "domain": summary["usd_pxr"].get("domain"),
        "render_frame": a.render_frame if a.render_frame is not None else exp["frames"][len(exp["frames"]) // 2],
        "resolution": a.resolution,
        "samples": a.samples,
    }
    summary["runs"] = {}
    for tag, cmd, image in runners:
        r = run_blender(cmd, {**plan, "image": str(Path(image).resolve()) if image else ""}, tag, results, a.timeout)
        summary["runs"][tag] = r
        print(f"{tag}: {r.get('version', '?')}, USD in the build: {r.get('usd_build')}, ok: {r.get('ok')} ({r['wall_s']:.1f} s)")
    summary["doc_loader_matches"] = doc_has_loader(ROOT / "docs" / "blender.md")
    summary["total_s"] = time.perf_counter() - t0
    ok = summary["usd_pxr"].get("ok", True) is not False and all(r.get("ok") for r in summary["runs"].values())
    summary["ok"] = bool(ok)
    write_results(results, Path(a.summary).stem, doc=summary, argv=script_argv(__file__, argv))
    print(f"pxr check of run.usd: {summary['usd_pxr'].get('ok')}; summary -> {a.summary}")
    return 0 if ok else 1


# --------------------------------------------------------------------- inside Blender


def _timed(fn: Any, *args: Any) -> tuple[Any, float]:
    t = time.perf_counter()
    r = fn(*args)
    return r, time.perf_counter() - t


def _mesh_figures(obj: Any, dg: Any) -> dict[str, Any]:
    """Counts and centroid (the object's own coordinates) of the evaluated object; plain Python (Debian's Blender has no numpy)."""
    from array import array

    ev = obj.evaluated_get(dg)
    if obj.type == "POINTCLOUD":
        n = len(ev.data.points)
        co = array("f", bytes(12 * n))
        ev.data.attributes["position"].data.foreach_get("vector", co)
        faces = None
    else:
        me = ev.to_mesh()
        n = len(me.vertices)
        co = array("f", bytes(12 * n))
        me.vertices.foreach_get("co", co)
        faces = len(me.polygons)
        ev.to_mesh_clear()
    centroid = [math.fsum(co[a::3]) / n for a in range(3)] if n else None
    return {"vertices": n, "faces": faces, "centroid": centroid}


def _same(got: dict[str, Any], want: dict[str, Any], faces: bool = True) -> bool:
    """Same vertex count, face count (the file's, or its count of distinct vertex sets: an importer may merge
    two faces on the same three vertices) and centroid within 1e-5 m."""
    if got["vertices"] != want["vertices"] or (faces and got["faces"] not in (want["faces"], want["faces_distinct"])):
        return False
    return got["centroid"] is None or all(abs(a - b) <= 1e-5 for a, b in zip(got["centroid"], want["centroid"]))


def inside_usd(bpy: Any, plan: dict[str, Any]) -> dict[str, Any]:
    """(a) Blender's own USD importer, if the build has it."""
    out: dict[str, Any] = {"build_option_usd": bool(getattr(bpy.app.build_options, "usd", False)), "operator": "usd_import" in dir(bpy.ops.wm)}
    if not (out["build_option_usd"] and out["operator"]):
        out.update(ran=False, ok=None, reason="this Blender is built without USD (bpy.app.build_options.usd is False, no bpy.ops.wm.usd_import)")
        return out
    if not plan["usd"]:
        out.update(ran=False, ok=None, reason="no run.usd in the export")
        return out
    bpy.ops.wm.read_factory_settings(use_empty=True)
    scene = bpy.context.scene
    props = bpy.ops.wm.usd_import.get_rna_type().properties.keys()
    opts = {k: True for k in ("import_guide", "set_frame_range", "import_points", "import_shapes", "import_curves", "import_meshes") if k in props}
    res, out["import_s"] = _timed(lambda: bpy.ops.wm.usd_import(filepath=plan["usd"], **opts))
    out["options"] = opts
    out["ran"] = "FINISHED" in res
    out["objects"] = {
        o.name: {
            "type": o.type,
            "parent": o.parent.name if o.parent else None,
            "modifiers": [m.type for m in o.modifiers],
            "world_rotation_deg": [round(math.degrees(x), 3) for x in o.matrix_world.to_euler()],
        }
        for o in bpy.data.objects
    }
    out["frame_range"] = [scene.frame_start, scene.frame_end]
    out["fps_scene_after_import"] = scene.render.fps / scene.render.fps_base
    out["fps_file"] = plan["fps_file"]
    checks: dict[str, bool] = {"frame_range": out["frame_range"] == [plan["frames"][0], plan["frames"][-1]]}
    water, pts = bpy.data.objects.get("water"), bpy.data.objects.get("Particles")
    checks["surface_object"] = water is not None and water.type == "MESH"
    out["points_object_type"] = pts.type if pts else None
    checks["points_object"] = pts is not None and pts.type in ("POINTCLOUD", "MESH")
    if pts is not None and pts.type == "POINTCLOUD":
        out["points_attributes"] = sorted(pts.data.attributes.keys())
    frames: dict[str, Any] = {}
    t = time.perf_counter()
    seen: set[tuple[float, ...]] = set()
    for k in plan["check_frames"]:
        scene.frame_set(k)
        dg = bpy.context.evaluated_depsgraph_get()
        row: dict[str, Any] = {}
        good = True
        if checks["surface_object"]:
            row["surface"] = _mesh_figures(water, dg)
            row["surface_file_vertices"] = plan["water_ply"][str(k)]["vertices"]
            row["surface_file_faces"] = plan["water_ply"][str(k)]["faces"]
            good = good and _same(row["surface"], plan["water_ply"][str(k)])
            if row["surface"]["centroid"]:
                seen.add(tuple(round(x, 6) for x in row["surface"]["centroid"]))
        if checks["points_object"] and str(k) in plan["points_ply"]:
            row["points"] = _mesh_figures(pts, dg)
            row["points_file"] = plan["points_ply"][str(k)]["vertices"]
            good = good and _same(row["points"], plan["points_ply"][str(k)], faces=False)
        row["ok"] = bool(good)
        frames[str(k)] = row
    out["check_s"] = time.perf_counter() - t
    out["frames"] = frames
    out["faces_merged"] = [
        [int(k), r["surface_file_faces"], r["surface"]["faces"]]
        for k, r in frames.items()
        if "surface" in r and r["surface"]["faces"] != r["surface_file_faces"]
    ]
    checks["frames_match_files"] = all(r["ok"] for r in frames.values())
    checks["surface_changes_between_frames"] = len(seen) == len(plan["check_frames"])
    domain = bpy.data.objects.get("Domain")
    checks["domain_guide_imported"] = domain is not None
    out["checks"] = checks
    out["ok"] = all(checks.values())
    out["fps_note"] = (
        "the importer sets the frame range, not the scene frame rate: set Output Properties > Frame Rate to fps_file (or keep 24 and play slowed down)"
    )
    return out


def inside_sequences(bpy: Any, plan: dict[str, Any], ns: dict[str, Any]) -> dict[str, Any]:
    """(b) The mesh sequences through LOADER, every frame; the point-cloud PLY of the checked frames."""
    bpy.ops.wm.read_factory_settings(use_empty=True)
    scene = bpy.context.scene
    out: dict[str, Any] = {}
    seqs = [("ply", plan["export_dir"], plan["water_ply"])]
    if plan["obj_dir"]:
        seqs.append(("obj", plan["obj_dir"], plan["water_obj"]))
    for fmt, folder, want in seqs:
        before = set(bpy.data.collections)
        coll, secs = _timed(ns["load_sequence"], folder)
        assert coll not in before
        coll.name = f"water_{fmt}"
        meshes = [o for o in coll.objects if o.type == "MESH"]
        bad: list[int] = []
        merged: list[list[int]] = []  # [frame, faces in the file, faces in Blender]
        counts: dict[str, int] = {}
        t = time.perf_counter()
        for k in plan["frames"]:
            scene.frame_set(k)
            dg = bpy.context.evaluated_depsgraph_get()
            shown = [o for o in meshes if not o.hide_render and not o.hide_viewport]
            if len(shown) != 1:
                bad.append(k)
                continue
            got = _mesh_figures(shown[0], dg)
            counts[str(k)] = got["vertices"]
            if got["faces"] != want[str(k)]["faces"]:
                merged.append([k, want[str(k)]["faces"], got["faces"]])
            if not _same(got, want[str(k)]):
                bad.append(k)
        out[f"water_{fmt}"] = {
            "objects": len(meshes),
            "frame_range": [scene.frame_start, scene.frame_end],
            "frames_checked": len(plan["frames"]),
            "frames_wrong": bad,
            "faces_merged": merged,
            "vertices_per_frame": counts,
            "import_s": secs,
            "check_s": time.perf_counter() - t,
            "ok": not bad and len(meshes) == len(plan["frames"]) and [scene.frame_start, scene.frame_end] == [plan["frames"][0], plan["frames"][-1]],
        }
    # the point-cloud files: a mesh of vertices only
    rows = {}
    for k, path in plan["points_files"].items():
        before = set(bpy.data.objects)
        if "ply_import" in dir(bpy.ops.wm):
            bpy.ops.wm.ply_import(filepath=path)
        else:
            bpy.ops.import_mesh.ply(filepath=path)
        new = [o for o in bpy.data.objects if o not in before]
        got = _mesh_figures(new[0], bpy.context.evaluated_depsgraph_get()) if new else {"vertices": 0, "faces": None, "centroid": None}
        rows[k] = {
            "vertices": got["vertices"],
            "faces": got["faces"],
            "file": plan["points_ply"][k]["vertices"],
            "ok": _same(got, plan["points_ply"][k], faces=False),
        }
        if new:
            rows[k]["attributes"] = sorted(a.name for a in new[0].data.attributes if not a.name.startswith("."))
            bpy.data.objects.remove(new[0])
    out["points_ply"] = {"frames": rows, "ok": all(r["ok"] for r in rows.values())}
    out["ok"] = all(v["ok"] for v in out.values())
    return out


def _material(bpy: Any, name: str, color: tuple[float, float, float], roughness: float) -> Any:
    mat = bpy.data.materials.new(name)
    mat.use_nodes = True
    bsdf = mat.node_tree.nodes["Principled BSDF"]
    bsdf.inputs["Base Color"].default_value = (*color, 1.0)
    bsdf.inputs["Roughness"].default_value = roughness
    return mat


def inside_render(bpy: Any, plan: dict[str, Any]) -> dict[str, Any]:
    """(c) A Cycles still of the water surface at plan['render_frame'] (from the PLY sequence loaded by inside_sequences)."""
    scene = bpy.context.scene
    k = plan["render_frame"]
    coll = bpy.data.collections["water_ply"]
    for c in list(bpy.data.collections):
        if c is not coll:
            bpy.data.collections.remove(c)
    scene.frame_set(k)
    water = _material(bpy, "water", (0.05, 0.28, 0.75), 0.08)
    for o in coll.objects:
        if o.type == "MESH":
            o.data.materials.append(water)
            o.data.polygons.foreach_set("use_smooth", [True] * len(o.data.polygons))
    lo, hi = plan["domain"] or [[0.0] * 3, [1.0] * 3]
    # Blender z up: (x, y, z) of the files -> (x, -z, y)
    blo = (lo[0], -hi[2], lo[1])
    bhi = (hi[0], -lo[2], hi[1])
    centre = [(a + b) / 2 for a, b in zip(blo, bhi)]
    size = [b - a for a, b in zip(blo, bhi)]
    bpy.ops.mesh.primitive_plane_add(size=1.0, location=(centre[0], centre[1], blo[2]))
    floor = bpy.context.active_object
    floor.scale = (size[0], size[1], 1)
    floor.data.materials.append(_material(bpy, "floor", (0.32, 0.32, 0.33), 0.6))
    bpy.ops.mesh.primitive_cube_add(size=1.0, location=centre)
    box = bpy.context.active_object
    box.scale = size
    wire = box.modifiers.new("edges", "WIREFRAME")
    wire.thickness = 0.004
    box.data.materials.append(_material(bpy, "edges", (0.05, 0.05, 0.05), 0.9))
    sun = bpy.data.objects.new("sun", bpy.data.lights.new("sun", "SUN"))
    sun.data.energy = 3.5
    sun.data.angle = math.radians(8)
    sun.rotation_euler = (math.radians(40), math.radians(10), math.radians(35))
    scene.collection.objects.link(sun)
    cam = bpy.data.objects.new("camera", bpy.data.cameras.new("camera"))
    cam.data.lens = 35
    cam.location = (centre[0] + 1.3 * size[0], centre[1] - 1.7 * size[1], centre[2] + 0.8 * size[2])
    target = bpy.data.objects.new("target", None)
    target.location = (centre[0], centre[1], blo[2] + 0.42 * size[2])
    scene.collection.objects.link(target)
    track = cam.constraints.new("TRACK_TO")
    track.target = target
    track.track_axis, track.up_axis = "TRACK_NEGATIVE_Z", "UP_Y"
    scene.collection.objects.link(cam)
    scene.camera = cam
    world = bpy.data.worlds.new("world")
    world.use_nodes = True
    world.node_tree.nodes["Background"].inputs["Color"].default_value = (0.8, 0.85, 0.9, 1)
    world.node_tree.nodes["Background"].inputs["Strength"].default_value = 0.6
    scene.world = world
    scene.render.engine = "CYCLES"
    scene.cycles.device = "CPU"
    scene.cycles.samples = plan["samples"]
    scene.render.resolution_x, scene.render.resolution_y = plan["resolution"]
    scene.render.resolution_percentage = 100
    scene.render.image_settings.file_format = "PNG"
    scene.render.filepath = plan["image"]
    scene.view_settings.view_transform = "Standard"
    import _cycles  # Cycles' own module: which denoisers this build has

    oidn = bool(getattr(_cycles, "with_openimagedenoise", False))
    scene.cycles.use_denoising = oidn  # Debian's 3.4 is built without OpenImageDenoise
    if oidn:
        scene.cycles.denoiser = "OPENIMAGEDENOISE"
    shown = [o.name for o in coll.objects if o.type == "MESH" and not o.hide_render]
    _, secs = _timed(lambda: bpy.ops.render.render(write_still=True))
    ok = Path(plan["image"]).is_file()
    return {
        "image": plan["image"],
        "frame": k,
        "shown": shown,
        "engine": "CYCLES",
        "samples": plan["samples"],
        "denoiser": "OPENIMAGEDENOISE" if oidn else None,
        "resolution": plan["resolution"],
        "render_s": secs,
        "ok": ok and len(shown) == 1 and re.fullmatch(rf"water_{k:05d}(\.\d+)?", shown[0]) is not None,
    }


def inside(plan_path: str) -> None:
    import platform  # Blender's own Python, reported with the build

    import bpy

    plan = json.loads(Path(plan_path).read_text())
    t0 = time.perf_counter()
    opts = bpy.app.build_options
    res: dict[str, Any] = {
        "version": bpy.app.version_string,
        "build_platform": bpy.app.build_platform.decode() if isinstance(bpy.app.build_platform, bytes) else str(bpy.app.build_platform),
        "binary_path": bpy.app.binary_path,
        "python": platform.python_version(),
        "usd_build": bool(getattr(opts, "usd", False)),
        "alembic_build": bool(getattr(opts, "alembic", False)),
    }
    ns: dict[str, Any] = {}
    exec(compile(plan["loader"], "docs/blender.md (load_sequence)", "exec"), ns)
    res["usd"] = inside_usd(bpy, plan)
    res["sequences"] = inside_sequences(bpy, plan, ns)
    if plan["image"]:
        res["render"] = inside_render(bpy, plan)
    res["seconds"] = time.perf_counter() - t0
    res["ok"] = res["usd"]["ok"] is not False and res["sequences"]["ok"] and res.get("render", {"ok": True})["ok"]
    Path(plan["result"]).write_text(json.dumps(res, indent=1))


if __name__ == "__main__":
    if "--inside" in sys.argv:
        inside(sys.argv[sys.argv.index("--inside") + 1])
    else:
        sys.exit(main())
