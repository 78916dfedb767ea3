"""Sessions on a Ray cluster against one process: how many sessions each
backend holds with every session stepping at >= 30 steps/s.

For the local backend (one ``hybridmpm serve`` process) and for the ray
backend (one front end, ``hybridmpm serve --backend ray``, on a local Ray
cluster of 1 and of 2 node processes on this machine) and two workloads
(water2d MPM; the dam break with the hybrid solver), N sessions are created
and each is stepped by its own client in a closed loop (``POST /step
{frames: 1}``, binary answer: one coarse step, 1 frame of 2.5 ms for water2d
MPM, r_t = 4 frames for the hybrid) for ``--seconds``; N grows through
``--levels`` until the slowest session falls under ``--rate`` steps/s.
Reported per level: each session's steps/s (the slowest and the median), step
latency p50/p95 at that load, memory per session (local: the server's RSS
growth / N; ray: the private memory of the sessions' actor processes / N,
plus the front end's RSS growth / N). For the ray backend also the time
from an actor's death (SIGKILL of its process) to its session answering a
step again (restored from its last save), per workload.

    python benchmarks/bench_cluster.py [--seconds 5] [--levels 1,2,4,8,12,16,24,32] [--out benchmarks/results/service.md]
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import secrets
import shutil
import signal
import tempfile
import time
from pathlib import Path

import httpx
import numpy as np

from hybridmpm.bench.harness import write_results
from hybridmpm.service.testing import LiveServer, RayCluster, cpu_seconds, private_bytes

OCTET = {"Accept": "application/octet-stream"}
WORKLOADS = [("water2d", "mpm"), ("dam_break2d", "hybrid")]


async def level(srv: LiveServer, cluster: RayCluster | None, scene: str, solver: str, n: int, seconds: float) -> dict:
    """``n`` sessions stepping at once for ``seconds``: rates, latencies, memory."""
    async with httpx.AsyncClient(base_url=srv.url, timeout=600, limits=httpx.Limits(max_connections=n + 4)) as c:
        rss0 = srv.rss()
        t0 = time.perf_counter()
        made = await asyncio.gather(*(c.post("/v1/sessions", json={"scene": scene, "seed": i, "solver": solver}) for i in range(n)))
        create_s = time.perf_counter() - t0
        if any(r.status_code != 201 for r in made):
            bad = next(r for r in made if r.status_code != 201)
            for r in made:
                if r.status_code == 201:
                    await c.delete(f"/v1/sessions/{r.json()['id']}")
            return {"sessions": n, "error": f"{bad.status_code} {bad.text[:160]}"}
        ids = [r.json()["id"] for r in made]
        for sid in ids:  # one step each first: warm (the hybrid's first network step loads more)
            await c.post(f"/v1/sessions/{sid}/step", json={"frames": 1}, headers=OCTET)
        lat: list[float] = []
        counts = dict.fromkeys(ids, 0)
        t_end = time.perf_counter() + seconds

        async def loop(sid: str) -> None:
            while time.perf_counter() < t_end:
                t = time.perf_counter()
                r = await c.post(f"/v1/sessions/{sid}/step", json={"frames": 1}, headers=OCTET)
                assert r.status_code == 200, r.text
                lat.append((time.perf_counter() - t) * 1e3)
                counts[sid] += 1

        actors = cluster.actor_pids() if cluster is not None else []
        cpu0 = cpu_seconds([srv.proc.pid]), cpu_seconds(actors)
        t1 = time.perf_counter()
        await asyncio.gather(*(loop(s) for s in ids))
        wall = time.perf_counter() - t1
        cpu1 = cpu_seconds([srv.proc.pid]), cpu_seconds(actors)
        rss1 = srv.rss()
        actor_private = sum(private_bytes(p) for p in actors)
        for s in ids:
            await c.delete(f"/v1/sessions/{s}")
    rates = np.array([counts[s] / wall for s in ids])
    a = np.array(lat)
    per_session = (rss1 - rss0 + actor_private) / n
    steps = max(1, len(a))
    return {
        "sessions": n,
        "create_s": create_s,
        "min_rate": float(rates.min()),
        "median_rate": float(np.median(rates)),
        "total_rate": float(rates.sum()),
        "p50_ms": float(np.percentile(a, 50)),
        "p95_ms": float(np.percentile(a, 95)),
        "mib_per_session": per_session / 2**20,
        "actors": len(actors),
        "server_cpu_ms_per_step": (cpu1[0] - cpu0[0]) / steps * 1e3,
        "actor_cpu_ms_per_step": (cpu1[1] - cpu0[1]) / steps * 1e3,
    }


async def death_to_answer(srv: LiveServer, cluster: RayCluster, scene: str, solver: str, repeats: int) -> list[float]:
    """Seconds from SIGKILL of a session's actor process to its next step answered."""
    out = []
    async with httpx.AsyncClient(base_url=srv.url, timeout=600) as c:
        sid = (await c.post("/v1/sessions", json={"scene": scene, "solver": solver})).json()["id"]
        for _ in range(repeats):
            await c.post(f"/v1/sessions/{sid}/step", json={"frames": 4}, headers=OCTET)
            while True:
                info = (await c.get(f"/v1/sessions/{sid}")).json()
                if info["saved_frame"] == info["frame"]:
                    break
                await asyncio.sleep(0.05)
            pids = cluster.actor_pids()
            assert len(pids) == 1, pids
            os.kill(pids[0], signal.SIGKILL)
            t = time.perf_counter()
            r = await c.post(f"/v1/sessions/{sid}/step", json={"frames": 1}, headers=OCTET)
            out.append(time.perf_counter() - t)
            assert r.status_code == 200, r.text
            assert (await c.get(f"/v1/sessions/{sid}")).json()["restored_from_frame"] == info["frame"]
        await c.delete(f"/v1/sessions/{sid}")
    return out


