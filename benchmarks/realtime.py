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

With ``--realtime`` each scene also runs ``make_simulator(scene, "realtime")`` (docs/realtime.md) as a host
runs it: a loop ticking ``--tick-hz`` times a second, each tick a :func:`~hybridmpm.sim.step_realtime` call
with the wall time since the last (what a tick cannot step in its time is dropped, never owed), sleeping to
the next tick. ``--settle`` seconds pick its rung, then ``--hold`` seconds are timed. Its row names the rung
it ended on and how often it changed; ``held`` is the simulated time over the elapsed wall time (1.0: it kept
real time, the most a host gets), ``worst_held`` the same over the worst 5 s, and ``rtf`` the simulated time
over the wall time spent stepping (what its pace would allow).

    python benchmarks/realtime.py --out benchmarks/results/realtime

With ``--n-grid N`` each scene is built on an N-cell grid, e.g. the 3D dam break of 104,742 particles
on 56³ (docs/large-step.md):

    python benchmarks/realtime.py --scenes dam_break3d --n-grid 56 --repeats 3 --out benchmarks/results/realtime_large
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
from hybridmpm.sim import make_simulator, rollout, step_realtime
from hybridmpm.sim.config import default_settings
from hybridmpm.sim.ladder import projection_allowed

#: The window [s] over which the worst share of real time held is read.
WINDOW_S = 5.0


def host_loop(sim: Any, seconds: float, tick_hz: float) -> dict[str, float]:
    """Drive ``sim`` for ``seconds`` of wall time as a host does: a tick every ``1 / tick_hz`` s, each
    :func:`~hybridmpm.sim.step_realtime` with the wall time since the last tick (what it could not step in that
    time is dropped, not owed), sleeping to the next tick. Returns the frames, the simulated time, the wall
    time spent stepping (``busy``), the elapsed wall time, and the worst :data:`WINDOW_S` window's share of
    real time held."""
    start = last = time.perf_counter()
    owed = simulated = busy = 0.0
    frames, steps, marks = 0, 0.0, [(start, 0.0)]
    while (now := time.perf_counter()) - start < seconds:
        tick = step_realtime(sim, now - last, owed_s=owed)
        if tick.rollout.failure not in (None, "budget"):
            raise RuntimeError(f"the host loop broke off: {tick.rollout.failure} {tick.rollout.failure_detail}")
        last, owed = now, tick.owed_s
        frames, simulated, busy = frames + tick.frames, simulated + tick.simulated_s, busy + tick.wall_s
        steps += float(np.asarray(tick.rollout.substeps)[1:].sum())
        marks.append((time.perf_counter(), simulated))
        time.sleep(max(0.0, now + 1.0 / tick_hz - time.perf_counter()))
    elapsed = time.perf_counter() - start
    t, s = np.array(marks).T
    ends = np.searchsorted(t, t + WINDOW_S)  # each window from a tick to the first tick WINDOW_S later
    ok = ends < len(t)
    worst = float(np.min((s[ends[ok]] - s[ok]) / (t[ends[ok]] - t[ok]))) if ok.any() else simulated / elapsed
    return {"frames": frames, "steps": steps, "simulated": simulated, "busy": busy, "elapsed": elapsed, "worst": worst}


def measure_realtime(scene: str, settle_s: float, hold_s: float, tick_hz: float) -> dict[str, Any]:
    """Real-time mode's figures as a host runs it (:func:`host_loop`): ``settle_s`` seconds to pick its rung,
    then ``hold_s`` seconds timed. ``held`` is the simulated time over the elapsed wall time (1.0: it kept real
    time; a host never gets more), ``worst_held`` the same over the worst :data:`WINDOW_S` window, and ``rtf``
    the simulated time over the wall time spent stepping (what its frame pace would allow)."""
    sim = make_simulator(scene, "realtime")
    host_loop(sim, settle_s, tick_hz)
    settled = len(sim.changes)
    rungs = {sim.realtime_info()["rung"]}
    seen = len(sim.changes)
    h = host_loop(sim, hold_s, tick_hz)
    rungs |= {c["to"] for c in sim.changes[seen:]}
    info = sim.realtime_info()
    return {
        "scene": scene,
        "run": f"realtime: {info['rung']} ({settled} changes settling, {len(sim.changes) - settled} timed)",
        "particles": int(sim.solver.num_particles),
        "steps_per_frame": h["steps"] / max(h["frames"], 1),
        "ms_per_frame": 1e3 * h["busy"] / max(h["frames"], 1),
        "rtf": h["simulated"] / h["busy"] if h["busy"] else float("nan"),
        "held": h["simulated"] / h["elapsed"],
        "worst_held": h["worst"],
        "rungs": sorted(rungs),
    }


