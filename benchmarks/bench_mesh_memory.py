"""What loading a mesh obstacle and a session's mesh download take in memory,
measured with tracemalloc (numpy's buffers are traced), against what the
code reserves for them.

* ``--part load``: :func:`hybridmpm.scenes.obstacle_mesh.load_mesh` of an
  icosphere (``--subdivisions``, 81,920 triangles at 6) in each file kind:
  its peak per triangle, against ``MESH_BYTES_PER_TRIANGLE``.
* ``--part download``: ``GET .../trajectory?format=mesh`` of a session that
  recorded ``--frames`` coarse steps of each registered scene (MPM; a
  ``--simulate``-frame rollout repeated to that length: the surfaces'
  sizes are a moving fluid's, each frame meshed on its own): the peak of
  the route's work (the stacked trajectory, every frame's surfaces, the zip)
  against the route's reservation (``mesh_download_bytes``).

``python benchmarks/bench_mesh_memory.py --part load download --out benchmarks/results/mesh_memory.json``
"""

from __future__ import annotations

import argparse
import tempfile
import time
import tracemalloc
from pathlib import Path

import numpy as np

from hybridmpm.bench.harness import write_results


def measure_load(subdivisions: int) -> list[dict[str, float]]:
    import trimesh

    from hybridmpm.scenes import obstacle_mesh

    mesh = trimesh.creation.icosphere(subdivisions=subdivisions)
    out = []
    with tempfile.TemporaryDirectory() as d:
        for kind in ("stl", "obj", "ply", "glb"):
            path = Path(d) / f"sphere.{kind}"
            mesh.export(path)
            tracemalloc.start()
            _, faces = obstacle_mesh.load_mesh(path, "bench")
            peak = tracemalloc.get_traced_memory()[1]
            tracemalloc.stop()
            out.append({"kind": kind, "triangles": len(faces), "peak_bytes": peak, "bytes_per_triangle": peak / len(faces)})
            print(f"load {kind}: {len(faces)} triangles, peak {peak / 2**20:.1f} MiB = {peak / len(faces):.0f} B/triangle", flush=True)
    return out


def measure_download(scenes: list[str], frames: int, simulate: int) -> list[dict[str, float]]:
    """Per scene: the peak of one frame's download (its surface: bytes per grid node once the frame's own
    values are taken off) and of ``frames`` frames' (bytes per position value), against the reservation."""
    from hybridmpm.service.budget import MESH_DOWNLOAD_BYTES_PER_VALUE, SURFACE_PAD_NODES, mesh_download_bytes
    from hybridmpm.service.facts import SessionFacts
    from hybridmpm.service.routes.trajectory import trajectory_mesh_zip
    from hybridmpm.sim import make_simulator, rollout
    from hybridmpm.trajectory import Trajectory

    def peak_of(f: SessionFacts, ro: object, count: int) -> tuple[int, int]:
        n = len(ro.positions)  # type: ignore[attr-defined]
        held = [ro.positions[k % n] for k in range(count)]  # type: ignore[attr-defined] # the recording: float32 [N + B, D] per step
        oc = ro.obstacle_centers  # type: ignore[attr-defined]
        tracemalloc.start()
        traj = Trajectory(
            positions=np.stack(held),
            particle_type=f.particle_type,
            dt_frame=f.step_dt,
            n_grid=f.n_grid,
            masses=f.masses,
            material=f.material,
            obstacle_centers=None if oc is None else np.stack([oc[k % n] for k in range(count)]),
        )
        data = trajectory_mesh_zip(traj, f.surface)
        peak = tracemalloc.get_traced_memory()[1]
        tracemalloc.stop()
        return peak, len(data)

    out = []
    warmed: set[int] = set()
    for scene in scenes:
        sim = make_simulator(scene, "mpm", seed=0, threads=1)
        f = SessionFacts.of(sim)
        t0 = time.perf_counter()
        ro = rollout(sim, simulate)
        if f.dim not in warmed:  # the first mesh of a process imports scikit-image and friends: not the download's own memory
            peak_of(f, ro, 1)
            warmed.add(f.dim)
        one, _ = peak_of(f, ro, 1)
        peak, zip_bytes = peak_of(f, ro, frames)
        values = frames * f.num_total * f.dim
        reserved = mesh_download_bytes(frames, f.num_total, f.dim, f.n_grid)
        row = {
            "scene": scene,
            "dim": f.dim,
            "particles": f.num_total,
            "n_grid": f.n_grid,
            "frames": frames,
            "zip_bytes": zip_bytes,
            "peak_bytes": peak,
            "peak_bytes_per_value": peak / values,
            "one_frame_peak_bytes": one,
            "surface_bytes_per_node": max(0.0, one - MESH_DOWNLOAD_BYTES_PER_VALUE * f.num_total * f.dim) / (f.n_grid + SURFACE_PAD_NODES) ** f.dim,
            "reserved_bytes": reserved,
            "reserved_over_peak": reserved / peak,
            "seconds": time.perf_counter() - t0,
        }
        out.append(row)
        print(
            f"download {scene}: {f.num_total} particles, {frames} frames: peak {peak / 2**20:.1f} MiB ({peak / values:.2f} B/value), "
            f"one frame {one / 2**20:.2f} MiB ({row['surface_bytes_per_node']:.1f} B/node), zip {zip_bytes / 2**20:.1f} MiB, "
            f"reserved {reserved / 2**20:.1f} MiB ({reserved / peak:.2f}x)",
            flush=True,
        )
    return out


def main() -> int:
    from hybridmpm.scenes import DOMAINS

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--part", nargs="+", choices=["load", "download"], default=["load", "download"])
    ap.add_argument("--subdivisions", type=int, default=6)
    ap.add_argument("--scenes", nargs="*", default=sorted(DOMAINS))
    ap.add_argument("--frames", type=int, default=300, help="recorded coarse steps (the route's most: 300)")
    ap.add_argument("--simulate", type=int, default=40, help="frames actually simulated, repeated to --frames")
    ap.add_argument("--out", default=None, help="JSON file for the results (FILE.json)")
    args = ap.parse_args()
    report: dict[str, object] = {}
    if "load" in args.part:
        report["load"] = measure_load(args.subdivisions)
    if "download" in args.part:
        report["download"] = measure_download(args.scenes, args.frames, args.simulate)
    if args.out:
        out = Path(args.out)
        write_results(out.parent, out.stem, doc=report)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
