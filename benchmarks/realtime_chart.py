"""The real-time chart of every registered scene: each rung of real-time mode, its error and its time.

A rung is one grid (the scene's, ¾ or ½ of it where the walls' faces stay put), stepped by one integrator
(explicit; the projection where the scene is water round free-slip obstacles), on the scene's default particles
(its chart's ``r_p``) or, on a coarser grid, those merged to the scene's density per cell:
:func:`hybridmpm.sim.ladder.candidate_rungs`. Each rung runs ``--frames`` frames from the scene's initial
condition on both threads. Its error is the grid-mass error against the scene's full-resolution MPM reference
(:func:`hybridmpm.sim.reference`, paper Sec. 3.1.1's ``RMSE_m̃``, mass-weighted), averaged over the frames; its
time the mean wall time per frame after ``--warmup`` frames, and its ``time_ratio`` that over the first rung's
in the same run (ratios carry over between machines; milliseconds do not).

Real-time mode (docs/realtime.md) orders the rungs by error and keeps those that buy time; ``--ship`` writes the
charted scenes into the package's chart (``python/hybridmpm/models/realtime.json``, the other scenes kept), which
the mode reads. The figure marks, per
scene, the rung this machine picks: the most accurate whose frame fits the budget (2.5 ms / 1.25).

    python benchmarks/realtime_chart.py --out benchmarks/results/realtime_chart --ship
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path
from typing import Any

import numpy as np

from hybridmpm.bench.harness import script_argv, table, write_json, write_results
from hybridmpm.metrics.compare import evaluate
from hybridmpm.scenes import make_scene
from hybridmpm.scenes.registry import DOMAINS
from hybridmpm.sim import RealtimeSimulator, reference, rollout
from hybridmpm.sim.config import default_settings
from hybridmpm.sim.ladder import CHART_FILE, Rung, candidate_rungs, pareto
from hybridmpm.sim.realtime import REALTIME_MARGIN

SHIP = Path(__file__).resolve().parent.parent / "python" / "hybridmpm" / "models" / CHART_FILE


def chart_scene(name: str, frames: int, warmup: int) -> dict[str, Any]:
    """One scene's chart: its rungs with error, ms per frame and time ratio."""
    scene = make_scene(name)
    settings = default_settings(name)
    r_p = float(settings.get("r_p", 1.0)) if settings.get("solver") == "mpm" else 1.0
    ref = reference(scene, frames)
    rows: list[dict[str, Any]] = []
    clusters = None
    for rung in candidate_rungs(scene):
        sim = RealtimeSimulator(scene, r_p=r_p, clusters=clusters, rung=rung.key, adaptive=False)  # the mode's own change of rung, held
        clusters = sim.scene.clusters
        ro = rollout(sim, frames)
        if ro.failure is not None:
            print(f"{name} {rung.key}: broke off ({ro.failure})", flush=True)
            continue
        seconds = np.asarray(ro.seconds)[1 + warmup :]
        ms = 1e3 * float(np.mean(seconds))  # the mean: a projection step spanning frames puts its cost on one of them
        m = evaluate(ro, ref, scene.params.resolved_n_grid())
        err = m.get("grid_mass_error_mass_weighted") or m["grid_mass_error"]
        rows.append({"key": rung.key, "n_grid": rung.n_grid, "integrator": rung.integrator, "r_p": rung.r_p, "error": float(err["mean"]), "ms": ms})
        print(name, rows[-1], flush=True)
    t0 = rows[0]["ms"]
    for r in rows:
        r["time_ratio"] = round(r["ms"] / t0, 4)
        r["ms"] = round(r["ms"], 4)
        r["error"] = round(r["error"], 6)
    return {"r_p": r_p, "frames": frames, "particles": int(sim.particles.num_fluid), "dim": scene.dim, "rungs": rows}


def pick(chart: dict[str, Any], budget_ms: float) -> str:
    """The rung this machine picks from ``chart``: the most accurate on the Pareto ladder whose measured frame
    fits ``budget_ms``, else the fastest."""
    ladder = pareto([Rung(r["n_grid"], r["integrator"], r["error"], r["time_ratio"], r.get("r_p", 1.0)) for r in chart["rungs"]])
    ms = {r["key"]: r["ms"] for r in chart["rungs"]}
    return next((r.key for r in ladder if ms[r.key] <= budget_ms), ladder[-1].key)


