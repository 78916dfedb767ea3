"""Issue 5 numbers: per-frame latency and grid-mass error of MPM at full
resolution, MPM at r_p, neural and hybrid (r_c = 0.8), from the same initial
conditions, per scene.

    python benchmarks/bench_hybrid.py --scenes water2d sand2d water_ramps2d sand_ramps2d water_sand2d \
        --seeds 1000 1001 1002 --out benchmarks/results/hybrid

Frames: the paper's T per domain (``--frames`` overrides). Errors: grid-mass
error (DESIGN.md) against the full-resolution MPM rollout, every r_t frames,
mean over frames then over seeds; "last" is the last frame. Latency: wall time
of the whole rollout / frames (neural and hybrid include their MPM warm-up
frames and every conversion), MPM with ``--threads`` threads, onnxruntime
with one. Also: the share of frames on MPM and the switches of the hybrid.
"""

from __future__ import annotations

import argparse
import json
import platform
import sys
import time
from pathlib import Path

import numpy as np

from hybridmpm.hybrid.stress import reference_rollout, run_method
from hybridmpm.metrics import grid_mass_error
from hybridmpm.models import shipped_model
from hybridmpm.neural import NeuralModel
from hybridmpm.scenes import make_scene
from hybridmpm.scenes.registry import PAPER_FRAMES

METHODS = ("mpm_full", "mpm_rp", "neural", "hybrid")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scenes", nargs="+", default=["water2d", "sand2d", "water_ramps2d", "sand_ramps2d", "water_sand2d"])
    ap.add_argument("--seeds", nargs="+", type=int, default=[1000, 1001, 1002])
    ap.add_argument("--frames", type=int, default=None, help="frames per rollout (default: the paper's T of each domain)")
    ap.add_argument("--r-c", type=float, default=0.8)
    ap.add_argument("--threads", type=int, default=2, help="MPM threads (default 2)")
    ap.add_argument("--out", default="benchmarks/results/hybrid")
    args = ap.parse_args(argv)
    rows = []
    for name in args.scenes:
        model = NeuralModel(shipped_model(name))
        frames = args.frames or PAPER_FRAMES.get(name, 300)
        acc: dict[str, dict[str, list[float]]] = {m: {"mean": [], "last": [], "ms": [], "mpm_share": [], "switches": [], "n": []} for m in METHODS}

        def record(key: str, pos: np.ndarray, secs: float, mpm_share: float, switches: int, ref: np.ndarray, n_grid: int) -> None:
            """Append one rollout's error (against ``ref``), ms/frame, MPM share and switches to ``acc[key]``."""
            err = grid_mass_error(pos, ref[: len(pos)], n_grid) if key != "mpm_full" else np.zeros(1)
            a = acc[key]
            a["mean"].append(float(err.mean()))
            a["last"].append(float(err[-1]))
            a["ms"].append(secs / max(1, (len(pos) - 1) * model.r_t) * 1e3)
            a["mpm_share"].append(mpm_share)
            a["switches"].append(switches)
            a["n"].append(pos.shape[1])

        for seed in args.seeds:
            scene = make_scene(name, seed=seed)
            n_grid = scene.params.resolved_n_grid()

            t0 = time.perf_counter()
            ref = reference_rollout(scene, frames, model.r_t, args.threads)
            record("mpm_full", ref, time.perf_counter() - t0, 1.0, 0, ref, n_grid)
            for method, key in (("mpm", "mpm_rp"), ("neural", "neural"), ("hybrid", "hybrid")):
                # "neural": the network alone over the whole rollout (no safeguard, no failure checks)
                kw = {"r_c": args.r_c} if method == "hybrid" else {"detect_failures": False} if method == "neural" else {}
                pos, failure, sim, secs = run_method(scene, method, frames, model, seed=0, mpm_threads=args.threads, **kw)
                st = sim.stats.steps
                record(key, pos, secs, st["mpm"] / max(1, st["mpm"] + st["neural"]), sim.stats.switches, ref, n_grid)
                if failure:
                    print(f"{name} seed {seed} {method}: failed ({failure})", file=sys.stderr)
            print(f"{name} seed {seed} done", file=sys.stderr)
        for m in METHODS:
            a = acc[m]
            rows.append(
                {
                    "scene": name, "method": m, "frames": frames, "seeds": args.seeds, "particles": float(np.mean(a["n"])),
                    "error_mean": float(np.mean(a["mean"])), "error_last": float(np.mean(a["last"])),
                    "ms_per_frame": float(np.median(a["ms"])), "mpm_share": float(np.mean(a["mpm_share"])),
                    "switches": float(np.mean(a["switches"])),
                }
            )  # fmt: skip
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    cmd = "python benchmarks/bench_hybrid.py " + " ".join(sys.argv[1:] if argv is None else argv)
    label = {"mpm_full": "MPM full resolution", "mpm_rp": "MPM at r_p", "neural": "neural", "hybrid": f"hybrid r_c = {args.r_c:g}"}
    lines = [
        f"Command: `{cmd}`  ",
        f"Machine: {platform.machine()}, {platform.python_version()}; MPM {args.threads} threads, onnxruntime 1 thread.",
        "",
        "| scene | method | particles | frames | grid-mass error mean | last | ms/frame | share of frames on MPM | switches |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        err = "reference" if r["method"] == "mpm_full" else f"{r['error_mean']:.3f}"
        last = "–" if r["method"] == "mpm_full" else f"{r['error_last']:.3f}"
        lines.append(
            f"| {r['scene']} | {label[r['method']]} | {r['particles']:.0f} | {r['frames']} | {err} | {last} | {r['ms_per_frame']:.2f} "
            f"| {100 * r['mpm_share']:.0f}% | {r['switches']:.1f} |"
        )
    Path(str(out) + ".md").write_text("\n".join(lines) + "\n")
    Path(str(out) + ".json").write_text(json.dumps(rows, indent=2))
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    sys.exit(main())
