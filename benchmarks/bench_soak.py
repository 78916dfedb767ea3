"""A soak of the service: 16 mixed sessions driven by 6 clients for minutes
(steps, controls of every method, checkpoint round trips, downloads, stream
views, deletes during 1000-frame controls) and a witness session compared
bit for bit with an uninterrupted run (:func:`hybridmpm.service.testing.soak`),
on a durable server (``--store``, ``--save-every 1``) or a front end of a
two-node local Ray cluster. Prints the answers by status, and checks: no 5xx,
every control whose session was deleted answered 404, the memory budget's
ledger back at its start, the witness bitwise.

    python benchmarks/bench_soak.py --backend local --seconds 180 [--out benchmarks/results/soak]
    python benchmarks/bench_soak.py --backend ray --seconds 180

``--restarts`` runs the restart soak instead (:func:`restart_soak`, one
durable local server): sessions with obstacles (2D and 3D, MPM and hybrid)
and without, driven with steps, obstacle moves, checkpoint round trips
(with moves pending) while the server is stopped every 20-45 s, at random
by SIGTERM (after the requests in flight are answered: a clean stop must
lose nothing, so every session must come back at its last answered frame)
or by SIGKILL (at any moment: a session may come back at most
``--save-every`` seconds of stepping behind), then started again on its
store. Counts the sessions lost (404 after a restart; the promise is none)
and the frames a clean stop lost (none):

    python benchmarks/bench_soak.py --restarts --seconds 600 [--out benchmarks/results/soak]
"""

from __future__ import annotations

import argparse
import asyncio
import json
import random
import secrets
import shutil
import tempfile
import time
from pathlib import Path

import numpy as np

from hybridmpm.bench.harness import write_results
from hybridmpm.service.testing import SOAK_WITNESS, LiveServer, RayCluster, soak
from hybridmpm.sim import make_simulator, rollout


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--backend", choices=["local", "ray"], default="local")
    ap.add_argument("--seconds", type=float, default=180.0)
    ap.add_argument("--sessions", type=int, default=16)
    ap.add_argument("--workers", type=int, default=6)
    ap.add_argument("--seed", type=int, default=None, help="the mix's random seed (default: a fresh one, printed)")
    ap.add_argument("--out", default="benchmarks/results/soak")
    ap.add_argument("--restarts", action="store_true", help="the restart soak (local backend): obstacle moves, checkpoints, SIGTERM and SIGKILL restarts")
    ap.add_argument("--save-every", type=float, default=1.0, help="--restarts: the server's --save-every [s]")
    args = ap.parse_args()
    seed = args.seed if args.seed is not None else random.SystemRandom().randrange(1 << 30)
    root = Path(tempfile.mkdtemp(prefix="hmsoak", dir="/tmp"))  # short: Ray's socket paths live under it
    if args.restarts:
        main_restarts(args, seed, root)
        return
    common = ["--store", str(root / "store"), "--save-every", "1"]
    t0 = time.monotonic()
    try:
        if args.backend == "local":
            with LiveServer(max_sessions=64, args=common, log=root / "server.log") as srv:
                rep = asyncio.run(soak(srv.url, args.seconds, args.sessions, args.workers, seed))
        else:
            with RayCluster(root / "ray", secrets.token_hex(16), nodes=2, num_cpus=4) as cluster:
                fe = ["--backend", "ray", "--ray-address", cluster.address, *common]
                env = {"RAY_AUTH_MODE": "token", "RAY_AUTH_TOKEN": cluster.token}
                with LiveServer(max_sessions=64, args=fe, env=env, log=root / "front.log").start(180.0) as srv:
                    rep = asyncio.run(soak(srv.url, args.seconds, args.sessions, args.workers, seed))
    finally:
        shutil.rmtree(root, ignore_errors=True)
    took = time.monotonic() - t0
    scene, solver, wseed = SOAK_WITNESS
    ref = rollout(make_simulator(scene, solver, seed=wseed, threads=1, nn_threads=1), len(rep["witness"])).positions[1:]
    checks = {
        "no_5xx": not any(int(code) >= 500 for code in rep["statuses"]),
        "deleted_controls_404": all(code == 404 for code in rep["deleted_controls"]),
        "ledger_back_at_start": rep["memory_used_end"] == rep["memory_used_start"],
        "witness_bitwise": bool(len(ref) > 0 and np.array_equal(ref, rep["witness"])),
    }
    summary = {
        "backend": args.backend,
        "seconds": args.seconds,
        "wall_s": round(took, 1),
        "sessions": args.sessions,
        "workers": args.workers,
        "seed": seed,
        "operations": rep["ops"],
        "statuses": {str(k): v for k, v in sorted(rep["statuses"].items())},
        "deleted_controls": rep["deleted_controls"],
        "witness_frames": len(rep["witness"]),
        "refusals": rep["refusals"],
        "checks": checks,
    }
    write_results(args.out, args.backend, doc=summary)
    print(json.dumps({k: v for k, v in summary.items() if k != "refusals"}, indent=1))
    if not all(checks.values()):
        raise SystemExit(f"soak failed: {[k for k, v in checks.items() if not v]}")


