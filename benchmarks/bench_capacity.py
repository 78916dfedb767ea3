"""Capacity: how many water2d sessions one server holds at real time.

A real ``hybridmpm serve`` on 127.0.0.1 (child process). For each N of the
ladder (1, 2, 4, 6, 8, 10, 12, ... until a rung fails), N water2d sessions
are created with the service's default configuration (solver ``default``:
what the scene ships, ``models/defaults.json``; seeds 0..N-1), each gets one
WebSocket viewer that sends ``play`` as the page does (a session plays only
while it has a viewer), and after ``--warmup`` seconds, for ``--seconds``:

* frames/s each session reaches: the frame numbers in the headers its viewer
  receives (the stream sends at most ``max_fps`` of them a second, the newest
  one: latest wins), first and last of the window; min and median over the N;
* step latency p50/p95: a probe, one more water2d session of the same
  configuration that does not play, stepped one frame at a time (``POST
  /step {frames: 1}``, binary answer) every ``--probe-gap`` seconds: the
  client's round trip, and the engine's part of it (``X-Seconds``);
* CPU: the server process (cores busy), its main thread (the event loop:
  frame offers, the WebSocket sends, the play loops' waits), this client
  (the viewers and the probe), and the whole machine (the rest is other
  processes);
* real time held: every session at >= ``REAL_TIME_SHARE`` of 1/dt_frame
  (water2d: 400 frames/s, dt_frame 2.5 ms).

After the first failing rung, the counts between the last that held and it
are tried. Last, the engine alone (``--engine-frames``, default warmup +
window): each seed's simulator stepped in this process, one at a time: the
cores a rung's sessions need at real time without the service, and, over
at least ``--engine-seeds`` seeds (8), the most sessions whose engine work
alone fits in the machine's cores (an upper bound on the capacity).

Each rung runs ``--repeats`` times (fresh sessions each time) and keeps its
best run: a shared machine's slow spells only lower a rate. The capacity is
the largest N whose rung and every smaller one held. Then
one dam_break3d session (default solver) with one viewer, best of the same
repeats: the frames/s it steps (the page's 3D scene).

    python benchmarks/bench_capacity.py [--seconds 4] [--warmup 1.5] [--repeats 3] [--out-dir benchmarks/results]
    python benchmarks/bench_capacity.py --quick --out-dir /tmp/cap   # seconds, tiny settings
    python benchmarks/bench_capacity.py --realtime --warmup 8 --repeats 1 --out-dir benchmarks/results/capacity_realtime

``--backend ray`` serves the sessions from a Ray cluster of one node on this machine (``RayCluster``: as many
CPUs as the machine's cores, each session an actor process reserving ``ray_num_cpus`` of one): the sessions'
frames then share the cores through the operating system, not through the server's compute limiter, and
"server CPU" is the front end's alone (the sessions' work is in "machine").

    python benchmarks/bench_capacity.py --backend ray --ray-num-cpus 0.1 --realtime --warmup 8 --repeats 1 --scene3d "" --out-dir benchmarks/results/capacity_ray
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import itertools
import json
import os
import secrets
import shutil
import statistics
import tempfile
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import httpx
import numpy as np
import websockets

from hybridmpm.bench.harness import REPO_ROOT, load_average, script_argv, table, write_results
from hybridmpm.service import decode_frame
from hybridmpm.service.core import PLAY_LAG_S, PLAY_TICK_S
from hybridmpm.service.testing import LiveServer, RayCluster, cpu_seconds, thread_cpu_seconds

OCTET = {"Accept": "application/octet-stream"}
#: A session holds real time when it steps at least this share of 1/dt_frame frames/s.
REAL_TIME_SHARE = 0.95
#: Frames a viewer's stream sends per second at most (the service's default ``max_fps``).
STREAM_FPS = 60.0


def ladder(most: int) -> list[int]:
    """The session counts tried, in order: 1, 2, 4, then every second count up to ``most``."""
    return [n for n in (1, 2, 4) if n <= most] + list(range(6, most + 1, 2))


def stream_rate(seen: Sequence[tuple[float, int]], t0: float, t1: float) -> float:
    """Frames/s a session stepped in the window [``t0``, ``t1``] as its viewer
    saw it: ``seen`` the (arrival time [s], frame number) of every frame
    received; the first and last of the window. 0 with fewer than two."""
    inside = [(t, f) for t, f in seen if t0 <= t <= t1]
    if len(inside) < 2 or inside[-1][0] <= inside[0][0]:
        return 0.0
    return (inside[-1][1] - inside[0][1]) / (inside[-1][0] - inside[0][0])


def rate_bound(dt_frame: float, r_t: int, window: float, max_fps: float = STREAM_FPS) -> float:
    """The most frames/s :func:`stream_rate` can show for a session the play
    loop paces at real time over a ``window`` of seconds: one coarse step
    (``r_t`` frames of ``dt_frame`` s) per ``r_t·dt_frame`` of wall time,
    plus a catch-up of at most ``PLAY_LAG_S``, the stream's latest-wins
    lag (one send gap ``1/max_fps`` at either end), the play loop's tick
    (a call shows its last step: ``PLAY_TICK_S`` at either end) and one
    step of rounding."""
    return ((window + PLAY_LAG_S + 2.0 / max_fps + 2.0 * PLAY_TICK_S) / dt_frame + r_t) / window


def holds(rate: float, dt_frame: float) -> bool:
    """Real time: at least :data:`REAL_TIME_SHARE` of 1/``dt_frame`` frames/s."""
    return rate >= REAL_TIME_SHARE / dt_frame


def capacity(rows: Sequence[dict[str, Any]]) -> int:
    """The largest ``sessions`` of ``rows`` whose row and every row of fewer
    sessions held real time (``all_real_time``); 0 when the smallest did not."""
    best = 0
    for r in sorted(rows, key=lambda r: r["sessions"]):
        if not r["all_real_time"]:
            break
        best = r["sessions"]
    return best


def engine_cores(cost_ms: Sequence[float], dt_frame: float) -> list[float]:
    """The cores the engine alone needs at real time (1/``dt_frame``
    frames/s) for the first 1, 2, ... sessions (seeds 0, 1, ..., one thread
    each, ``cost_ms`` per frame [ms]), with no service at all."""
    return list(itertools.accumulate(c / 1e3 / dt_frame for c in cost_ms))


def engine_bound(cost_ms: Sequence[float], dt_frame: float, cores: float) -> int:
    """The most sessions whose engine work alone (:func:`engine_cores`) fits
    in ``cores``: an upper bound on the capacity."""
    return sum(1 for need in engine_cores(cost_ms, dt_frame) if need <= cores)


def best_of(repeats: int, measure: Callable[[], dict[str, Any]]) -> dict[str, Any]:
    """``measure()`` ``repeats`` times; the run that held real time with the
    highest slowest-session rate (a shared machine's slow spells only lower
    a rate), with every run's slowest rate under ``min_fps_runs``."""
    runs = [measure() for _ in range(repeats)]
    best = max(runs, key=lambda r: (r["all_real_time"], r["min_fps"]))
    return {**best, "min_fps_runs": [r["min_fps"] for r in runs]}


