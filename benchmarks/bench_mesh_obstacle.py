"""Mesh obstacles at full size: signed-distance sampling time, and MPM with a
mesh obstacle against the analytic shape it approximates.

Runs (3D, 64³ grid, 200 frames, water block dropped from above):

* ``sdf``: :func:`hybridmpm.scenes.obstacle_mesh.sample_mesh_sdf` time for
  icospheres of 1,280 / 5,120 / 20,480 triangles and a 2,000-triangle
  sphere (trimesh.creation.uv_sphere) on the 64³ grid (best of 3), and the
  largest deviation of its samples from the analytic sphere's distance.
* ``sphere``: a mesh sphere (icosphere, subdivisions 3 and 4) against the
  analytic sphere of the same radius: the largest grid-mass error over the
  frames (:func:`hybridmpm.metrics.grid_mass_error` on the 64³ grid), the
  same for no obstacle at all (how much the obstacle matters), the
  deepest particle inside the analytic sphere at the last frame and at any
  frame [cells], and the wall time per frame of each run.
* ``ramp``: a mesh box rotated -20° about z against the analytic rotated box.

``--project off`` runs the obstacles without the particle projection
(``project = false``: the grid condition alone, as before it existed).

``--frame-cost`` measures the projection's cost alone instead: the
icosphere(4) obstacle and the analytic sphere, each with and without the
projection, frames 40-100 of the sphere run on one thread, the four runs
interleaved in one process ``--repeats`` times (each from its frame-40
state); the fastest wall and CPU (``time.process_time``) time per frame of
each, and the ratios with/without.

Usage::

    python benchmarks/bench_mesh_obstacle.py [--n-grid 64] [--frames 200] [--project on|off] [--out runs/bench_mesh_obstacle.json]
        [--figure docs/img/mesh_obstacle_sdf.png]
    python benchmarks/bench_mesh_obstacle.py --frame-cost [--repeats 5] [--out runs/mesh_obstacle_frame_cost.json]

``--figure`` also draws the slice z = 0.5 of the sampled signed distance of
the icosphere(4) obstacle with the water particles within half a cell of
that plane at frame 60 of the sphere run (matplotlib).
"""

from __future__ import annotations

import argparse
import math
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np
import trimesh

from hybridmpm.bench.harness import save_figure, write_results
from hybridmpm.metrics import grid_mass_error
from hybridmpm.mpm import Box
from hybridmpm.scenes import SceneSpec, collider_sdf
from hybridmpm.scenes.obstacle_mesh import sample_mesh_sdf
from hybridmpm.sim import MpmSimulator, rollout

CENTER = [0.5, 0.4, 0.5]
RADIUS = 0.15


def _scene(obstacles: list[dict[str, Any]], n: int, frames: int) -> dict[str, Any]:
    return {
        "name": "bench_mesh",
        "dim": 3,
        "n_grid": n,
        "frames": frames,
        "blocks": [{"material": "water", "lo": [0.38, 0.62, 0.38], "hi": [0.62, 0.8, 0.62]}],
        "obstacles": obstacles,
    }


#: Wall time per frame [ms] of each rollout, in the order they ran.
FRAME_MS: list[float] = []


def _rollout(spec: SceneSpec) -> np.ndarray:
    """Fluid positions of frames 1 … ``spec.frames``: float32 [T, N, 3]."""
    sim = MpmSimulator(spec.build())
    t = time.perf_counter()
    r = rollout(sim, spec.frames)
    FRAME_MS.append(1e3 * (time.perf_counter() - t) / spec.frames)
    return np.asarray(r.positions[1:, : r.num_fluid])


def bench_sdf(n: int) -> list[dict[str, Any]]:
    rows = []
    meshes = [(f"icosphere({s})", trimesh.creation.icosphere(subdivisions=s, radius=RADIUS)) for s in (3, 4, 5)]
    meshes.append(("uv_sphere(32x32)", trimesh.creation.uv_sphere(radius=RADIUS, count=[32, 33])))
    for name, m in meshes:
        v = np.asarray(m.vertices) + CENTER
        f = np.asarray(m.faces)
        times = []
        for _ in range(3):
            t = time.perf_counter()
            origin, cell, values, _ = sample_mesh_sdf(v, f, n, "bench")
            times.append(time.perf_counter() - t)
        idx = np.stack(np.meshgrid(*[np.arange(s) for s in values.shape], indexing="ij"), -1).reshape(-1, 3)
        exact = np.linalg.norm(np.asarray(origin) + cell * idx - CENTER, axis=1) - RADIUS
        rows.append(
            {
                "mesh": name,
                "triangles": len(f),
                "nodes": list(values.shape),
                "seconds": min(times),
                "max_dev_cells": float(np.abs(values.ravel() - exact).max() / cell),
            }
        )
        print(f"sdf {name:18s} {len(f):6d} tris  nodes {values.shape}  {min(times):.2f} s  max |sdf - sphere| {rows[-1]['max_dev_cells']:.3f} cells")
    return rows