def plot(charts: dict[str, dict[str, Any]], budget_ms: float) -> Any:
    """The chart per scene: error against ms per frame, the pick in red."""
    import matplotlib  # the figure only: the runs need no matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = list(charts)
    cols = 4
    rows = (len(names) + cols - 1) // cols
    fig, axes = plt.subplots(rows, cols, figsize=(3.4 * cols, 2.8 * rows), squeeze=False)
    for ax, name in zip(axes.flat, names):
        ch = charts[name]
        chosen = ch["pick"]
        for r in ch["rungs"]:
            marker = "o" if r["integrator"] == "explicit" else "s"
            ax.scatter(r["ms"], r["error"], marker=marker, color="C3" if r["key"] == chosen else "C0", zorder=3)
            ax.annotate(r["key"], (r["ms"], r["error"]), fontsize=6, xytext=(3, 3), textcoords="offset points")
        ax.axvline(budget_ms, color="0.5", ls="--", lw=0.8)
        ax.set_title(name, fontsize=9)
        ax.set_xscale("log")
        ax.tick_params(labelsize=7)
    for ax in list(axes.flat)[len(names) :]:
        ax.axis("off")
    fig.supxlabel("wall ms per 2.5 ms frame (both threads; dashed: the budget)", fontsize=9)
    fig.supylabel("grid-mass error vs full resolution", fontsize=9)
    fig.suptitle("Real-time chart: circles explicit, squares projection, red the rung this machine picks", fontsize=10)
    fig.tight_layout()
    return fig


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scenes", default=",".join(DOMAINS), help="comma-separated registered scenes (default: all)")
    ap.add_argument("--frames", type=int, default=200, help="frames per rung (default 200)")
    ap.add_argument("--warmup", type=int, default=10, help="frames left out of the timing (default 10)")
    ap.add_argument("--out", required=True, help="output folder")
    ap.add_argument("--ship", action="store_true", help=f"write the chart into the package (models/{CHART_FILE})")
    args = ap.parse_args(argv)
    budget_ms = 2.5 / REALTIME_MARGIN
    charts: dict[str, dict[str, Any]] = {}
    t_start = time.perf_counter()
    for name in [s.strip() for s in args.scenes.split(",") if s.strip()]:
        if name not in DOMAINS:
            ap.error(f"--scenes: unknown scene {name!r}; choose from {', '.join(DOMAINS)}")
        charts[name] = chart_scene(name, args.frames, args.warmup)
        charts[name]["pick"] = pick(charts[name], budget_ms)
    keys = ["scene", "rung", "error", "ms", "time_ratio", "picked here"]
    lines = [
        f"# Real-time chart ({args.frames} frames a rung, both threads; budget {budget_ms:.2f} ms a frame)",
        "\n".join(
            table(
                keys,
                [
                    [n, r["key"], f"{r['error']:.4f}", f"{r['ms']:.3f}", f"{r['time_ratio']:.3f}", "yes" if r["key"] == c["pick"] else ""]
                    for n, c in charts.items()
                    for r in c["rungs"]
                ],
            )
        ),
    ]
    figures = {"realtime_chart.png": plot(charts, budget_ms)}
    write_results(args.out, "realtime_chart", doc={"scenes": charts}, markdown=lines, figures=figures, argv=script_argv("realtime_chart.py", argv), dpi=110)
    if args.ship:  # the charted scenes replace theirs in the shipped chart; the others are kept (each scene's ratios are its own run's)
        before = json.loads(SHIP.read_text()) if SHIP.is_file() else {}
        if before.get("frames", args.frames) != args.frames:
            ap.error(f"--frames: the shipped chart was made with {before['frames']} frames a rung; chart every scene to change it")
        scenes = {**before.get("scenes", {}), **{n: {k: v for k, v in c.items() if k != "pick"} for n, c in charts.items()}}
        shipped = {"made_by": "benchmarks/realtime_chart.py", "frames": args.frames, "scenes": {n: scenes[n] for n in DOMAINS if n in scenes}}
        write_json(SHIP, shipped)
        print(f"wrote {SHIP}")
    print(f"{time.perf_counter() - t_start:.0f} s")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
