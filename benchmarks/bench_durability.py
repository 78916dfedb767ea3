"""What a crash loses: SIGKILLs at random moments against durable sessions
(``hybridmpm serve --store``), measured as the seconds of answered stepping
that a session does not have once it is back.

Each round, clients step three sessions one frame at a time (a water2d MPM,
a dam_break2d hybrid and a sand2d MPM session) and a fourth session runs
1000-frame controls back to back (a control holds its session for seconds;
it must delay no other session's save). After a random moment (uniform in
``[--min-wait, --max-wait]`` seconds) a process is killed with SIGKILL:

- ``local``: the server itself; it is started again on the same store and
  restores every session.
- ``ray``: one session actor of a two-node local cluster (chosen at random,
  the controlled session's included); the front end builds it again from the
  store while clients retry.

For every stepped session the loss is the span of answered steps it no
longer has: from the answer that reached the frame it came back at to the
last answer before the kill (0 when it came back at its last answered
frame). The promise (docs/durability.md) is a loss of at most ``--save-every``
seconds; the table gives the worst loss per kill and over all kills, with
the save interval beside it.

    python benchmarks/bench_durability.py --backend local --kills 20 [--save-every 1] [--out benchmarks/results/durability]
    python benchmarks/bench_durability.py --backend ray --kills 20
"""

from __future__ import annotations

import argparse
import os
import random
import shutil
import signal
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import httpx

from hybridmpm.bench.harness import write_results
from hybridmpm.service.testing import LiveServer, RayCluster

STEPPED = [("water2d", "mpm", 11), ("dam_break2d", "hybrid", 12), ("sand2d", "mpm", 13)]
CONTROLLED = ("dam_break2d", "mpm", 14)
ARROW = {"kind": "arrow", "points": [[0.3, 0.3], [0.6, 0.4]]}
OCTET = {"Accept": "application/octet-stream"}
WAIT_S = 180.0


class Stepper(threading.Thread):
    """Steps one session a frame at a time until stopped; keeps (frame reached, time answered) of every 200."""

    def __init__(self, url: str, sid: str) -> None:
        super().__init__(daemon=True)
        self.url, self.sid = url, sid
        self.answers: list[tuple[int, float]] = []
        self.errors: list[int] = []
        self.halt = threading.Event()

    def run(self) -> None:
        with httpx.Client(base_url=self.url, timeout=WAIT_S) as c:
            while not self.halt.is_set():
                try:
                    r = c.post(f"/v1/sessions/{self.sid}/step", json={"frames": 1}, headers=OCTET)
                except httpx.HTTPError:
                    time.sleep(0.05)  # the server is down (local kill): its loss is measured after
                    continue
                if r.status_code == 200:
                    self.answers.append((int(r.headers["x-frames"].split(",")[-1]), time.monotonic()))
                else:
                    if r.status_code >= 500 and r.status_code != 503:
                        self.errors.append(r.status_code)
                    time.sleep(0.1)


class Controller(threading.Thread):
    """Runs 1000-frame controls on one session back to back until stopped."""

    def __init__(self, url: str, sid: str) -> None:
        super().__init__(daemon=True)
        self.url, self.sid = url, sid
        self.halt = threading.Event()
        self.done = 0

    def run(self) -> None:
        with httpx.Client(base_url=self.url, timeout=WAIT_S) as c:
            while not self.halt.is_set():
                try:
                    r = c.post(f"/v1/sessions/{self.sid}/controls", json={"sketch": ARROW, "frames": 1000})
                    self.done += r.status_code == 200
                    if r.status_code != 200:
                        time.sleep(0.2)
                except httpx.HTTPError:
                    time.sleep(0.2)


def loss_s(answers: list[tuple[int, float]], t_start: float, t_kill: float, back_at: int) -> float:
    """Seconds of answered stepping lost: from the answer that reached frame ``back_at`` (or the round's start
    ``t_start``, when it came back at a frame answered before this round) to the last answer before the kill."""
    before = [(f, t) for f, t in answers if t <= t_kill]
    if not before or back_at >= before[-1][0]:
        return 0.0
    reached = [t for f, t in before if f <= back_at]
    return before[-1][1] - (reached[-1] if reached else t_start)


def info_of(c: httpx.Client, sid: str) -> dict[str, Any]:
    """The session's description once it answers again (a Ray actor being restored answers 503 until it is back)."""
    deadline = time.monotonic() + WAIT_S
    while time.monotonic() < deadline:
        try:
            r = c.get(f"/v1/sessions/{sid}")
            if r.status_code == 200:
                return dict(r.json())
        except httpx.HTTPError:
            pass
        time.sleep(0.1)
    raise RuntimeError(f"session {sid[:6]}… did not come back within {WAIT_S} s")


def create(c: httpx.Client, scene: str, solver: str, seed: int) -> str:
    r = c.post("/v1/sessions", json={"scene": scene, "solver": solver, "seed": seed})
    r.raise_for_status()
    return str(r.json()["id"])


def start_round(url: str, sids: list[str], csid: str, args: argparse.Namespace, rng: random.Random) -> tuple[list[Stepper], Controller, float]:
    """Start a round's clients (a stepper per stepped session, the controller on ``csid``) and wait the random
    time to the kill: (steppers, controller, the round's start)."""
    steppers = [Stepper(url, sid) for sid in sids]
    ctl = Controller(url, csid)
    t_start = time.monotonic()
    for t in (*steppers, ctl):
        t.start()
    time.sleep(rng.uniform(args.min_wait, args.max_wait))
    return steppers, ctl, t_start


def stop_round(steppers: list[Stepper], ctl: Controller) -> None:
    """Stop a round's clients and wait for them (after the kill)."""
    clients: list[Stepper | Controller] = [*steppers, ctl]
    for t in clients:
        t.halt.set()
    for t in clients:
        t.join(WAIT_S)


