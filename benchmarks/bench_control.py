#!/usr/bin/env python3
"""Control baselines on held-out reverse-simulation cases (paper Table 4).

    python benchmarks/bench_control.py --scenes water2d,sand2d --cases 50 --out benchmarks/results/control

Per scene, ``--cases`` cases (seeds 5000+, arrows and ovals alternating;
:func:`hybridmpm.train.control.cases.make_case`): the fluid at the controlled start
(``X_T`` reversed) and the sketch made from the reverse run; every method
runs the same ``T_ctr`` = 100 frames of MPM at r_p = 0.5714 from that state:

* ``none`` — no control; ``constant`` — the paper's baseline; ``pd`` — PD
  attraction; ``mpc`` — model-predictive control on the coarse grid
  (:mod:`hybridmpm.control.mpc`, its default budget; sampler seed = the case's); ``diffusion`` — the Fluid ControlNet (shipped models, or
  ``--model-root DIR/SCENE``; noise seed = the case's seed), which plans a
  fluid in free flight without its network
  (:func:`hybridmpm.control.prior.in_free_flight`); ``diffusion_net`` — the
  same with its network on every case;
  ``oracle_path`` — the true reverse path tracked by the diffusion
  controller's tracking law (the floor of that design); ``prior`` — what the
  free-sketch models plan relative to, alone (the coarse free rollout bent
  onto the sketch, :mod:`hybridmpm.control.prior`), tracked the same way:
  what the network adds is the gap between this row and ``diffusion``; ``oracle`` — the
  tracking field replayed open loop; ``smoothed`` — the same field smoothed afterwards
  as the paper's App. D does; ``kinematic`` — the paper's reverse formula
  replayed (how far the untracked data would land).

Metrics (docs/design.md): final-shape grid-mass error against ``X_1`` and the
paper's RMSE_m̃, arrow adherence (cosine, length ratio) or oval adherence
(fraction inside, IoU), effort (‖a‖/g), smoothness, plan latency (sketch →
field) and whole-episode latency. Writes ``OUT.json`` (every case) and
``OUT.md`` (means per scene and method, and the share of cases each method
beats the constant force on).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
from tqdm import tqdm

from hybridmpm.bench.harness import read_results, script_argv, write_results
from hybridmpm.control import Controller, control_episode
from hybridmpm.control.prior import free_motion_of, prior_path
from hybridmpm.train.control.cases import make_case

METHODS = ("none", "constant", "pd", "mpc", "diffusion", "diffusion_net", "prior", "oracle_path", "oracle", "smoothed", "kinematic")


def run_case(scene: str, seed: int, kind: str, model_root: str | None = None, methods: tuple[str, ...] = METHODS) -> dict:
    t0 = time.perf_counter()
    case = make_case(scene, seed, kind, tracking=bool({"oracle", "smoothed"} & set(methods)))  # the tracking field: 2/3 of the cost
    rows = {"scene": scene, "seed": seed, "kind": kind, "preroll": case.preroll, "make_s": time.perf_counter() - t0, "methods": {}}
    frames = len(case.path) - 1
    for m in methods:
        sim = case.simulator()
        if m == "oracle":
            ctl = Controller("oracle", frames=frames, oracle=case.target_field)
        elif m == "kinematic":
            ctl = Controller("oracle", frames=frames, oracle=case.kinematic)
        elif m == "smoothed":
            ctl = Controller("oracle", frames=frames, oracle=case.smoothed_field)
        elif m == "oracle_path":
            ctl = Controller("oracle", frames=frames, oracle_path=case.path)
        elif m == "prior":  # the diffusion model's prior alone: the coarse free motion bent onto the sketch, tracked
            ctl = Controller("oracle", frames=frames, oracle_path=prior_path(free_motion_of(sim, frames), sim.particles.fluid(sim.positions), case.sketch))
        elif m in ("diffusion", "diffusion_net"):  # diffusion_net: the network even where the fluid is in free flight
            model = None if model_root is None else Path(model_root) / scene
            ctl = Controller.for_scene(scene, "diffusion", frames=frames, model=model, seed=seed, free_flight=m == "diffusion")
        else:
            ctl = Controller(m, frames=frames, seed=seed)
        ep = control_episode(sim, case.sketch, ctl, target=case.target)
        rows["methods"][m] = {k: (None if isinstance(v, float) and not np.isfinite(v) else v) for k, v in ep.metrics.items()}
    return rows


def summarise(cases: list[dict]) -> str:
    lines = []
    for scene in sorted({c["scene"] for c in cases}):
        cs = [c for c in cases if c["scene"] == scene]
        lines += [
            f"### {scene} ({len(cs)} cases: {sum(c['kind'] == 'arrow' for c in cs)} arrows, {sum(c['kind'] == 'oval' for c in cs)} ovals)",
            "",
            "| method | grid-mass error at T_ctr | RMSE_m̃ | arrow cosine | arrow length ratio | oval inside | oval IoU | effort mean / max (g) | smoothness | plan ms p50 / p95 | episode ms p50 | better than constant | better than PD |",
            "|---|---|---|---|---|---|---|---|---|---|---|---|---|",
        ]
        for m in [m for m in METHODS if m in cs[0]["methods"]]:

            def col(key: str, kind: str | None = None, m: str = m, cs: list = cs) -> np.ndarray:
                vals = [c["methods"][m].get(key) for c in cs if kind is None or c["kind"] == kind]
                return np.array([v for v in vals if v is not None], np.float64)

            err = col("grid_mass_error")
            base = np.array([c["methods"]["constant"]["grid_mass_error"] for c in cs])
            better = float(np.mean(err < base)) if m != "constant" else float("nan")
            pd_err = np.array([c["methods"]["pd"]["grid_mass_error"] for c in cs])
            better_pd = float(np.mean(err < pd_err))
            plan = col("plan_ms")
            lines.append(
                f"| {m} | {err.mean():.3f} | {col('rmse_m').mean():.2e} | {col('cosine', 'arrow').mean():.2f} | {col('length_ratio', 'arrow').mean():.2f} "
                f"| {col('inside', 'oval').mean():.2f} | {col('iou', 'oval').mean():.2f} | {col('effort_mean_g').mean():.1f} / {col('effort_max_g').max():.1f} "
                f"| {np.nanmean(col('smoothness')) if len(col('smoothness')) else float('nan'):.2f} | {np.percentile(plan, 50):.2f} / {np.percentile(plan, 95):.2f} "
                f"| {np.median(col('episode_ms')):.0f} | {'–' if m == 'constant' else f'{100 * better:.0f}%'} | {'–' if m == 'pd' else f'{100 * better_pd:.0f}%'} |"
            )
        ff = [c for c in cs if "network" in c["methods"].get("diffusion", {}) and not c["methods"]["diffusion"]["network"]]
        lines += ["", f"In free flight (the diffusion controller planned without its network): {len(ff)} of {len(cs)} cases.", ""]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scenes", default="water2d,sand2d")
    ap.add_argument("--cases", type=int, default=50)
    ap.add_argument("--first-seed", type=int, default=5000)
    ap.add_argument("--out", default="benchmarks/results/control")
    ap.add_argument("--model-root", default=None, help="diffusion controllers as ROOT/SCENE (default: the shipped ones)")
    ap.add_argument("--methods", default=",".join(METHODS), help=f"comma-separated subset of {', '.join(METHODS)} (constant and pd are always run)")
    args = ap.parse_args(argv)
    methods = tuple(m for m in METHODS if m in set(args.methods.split(",")) | {"constant", "pd"})
    unknown = set(args.methods.split(",")) - set(METHODS)
    if unknown:
        ap.error(f"--methods: unknown {', '.join(sorted(unknown))}")
    out = Path(args.out)
    done = read_results(out.with_suffix(".json"))["cases"] if out.with_suffix(".json").is_file() else []
    have = {(c["scene"], c["seed"]) for c in done}
    todo = [(s, args.first_seed + i, "arrow" if i % 2 == 0 else "oval") for s in args.scenes.split(",") for i in range(args.cases)]
    for scene, seed, kind in tqdm([t for t in todo if (t[0], t[1]) not in have], desc="control cases"):
        done.append(run_case(scene, seed, kind, args.model_root, methods))
        write_results(out.parent, out.name, doc={"cases": done}, indent=None, argv=script_argv(__file__, argv))  # resumable
    text = summarise([c for c in done if (c["scene"], c["seed"], c["kind"]) in set(todo)])
    write_results(out.parent, out.name, markdown=text, argv=script_argv(__file__, argv))
    print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
