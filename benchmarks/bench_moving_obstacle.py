"""A paddle moved through a water tank (2D, 64², the setup of
tests/test_moving_obstacles.py): what it does to the water, per boundary
condition, against a still paddle and against the same paddle held still
with the water streaming past it at the paddle's speed (the Galilean
equivalent near the paddle).

Figures: the deepest particle inside the paddle over the run [cells]
(analytic distance at the paddle's pose of each frame); the water's x
momentum gained over the still-paddle run, against a piston's
``ρ·h·U²·t`` (h the paddle's immersed depth); the free surface 0.1 m ahead
of and behind the paddle at the end, against the rest height and the
linear piston-wavemaker rise ``U·h/√(g·depth)``; wall time per frame.
``--project off`` runs the paddle without the particle projection
(``project = false``: the grid condition alone, as before it existed).

Usage::

    python benchmarks/bench_moving_obstacle.py [--speed 0.5] [--frames 80] [--project on|off] [--out runs/bench_moving_obstacle.json]
"""

from __future__ import annotations

import argparse
import math
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

from hybridmpm.bench.harness import write_results
from hybridmpm.scenes import SceneSpec
from hybridmpm.scenes.spec import collider_sdf
from hybridmpm.sim import MpmSimulator

N_GRID = 64
HALF = [0.03, 0.15]
START = [0.3, 0.25]
TOP = 0.22
FLOOR = 0.04


def tank(obstacle: dict[str, Any], velocity: list[float] | None = None) -> SceneSpec:
    block: dict[str, Any] = {"material": "water", "lo": [FLOOR, FLOOR], "hi": [0.96, TOP], "hydrostatic": True}
    if velocity is not None:
        block["velocity"] = velocity
    return SceneSpec.from_dict({"name": "paddle", "dim": 2, "n_grid": N_GRID, "blocks": [block], "obstacles": [obstacle]})


def run(spec: SceneSpec, frames: int) -> dict[str, Any]:
    sim = MpmSimulator(spec.build(), threads=1)
    c = sim.scene.params.colliders[0]
    deepest = 0.0
    t0 = time.perf_counter()
    for _ in range(frames):
        fr = sim.advance()
        at = replace(c, center=list(sim.obstacle_centers[0]), keyframes=None)
        deepest = max(deepest, float(-collider_sdf(at, sim.particles.fluid(fr.positions)).min()) * N_GRID)
    seconds = time.perf_counter() - t0
    pos = sim.fluid_positions
    xc = float(sim.obstacle_centers[0][0])

    def surface(lo: float, hi: float) -> float:
        band = pos[(pos[:, 0] > lo) & (pos[:, 0] < hi)]
        return float(band[:, 1].max())

    return {
        "deepest_cells": deepest,
        "px": float((sim.solver.masses * sim.velocities[:, 0]).sum()),
        "ahead": surface(xc + HALF[0], xc + HALF[0] + 0.1),
        "behind": surface(xc - HALF[0] - 0.1, xc - HALF[0]),
        "rest": float(sim.scene.positions[:, 1].max()),
        "ms_per_frame": 1e3 * seconds / frames,
        "particles": int(len(pos)),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--speed", type=float, default=0.5, help="paddle speed [m/s]")
    ap.add_argument("--frames", type=int, default=80)
    ap.add_argument("--project", choices=["on", "off"], default="on", help="the paddle's particle projection")
    ap.add_argument("--out", type=Path, default=None)
    args = ap.parse_args()
    u, frames = args.speed, args.frames
    duration = frames * 2.5e-3
    immersed = TOP - (START[1] - HALF[1])
    piston = 1000.0 * immersed * u * duration * u
    rise = u * immersed / math.sqrt(9.8 * (TOP - FLOOR))
    rows = []
    for cond in ("sticky", "slip", "separate"):
        base = {"shape": "box", "half_extents": HALF, "condition": cond, "project": args.project == "on"}
        moving = run(tank({**base, "keyframes": [{"t": 0.0, "center": START}, {"t": duration, "center": [START[0] + u * duration, START[1]]}]}), frames)
        still = run(tank({**base, "center": START}), frames)
        streaming = run(tank({**base, "center": [0.5, START[1]]}, velocity=[-u, 0.0]), frames)
        rows.append({"condition": cond, "moving": moving, "still": still, "streaming": streaming})
    print(f"paddle {2 * HALF[0]} x {2 * HALF[1]} m at {u} m/s for {frames} frames, {N_GRID}^2, immersed {immersed:.2f} m, projection {args.project}")
    print(f"piston momentum {piston:.2f} kg·m/s per m; linear piston rise {rise:.3f} m")
    print(
        "| condition | deepest inside, moving / still / static in streaming water [cells] | x momentum gained [kg·m/s per m] | surface ahead / behind / rest [m] | ms/frame |"
    )
    print("|---|---|---|---|---|")
    for r in rows:
        m, s, f = r["moving"], r["still"], r["streaming"]
        print(
            f"| {r['condition']} | {m['deepest_cells']:.2f} / {s['deepest_cells']:.2f} / {f['deepest_cells']:.2f} | {m['px'] - s['px']:.1f} "
            f"| {m['ahead']:.3f} / {m['behind']:.3f} / {m['rest']:.3f} | {m['ms_per_frame']:.2f} |"
        )
    if args.out is not None:
        doc = {"speed": u, "frames": frames, "project": args.project == "on", "piston": piston, "rise": rise, "rows": rows}
        write_results(args.out.parent, args.out.stem, doc=doc)


if __name__ == "__main__":
    main()
