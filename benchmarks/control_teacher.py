#!/usr/bin/env python3
"""The teacher and the go/no-go of a learned controller: the force field of
:mod:`hybridmpm.control.mpc` optimised offline against the full simulation,
against PD on validation sketches.

    nice -n 19 python benchmarks/control_teacher.py --scenes water2d,sand2d --out benchmarks/results/control_teacher

Validation sketches (seeds 8300+, no benchmark's or test's; the fluid 40 frames
into the flow, MPM at r_p = 0.5714, one thread): per start state the
``--ovals`` ovals of :func:`bench_control_user.user_sketches` and the arrow
straight up (against gravity). Per case, PD (the default gain, 50 g cap) is the
reference; then two cross-entropy searches (:func:`hybridmpm.control.mpc.cem`,
starting from PD's field, ``--rollouts`` full-simulation rollouts of the 100
frames each in rounds of 8):

* **adherence at equal effort**: maximise adherence (oval IoU on 64² cells;
  arrow: minus the centroid's miss of the tip over the arrow's length) less
  1 per g of mean effort above PD's;
* **effort at equal adherence**: minimise mean effort / PD's, less 10 per unit
  of adherence below PD's (within 0.005 of PD's counts as equal in the verdict).

The go/no-go (a learned controller amortising this optimiser is worth
building only if the teacher beats the PD front by a margin): >= 25% higher
IoU at PD's effort, or >= 40% less effort at PD's adherence. Cases run in
``--procs`` processes; each case is written when done (resumable: rerun the
same command), each round logged on stdout (redirect it to a file). Writes ``OUT.json`` and ``OUT.md``.
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from concurrent.futures import ProcessPoolExecutor, as_completed
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_control_user import start_sim, user_sketches  # noqa: E402

from hybridmpm.bench.harness import read_results, script_argv, table, write_results  # noqa: E402
from hybridmpm.control import Sketch  # noqa: E402
from hybridmpm.control.mpc import FIELD_HI, FIELD_LO, FIELD_STD, QUARTERS, cem, pd_field, roll_field  # noqa: E402
from hybridmpm.control.targets import pd_targets  # noqa: E402
from hybridmpm.conventions import T_CTR  # noqa: E402

N_GRID = 64  # the oval IoU's cells (control_metrics')
PER_ROUND = 8


def validation_cases(scene: str, seeds: range, ovals: int) -> list[tuple[str, int, str, str]]:
    out = []
    for seed in seeds:
        for label, sk in user_sketches(start_sim(scene, seed), seed, ovals):
            if label.startswith("oval") or label == "arrow-up":
                out.append((scene, seed, label, sk.to_json()))
    return out


GOALS = ("equal_effort", "equal_adherence")
#: Adherence within this of PD's counts as equal (IoU, or the arrow's miss over its length).
ADHERENCE_TOL = 0.005


def run_case(scene: str, seed: int, label: str, sketch_json: str, rollouts: int, goals: tuple[str, ...] = GOALS) -> dict[str, Any]:
    sketch = Sketch.from_json(sketch_json)
    sim = start_sim(scene, seed)
    state = sim.state()
    x0 = np.asarray(sim.particles.fluid(sim.positions), np.float64)
    targets = pd_targets(x0, sketch)
    g = sim.scene.params.resolved_gravity()

    def measure(theta: np.ndarray) -> tuple[float, float]:
        ro = roll_field(sim, state, theta, targets, sketch, T_CTR, N_GRID)
        return ro.adherence, ro.applied.effort()["effort_mean_g"]

    t0 = time.perf_counter()
    pd_adh, pd_eff = measure(pd_field(g))
    row: dict[str, Any] = {"scene": scene, "seed": seed, "label": label, "kind": sketch.kind, "pd": {"adherence": pd_adh, "effort_mean_g": pd_eff}}
    kw = {
        "rollouts": rollouts,
        "rounds": max(1, rollouts // PER_ROUND),
        "std": np.tile(FIELD_STD, QUARTERS),
        "lo": np.tile(FIELD_LO, QUARTERS),
        "hi": np.tile(FIELD_HI, QUARTERS),
    }
    seen: dict[str, dict[bytes, tuple[float, float]]] = {g: {} for g in GOALS}

    def objective(goal: str):
        def f(theta: np.ndarray) -> float:
            adh, eff = measure(theta)
            seen[goal][theta.tobytes()] = (adh, eff)
            if goal == "equal_effort":
                return adh - 1.0 * max(0.0, eff - pd_eff)
            return -eff / max(pd_eff, 1e-9) - 10.0 * max(0.0, pd_adh - adh)

        return f

    for goal in goals:

        def on_round(r: int, best: np.ndarray, score: float, goal: str = goal) -> None:
            print(f"{time.strftime('%H:%M:%S')} {scene} {seed} {label} {goal} round {r}: best score {score:.4f}", flush=True)

        theta, score = cem(objective(goal), pd_field(g), rng=np.random.default_rng([seed, 99]), on_round=on_round, **kw)
        adh, eff = seen[goal][theta.tobytes()]
        row[goal] = {"adherence": adh, "effort_mean_g": eff, "score": score, "theta": theta.tolist()}
    row["seconds"] = time.perf_counter() - t0
    return row


def verdict(cases: list[dict]) -> tuple[list[str], dict[str, Any]]:
    lines = []
    out: dict[str, Any] = {}
    for scene in sorted({c["scene"] for c in cases}):
        cs = [c for c in cases if c["scene"] == scene]
        ov = [c for c in cs if c["kind"] == "oval"]
        iou_gain = [c["equal_effort"]["adherence"] / max(c["pd"]["adherence"], 1e-9) for c in ov if "equal_effort" in c]
        eff_ratio = [
            c["equal_adherence"]["effort_mean_g"] / max(c["pd"]["effort_mean_g"], 1e-9)
            for c in cs
            if "equal_adherence" in c and c["equal_adherence"]["adherence"] >= c["pd"]["adherence"] - ADHERENCE_TOL
        ]
        mean_gain = float(np.mean(iou_gain)) if iou_gain else math.nan
        mean_eff = float(np.mean(eff_ratio)) if eff_ratio else math.nan
        go = (mean_gain >= 1.25) or (mean_eff <= 0.60)
        out[scene] = {"iou_ratio_at_pd_effort": mean_gain, "effort_ratio_at_pd_adherence": mean_eff, "go": bool(go)}
        lines.append(
            f"- **{scene}**: IoU at PD's effort {mean_gain:.2f}x PD's (mean of {len(iou_gain)} ovals; go needs >= 1.25x); "
            f"effort at PD's adherence {mean_eff:.2f}x PD's (mean of {len(eff_ratio)} cases; go needs <= 0.60x): **{'go' if go else 'no-go'}**"
        )
    return lines, out


def summarise(cases: list[dict]) -> str:
    rows = []
    for c in sorted(cases, key=lambda c: (c["scene"], c["seed"], c["label"])):
        p = c["pd"]
        cell = {g: f"{c[g]['adherence']:.3f} / {c[g]['effort_mean_g']:.2f}" if g in c else "–" for g in GOALS}
        rows.append(
            [c["scene"], c["seed"], c["label"], f"{p['adherence']:.3f} / {p['effort_mean_g']:.2f}", cell["equal_effort"], cell["equal_adherence"], f"{c['seconds']:.0f}"]
        )  # fmt: skip
    lines = table(
        ["scene", "seed", "sketch", "PD adherence / effort g", "teacher at PD's effort", "teacher at PD's adherence", "s"], rows
    )  # fmt: skip
    v, _ = verdict(cases)
    return "\n".join(["Adherence: oval IoU (64² cells); arrow: minus the centroid's miss of the tip / arrow length.", "", *lines, "", *v, ""])


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scenes", default="water2d,sand2d")
    ap.add_argument("--seeds", type=int, default=2)
    ap.add_argument("--first-seed", type=int, default=8300)
    ap.add_argument("--ovals", type=int, default=2)
    ap.add_argument("--rollouts", type=int, default=64, help="full-simulation rollouts per search (rounds of 8)")
    ap.add_argument("--procs", type=int, default=2)
    ap.add_argument("--goals", default=",".join(GOALS), help=f"comma-separated subset of {', '.join(GOALS)}")
    ap.add_argument("--labels", default=None, help="only these sketches (comma-separated labels, e.g. oval-9,arrow-up)")
    ap.add_argument("--out", default="benchmarks/results/control_teacher")
    args = ap.parse_args(argv)
    out = Path(args.out)
    done = read_results(out.with_suffix(".json"))["cases"] if out.with_suffix(".json").is_file() else []
    have = {(c["scene"], c["seed"], c["label"]) for c in done}
    todo = [t for s in args.scenes.split(",") for t in validation_cases(s, range(args.first_seed, args.first_seed + args.seeds), args.ovals)]
    todo = [t for t in todo if t[:3] not in have and (args.labels is None or t[2] in args.labels.split(","))]
    goals = tuple(g for g in GOALS if g in args.goals.split(","))
    with ProcessPoolExecutor(args.procs) as pool:
        futs = [pool.submit(run_case, *t, args.rollouts, goals) for t in todo]
        for f in as_completed(futs):
            done.append(f.result())
            write_results(out.parent, out.name, doc={"cases": done}, indent=None, argv=script_argv(__file__, argv))
            print(f"{len(done)} cases done", flush=True)
    _, v = verdict(done)
    text = summarise(done)
    write_results(out.parent, out.name, doc={"cases": done, "verdict": v}, markdown=text, indent=None, argv=script_argv(__file__, argv))
    print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