def run_backend(name: str, srv: LiveServer, cluster: RayCluster | None, args: argparse.Namespace) -> dict:
    rows = []
    for scene, solver in WORKLOADS:
        held = None
        for n in args.levels:
            r = {"backend": name, "scene": scene, "solver": solver, **asyncio.run(level(srv, cluster, scene, solver, n, args.seconds))}
            print(json.dumps(r), flush=True)
            rows.append(r)
            if "error" in r or r["min_rate"] < args.rate:
                break
            held = r
        rows.append({"backend": name, "scene": scene, "solver": solver, "held": held["sessions"] if held else 0, "summary": True})
    deaths = {}
    if cluster is not None:
        for scene, solver in WORKLOADS:
            deaths[f"{scene} {solver}"] = asyncio.run(death_to_answer(srv, cluster, scene, solver, args.repeats))
            print(name, scene, solver, "death → answer [s]", deaths[f"{scene} {solver}"], flush=True)
    return {"rows": rows, "deaths": deaths}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seconds", type=float, default=5.0, help="stepping time per level")
    ap.add_argument("--levels", default="1,2,4,8,12,16,24,32", help="session counts tried, in order, until one falls under --rate")
    ap.add_argument("--rate", type=float, default=30.0, help="steps/s every session must hold")
    ap.add_argument("--repeats", type=int, default=3, help="actor deaths per workload")
    ap.add_argument("--backends", default="local,ray1,ray2", help="local, ray1 (one node process), ray2 (two)")
    ap.add_argument("--num-cpus", type=int, default=16, help="logical CPUs of each node process (the sessions' placement, not the machine's cores)")
    ap.add_argument("--out", default=None, help="append a Markdown report here (FILE.md)")
    args = ap.parse_args()
    args.levels = [int(x) for x in args.levels.split(",")]
    results = {}
    big = max(args.levels) + 4
    for name in args.backends.split(","):
        tmp = Path(tempfile.mkdtemp(prefix="hmbench", dir="/tmp"))
        try:
            if name == "local":
                with LiveServer(max_sessions=big, log=tmp / "server.log") as srv:
                    results[name] = run_backend(name, srv, None, args)
                continue
            nodes = int(name[3:])
            cluster = RayCluster(tmp, secrets.token_hex(16), nodes=nodes, num_cpus=args.num_cpus, object_store_bytes=200 << 20)
            with cluster:
                fe_args = ["--backend", "ray", "--ray-address", cluster.address, "--store", str(tmp / "store"), "--save-every", "1"]
                env = {"RAY_AUTH_MODE": "token", "RAY_AUTH_TOKEN": cluster.token}
                with LiveServer(max_sessions=big, args=fe_args, env=env, log=tmp / "front.log").start(timeout=300) as srv:
                    results[name] = run_backend(name, srv, cluster, args)
        finally:
            shutil.rmtree(tmp, ignore_errors=True)
    print(json.dumps(results, indent=1))
    if args.out:
        write(args, results)


