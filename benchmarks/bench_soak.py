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
    args = ap.parse_args()
    seed = args.seed if args.seed is not None else random.SystemRandom().randrange(1 << 30)
    root = Path(tempfile.mkdtemp(prefix="hmsoak", dir="/tmp"))  # short: Ray's socket paths live under it
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
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / f"{args.backend}.json").write_text(json.dumps(summary, indent=1))
    print(json.dumps({k: v for k, v in summary.items() if k != "refusals"}, indent=1))
    if not all(checks.values()):
        raise SystemExit(f"soak failed: {[k for k, v in checks.items() if not v]}")


if __name__ == "__main__":
    main()
