"""Service benchmark: a real ``hybridmpm serve`` on 127.0.0.1 (child process).

Measures sessions held at once with step latency p50/p95 under that load
(every session stepping concurrently), memory per session (server RSS), frames
per second streamed to one WebSocket client (dam_break2d, and the 3D dam
break with its 23,520 particles), and sketch → first controlled
frame latency (as the client sees it on the stream).

    python benchmarks/bench_service.py [--sessions 100] [--rounds 5] [--out benchmarks/results/service.md]
"""

from __future__ import annotations

import argparse
import asyncio
import json
import time
from pathlib import Path

import httpx
import numpy as np
import websockets

from hybridmpm.bench.harness import write_results
from hybridmpm.service import decode_frame
from hybridmpm.service.testing import LiveServer

OCTET = {"Accept": "application/octet-stream"}


async def hold_and_step(srv: LiveServer, n: int, rounds: int, scene: str, solver: str) -> dict:
    async with httpx.AsyncClient(base_url=srv.url, timeout=600, limits=httpx.Limits(max_connections=n + 4)) as c:
        rss0 = srv.rss()
        t0 = time.perf_counter()
        ids = [(await c.post("/v1/sessions", json={"scene": scene, "seed": i, "solver": solver})).json()["id"] for i in range(n)]
        create_s = time.perf_counter() - t0
        rss1 = srv.rss()
        lat: list[float] = []

        async def step(sid: str) -> None:
            t = time.perf_counter()
            r = await c.post(f"/v1/sessions/{sid}/step", json={"frames": 1}, headers=OCTET)
            assert r.status_code == 200, r.text
            lat.append((time.perf_counter() - t) * 1e3)

        t1 = time.perf_counter()
        for _ in range(rounds):
            await asyncio.gather(*(step(s) for s in ids))
        wall = time.perf_counter() - t1
        threads = srv.threads()
        for s in ids:
            await c.delete(f"/v1/sessions/{s}")
    a = np.array(lat)
    return {
        "scene": scene,
        "solver": solver,
        "sessions": n,
        "create_s": create_s,
        "p50_ms": float(np.percentile(a, 50)),
        "p95_ms": float(np.percentile(a, 95)),
        "steps_per_s": len(a) / wall,
        "mib_per_session": (rss1 - rss0) / n / 2**20,
        "threads": threads,
    }


async def stream_rate(srv: LiveServer, scene: str, solver: str, seconds: float, control: bool = True) -> dict:
    """Frames streamed to one client of a playing session of ``scene`` for
    ``seconds``, and (``control``: a 2D scene) the latency of a sketch to the
    first controlled frame."""
    first, resp = None, {"first_frame_ms": None, "total_ms": None}
    async with httpx.AsyncClient(base_url=srv.url, timeout=600) as c:
        sid = (await c.post("/v1/sessions", json={"scene": scene, "solver": solver})).json()["id"]
        async with websockets.connect(f"{srv.ws_url}/v1/sessions/{sid}/stream", max_size=None) as ws:
            await ws.send('{"type": "play"}')
            n, solvers, frames = 0, [], []
            t_end = time.monotonic() + seconds
            while time.monotonic() < t_end:
                try:
                    m = await asyncio.wait_for(ws.recv(), max(0.01, t_end - time.monotonic()))
                except asyncio.TimeoutError:
                    break
                if isinstance(m, bytes):
                    h, _ = decode_frame(m)
                    n += 1
                    solvers.append(h.solver)
                    frames.append(h.frame)
            if control:  # sketch → first controlled frame on the stream
                body = {"sketch": {"kind": "arrow", "points": [[0.3, 0.4], [0.6, 0.4]]}, "method": "constant"}
                t0 = time.perf_counter()
                task = asyncio.create_task(c.post(f"/v1/sessions/{sid}/controls", json=body))
                while first is None:
                    m = await ws.recv()
                    if isinstance(m, bytes) and decode_frame(m)[0].controlled:
                        first = (time.perf_counter() - t0) * 1e3
                resp = (await task).json()
        await c.delete(f"/v1/sessions/{sid}")
    return {
        "scene": scene,
        "solver": solver,
        "fps_received": n / seconds,
        "sim_frames_per_s": (frames[-1] - frames[0]) / seconds if len(frames) > 1 else 0.0,
        "neural_share": float(np.mean([s == "neural" for s in solvers])) if solvers else 0.0,
        "sketch_to_first_controlled_frame_ms": first,
        "server_first_frame_ms": resp["first_frame_ms"],
        "control_total_ms": resp["total_ms"],
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sessions", type=int, default=100)
    ap.add_argument("--hybrid-sessions", type=int, default=8)
    ap.add_argument("--rounds", type=int, default=5)
    ap.add_argument("--seconds", type=float, default=5.0)
    ap.add_argument("--out", default=None, help="append a Markdown report here (FILE.md)")
    ap.add_argument("--server-log", default=None, help="write the server's output here")
    args = ap.parse_args()
    log = Path(args.server_log) if args.server_log else None
    with LiveServer(max_sessions=max(args.sessions, args.hybrid_sessions) + 4, log=log) as srv:
        rows = [
            asyncio.run(hold_and_step(srv, args.sessions, args.rounds, "water2d", "mpm")),
            asyncio.run(hold_and_step(srv, args.hybrid_sessions, args.rounds, "dam_break2d", "hybrid")),
        ]
        streams = [
            asyncio.run(stream_rate(srv, "dam_break2d", "mpm", args.seconds)),
            asyncio.run(stream_rate(srv, "dam_break2d", "hybrid", args.seconds)),
            asyncio.run(stream_rate(srv, "dam_break3d", "mpm", args.seconds, control=False)),  # the page's 3D dam break
        ]
    print(json.dumps({"load": rows, "stream": streams}, indent=2))
    if args.out:
        lines = [
            "\n## Sessions held, stepping and streaming\n",
            "| scene | solver | sessions held | create all [s] | step p50 [ms] | step p95 [ms] | steps/s (all) | MiB / session | server threads |",
            "|---|---|---:|---:|---:|---:|---:|---:|---:|",
        ]
        for r in rows:
            lines.append(
                f"| {r['scene']} | {r['solver']} | {r['sessions']} | {r['create_s']:.1f} | {r['p50_ms']:.0f} | {r['p95_ms']:.0f} | {r['steps_per_s']:.1f} | {r['mib_per_session']:.2f} | {r['threads']} |"
            )
        lines += [
            "",
            "| scene | solver | frames/s to one client | simulated frames/s | neural share | sketch → first controlled frame [ms] (client) | (server) | control of 100 frames [ms] |",
            "|---|---|---:|---:|---:|---:|---:|---:|",
        ]
        for s in streams:
            ms = ["—" if s[k] is None else f"{s[k]:.0f}" for k in ("sketch_to_first_controlled_frame_ms", "server_first_frame_ms", "control_total_ms")]
            lines.append(
                f"| {s['scene']} | {s['solver']} | {s['fps_received']:.1f} | {s['sim_frames_per_s']:.0f} | {s['neural_share']:.2f} | {ms[0]} | {ms[1]} | {ms[2]} |"
            )
        out = Path(args.out)
        write_results(out.parent, out.stem, markdown="\n".join(lines), append=True)


if __name__ == "__main__":
    main()