def engine_ms_per_frame(scene: str, seed: int, frames: int) -> float:
    """The engine alone, in this process, one thread: wall time per frame [ms]
    of ``frames`` frames of a ``scene`` simulator of the default configuration
    from the initial condition of ``seed`` (what a session's play loop steps)."""
    from hybridmpm.sim import make_simulator

    sim = make_simulator(scene, "default", seed=seed, threads=1)
    t0 = time.perf_counter()
    for _ in range(frames):
        sim.advance()
    return (time.perf_counter() - t0) / frames * 1e3


def machine_ticks() -> tuple[int, int]:
    """(busy, total) CPU ticks of the whole machine since boot (``/proc/stat``; idle and iowait are not busy)."""
    v = [int(x) for x in Path("/proc/stat").read_text().split("\n", 1)[0].split()[1:]]
    total = sum(v[:8])
    return total - v[3] - v[4], total


async def watch(ws_url: str, sid: str, seen: list[tuple[float, int]], playing: asyncio.Event) -> None:
    """A viewer of session ``sid`` as the page is one: its ``meta`` message,
    then ``play``; every binary frame's (arrival time, frame number) into ``seen``."""
    async with websockets.connect(f"{ws_url}/v1/sessions/{sid}/stream", max_size=None) as ws:
        await ws.recv()  # meta
        await ws.send('{"type": "play"}')
        playing.set()
        while True:
            m = await ws.recv()
            if isinstance(m, bytes):
                seen.append((time.monotonic(), decode_frame(m)[0].frame))


