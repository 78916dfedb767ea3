#!/usr/bin/env python3
"""Does the network alone finish its rollouts? Every 2D scene with a shipped
model, seeds 0-9 (the scenes' own seeds, none chosen), 400 frames after the
MPM warm-up: the runs that stop early (a network step rejected by the
failure checks: "compressed", "escaped", "energy", "nan") and at which frame,
and the steps whose density relaxation had to run more than one round.

    python benchmarks/network_failures.py [--seeds 0-9] [--frames 400] [--out benchmarks/results/network_failures.md]
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

from hybridmpm.bench.harness import write_results
from hybridmpm.models import shipped_models
from hybridmpm.scenes import make_scene
from hybridmpm.sim import NeuralSimulator, rollout
from hybridmpm.sim.base import NEURAL


def check(scene: str, seeds: list[int], frames: int) -> dict:
    stopped, again = [], []
    t0 = time.perf_counter()
    for seed in seeds:
        sim = NeuralSimulator(scene, seed=seed, mpm_threads=1)
        rounds: list[int] = []
        ro = rollout(sim, frames, on_frame=lambda fr, s=sim, r=rounds: r.append(s.last_relax_rounds) if fr.solver == NEURAL else None)
        if ro.failure is not None:
            stopped.append(f"seed {seed}: {ro.failure} at frame {ro.frames_done}")
        again += [seed] * sum(1 for r in rounds if r > 1)
    return {"scene": scene, "stopped": stopped, "relaxed_again": len(again), "rollouts_relaxed_again": len(set(again)), "seconds": time.perf_counter() - t0}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seeds", default="0-9", help="first-last seed (default 0-9)")
    ap.add_argument("--frames", type=int, default=400)
    ap.add_argument("--out", default=None, help="append a Markdown table here (FILE.md)")
    args = ap.parse_args()
    lo, hi = (int(x) for x in args.seeds.split("-"))
    seeds = list(range(lo, hi + 1))
    scenes = sorted(s for s in shipped_models() if make_scene(s, seed=0).dim == 2)
    rows = [check(s, seeds, args.frames) for s in scenes]
    lines = [
        "\n## Network alone: rollouts that stop early\n",
        "Shipped models, default settings.\n",
        "| scene | rollouts stopped early | steps relaxed again (rollouts) | seconds |",
        "|---|---|---:|---:|",
    ]
    for r in rows:
        stopped = "; ".join(r["stopped"]) or f"none of {len(seeds)}"
        lines.append(f"| {r['scene']} | {stopped} | {r['relaxed_again']} ({r['rollouts_relaxed_again']}) | {r['seconds']:.0f} |")
    text = "\n".join(lines) + "\n"
    print(text)
    if args.out:
        out = Path(args.out)
        write_results(out.parent, out.stem, markdown=text, append=True)


if __name__ == "__main__":
    main()