#: The restart soak's sessions (scene, solver), cycled; the first four have an obstacle to move.
RESTART_MIX = [
    ("water_ramps2d", "mpm"),
    ("paddle3d", "mpm"),
    ("water_ramps2d", "hybrid"),
    ("sand_ramps2d", "mpm"),
    ("water2d", "mpm"),
    ("dam_break2d", "hybrid"),
]
#: Bounds on waiting for the server (never a pass/fail threshold on time).
WAIT_S = 300.0


async def restart_soak(root: Path, seconds: float, sessions: int, workers: int, seed: int, save_every: float) -> dict:
    """The restart soak (see the module's docstring) on a store under ``root``; returns its counts and one row per restart."""
    import signal

    import httpx

    rng = random.Random(seed)
    args = ["--store", str(root / "store"), "--save-every", str(save_every), "--log-level", "info"]
    loop = asyncio.get_running_loop()
    n_server = 0

    def start() -> LiveServer:
        nonlocal n_server
        n_server += 1
        return LiveServer(max_sessions=64, ttl=3600.0, args=args, log=root / f"server{n_server}.log").start(WAIT_S)

    server = await loop.run_in_executor(None, start)
    state = {"url": server.url}
    statuses: dict[int, int] = {}
    refusals: list[str] = []
    ops = {"step": 0, "move": 0, "checkpoint": 0, "move_checkpoint": 0, "interrupted": 0}
    last: dict[str, int] = {}  # each session's last answered frame
    home: dict[str, list[float]] = {}  # where its obstacle started
    up = asyncio.Event()
    up.set()
    busy: set[str] = set()
    restarts: list[dict] = []

    def seen(r: httpx.Response) -> httpx.Response:
        statuses[r.status_code] = statuses.get(r.status_code, 0) + 1
        if r.status_code >= 400:
            refusals.append(f"{r.request.method} {r.request.url.path.rsplit('/', 1)[-1]}: {r.status_code} {r.text[:160]}")
        return r

    async with httpx.AsyncClient(timeout=WAIT_S) as c:
        sids = []
        for k in range(sessions):
            scene, solver = RESTART_MIX[k % len(RESTART_MIX)]
            r = seen(await c.post(f"{state['url']}/v1/sessions", json={"scene": scene, "solver": solver, "seed": rng.randrange(1000)}))
            assert r.status_code == 201, r.text[:300]
            sid = r.json()["id"]
            sids.append(sid)
            last[sid] = 0
            if r.json()["obstacle_centers"]:
                home[sid] = r.json()["obstacle_centers"][0]
        t_end = time.monotonic() + seconds

        async def move(sid: str) -> None:
            info = seen(await c.get(f"{state['url']}/v1/sessions/{sid}"))
            if info.status_code != 200:
                return
            now = info.json()["obstacle_centers"][0]
            target = [min(max(h + rng.uniform(-0.03, 0.03), 0.05), 0.95) for h in home[sid]]
            step = [n + max(-0.005, min(0.005, t - n)) for n, t in zip(now, target)]
            seen(await c.put(f"{state['url']}/v1/sessions/{sid}/obstacles/0", json={"center": step}))

        async def op(sid: str) -> None:
            kind = rng.choice(["step", "step", "move", "checkpoint", "move_checkpoint"] if sid in home else ["step", "step", "checkpoint"])
            ops[kind] += 1
            if kind in ("move", "move_checkpoint"):
                await move(sid)
            if kind in ("checkpoint", "move_checkpoint"):
                got = seen(await c.get(f"{state['url']}/v1/sessions/{sid}/checkpoint"))
                if got.status_code == 200:
                    seen(await c.put(f"{state['url']}/v1/sessions/{sid}/checkpoint", content=got.content, headers={"Content-Type": "application/octet-stream"}))
            if kind == "step":
                r = seen(
                    await c.post(f"{state['url']}/v1/sessions/{sid}/step", json={"frames": rng.randint(1, 10)}, headers={"Accept": "application/octet-stream"})
                )
                if r.status_code == 200:
                    last[sid] = int(r.headers["x-frames"].split(",")[-1])

        async def worker() -> None:
            while time.monotonic() < t_end:
                await up.wait()
                free = [s for s in sids if s not in busy]
                if not free:
                    await asyncio.sleep(0.01)
                    continue
                sid = rng.choice(free)
                busy.add(sid)
                try:
                    await op(sid)
                except httpx.HTTPError:
                    ops["interrupted"] += 1  # the server was killed under it
                    await asyncio.sleep(0.2)
                finally:
                    busy.discard(sid)

        async def restarter() -> None:
            nonlocal server
            while time.monotonic() < t_end - 30:
                await asyncio.sleep(rng.uniform(20, 45))
                how = rng.choice(["sigterm", "sigkill"])
                up.clear()
                if how == "sigterm":
                    while busy:  # a clean stop after the answers in flight: it must lose nothing
                        await asyncio.sleep(0.05)
                    answered = dict(last)
                    server.proc.send_signal(signal.SIGTERM)  # the clean stop saves every changed session: waited for however long it takes
                    await loop.run_in_executor(None, server.proc.wait)
                    await loop.run_in_executor(None, server.stop)
                else:
                    answered = dict(last)
                    server.proc.send_signal(signal.SIGKILL)
                    await loop.run_in_executor(None, server.proc.wait)
                    await loop.run_in_executor(None, server.stop)
                t0 = time.monotonic()
                server = await loop.run_in_executor(None, start)
                state["url"] = server.url
                row = {"how": how, "restart_s": round(time.monotonic() - t0, 2), "lost": [], "behind": {}}
                for sid in sids:
                    r = await c.get(f"{state['url']}/v1/sessions/{sid}")
                    if r.status_code != 200:
                        row["lost"].append(sid[:6])
                        continue
                    frame = int(r.json()["frame"])
                    last[sid] = frame
                    if frame != answered[sid]:
                        row["behind"][sid[:6]] = answered[sid] - frame
                restarts.append(row)
                print(f"restart {len(restarts)} ({how}): back in {row['restart_s']} s, lost {len(row['lost'])}, behind {row['behind']}", flush=True)
                up.set()

        try:
            await asyncio.gather(restarter(), *(worker() for _ in range(workers)))
        finally:
            await loop.run_in_executor(None, server.stop)
    return {"ops": ops, "statuses": statuses, "refusals": refusals, "restarts": restarts, "sessions": sessions}