async def play_sessions(srv: LiveServer, scene: str, n: int, warmup: float, seconds: float, probe_gap: float | None, realtime: bool = False) -> dict[str, Any]:
    """``n`` sessions of ``scene`` (default solver; with ``realtime`` real-time mode, started coarser when the
    server's real time is full: docs/realtime.md) playing at once, one viewer
    each, measured for ``seconds`` after ``warmup``; with ``probe_gap`` one more
    session of ``scene`` stepped one frame at a time that often (step latency)."""
    extra = {"realtime": True, "when_full": "coarser"} if realtime else {}
    async with httpx.AsyncClient(base_url=srv.url, timeout=120, limits=httpx.Limits(max_connections=n + 4)) as c:
        made = [await c.post("/v1/sessions", json={"scene": scene, "seed": i, **extra}) for i in range(n + (probe_gap is not None))]
        bad = [r for r in made if r.status_code != 201]
        if bad:
            raise RuntimeError(f"creating a {scene} session: {bad[0].status_code} {bad[0].text[:200]}")
        info = made[0].json()
        listed = (await c.get("/v1/scenes")).json()
        listed = listed.get("scenes", listed) if isinstance(listed, dict) else listed
        default = next((x.get("default_configuration") for x in listed if x.get("name") == scene), None)
        ids = [r.json()["id"] for r in made]
        probe = ids.pop() if probe_gap is not None else None
        seen: list[list[tuple[float, int]]] = [[] for _ in ids]
        playing = [asyncio.Event() for _ in ids]
        viewers = [asyncio.create_task(watch(srv.ws_url, sid, s, p)) for sid, s, p in zip(ids, seen, playing)]
        try:
            await asyncio.wait_for(asyncio.gather(*(p.wait() for p in playing)), 60)
            await asyncio.sleep(warmup)
            lat, engine = [], []
            pid = srv.proc.pid
            cpu0, loop0, mine0, box0 = cpu_seconds([pid]), thread_cpu_seconds(pid), time.process_time(), machine_ticks()
            t0 = time.monotonic()
            t_end = t0 + seconds
            while time.monotonic() < t_end:
                if probe is None:
                    await asyncio.sleep(t_end - time.monotonic())
                    break
                t = time.perf_counter()
                r = await c.post(f"/v1/sessions/{probe}/step", json={"frames": 1}, headers=OCTET)
                lat.append((time.perf_counter() - t) * 1e3)
                if r.status_code != 200:
                    raise RuntimeError(f"probe step: {r.status_code} {r.text[:200]}")
                engine.append(sum(float(x) for x in r.headers["x-seconds"].split(",")) * 1e3)
                await asyncio.sleep(max(0.0, min(probe_gap or 0.0, t_end - time.monotonic())))
            t1 = time.monotonic()
            wall = t1 - t0
            cpu1, loop1, mine1, box1 = cpu_seconds([pid]), thread_cpu_seconds(pid), time.process_time(), machine_ticks()
            failed = [v for v in viewers if v.done()]
            if failed:  # a viewer that ended early: its error
                failed[0].result()
        finally:
            for v in viewers:
                v.cancel()
            await asyncio.gather(*viewers, return_exceptions=True)
            for sid in [*ids, *([probe] if probe else [])]:
                await c.delete(f"/v1/sessions/{sid}")
    rates = np.array([stream_rate(s, t0, t1) for s in seen])
    cores = os.cpu_count() or 1
    out: dict[str, Any] = {
        "scene": scene,
        "solver": info["solver"],
        "configuration": default if info["solver"] == "default" else None,
        "particles": [r.json()["num_particles"] for r in made[:n]],
        "dt_frame": info["dt_frame"],
        "r_t": info["r_t"],
        "sessions": n,
        "window_s": wall,
        "rates": rates.tolist(),
        "min_fps": float(rates.min()),
        "median_fps": float(np.median(rates)),
        "all_real_time": bool(all(holds(x, info["dt_frame"]) for x in rates)),
        "server_cores": (cpu1 - cpu0) / wall,
        "loop_thread_share": (loop1 - loop0) / wall,
        "client_cores": (mine1 - mine0) / wall,
        "machine_cores": cores * (box1[0] - box0[0]) / max(1, box1[1] - box0[1]),
        "load_1min": load_average()[0],
    }
    if lat:
        out |= {
            "probe_steps": len(lat),
            "step_p50_ms": float(np.percentile(lat, 50)),
            "step_p95_ms": float(np.percentile(lat, 95)),
            "engine_p50_ms": float(np.percentile(engine, 50)),
        }
    return out