def bench_pair(mesh_ob: dict[str, Any], ana_ob: dict[str, Any], sdf_of: Any, n: int, frames: int, base: Path) -> dict[str, Any]:
    t = time.perf_counter()
    mesh = SceneSpec.from_dict(_scene([mesh_ob], n, frames), base_dir=base)
    load_s = time.perf_counter() - t
    ana = SceneSpec.from_dict(_scene([ana_ob], n, frames))
    free = SceneSpec.from_dict(_scene([], n, frames))
    pm, pa, pf = _rollout(mesh), _rollout(ana), _rollout(free)
    ms_mesh, ms_ana, ms_free = FRAME_MS[-3:]
    err = grid_mass_error(pm, pa, n)
    dx = 1.0 / n
    return {
        "ms_per_frame_mesh": ms_mesh,
        "ms_per_frame_analytic": ms_ana,
        "ms_per_frame_no_obstacle": ms_free,
        "scene_load_s": load_s,
        "grid_mass_error_max": float(err.max()),
        "grid_mass_error_final": float(err[-1]),
        "no_obstacle_error_max": float(grid_mass_error(pf, pa, n).max()),
        "depth_mesh_cells": float(max(0.0, -sdf_of(pm[-1]).min() / dx)),
        "depth_analytic_cells": float(max(0.0, -sdf_of(pa[-1]).min() / dx)),
        "depth_mesh_cells_any_frame": float(max(0.0, -min(sdf_of(p).min() for p in pm) / dx)),
        "depth_analytic_cells_any_frame": float(max(0.0, -min(sdf_of(p).min() for p in pa) / dx)),
    }


def frame_cost(n: int, repeats: int, base: Path) -> dict[str, Any]:
    """The projection's cost (see the module docstring): per run, the fastest
    wall and CPU time per frame of frames 40-100 [ms] over ``repeats``
    interleaved rounds, and the ratios with/without the projection."""
    trimesh.creation.icosphere(subdivisions=4, radius=1.0).export(base / "sphere4.stl")
    mesh = {"shape": "mesh", "path": "sphere4.stl", "center": CENTER, "scale": RADIUS}
    sphere = {"shape": "sphere", "center": CENTER, "radius": RADIUS}
    runs = {f"{name}_{'on' if proj else 'off'}": {**ob, "project": proj} for name, ob in (("mesh", mesh), ("analytic", sphere)) for proj in (True, False)}
    sims = {}
    for name, ob in runs.items():
        sim = MpmSimulator(SceneSpec.from_dict(_scene([ob], n, 100), base_dir=base).build(), threads=1)
        for _ in range(40):
            sim.advance()
        sims[name] = (sim, sim.state())
    times: dict[str, list[tuple[float, float]]] = {name: [] for name in runs}
    for _ in range(repeats):
        for name, (sim, state) in sims.items():
            sim.restore(state)
            wall, cpu = time.perf_counter(), time.process_time()
            for _ in range(60):
                sim.advance()
            times[name].append((1e3 * (time.perf_counter() - wall) / 60, 1e3 * (time.process_time() - cpu) / 60))
    out: dict[str, Any] = {"n_grid": n, "frames": [40, 100], "repeats": repeats, "threads": 1}
    for name, t in times.items():
        out[name] = {"wall_ms_per_frame": min(w for w, _ in t), "cpu_ms_per_frame": min(c for _, c in t)}
        print(f"{name:13s} wall {out[name]['wall_ms_per_frame']:6.1f} ms/frame  cpu {out[name]['cpu_ms_per_frame']:6.1f} ms/frame")
    for name in ("mesh", "analytic"):
        r = out[f"{name}_on"]["cpu_ms_per_frame"] / out[f"{name}_off"]["cpu_ms_per_frame"]
        out[f"{name}_cpu_ratio_on_off"] = r
        print(f"{name}: CPU time with/without the projection {r:.3f}")
    return out


