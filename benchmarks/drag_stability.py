#!/usr/bin/env python3
"""Stability of a dragged obstacle and of the largest control push, per integrator.

The paddle of ``paddle3d`` (or the first obstacle of ``--scene``) is dragged for ``--frames`` frames: every 20
frames it takes a new random direction (mostly horizontal; ``--seed``), it moves for 30 frames of every 40 at
``--speed`` m/s and rests for 10, kept inside a box of the domain. The page lets a drag reach the solver's limit,
50 m/s (``hybridmpm.mpm.motion.MAX_OBSTACLE_SPEED``). ``--push`` adds a run per integrator in which the paddle
rests and the water is pushed instead: the controls' largest acceleration (``hybridmpm.control.reverse.A_MAX``,
50 g) on every particle, in the same pattern of directions and pauses. Per case and integrator: the frames rolled
back and retried (``SimStats.mpm_retries``; the target is at most 1 in 100), the projection's steps replanned
shorter before their particles moved (``SimStats.mpm_replans``: no rollback, one solve redone), the steps a frame, whether the run
ended early (a non-finite particle, or a frame MPM could not finish) and the wall time a frame.

    python benchmarks/drag_stability.py --speeds 5,20,50 --push --out benchmarks/results/drag_stability
"""

from __future__ import annotations

import argparse
import time
from typing import Any

import numpy as np

from hybridmpm.bench.harness import script_argv, table, write_results
from hybridmpm.control.reverse import A_MAX
from hybridmpm.mpm import INTEGRATORS
from hybridmpm.sim import make_simulator, rollout

#: The box the dragged obstacle's centre stays in [m] (low, high; the paddle3d page's reach).
REACH = (np.array([0.1, 0.25, 0.25]), np.array([0.9, 0.3, 0.75]))


def drag_run(scene: str, integrator: str, speed: float, frames: int, seed: int, push: bool = False) -> dict[str, Any]:
    """One dragged run at ``speed`` [m/s], or with ``push`` one pushed at ``A_MAX`` (module docstring)."""
    sim = make_simulator(scene, "mpm", integrator=integrator)
    rng = np.random.default_rng(seed)
    dim = sim.particles.dim
    lo, hi = REACH[0][:dim], REACH[1][:dim]
    state = {"dir": np.zeros(dim), "k": 0}

    def drag(_frame: Any) -> None:
        k = state["k"]
        if k % 20 == 0:
            d = rng.normal(size=dim)
            d[1] *= 0.3  # mostly horizontal
            state["dir"] = d / np.linalg.norm(d)
        on = k % 40 < 30
        if push:
            sim.forcing = np.broadcast_to(np.float32(A_MAX * on) * state["dir"].astype(np.float32), (sim.velocities.shape[0], dim))
        elif on:
            c = sim.solver.collider_positions[0]
            sim.move_obstacle(0, np.clip(c + speed * sim.dt_frame * state["dir"], lo, hi))
        state["k"] = k + 1

    drag(None)
    t0 = time.perf_counter()
    ro = rollout(sim, frames, on_frame=drag)
    wall = time.perf_counter() - t0
    done = len(ro.frame_index) - 1
    return {
        "scene": scene,
        "integrator": integrator,
        "case": f"push {A_MAX / 9.81:.0f} g" if push else f"drag {speed:g} m/s",
        "speed": 0.0 if push else speed,
        "frames": done,
        "retries": int(sim.stats.mpm_retries),
        "retries_per_100": 100.0 * sim.stats.mpm_retries / max(done, 1),
        "replans_per_100": 100.0 * sim.stats.mpm_replans / max(done, 1),
        "steps_per_frame": float(np.sum(ro.substeps[1:]) / max(done, 1)),
        "failure": ro.failure,
        "ms_per_frame": 1e3 * wall / max(done, 1),
    }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scene", default="paddle3d", help="a registered scene with an obstacle (default paddle3d)")
    ap.add_argument("--speeds", default="5,20,50", help="drag speeds [m/s], comma-separated")
    ap.add_argument("--integrators", default=",".join(INTEGRATORS), help="integrators, comma-separated")
    ap.add_argument("--frames", type=int, default=600)
    ap.add_argument("--seed", type=int, default=1, help="the drag's directions")
    ap.add_argument("--push", action="store_true", help="also push the water at the controls' largest acceleration")
    ap.add_argument("--out", required=True, help="output folder")
    a = ap.parse_args(argv)
    integrators = [s.strip() for s in a.integrators.split(",") if s.strip()]
    # (speed, push) per case: each drag speed, then the push
    cases = [(float(s), False) for s in a.speeds.split(",") if s.strip()] + ([(0.0, True)] if a.push else [])
    rows = []
    for speed, push in cases:
        for integrator in integrators:
            r = drag_run(a.scene, integrator, speed, a.frames, a.seed, push=push)
            print(r)
            rows.append(r)
    keys = ["integrator", "case", "frames", "retries", "retries_per_100", "replans_per_100", "steps_per_frame", "failure", "ms_per_frame"]
    lines = [
        f"# A dragged obstacle{' and a pushed fluid' if a.push else ''}: {a.scene}, {a.frames} frames a run, seed {a.seed}",
        "\n".join(table(keys, [[r[k] if not isinstance(r[k], float) else f"{r[k]:.2f}" for k in keys] for r in rows])),
    ]
    write_results(a.out, "drag_stability", doc={"runs": rows}, markdown=lines, argv=script_argv("drag_stability.py", argv))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