@contextlib.contextmanager
def serving(backend: str, most: int, log: Path | None, ray_num_cpus: float | None = None) -> Any:
    """A live server for ``most`` sessions and more: the local backend, or a front end on a one-node Ray cluster
    of this machine's cores, each session's actor reserving ``ray_num_cpus`` (None: the service's default),
    stopped and its files removed on the way out."""
    if backend == "local":
        with LiveServer(max_sessions=most + 4, log=log) as srv:
            yield srv
        return
    root = Path(tempfile.mkdtemp(prefix="hmcap", dir="/tmp"))  # short: Ray's socket paths live under it
    cluster = RayCluster(root, secrets.token_hex(16), nodes=1, num_cpus=os.cpu_count() or 1)
    try:
        cluster.start()
        args = ["--backend", "ray", "--ray-address", cluster.address]
        args += [] if ray_num_cpus is None else ["--ray-num-cpus", str(ray_num_cpus)]
        with LiveServer(max_sessions=most + 4, log=log, args=args, env={"RAY_AUTH_MODE": "token", "RAY_AUTH_TOKEN": cluster.token}) as srv:
            yield srv
    finally:
        cluster.stop()
        shutil.rmtree(root, ignore_errors=True)


def run(args: argparse.Namespace) -> dict[str, Any]:
    rows: list[dict[str, Any]] = []
    log = Path(args.server_log) if args.server_log else None
    with serving(args.backend, args.most, log, args.ray_num_cpus) as srv:

        def rung(n: int) -> bool:
            r = best_of(args.repeats, lambda: asyncio.run(play_sessions(srv, "water2d", n, args.warmup, args.seconds, args.probe_gap, args.realtime)))
            rows.append(r)
            print(json.dumps({k: v for k, v in r.items() if k != "rates"}), flush=True)
            return bool(r["all_real_time"])

        for n in ladder(args.most):
            if not rung(n):  # then the counts between the last that held and this one
                held = max([r["sessions"] for r in rows if r["all_real_time"]], default=0)
                for k in range(held + 1, n):
                    if not rung(k):
                        break
                break
        three = (
            best_of(args.repeats, lambda: asyncio.run(play_sessions(srv, args.scene3d, 1, args.warmup, args.seconds, None, args.realtime)))
            if args.scene3d
            else None
        )
        if three:
            print(json.dumps(three), flush=True)
    frames = round((args.warmup + args.seconds) / rows[0]["dt_frame"]) if args.engine_frames is None else args.engine_frames
    out: dict[str, Any] = {
        "rows": rows,
        "capacity": capacity(rows),
        "engine_frames": frames,
        "real_time_share": REAL_TIME_SHARE,
        "repeats": args.repeats,
        "backend": args.backend,
        "scene3d": three,
    }
    if frames:  # the engine alone, one seed at a time: the CPU each rung's sessions need at real time
        dt = rows[0]["dt_frame"]
        cost = [engine_ms_per_frame("water2d", seed, frames) for seed in range(max(args.engine_seeds, *(r["sessions"] for r in rows)))]
        need = engine_cores(cost, dt)
        for r in rows:
            r["engine_ms_per_frame"] = cost[: r["sessions"]]
            r["engine_cores"] = need[r["sessions"] - 1]
        cores = float(os.cpu_count() or 1)
        out |= {"engine_ms_by_seed": cost, "engine_cores_by_count": need, "engine_bound": engine_bound(cost, dt, cores), "cores": cores}
        print("engine alone [ms/frame] by seed:", [round(x, 3) for x in cost], flush=True)
    return out