def main_restarts(args: argparse.Namespace, seed: int, root: Path) -> None:
    """Run :func:`restart_soak`, write ``restarts.json`` under ``--out``, fail on a lost session or a clean stop that lost frames."""
    t0 = time.monotonic()
    try:
        rep = asyncio.run(restart_soak(root, args.seconds, min(args.sessions, 8), args.workers, seed, args.save_every))
    finally:
        shutil.rmtree(root, ignore_errors=True)
    rows = rep["restarts"]
    kills = [r for r in rows if r["how"] == "sigkill"]
    checks = {
        "no_session_lost": not any(r["lost"] for r in rows),
        "clean_stops_lose_nothing": not any(r["behind"] for r in rows if r["how"] == "sigterm"),
        "no_5xx": not any(int(code) >= 500 for code in rep["statuses"]),
    }
    summary = {
        "mode": "restarts",
        "seconds": args.seconds,
        "wall_s": round(time.monotonic() - t0, 1),
        "sessions": rep["sessions"],
        "workers": args.workers,
        "save_every_s": args.save_every,
        "seed": seed,
        "operations": rep["ops"],
        "statuses": {str(k): v for k, v in sorted(rep["statuses"].items())},
        "restarts": {"sigterm": len(rows) - len(kills), "sigkill": len(kills)},
        "sessions_lost": sum(len(r["lost"]) for r in rows),
        "most_frames_behind_after_sigkill": max((max(r["behind"].values(), default=0) for r in kills), default=0),
        "rows": rows,
        "refusals": rep["refusals"][:50],
        "checks": checks,
    }
    write_results(args.out, "restarts", doc=summary)
    print(json.dumps({k: v for k, v in summary.items() if k not in ("rows", "refusals")}, indent=1))
    if not all(checks.values()):
        raise SystemExit(f"restart soak failed: {[k for k, v in checks.items() if not v]}")


if __name__ == "__main__":
    main()