def cluster_row(name: str) -> bool:
    return name != "local"


def write(args: argparse.Namespace, results: dict) -> None:
    names = {"local": "local (1 process)", "ray1": "ray, 1 node process", "ray2": "ray, 2 node processes"}
    lines = [
        "\n## Sessions on a Ray cluster\n",
        "The machine is shared with other jobs (the load average before and after above).\n",
        "Each session stepped by its own client in a closed loop, `POST /step {frames: 1}` with a binary answer: one coarse step "
        '(water2d MPM: 1 frame of 2.5 ms; dam break hybrid: r_t = 4 frames). "Held": the most sessions with every one at '
        f">= {args.rate:g} steps/s. Ray: one front end, sessions of 0.25 CPU, node processes of {args.num_cpus} logical CPUs all on "
        "this machine's cores (the nodes share them: the rows show the backend's cost, not more cores). Memory: local, the server's RSS "
        "growth per session; ray, the actor processes' private memory + the front end's RSS growth, per session. "
        "CPU / step: the CPU time the server (local) or the front end (ray) and the sessions' actors used while stepping, per step "
        "answered: what a step costs whatever else runs on the machine.\n",
        "| backend | scene | solver | sessions | slowest session [steps/s] | median [steps/s] | all [steps/s] | step p50 [ms] | step p95 [ms] "
        "| CPU / step: server or front end [ms] | CPU / step: actor [ms] | MiB / session | create all [s] |",
        "|---|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    held = []
    for name, res in results.items():
        for r in res["rows"]:
            if r.get("summary"):
                held.append(f"{names[name]}, {r['scene']} {r['solver']}: **{r['held']}**")
                continue
            if "error" in r:
                lines.append(f"| {names[name]} | {r['scene']} | {r['solver']} | {r['sessions']} | refused: {r['error'][:80]} | | | | | | | | |")
                continue
            lines.append(
                f"| {names[name]} | {r['scene']} | {r['solver']} | {r['sessions']} | {r['min_rate']:.1f} | {r['median_rate']:.1f} | {r['total_rate']:.0f} "
                f"| {r['p50_ms']:.1f} | {r['p95_ms']:.1f} | {r['server_cpu_ms_per_step']:.2f} | {r['actor_cpu_ms_per_step'] if cluster_row(name) else 0:.2f} "
                f"| {r['mib_per_session']:.1f} | {r['create_s']:.1f} |"
            )
    lines += ["", f"Sessions held at >= {args.rate:g} steps/s each: " + "; ".join(held) + ".", ""]
    proj = []
    for name, res in results.items():
        for scene, solver in WORKLOADS:
            rows = [r for r in res["rows"] if not r.get("summary") and "error" not in r and r["scene"] == scene]
            if rows:
                r = max(rows, key=lambda x: x["sessions"])
                ms = r["server_cpu_ms_per_step"] + (r["actor_cpu_ms_per_step"] if cluster_row(name) else 0.0)
                proj.append(f"{names[name]}, {scene} {solver}: {ms:.2f} ms of CPU per step → {1000.0 / (args.rate * ms):.1f} sessions per core")
    if proj:
        lines += [f"Projected per core (CPU time per step, at {args.rate:g} steps/s each): " + "; ".join(proj) + ".", ""]
    deaths = [(names[n], k, v) for n, res in results.items() for k, v in res["deaths"].items()]
    if deaths:
        lines += ["| backend | workload | actor death → session answering a step [s] (each kill) | median |", "|---|---|---|---:|"]
        for n, k, v in deaths:
            lines.append(f"| {n} | {k} | {', '.join(f'{x:.2f}' for x in v)} | {float(np.median(v)):.2f} |")
    out = Path(args.out)
    write_results(out.parent, out.stem, markdown="\n".join(lines), append=True)


if __name__ == "__main__":
    main()