def markdown(doc: dict[str, Any]) -> str:
    rows = doc["rows"]
    r0 = rows[0]
    lines = [
        "# Capacity: real-time water2d sessions on one server"
        + (" (the Ray backend: one node of this machine's cores, a session an actor process)" if doc.get("backend") == "ray" else ""),
        "",
        f"water2d, solver `{r0['solver']}` ({r0['configuration'] or 'the scene default'}), session i of a rung on seed i "
        f"({min(min(r['particles']) for r in rows)} to {max(max(r['particles']) for r in rows)} particles: the scene's random blocks), real time = {1 / r0['dt_frame']:.0f} frames/s (dt_frame {r0['dt_frame'] * 1e3:g} ms); a session holds it at >= "
        f"{doc['real_time_share']:.2f}x. Each session has one WebSocket viewer playing it; step latency: one more session stepped "
        "one frame at a time (client round trip; engine: its X-Seconds). CPU in cores busy over the window. Each rung is run "
        f"{doc['repeats']} times; the table shows the best run (the slowest session's rate of every run in the third column). "
        f"Engine alone: the same seeds' simulators stepped {doc['engine_frames']} frames each in one process, one at a time; "
        "the cores their sessions need at real time (sum over the rung's seeds of the time per frame, times the frame rate).",
        "",
        f"**Sessions held at real time: {doc['capacity']}**",
        "",
    ]
    lines += table(
        [
            "sessions",
            "frames/s min",
            "min, every run",
            "frames/s median",
            "all real time",
            "step p50 [ms]",
            "step p95 [ms]",
            "engine p50 [ms]",
            "engine alone: cores needed",
            "server CPU",
            "event loop thread",
            "client CPU",
            "machine CPU",
            "load (1 min)",
        ],
        [
            [
                r["sessions"],
                f"{r['min_fps']:.0f}",
                " / ".join(f"{x:.0f}" for x in r["min_fps_runs"]),
                f"{r['median_fps']:.0f}",
                "yes" if r["all_real_time"] else "no",
                f"{r.get('step_p50_ms', float('nan')):.2f}",
                f"{r.get('step_p95_ms', float('nan')):.2f}",
                f"{r.get('engine_p50_ms', float('nan')):.2f}",
                f"{r['engine_cores']:.2f}" if "engine_cores" in r else "—",
                f"{r['server_cores']:.2f}",
                f"{r['loop_thread_share']:.2f}",
                f"{r['client_cores']:.2f}",
                f"{r['machine_cores']:.2f}",
                f"{r['load_1min']:.2f}",
            ]
            for r in sorted(rows, key=lambda r: r["sessions"])
        ],
        "rrrrlrrrrrrrrr",
    )
    if "engine_bound" in doc:
        need = doc["engine_cores_by_count"]
        lines += [
            "",
            f"**The engine alone bounds it at {doc['engine_bound']} sessions on {doc['cores']:.0f} cores**: seeds 0..N-1 stepped one at a "
            "time on one thread each, with no service at all, need at real time (cores, N = 1, 2, ...): "
            + ", ".join(f"{x:.2f}" for x in need)
            + "; ms a frame by seed: "
            + ", ".join(f"{x:.2f}" for x in doc["engine_ms_by_seed"])
            + ".",
        ]
    t = doc.get("scene3d")
    if t:
        lines += [
            "",
            f"{t['scene']}, solver `{t['solver']}` ({t['configuration'] or 'the scene default'}), {t['particles'][0]} particles, one session, one viewer: "
            f"**{t['min_fps']:.1f} frames/s** stepped (real time {1 / t['dt_frame']:.0f}); server CPU {t['server_cores']:.2f} cores, "
            f"event loop thread {t['loop_thread_share']:.2f}, load {t['load_1min']:.2f}.",
        ]
    return "\n".join(lines)