def round_row(k: int, args: argparse.Namespace, killed: str, said: str, losses: list[float], steppers: list[Stepper], ctl: Controller) -> dict[str, Any]:
    """A round's row of the results (``killed``), printed as a line (``said``: what was killed)."""
    row = {"kill": k, "killed": killed, "loss_s": losses, "errors_5xx": sum(len(s.errors) for s in steppers), "controls_done": ctl.done}
    print(f"kill {k + 1}/{args.kills}: {said}; lost {max(losses):.2f} s (per session {', '.join(f'{x:.2f}' for x in losses)})", flush=True)
    return row


def run_local(args: argparse.Namespace, root: Path, rng: random.Random) -> list[dict[str, Any]]:
    store = root / "store"

    def server() -> LiveServer:
        return LiveServer(max_sessions=8, args=["--store", str(store), "--save-every", str(args.save_every)], log=root / "server.log").start(WAIT_S)

    srv = server()
    with httpx.Client(base_url=srv.url, timeout=WAIT_S) as c:
        sids = [create(c, *spec) for spec in STEPPED]
        csid = create(c, *CONTROLLED)
    rows = []
    for k in range(args.kills):
        steppers, ctl, t_start = start_round(srv.url, sids, csid, args, rng)
        t_kill = time.monotonic()
        srv.proc.send_signal(signal.SIGKILL)
        srv.proc.wait(WAIT_S)
        stop_round(steppers, ctl)
        srv.stop()
        srv = server()
        with httpx.Client(base_url=srv.url, timeout=WAIT_S) as c:
            back = [int(info_of(c, sid)["frame"]) for sid in sids]
        losses = [loss_s(s.answers, t_start, t_kill, b) for s, b in zip(steppers, back)]
        rows.append(round_row(k, args, "server", "the server", losses, steppers, ctl))
    srv.stop()
    return rows


def run_ray(args: argparse.Namespace, root: Path, rng: random.Random) -> list[dict[str, Any]]:
    import secrets

    ray_root = Path(tempfile.mkdtemp(prefix="hmray", dir="/tmp"))  # short: Ray's socket paths live under it
    rows = []
    with RayCluster(ray_root, secrets.token_hex(16), nodes=2, num_cpus=2, timeout=WAIT_S) as cluster:
        fe_args = ["--backend", "ray", "--ray-address", cluster.address, "--store", str(root / "store"), "--save-every", str(args.save_every)]
        env = {"RAY_AUTH_MODE": "token", "RAY_AUTH_TOKEN": cluster.token}
        with LiveServer(max_sessions=8, args=fe_args, env=env, log=root / "front.log").start(WAIT_S) as srv:
            with httpx.Client(base_url=srv.url, timeout=WAIT_S) as c:
                sids = [create(c, *spec) for spec in STEPPED]
                csid = create(c, *CONTROLLED)
                for k in range(args.kills):
                    steppers, ctl, t_start = start_round(srv.url, sids, csid, args, rng)
                    restored_before = [info_of(c, sid)["restored_from_frame"] for sid in sids]
                    pids = sorted(cluster.actor_pids())
                    victim = rng.choice(pids)
                    t_kill = time.monotonic()
                    os.kill(victim, signal.SIGKILL)
                    time.sleep(1.0)  # its clients see it gone and retry until it is back
                    stop_round(steppers, ctl)
                    # a session whose actor was built again says from which saved frame (the others lost nothing)
                    after = [info_of(c, sid)["restored_from_frame"] for sid in sids]
                    losses = [
                        loss_s(s.answers, t_start, t_kill, int(b)) if b is not None and b != b0 else 0.0 for s, b, b0 in zip(steppers, after, restored_before)
                    ]
                    rows.append(round_row(k, args, f"actor pid {victim}", f"actor {victim}", losses, steppers, ctl))
    shutil.rmtree(ray_root, ignore_errors=True)
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--backend", choices=["local", "ray"], default="local")
    ap.add_argument("--kills", type=int, default=20)
    ap.add_argument("--save-every", type=float, default=1.0, help="the server's --save-every [s]")
    ap.add_argument("--min-wait", type=float, default=2.0, help="shortest time from the round's start to the kill [s]")
    ap.add_argument("--max-wait", type=float, default=6.0, help="longest time from the round's start to the kill [s]")
    ap.add_argument("--seed", type=int, default=None, help="the kill moments' random seed (default: a fresh one, printed)")
    ap.add_argument("--out", default="benchmarks/results/durability")
    args = ap.parse_args()
    seed = args.seed if args.seed is not None else random.SystemRandom().randrange(1 << 30)
    rng = random.Random(seed)
    root = Path(tempfile.mkdtemp(prefix="hm-durability-"))
    try:
        rows = (run_local if args.backend == "local" else run_ray)(args, root, rng)
    finally:
        shutil.rmtree(root, ignore_errors=True)
    worst = max(max(r["loss_s"]) for r in rows)
    summary = {
        "backend": args.backend,
        "kills": args.kills,
        "save_every_s": args.save_every,
        "seed": seed,
        "worst_loss_s": worst,
        "kills_over_save_every": sum(max(r["loss_s"]) > args.save_every for r in rows),
        "errors_5xx": sum(r["errors_5xx"] for r in rows),
        "rows": rows,
    }
    write_results(args.out, args.backend, doc=summary)
    print(
        f"{args.backend}: {args.kills} kills, --save-every {args.save_every:g} s: worst loss {worst:.2f} s, "
        f"{summary['kills_over_save_every']} kills over the interval, {summary['errors_5xx']} answers 5xx other than 503"
    )


if __name__ == "__main__":
    main()