def figure(path: Path, n: int, base: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    spec = SceneSpec.from_dict(_scene([{"shape": "mesh", "path": "sphere4.stl", "center": CENTER, "scale": RADIUS}], n, 60), base_dir=base)
    c = spec.params.colliders[0]
    pos = _rollout(spec)[-1]
    xs = np.linspace(0.0, 1.0, 401)
    gx, gy = np.meshgrid(xs, xs, indexing="xy")
    pts = np.stack([gx.ravel(), gy.ravel(), np.full(gx.size, 0.5)], axis=1)
    sdf = collider_sdf(c, pts).reshape(gx.shape)
    fig, ax = plt.subplots(figsize=(5.5, 5))
    lim = float(np.abs(sdf).max())
    im = ax.pcolormesh(gx, gy, sdf, cmap="RdBu", vmin=-lim, vmax=lim, shading="auto")
    ax.contour(gx, gy, sdf, levels=[0.0], colors="k", linewidths=1.2)
    th = np.linspace(0, 2 * np.pi, 200)
    ax.plot(CENTER[0] + RADIUS * np.cos(th), CENTER[1] + RADIUS * np.sin(th), "y--", lw=0.8, label="analytic sphere")
    sl = np.abs(pos[:, 2] - 0.5) < 0.5 / n
    ax.plot(pos[sl, 0], pos[sl, 1], ".", ms=2, color="tab:cyan", label="water, |z - 0.5| < dx/2")
    lo = np.asarray(c.origin)
    hi = lo + c.cell * (np.asarray(c.values.shape) - 1)
    ax.add_patch(plt.Rectangle((lo[0], lo[1]), hi[0] - lo[0], hi[1] - lo[1], fill=False, ls=":", color="k", label="sampled box"))
    fig.colorbar(im, ax=ax, label="sampled signed distance [m]")
    ax.set(xlim=(0, 1), ylim=(0, 1), aspect="equal", xlabel="x [m]", ylabel="y [m]", title=f"icosphere(4) obstacle, {n}³ grid, frame 60, z = 0.5")
    ax.legend(loc="upper right", fontsize=7)
    save_figure(fig, path, dpi=110, bbox_inches="tight")
    print(f"wrote {path}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--n-grid", type=int, default=64)
    ap.add_argument("--frames", type=int, default=200)
    ap.add_argument("--out", type=Path, default=None, help="JSON file for the results (FILE.json)")
    ap.add_argument("--figure", type=Path, default=None)
    ap.add_argument("--project", choices=["on", "off"], default="on", help="the obstacles' particle projection")
    ap.add_argument("--frame-cost", action="store_true", help="measure the projection's cost alone (module docstring)")
    ap.add_argument("--repeats", type=int, default=5, help="--frame-cost: interleaved rounds")
    a = ap.parse_args()
    if a.frame_cost:
        with tempfile.TemporaryDirectory() as tmp:
            cost = frame_cost(a.n_grid, a.repeats, Path(tmp))
        if a.out is not None:
            write_results(a.out.parent, a.out.stem, doc=cost)
            print(f"wrote {a.out}")
        return
    proj = a.project == "on"
    result: dict[str, Any] = {"n_grid": a.n_grid, "frames": a.frames, "project": proj, "sdf": bench_sdf(a.n_grid)}
    with tempfile.TemporaryDirectory() as tmp:
        base = Path(tmp)

        def sphere_sdf(p: np.ndarray) -> np.ndarray:
            return np.asarray(np.linalg.norm(p - CENTER, axis=1) - RADIUS)

        for sub in (3, 4):
            trimesh.creation.icosphere(subdivisions=sub, radius=1.0).export(base / f"sphere{sub}.stl")
            r = bench_pair(
                {"shape": "mesh", "path": f"sphere{sub}.stl", "center": CENTER, "scale": RADIUS, "project": proj},
                {"shape": "sphere", "center": CENTER, "radius": RADIUS, "project": proj},
                sphere_sdf,
                a.n_grid,
                a.frames,
                base,
            )
            result[f"sphere_icosphere{sub}"] = r
            print(f"sphere icosphere({sub}): {r}")
        half = [0.25, 0.04, 0.2]
        ang = math.radians(-20.0)
        rot = [[math.cos(ang), -math.sin(ang), 0.0], [math.sin(ang), math.cos(ang), 0.0], [0.0, 0.0, 1.0]]
        centre = [0.5, 0.45, 0.5]
        trimesh.creation.box(extents=2 * np.asarray(half)).export(base / "ramp.stl")
        box = Box(center=centre, half_extents=half, rotation=rot)
        r = bench_pair(
            {"shape": "mesh", "path": "ramp.stl", "center": centre, "rotation": rot, "project": proj},
            {"shape": "box", "center": centre, "half_extents": half, "rotation": rot, "project": proj},
            lambda p: collider_sdf(box, p),
            a.n_grid,
            a.frames,
            base,
        )
        result["ramp"] = r
        print(f"ramp: {r}")
        if a.figure is not None:
            figure(a.figure, a.n_grid, base)
    if a.out is not None:
        write_results(a.out.parent, a.out.stem, doc=result)
        print(f"wrote {a.out}")


if __name__ == "__main__":
    main()