def main(argv: Sequence[str] | None = None) -> dict[str, Any]:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seconds", type=float, default=4.0, help="measured window per rung [s]")
    ap.add_argument("--warmup", type=float, default=1.5, help="playing before the window [s]")
    ap.add_argument("--most", type=int, default=40, help="the largest session count tried")
    ap.add_argument("--repeats", type=int, default=3, help="runs of each rung; the best is reported (all runs' slowest rates beside it)")
    ap.add_argument("--engine-frames", type=int, default=None, help="frames of the engine alone per seed (0: skip; default: warmup + window)")
    ap.add_argument("--engine-seeds", type=int, default=8, help="seeds of the engine alone at least (the engine's bound on the count is read from them)")
    ap.add_argument("--probe-gap", type=float, default=0.05, help="seconds between the probe's one-frame steps")
    ap.add_argument("--scene3d", default="dam_break3d", help='the 3D scene of the last figure ("" to skip)')
    ap.add_argument(
        "--realtime", action="store_true", help="the sessions in real-time mode (when_full coarser; give --warmup 8 or more: it settles in seconds)"
    )
    ap.add_argument("--quick", action="store_true", help="tiny settings (1 and 2 sessions, short windows, no 3D): a check that it runs")
    ap.add_argument("--out-dir", default=str(REPO_ROOT / "benchmarks" / "results"), help="capacity.md and capacity.json go here")
    ap.add_argument("--server-log", default=None, help="write the server's output here")
    ap.add_argument("--backend", choices=("local", "ray"), default="local", help="the sessions in the server's process, or actors of a one-node Ray cluster")
    ap.add_argument(
        "--ray-num-cpus", type=float, default=None, help="with --backend ray: the CPU each session's actor reserves (the service's default: 0.25, 8 on 2 cores)"
    )
    args = ap.parse_args(argv)
    if args.quick:
        args.seconds, args.warmup, args.most, args.repeats, args.scene3d, args.engine_frames, args.engine_seeds = 1.0, 0.5, 2, 1, "", 20, 2
    for name in ("seconds", "warmup", "probe_gap"):
        if not getattr(args, name) > 0:
            ap.error(f"--{name.replace('_', '-')}: must be > 0")
    if args.engine_frames is not None and args.engine_frames < 0:
        ap.error("--engine-frames: must be >= 0")
    if not 0 <= args.engine_seeds <= 64:
        ap.error("--engine-seeds: must be in [0, 64]")
    for name in ("most", "repeats"):
        if getattr(args, name) < 1:
            ap.error(f"--{name}: must be >= 1")
    doc = run(args)
    write_results(args.out_dir, "capacity", doc=doc, markdown=markdown(doc), argv=script_argv(__file__, argv))
    print(
        f"sessions held at real time: {doc['capacity']}; median over the rungs of the median rate {statistics.median(r['median_fps'] for r in doc['rows']):.0f}"
    )
    return doc


if __name__ == "__main__":
    main()
