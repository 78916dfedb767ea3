#!/usr/bin/env python3
"""Sketches a user would draw, and the classical control front.

    nice -n 19 python benchmarks/bench_control_user.py --scenes water2d,sand2d,water3d,sand3d --out benchmarks/results/control_user

Per scene and seed (8200+: no other benchmark's or test's), the scene's fluid
is run 40 frames at r_p = 0.5714 (the control's MPM, one thread) and a user's
sketches are drawn on it (:func:`user_sketches`):

* **arrows** from the fluid's centroid in 8 directions (right, up-right, up —
  straight against gravity — … every 45°) and one against the flow (opposite
  the centroid's velocity), 0.25 m long, shortened so that the tip stays
  0.08 m inside the walls, dropped if that leaves less than 0.08 m (down from
  a pile on the floor);
* **ovals** anywhere the fluid can reach: centres uniform within 0.3 m of the
  centroid and 0.15 m inside the walls, radii 0.08–0.14 and 0.05–0.10 m,
  any angle (the seed's own generator).

Every controller runs the same 100 frames from the same state: ``none``, the
constant force at three magnitudes (``constant@g0.5`` … ``@g1.5``), PD at
three gains (settling in 0.25, 0.5, 1 horizon) and two caps (10, 50 g),
MPC (:mod:`hybridmpm.control.mpc`) at 8, 16 and 32 rollouts of the cheap
model per plan, and the shipped diffusion controller. Metrics
(:mod:`hybridmpm.control.metrics`): arrows — the centroid's cosine and
length ratio, its lateral deviation from the arrow's line, the share of the
mass carried at least half the arrow; ovals — intersection over union; both —
effort (mean and max, g), smoothness, how far fluid farther than 0.1 m from
the sketch ends from where no control leaves it (the table shows it for ovals:
an arrow asks the whole fluid to move), and plan latency.

Resumable (every case is written as it finishes; rerun the same command to
continue). Writes ``OUT.json`` (every case), ``OUT.md`` (per scene and
controller) and ``OUT_front_SCENE.png`` (adherence against effort and plan latency).
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

from hybridmpm.bench.harness import read_results, script_argv, table, write_results
from hybridmpm.control import Controller, Sketch, control_episode
from hybridmpm.control.metrics import lateral_deviation, mass_carried, off_sketch_disturbance
from hybridmpm.control.mpc import MpcSettings
from hybridmpm.sim import MpmSimulator, rollout
from hybridmpm.train.control.cases import CONTROL_R_P

PREROLL = 40
ARROW = 0.25
MARGIN = 0.08
DIRECTIONS = ("right", "up-right", "up", "up-left", "left", "down-left", "down", "down-right")
#: "followed": centroid cosine and length ratio within these (the targets of the control notes).
FOLLOW_COS, FOLLOW_RATIO = 0.9, (0.7, 1.3)


def controllers(scene: str) -> dict[str, dict[str, Any]]:
    """Name → Controller keyword arguments (``method`` among them) of every controller on the front."""
    out: dict[str, dict[str, Any]] = {"none": {"method": "none"}}
    for gain in (0.5, 1.0, 1.5):
        out[f"constant@g{gain:g}"] = {"method": "constant", "gain": gain}
    for settle in (0.25, 0.5, 1.0):
        for cap in (10, 50):
            out[f"pd@s{settle:g}c{cap}"] = {"method": "pd", "settle": settle, "cap_g": float(cap)}
    for budget, rounds in ((8, 2), (16, 4), (32, 4)):
        out[f"mpc@{budget}"] = {"method": "mpc", "mpc": MpcSettings(rollouts=budget, rounds=rounds)}
    out["diffusion"] = {"method": "diffusion"}
    return out


def start_sim(scene: str, seed: int) -> MpmSimulator:
    sim = MpmSimulator(scene, r_p=CONTROL_R_P, seed=seed, threads=1)
    rollout(sim, PREROLL)
    return sim


def user_sketches(sim: MpmSimulator, seed: int, ovals: int) -> list[tuple[str, Sketch]]:
    """The sketches of one start state: ``(label, sketch)``: 8 arrows by direction and one against the flow, then ``ovals`` ovals."""
    p = sim.particles
    x = np.asarray(p.fluid(sim.positions), np.float64)[:, :2]
    m = np.asarray(p.masses, np.float64)
    c = (m @ x) / m.sum()
    vel = (m @ np.asarray(sim.velocities, np.float64)[:, :2]) / m.sum()
    dirs = [(name, np.array([math.cos(i * math.pi / 4), math.sin(i * math.pi / 4)])) for i, name in enumerate(DIRECTIONS)]
    if np.linalg.norm(vel) > 1e-3:
        dirs.append(("against-flow", -vel / np.linalg.norm(vel)))
    out: list[tuple[str, Sketch]] = []
    for name, u in dirs:
        length = ARROW
        for k in range(2):  # the tip MARGIN inside the walls
            if u[k] > 1e-9:
                length = min(length, (1.0 - MARGIN - c[k]) / u[k])
            elif u[k] < -1e-9:
                length = min(length, (MARGIN - c[k]) / u[k])
        if length >= MARGIN:
            out.append((f"arrow-{name}", Sketch.arrow(c, c + length * u)))
    rng = np.random.default_rng([seed, 17])
    while sum(lbl.startswith("oval") for lbl, _ in out) < ovals:
        centre = c + rng.uniform(-0.3, 0.3, 2)
        if np.linalg.norm(centre - c) > 0.3 or (centre < 0.15).any() or (centre > 0.85).any():
            continue
        radii = np.array([rng.uniform(0.08, 0.14), rng.uniform(0.05, 0.10)])
        out.append((f"oval-{len(out)}", Sketch.oval(centre, radii, float(rng.uniform(0, math.pi)))))
    return out


def centroids(fluid: np.ndarray, masses: np.ndarray) -> np.ndarray:
    w = np.asarray(masses, np.float64) / np.sum(masses)
    return np.einsum("fnd,n->fd", np.asarray(fluid, np.float64), w)


def run_case(scene: str, seed: int, label: str, sketch: Sketch, names: list[str]) -> dict[str, Any]:
    sim = start_sim(scene, seed)
    state = sim.state()
    masses = sim.particles.masses
    row: dict[str, Any] = {"scene": scene, "seed": seed, "label": label, "kind": sketch.kind, "sketch": sketch.to_json(), "methods": {}}
    free_end = None
    specs = controllers(scene)
    for name in ["none", *[n for n in names if n != "none"]]:
        sim.restore(state)
        kw = dict(specs[name])
        method = kw.pop("method")
        ctl = Controller.for_scene(scene, method, seed=seed, **kw)
        ep = control_episode(sim, sketch, ctl)
        fluid = ep.rollout.fluid_positions
        met = {k: (None if isinstance(v, float) and not math.isfinite(v) else v) for k, v in ep.metrics.items() if not isinstance(v, str)}
        if name == "none":
            free_end = fluid[-1]
        assert free_end is not None
        if sketch.kind == "arrow":
            met.update(lateral_deviation(centroids(fluid, masses), sketch))
            met["mass_carried"] = mass_carried(fluid[0], fluid[-1], masses, sketch)
            met["followed"] = bool(met["cosine"] >= FOLLOW_COS and FOLLOW_RATIO[0] <= met["length_ratio"] <= FOLLOW_RATIO[1])
        met.update({k: (None if not math.isfinite(v) else v) for k, v in off_sketch_disturbance(fluid[0], fluid[-1], free_end, sketch).items()})
        row["methods"][name] = met
    return row


def _mean(rows: list[dict], name: str, key: str) -> float:
    vals = [r["methods"][name].get(key) for r in rows if name in r["methods"]]
    vals = [float(v) for v in vals if v is not None]
    return float(np.mean(vals)) if vals else math.nan


def _p95(rows: list[dict], name: str) -> float:
    vals = [r["methods"][name]["plan_ms"] for r in rows if name in r["methods"]]
    return float(np.percentile(vals, 95)) if vals else math.nan


def front(cases: list[dict], scene: str, names: list[str]) -> list[dict[str, Any]]:
    """Per controller on ``scene``: its means over arrows and ovals, and its plan p95 (ms)."""
    cs = [c for c in cases if c["scene"] == scene]
    arrows = [c for c in cs if c["kind"] == "arrow"]
    ovals = [c for c in cs if c["kind"] == "oval"]
    out = []
    for n in names:
        if not cs or not all(n in c["methods"] for c in cs):  # a controller on every case of the scene, or not on its front
            continue
        out.append(
            {
                "name": n,
                "arrows": len(arrows),
                "followed": _mean(arrows, n, "followed"),
                "cosine": _mean(arrows, n, "cosine"),
                "length_ratio": _mean(arrows, n, "length_ratio"),
                "lateral_max_rel": _mean(arrows, n, "lateral_max_rel"),
                "mass_carried": _mean(arrows, n, "mass_carried"),
                "arrow_effort": _mean(arrows, n, "effort_mean_g"),
                "ovals": len(ovals),
                "iou": _mean(ovals, n, "iou"),
                "oval_effort": _mean(ovals, n, "effort_mean_g"),
                "effort_max": max((c["methods"][n]["effort_max_g"] for c in cs if n in c["methods"]), default=math.nan),
                "smoothness": _mean(cs, n, "smoothness"),
                "off_sketch_mm": 1e3 * _mean(ovals, n, "off_sketch_mean_m"),
                "plan_p95_ms": _p95(cs, n),
            }
        )
    return out


def summarise(cases: list[dict], scenes: list[str], names: list[str]) -> str:
    lines = []
    for scene in scenes:
        rows = front(cases, scene, names)
        if not rows:
            continue
        lines += [f"### {scene} ({rows[0]['arrows']} arrows, {rows[0]['ovals']} ovals)", ""]
        lines += table(
            ["controller", "arrows followed", "cosine", "length ratio", "lateral max / length", "mass carried", "arrow effort g",
             "oval IoU", "oval effort g", "effort max g", "smoothness", "ovals: push off free motion 0.1 m from the oval, mm", "plan p95 ms"],
            [[r["name"], f"{r['followed']:.0%}", f"{r['cosine']:.2f}", f"{r['length_ratio']:.2f}", f"{r['lateral_max_rel']:.2f}", f"{r['mass_carried']:.2f}",
              f"{r['arrow_effort']:.1f}", f"{r['iou']:.3f}", f"{r['oval_effort']:.1f}", f"{r['effort_max']:.0f}", f"{r['smoothness']:.2f}",
              f"{r['off_sketch_mm']:.0f}", f"{r['plan_p95_ms']:.0f}"] for r in rows],
        )  # fmt: skip
        lines.append("")
    return "\n".join(lines)


def front_figure(cases: list[dict], scene: str, names: list[str]) -> Any:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = front(cases, scene, names)
    fig, ax = plt.subplots(1, 3, figsize=(15, 4.2))
    colours = {"none": "k", "constant": "tab:blue", "pd": "tab:orange", "mpc": "tab:green", "diffusion": "tab:red"}
    for r in rows:
        fam = r["name"].split("@")[0]
        kw = {"color": colours.get(fam, "grey"), "s": 30}
        ax[0].scatter(r["oval_effort"], r["iou"], **kw)
        ax[0].annotate(r["name"], (r["oval_effort"], r["iou"]), fontsize=6)
        ax[1].scatter(r["arrow_effort"], r["followed"], **kw)
        ax[1].annotate(r["name"], (r["arrow_effort"], r["followed"]), fontsize=6)
        ax[2].scatter(max(r["plan_p95_ms"], 1e-2), r["iou"], **kw)
        ax[2].annotate(r["name"], (max(r["plan_p95_ms"], 1e-2), r["iou"]), fontsize=6)
    ax[0].set(xlabel="oval effort, mean (g)", ylabel="oval IoU", title=f"{scene}: ovals")
    ax[1].set(xlabel="arrow effort, mean (g)", ylabel="arrows followed (cos >= 0.9, ratio 0.7-1.3)", title=f"{scene}: arrows")
    ax[2].set(xscale="log", xlabel="plan p95 (ms)", ylabel="oval IoU", title=f"{scene}: latency")
    ax[2].axvline(150, color="grey", ls=":")
    for f, c in colours.items():
        ax[0].scatter([], [], color=c, label=f)
    ax[0].legend(fontsize=7)
    fig.tight_layout()
    return fig


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scenes", default="water2d,sand2d,water3d,sand3d")
    ap.add_argument("--seeds", type=int, default=2, help="start states per scene (seeds FIRST_SEED, FIRST_SEED + 1, ...)")
    ap.add_argument("--first-seed", type=int, default=8200)
    ap.add_argument("--ovals", type=int, default=3, help="ovals per start state")
    ap.add_argument("--controllers", default=None, help="comma-separated subset of the controllers (default: all)")
    ap.add_argument("--out", default="benchmarks/results/control_user")
    args = ap.parse_args(argv)
    scenes = args.scenes.split(",")
    names = list(controllers(scenes[0]))
    if args.controllers:
        wanted = args.controllers.split(",")
        bad = set(wanted) - set(names)
        if bad:
            ap.error(f"--controllers: unknown {', '.join(sorted(bad))} (known: {', '.join(names)})")
        names = [n for n in names if n in wanted or n == "none"]
    out = Path(args.out)
    done = read_results(out.with_suffix(".json"))["cases"] if out.with_suffix(".json").is_file() else []
    have = {(c["scene"], c["seed"], c["label"]) for c in done}
    t_all = time.perf_counter()
    for scene in scenes:
        for seed in range(args.first_seed, args.first_seed + args.seeds):
            sketches = user_sketches(start_sim(scene, seed), seed, args.ovals)
            for label, sketch in sketches:
                if (scene, seed, label) in have:
                    continue
                t0 = time.perf_counter()
                done.append(run_case(scene, seed, label, sketch, names))
                write_results(out.parent, out.name, doc={"cases": done}, indent=None, argv=script_argv(__file__, argv))
                print(f"[{time.perf_counter() - t_all:7.0f} s] {scene} seed {seed} {label}: {time.perf_counter() - t0:.1f} s", flush=True)
    figures = {f"{out.name}_front_{s}.png": front_figure(done, s, names) for s in scenes if any(c["scene"] == s for c in done)}
    fronts = {s: front(done, s, names) for s in scenes}
    text = summarise(done, scenes, names)
    write_results(out.parent, out.name, doc={"cases": done, "front": fronts}, markdown=text, figures=figures, indent=None, argv=script_argv(__file__, argv))
    print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
