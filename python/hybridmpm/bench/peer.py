"""``hybridmpm bench --peer taichi``: the scene's MPM timed side by side with
Taichi's CPU backend in the same run (:mod:`hybridmpm.bench.taichi_peer`, the
strongest Taichi CPU variant measured on this class of machine: serial p2g).

Both start from the same initial particles of the same seed, on the same grid,
with the same number of substeps per frame (ours is CFL-adaptive: Taichi gets
the mean our solver took over the same frames). Taichi's side is the
textbook MLS-MPM with our water and Drucker-Prager sand; it starts at rest
and has no collider boxes, so it is a timing peer, not an accuracy one.
Needs the ``bench`` extra (``pip install 'hybridmpm[bench]'``).
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Any

import numpy as np

from hybridmpm.errors import HybridMpmError


def taichi_peer(scene_name: str, seed: int, frames: int | None, warmup: int, threads: int = 0, timed_frames: int = 200) -> dict[str, Any]:
    """Time ``timed_frames`` frames (after ``warmup``) of ``scene_name``/``seed``
    in our MPM and in Taichi, each with ``threads`` threads (0 = all cores).
    Returns ``ms_mean``, ``ms_median``, ``ms_p95`` (Taichi), ``ours_ms_mean``,
    ``ours_ms_median``, ``particles``, ``substeps``, ``threads``, ``taichi``
    and ``arch``. Raises :class:`HybridMpmError` if Taichi is missing or its
    run fails."""
    from hybridmpm.scenes import make_scene

    import importlib.util

    try:
        found = importlib.util.find_spec("taichi") is not None
    except ValueError:  # a module set to None in sys.modules
        found = False
    if not found:
        raise HybridMpmError("peer: Taichi is not installed; pip install 'hybridmpm[bench]'")
    scene = make_scene(scene_name, seed=seed)
    n = min(int(timed_frames), int(frames or scene.frames))
    threads = threads or os.cpu_count() or 1
    from hybridmpm.bench import taichi_peer as tp
    from hybridmpm.bench.run import run_mpm

    _, wall_all, subs_all = run_mpm(scene, warmup + n, threads)
    wall, subs = wall_all[warmup:], subs_all[warmup:]
    substeps = max(1, int(round(float(np.mean(subs)))))

    with tempfile.TemporaryDirectory() as tmp:
        npz = Path(tmp) / f"{scene_name}_seed{seed}.npz"
        np.savez(npz, positions=np.asarray(scene.positions, np.float32), material=np.asarray(scene.material, np.int32), n_grid=scene.params.resolved_n_grid(), substeps=substeps)
        out = Path(tmp) / "taichi.json"
        cmd = [sys.executable, tp.__file__, "--positions", str(npz), "--variants", "serial", "--threads", str(threads), "--frames", str(n), "--warmup", str(max(1, warmup)), "--json", str(out)]
        proc = subprocess.run(cmd, capture_output=True, text=True, timeout=1800)
        if not out.is_file():
            raise HybridMpmError(f"peer: the Taichi run failed: {(proc.stderr or proc.stdout).strip()[-500:]}")
        res = json.loads(out.read_text())["results"][0]
    if "error" in res:
        raise HybridMpmError(f"peer: the Taichi run failed: {res['error']}")
    ours = np.asarray(wall) * 1e3
    return {
        "scene": scene_name, "seed": int(seed), "particles": int(res["particles"]), "substeps": substeps, "threads": int(threads),
        "frames_timed": n, "ms_mean": float(res["mean_ms"]),
        "ms_median": float(res["median_ms"]), "ms_p95": float(res["p95_ms"]), "ours_ms_mean": float(ours.mean()),
        "ours_ms_median": float(np.median(ours)), "taichi": res.get("taichi_version", "?"), "arch": "cpu, serial p2g", "sane": bool(res.get("sane")),
    }  # fmt: skip