def measure(scene: str, integrator: str | None, frames: int, warmup: int, n_grid: int | None = None) -> dict[str, Any] | None:
    """One run's figures: the scene's default (``integrator`` None), or its default's settings stepped by
    ``integrator``; None where the integrator does not step the scene (refused, naming ``integrator``). With
    ``n_grid`` the scene is built on that grid (``make_scene(scene, n_grid=...)``: its blocks seeded at that
    resolution, so a finer grid has more particles)."""
    target = make_scene(scene, n_grid=n_grid) if n_grid is not None else make_scene(scene)
    try:
        if integrator is None:
            sim = make_simulator(target, "default")
        else:
            settings = default_settings(target)
            if settings.get("solver") != "mpm" or (integrator == INTEGRATORS[1] and not projection_allowed(target)):
                return None  # the projection steps water in free-slip walls and obstacles only (it refuses the rest)
            sim = make_simulator(target, **settings, integrator=integrator)
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
        "scene": scene if n_grid is None else f"{scene} on {n_grid}",
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
    ap.add_argument("--n-grid", type=int, default=None, help="build each scene on this grid (more particles on a finer one; default: the scene's own)")
    ap.add_argument("--realtime", action="store_true", help="also run real-time mode (docs/realtime.md)")
    ap.add_argument("--settle", type=float, default=10.0, help="with --realtime: seconds of the host loop before the timing (default 10)")
    ap.add_argument("--hold", type=float, default=60.0, help="with --realtime: seconds of the host loop timed (default 60)")
    ap.add_argument("--tick-hz", type=float, default=60.0, help="with --realtime: the host loop's ticks a second (default 60)")
    ap.add_argument("--out", required=True, help="output folder")
    args = ap.parse_args(argv)
    if not 1 <= args.repeats <= 20:
        ap.error(f"--repeats: got {args.repeats}; choose 1 to 20")
    if args.n_grid is not None and (not 8 <= args.n_grid <= 256 or args.realtime):
        ap.error(f"--n-grid: got {args.n_grid}; choose 8 to 256, without --realtime (its chart is the scene's own grid's)")
    rows: list[dict[str, Any]] = []
    for scene in [s.strip() for s in args.scenes.split(",") if s.strip()]:
        if scene not in DOMAINS:
            ap.error(f"--scenes: unknown scene {scene!r}; choose from {', '.join(DOMAINS)}")
        runs: dict[str | None, list[dict[str, Any]]] = {}
        for _ in range(args.repeats):  # interleaved, so a slow spell of the machine falls on both integrators
            for integrator in (None, "projection"):
                r = measure(scene, integrator, args.frames, args.warmup, args.n_grid)
                if r is not None:
                    runs.setdefault(integrator, []).append(r)
        for rs in runs.values():
            rows.append(median_row(rs))
            print(rows[-1], flush=True)
        if args.realtime:
            rows.append(measure_realtime(scene, args.settle, args.hold, args.tick_hz))
            print(rows[-1], flush=True)
    keys = ["scene", "run", "particles", "steps_per_frame", "ms_per_frame", "rtf", "held", "worst_held"]

    def cell(v: Any) -> str:
        return "" if v is None else f"{v:.3g}" if isinstance(v, float) else str(v)

    lines = [
        "# Real-time factor per scene (both threads; a frame is 2.5 ms, real time is RTF >= 1)",
        "\n".join(table(keys, [[cell(r.get(k)) for k in keys] for r in rows])),
    ]
    write_results(args.out, "realtime", doc={"rows": rows}, markdown=lines, argv=script_argv("realtime.py", argv))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
