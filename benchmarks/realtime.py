"""Real-time factor of every registered scene, as a session runs it, under each integrator that steps it, and in
real-time mode.

For each scene: ``make_simulator(scene, "default")`` (what a session and the
page run, the chart's choice), and, where the scene holds only water in the
box walls, the same configuration (its ``r_p``, its grid) stepped by the
projection, ``integrator="projection"`` (the large step; docs/large-step.md). Each runs ``--warmup`` frames, then
``--frames`` frames timed through :func:`~hybridmpm.sim.rollout` on both
threads; with ``--repeats N`` each scene's runs are repeated N times, interleaved, and each row is their median. The real-time factor is simulated seconds per wall second,
``frames · dt_frame / wall`` (a frame is 2.5 ms: real time is 400 frames a
wall second). Steps per frame are the MPM solver's (substeps for the explicit step; a
projection step spanning frames counts on its first). Run it on a quiet machine: its absolute times move with the CPU and
the load; the ratio of the two integrators in one run is what carries over.

With ``--realtime`` each scene also runs ``make_simulator(scene, "realtime")`` (docs/realtime.md): ``--settle``
seconds of wall time to pick its rung, then ``--frames`` frames timed as above; the row names the rung it ran
and how often it changed.

    python benchmarks/realtime.py --out benchmarks/results/realtime
"""

from __future__ import annotations

import argparse
import time
from typing import Any

import numpy as np

from hybridmpm.bench.harness import script_argv, table, write_results
from hybridmpm.errors import InvalidInputError
from hybridmpm.mpm import INTEGRATORS
from hybridmpm.scenes import make_scene
from hybridmpm.scenes.registry import DOMAINS
from hybridmpm.sim import make_simulator, rollout
from hybridmpm.sim.config import default_settings
from hybridmpm.sim.ladder import projection_allowed


def measure_realtime(scene: str, frames: int, settle_s: float) -> dict[str, Any]:
    """Real-time mode's figures: its rung after ``settle_s`` seconds of stepping, then ``frames`` frames timed."""
    sim = make_simulator(scene, "realtime")
    t0 = time.perf_counter()
    while time.perf_counter() - t0 < settle_s:
        sim.advance()
    settled = len(sim.changes)
    t0 = time.perf_counter()
    ro = rollout(sim, frames)
    wall = time.perf_counter() - t0
    if ro.failure is not None:
        raise RuntimeError(f"{scene} (realtime): the rollout broke off: {ro.failure} {ro.failure_detail}")
    info = sim.realtime_info()
    return {
        "scene": scene,
        "run": f"realtime: {info['rung']} ({settled} changes settling, {len(sim.changes) - settled} timed)",
        "particles": int(sim.solver.num_particles),
        "steps_per_frame": float(np.asarray(ro.substeps)[1:].sum()) / frames,
        "ms_per_frame": 1e3 * wall / frames,
        "rtf": frames * sim.dt_frame / wall,
    }


def measure(scene: str, integrator: str | None, frames: int, warmup: int) -> dict[str, Any] | None:
    """One run's figures: the scene's default (``integrator`` None), or its default's settings stepped by
    ``integrator``; None where the integrator does not step the scene (refused, naming ``integrator``)."""
    try:
        if integrator is None:
            sim = make_simulator(scene, "default")
        else:
            settings = default_settings(scene)
            if settings.get("solver") != "mpm" or (integrator == INTEGRATORS[1] and not projection_allowed(make_scene(scene))):
                return None  # the projection steps water in free-slip walls and obstacles only (it refuses the rest)
            sim = make_simulator(scene, **settings, integrator=integrator)
    except InvalidInputError as e:
        if e.field == "integrator":
            return None
        raise
    rollout(sim, warmup)
    t0 = time.perf_counter()
    ro = rollout(sim, frames)
    wall = time.perf_counter() - t0
    if ro.failure is not None:
        raise RuntimeError(f"{scene} ({integrator or 'default'}): the rollout broke off: {ro.failure} {ro.failure_detail}")
    ms = 1e3 * wall / frames
    steps = float(np.asarray(ro.substeps)[1:].sum()) / frames
    return {
        "scene": scene,
        "run": "default" if integrator is None else f"default, {integrator}",
        "particles": int(sim.scene.num_particles),
        "steps_per_frame": steps,
        "ms_per_frame": ms,
        "rtf": frames * sim.dt_frame / wall,
    }


def median_row(rs: list[dict[str, Any]]) -> dict[str, Any]:
    """One configuration's runs as one row: the median of each time (the steps are the same bits each run)."""
    row = dict(rs[0])
    for k in ("ms_per_frame", "rtf"):
        row[k] = float(np.median([r[k] for r in rs]))
    row["runs"] = len(rs)
    return row


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scenes", default=",".join(DOMAINS), help="comma-separated registered scenes (default: all)")
    ap.add_argument("--frames", type=int, default=150, help="frames timed (default 150)")
    ap.add_argument("--warmup", type=int, default=15, help="frames before the timing (default 15)")
    ap.add_argument("--repeats", type=int, default=1, help="runs of each scene's configurations, interleaved; the row is their median (default 1)")
    ap.add_argument("--realtime", action="store_true", help="also run real-time mode (docs/realtime.md)")
    ap.add_argument("--settle", type=float, default=10.0, help="with --realtime: seconds it steps before the timing (default 10)")
    ap.add_argument("--out", required=True, help="output folder")
    args = ap.parse_args(argv)
    if not 1 <= args.repeats <= 20:
        ap.error(f"--repeats: got {args.repeats}; choose 1 to 20")
    rows: list[dict[str, Any]] = []
    for scene in [s.strip() for s in args.scenes.split(",") if s.strip()]:
        if scene not in DOMAINS:
            ap.error(f"--scenes: unknown scene {scene!r}; choose from {', '.join(DOMAINS)}")
        runs: dict[str | None, list[dict[str, Any]]] = {}
        for _ in range(args.repeats):  # interleaved, so a slow spell of the machine falls on both integrators
            for integrator in (None, "projection"):
                r = measure(scene, integrator, args.frames, args.warmup)
                if r is not None:
                    runs.setdefault(integrator, []).append(r)
        for rs in runs.values():
            rows.append(median_row(rs))
            print(rows[-1], flush=True)
        if args.realtime:
            rows.append(measure_realtime(scene, args.frames, args.settle))
            print(rows[-1], flush=True)
    keys = ["scene", "run", "particles", "steps_per_frame", "ms_per_frame", "rtf"]
    lines = [
        "# Real-time factor per scene (both threads; a frame is 2.5 ms, real time is RTF >= 1)",
        "\n".join(table(keys, [[f"{r[k]:.3g}" if isinstance(r[k], float) else str(r[k]) for k in keys] for r in rows])),
    ]
    write_results(args.out, "realtime", doc={"rows": rows}, markdown=lines, argv=script_argv("realtime.py", argv))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
