"""Fluid surfaces and USD export: time per frame, the 200-frame USD check, the pictures of docs/mesh.md.

1. **Meshing + writing per frame** at a 64³ grid: a block of 16³ cells on the
   scenes' lattice (2 particles per cell per axis: 32 768 particles), jittered
   by 5 % of a cell so that the field is not the lattice's, meshed
   (:func:`hybridmpm.render.surface_mesh`, the volume-matched level and the
   fixed level 1/2) and written as binary PLY; then the frames of two water3d
   MPM rollouts (moving, splashing fluid: seed 1, 100 frames; seed 9, whose
   water spreads over the whole floor in films thinner than a cell, 200
   frames). Median wall and CPU ms per frame over ``--repeats`` runs (one
   core; nothing here is threaded), the enclosed volume against the
   particles', and in an untimed pass the marching-cubes calls per frame and
   the meshes that are not closed or hold a duplicate or zero-area face.
   Films thinner than a cell on the floor of a 32³ grid: level, volume, top.
2. **USD**: a ``--usd-frames`` (default 200) frame water3d MPM run written by
   :func:`hybridmpm.render.usd.write_usd` with its surfaces, read back with
   ``pxr``: one time sample per frame of the points and the mesh, point counts
   equal to the trajectory's.
3. ``--figure DIR``: ``mesh_water3d.png`` (frames 0 and 90 of water3d seed 9, matplotlib
   ``plot_trisurf``) and ``mesh_dam_break2d.png`` (the dam break's outline over
   its particles).

    python benchmarks/bench_surface.py --out benchmarks/results/surface.json --figure docs/img

Time it on a quiet machine (``uptime``: load near 0); the figures in
docs/mesh.md say which load they were measured under.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import skimage.measure

from hybridmpm.bench.harness import save_figure, write_results
from hybridmpm.render.surface import frame_surfaces, surface_mesh, surface_settings, write_surface
from hybridmpm.scenes import make_scene
from hybridmpm.scenes.core import lattice
from hybridmpm.sim import MpmSimulator, rollout


def _time(fn: Any, repeats: int) -> dict[str, float]:
    wall, cpu = [], []
    for _ in range(repeats):
        t, c = time.perf_counter(), time.process_time()
        fn()
        wall.append(time.perf_counter() - t)
        cpu.append(time.process_time() - c)
    return {"wall_ms_median": 1e3 * float(np.median(wall)), "cpu_ms_median": 1e3 * float(np.median(cpu)), "wall_ms_min": 1e3 * float(np.min(wall))}


@contextlib.contextmanager
def count_marching_cubes() -> Iterator[list[int]]:
    """Counts the calls of ``skimage.measure.marching_cubes`` (the surface
    module imports it at each call) in the list it yields."""
    calls, original = [0], skimage.measure.marching_cubes

    def counted(*args: Any, **kwargs: Any) -> Any:
        calls[0] += 1
        return original(*args, **kwargs)

    skimage.measure.marching_cubes = counted
    try:
        yield calls
    finally:
        skimage.measure.marching_cubes = original


def block_timing(repeats: int, tmp: Path) -> dict[str, Any]:
    n = 64
    dx = 1.0 / n
    face = 2 * dx
    p = lattice([face + 8 * dx, face, face + 8 * dx], [face + 24 * dx, face + 16 * dx, face + 24 * dx], dx / 2).astype(np.float64)
    p += np.random.default_rng(0).normal(0, 0.05 * dx, p.shape)
    pt = np.full(len(p), 5)
    domain = ([face] * 3, [1 - face] * 3)
    out: dict[str, Any] = {"grid": n, "particles": len(p)}
    for iso in ("volume", 0.5):

        def frame(iso: Any = iso) -> None:
            for m in surface_mesh(p, pt, domain=domain, dx=dx, iso=iso):
                write_surface(m, tmp / "block.ply")

        frame()
        with count_marching_cubes() as calls:
            (m,) = surface_mesh(p, pt, domain=domain, dx=dx, iso=iso)
        out[f"iso_{iso}"] = {
            **_time(frame, repeats), "faces": len(m.faces), "level": m.iso, "volume_error": m.volume / (16 * dx) ** 3 - 1,
            "marching_cubes_calls": calls[0],
        }  # fmt: skip
    return out


def mesh_faults(vertices: np.ndarray, faces: np.ndarray) -> int:
    """0 for a closed, consistently wound mesh with no face twice (by its
    vertices' positions) and none of zero area; else 1."""
    import trimesh

    if len(faces) == 0:
        return 0
    tm = trimesh.Trimesh(vertices, faces, process=False)
    _, at = np.unique(vertices, axis=0, return_inverse=True)
    pos = np.sort(at.ravel()[faces], axis=1)
    collapsed = ((pos[:, 0] == pos[:, 1]) | (pos[:, 1] == pos[:, 2])).any()
    twice = len(np.unique(pos, axis=0)) < len(faces)
    return int(not (tm.is_watertight and tm.is_winding_consistent) or collapsed or twice or tm.area_faces.min() <= 0)


def rollout_timing(frames: int, tmp: Path, seed: int = 1) -> dict[str, Any]:
    scene = make_scene("water3d", seed=seed)
    ro = rollout(MpmSimulator(scene, threads=1), frames)
    settings = surface_settings(scene.params, ro.particle_type, ro.masses)
    wall, cpu, err = [], [], []
    target = float(settings["volumes"].sum())
    for t in range(ro.num_frames):
        t0, c0 = time.perf_counter(), time.process_time()
        surfaces = frame_surfaces(ro.positions[t], ro.particle_type, **settings)
        for s in surfaces:
            write_surface(s, tmp / f"{s.material}.ply")
        wall.append(time.perf_counter() - t0)
        cpu.append(time.process_time() - c0)
        err.append(sum(s.volume for s in surfaces) / target - 1)  # type: ignore[union-attr]
    e = np.abs(np.asarray(err))
    faulty = 0
    with count_marching_cubes() as calls:
        for t in range(ro.num_frames):
            for s in frame_surfaces(ro.positions[t], ro.particle_type, **settings):
                faulty += mesh_faults(s.vertices, s.faces)  # type: ignore[union-attr]
    return {
        "scene": f"water3d seed {seed}", "particles": int(scene.num_particles), "frames": ro.num_frames,
        "wall_ms_median": 1e3 * float(np.median(wall)), "cpu_ms_median": 1e3 * float(np.median(cpu)), "cpu_ms_max": 1e3 * float(np.max(cpu)),
        "volume_error_abs_median": float(np.median(e)), "volume_error_abs_max": float(e.max()),
        "frames_volume_error_over_5pct": int((e > 0.05).sum()), "frames_volume_error_over_1pct": int((e > 0.01).sum()),
        "marching_cubes_calls_per_frame": calls[0] / ro.num_frames,
        "meshes_not_closed_or_with_a_duplicate_or_zero_area_face": faulty,
    }  # fmt: skip


def film_check() -> list[dict[str, Any]]:
    """Films on the floor of a 32³ grid: one layer of particles ``spacing``
    cells apart (``(1/2)³/spacing²`` cells thick at rest density), lying
    within a quarter cell of the wall face as an MPM run leaves them, 16 × 16
    cells; the volume-matched level, the enclosed volume against the
    particles' and the height of the mesh's top [cells]."""
    dx, out = 1 / 32, []
    face = 2 * dx
    for spacing in (0.4, 0.5, 0.75, 1.0):
        g = np.arange(0, 16, spacing) + spacing / 2
        x, z = np.meshgrid(face + (4 + g) * dx, face + (6 + g) * dx, indexing="ij")
        p = np.stack([x.ravel(), np.full(x.size, face), z.ravel()], axis=1)
        rng = np.random.default_rng(0)
        p[:, [0, 2]] += rng.uniform(-0.1, 0.1, (len(p), 2)) * spacing * dx
        p[:, 1] += rng.uniform(0, 0.25, len(p)) * dx
        (m,) = surface_mesh(p, np.full(len(p), 5), domain=([face] * 3, [1 - face] * 3), dx=dx)
        out.append({
            "spacing_cells": spacing, "thickness_cells": 0.125 / spacing**2, "level": m.iso,
            "volume_error": m.volume / (len(p) * (dx / 2) ** 3) - 1, "top_cells": float(m.vertices[:, 1].max() - face) / dx,
        })  # fmt: skip
    return out


def usd_check(frames: int, tmp: Path) -> dict[str, Any]:
    from pxr import Usd, UsdGeom

    from hybridmpm.render.usd import write_usd

    scene = make_scene("water3d", seed=0)
    ro = rollout(MpmSimulator(scene, threads=1), frames)
    settings = surface_settings(scene.params, ro.particle_type, ro.masses)
    t0 = time.perf_counter()
    surfaces = [frame_surfaces(ro.positions[t], ro.particle_type, **settings) for t in range(ro.num_frames)]
    t1 = time.perf_counter()
    path = write_usd(
        tmp / "run.usd", ro.positions, ro.particle_type, ro.dt_frame, solver=ro.extras["solver"], surfaces=surfaces,
        obstacles=settings["obstacles"], domain=settings["domain"], width=settings["dx"] / 2,
    )  # fmt: skip
    t2 = time.perf_counter()
    stage = Usd.Stage.Open(str(path))
    pts = UsdGeom.Points(stage.GetPrimAtPath("/Run/Particles")).GetPointsAttr()
    mesh = UsdGeom.Mesh(stage.GetPrimAtPath("/Run/Surfaces/water")).GetPointsAttr()
    samples_points, samples_mesh = len(pts.GetTimeSamples()), len(mesh.GetTimeSamples())
    counts_ok = all(len(pts.Get(t)) == ro.num_particles for t in range(ro.num_frames))
    ok = samples_points == samples_mesh == ro.num_frames and counts_ok and stage.GetFramesPerSecond() == 1 / ro.dt_frame
    return {
        "frames_stored": ro.num_frames, "particles": ro.num_particles, "time_samples_points": samples_points, "time_samples_mesh": samples_mesh,
        "point_counts_match": counts_ok, "fps": stage.GetFramesPerSecond(), "ok": bool(ok),
        "surfaces_s": t1 - t0, "write_s": t2 - t1, "file_mib": os.path.getsize(path) / 2**20,
    }  # fmt: skip


def figures(out: Path) -> list[str]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    scene = make_scene("water3d", seed=9)  # one block thrown at the floor
    ro = rollout(MpmSimulator(scene, threads=1), 90)
    settings = surface_settings(scene.params, ro.particle_type, ro.masses)
    fig = plt.figure(figsize=(9, 4.2))
    for k, t in enumerate((0, 90)):
        (m,) = frame_surfaces(ro.positions[t], ro.particle_type, **settings)
        ax = fig.add_subplot(1, 2, k + 1, projection="3d")
        v = m.vertices  # type: ignore[union-attr]
        ax.plot_trisurf(v[:, 0], v[:, 2], v[:, 1], triangles=m.faces, color="#4f8fd6", edgecolor="none", shade=True)  # type: ignore[union-attr]
        c, r = (v.min(axis=0) + v.max(axis=0)) / 2, (v.max(axis=0) - v.min(axis=0)).max() / 2 + 0.02  # zoomed on the fluid, equal axes
        ax.set(xlim=(c[0] - r, c[0] + r), ylim=(c[2] - r, c[2] + r), zlim=(c[1] - r, c[1] + r), xlabel="x [m]", ylabel="z [m]", zlabel="y [m]")
        ax.set_box_aspect((1, 1, 1))
        ax.set_title(f"water3d seed 9, frame {t} ({len(m.faces)} triangles, level {m.iso:.2f})", fontsize=9)  # type: ignore[union-attr]
    fig.tight_layout()
    a = save_figure(fig, out / "mesh_water3d.png", dpi=110)

    scene2 = make_scene("dam_break2d")
    ro2 = rollout(MpmSimulator(scene2, threads=1), 80)
    s2 = surface_settings(scene2.params, ro2.particle_type, ro2.masses)
    fig, ax = plt.subplots(figsize=(6, 3.6))
    pos = ro2.positions[80]
    ax.scatter(pos[:, 0], pos[:, 1], s=0.3, color="#888888", label="particles")
    (c,) = frame_surfaces(pos, ro2.particle_type, **s2)
    for i, loop in enumerate(c.loops):  # type: ignore[union-attr]
        ax.plot(loop[:, 0], loop[:, 1], color="#1f5fbf", lw=1.2, label="outline" if i == 0 else None)
    ax.set(xlim=(0, 0.75), ylim=(0, 0.45), aspect="equal", xlabel="x [m]", ylabel="y [m]")
    ax.set_title(f"dam_break2d, frame 80: outline (level {c.iso:.2f}, area error {c.area / s2['volumes'].sum() - 1:+.1%})", fontsize=9)  # type: ignore[union-attr]
    ax.legend(loc="upper right", fontsize=8)
    fig.tight_layout()
    b = save_figure(fig, out / "mesh_dam_break2d.png", dpi=110)
    return [str(a), str(b)]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--repeats", type=int, default=20)
    ap.add_argument("--rollout-frames", type=int, default=100)
    ap.add_argument("--spread-frames", type=int, default=200, help="frames of the water3d seed 9 rollout, spread over the whole floor (0: skip)")
    ap.add_argument("--usd-frames", type=int, default=200, help="frames of the USD check (0: skip)")
    ap.add_argument("--figure", default=None, help="folder for the PNGs of docs/mesh.md")
    ap.add_argument("--out", default=None, help="JSON file for the results (FILE.json)")
    args = ap.parse_args()
    res: dict[str, Any] = {}
    with tempfile.TemporaryDirectory() as d:
        tmp = Path(d)
        res["block_64"] = block_timing(args.repeats, tmp)
        res["films_32"] = film_check()
        res["water3d_rollout"] = rollout_timing(args.rollout_frames, tmp)
        if args.spread_frames:
            res["water3d_spread"] = rollout_timing(args.spread_frames, tmp, seed=9)
        if args.usd_frames:
            res["usd"] = usd_check(args.usd_frames, tmp)
    if args.figure:
        res["figures"] = figures(Path(args.figure))
    print(json.dumps(res, indent=2))
    if args.out:
        out = Path(args.out)
        write_results(out.parent, out.stem, doc=res)


if __name__ == "__main__":
    main()
