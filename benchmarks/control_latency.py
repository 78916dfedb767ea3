#!/usr/bin/env python3
"""Latency of the diffusion controller on a quiet machine (A7):

    python benchmarks/control_latency.py --scenes water2d,sand2d --out benchmarks/results/control_latency

Per scene, 5 held-out start states (seeds 5000+): sketch → field (the plan:
graph, state encoder, sketch encoder, the DDIM steps of the head on one
onnxruntime thread, while the free-motion prior's coarse MPM rollout runs on
a second thread) ``--repeats`` times each after a warm-up, p50/p95; the two
parts timed alone (the prior's rollout; the sampler given the prior), whose
sum is the one-core figure; and the whole controlled episode (plan + 99 MPM
frames, the case's one MPM thread), median. Check the load first
(``uptime``): nothing else running.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

from hybridmpm.bench.harness import script_argv, write_results
from hybridmpm.control import Controller, control_episode
from hybridmpm.control.prior import free_motion_of
from hybridmpm.train.control.cases import make_case


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scenes", default="water2d,sand2d")
    ap.add_argument("--repeats", type=int, default=20)
    ap.add_argument("--out", default="benchmarks/results/control_latency")
    args = ap.parse_args(argv)
    rows = []
    for scene in args.scenes.split(","):
        plans: list[float] = []
        eps: list[float] = []
        priors: list[float] = []
        samplers: list[float] = []
        sizes = []
        for i in range(5):
            case = make_case(scene, 5000 + i, "arrow" if i % 2 == 0 else "oval", tracking=False)
            sizes.append(int(case.target.shape[0]))
            ctl = Controller.for_scene(scene, "diffusion", frames=len(case.path) - 1, seed=i)
            sim = case.simulator()
            ctl.plan(sim, case.sketch)
            for _ in range(args.repeats):
                plans.append(ctl.plan(sim, case.sketch).seconds * 1e3)
            model, p = ctl.model, sim.particles
            assert model is not None
            x, v, pt = p.fluid(sim.positions), sim.velocities, p.particle_type[: p.num_fluid]
            for _ in range(max(3, args.repeats // 4)):
                t0 = time.perf_counter()
                free = free_motion_of(sim, model.frames - 1) if model.needs_free else None
                priors.append((time.perf_counter() - t0) * 1e3)
                samplers.append(model.sample(x, v, pt, case.sketch, seed=i, steps=ctl.steps, free=free).seconds * 1e3)
            sim = case.simulator()
            t0 = time.perf_counter()
            control_episode(sim, case.sketch, ctl)
            eps.append((time.perf_counter() - t0) * 1e3)
        rows.append(
            {"scene": scene, "particles": sizes, "plan_ms_p50": float(np.percentile(plans, 50)), "plan_ms_p95": float(np.percentile(plans, 95)),
             "prior_ms_p50": float(np.median(priors)), "sampler_ms_p50": float(np.median(samplers)), "episode_ms": float(np.median(eps))}
        )  # fmt: skip
    out = Path(args.out)
    lines = [
        "| scene | particles | sketch → field ms p50 / p95 (1 ORT thread + the prior on a 2nd thread) | prior alone ms p50 | sampler alone ms p50 | episode ms, plan + 99 MPM frames on one thread (median) |",
        "|---|---|---|---|---|---|",
    ]
    for r in rows:
        lines.append(
            f"| {r['scene']} | {min(r['particles'])}–{max(r['particles'])} | {r['plan_ms_p50']:.0f} / {r['plan_ms_p95']:.0f} | {r['prior_ms_p50']:.0f} | {r['sampler_ms_p50']:.0f} | {r['episode_ms']:.0f} |"
        )
    text = "\n".join(lines) + "\n"
    write_results(out.parent, out.name, doc={"scenes": rows}, markdown=text, argv=script_argv(__file__, argv))
    print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
