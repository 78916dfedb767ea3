"""A real server in a subprocess on 127.0.0.1 for tests and benchmarks
(``hybridmpm serve --port 0``: the server binds a port the system chooses,
read back from the child's listening socket, so no other process can take it
between choosing and binding; stopped with :meth:`LiveServer.stop`), and a
local Ray cluster for the ray backend (:class:`RayCluster`)."""

from __future__ import annotations

import http.client
import os
import shutil
import signal
import socket
import subprocess
import sys
import time
import urllib.request
from pathlib import Path
from typing import Any

import numpy as np


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def listening_port(pid: int) -> int | None:
    """The TCP port process ``pid`` listens on (Linux: its socket inodes
    matched in ``/proc/PID/net/tcp``), or None while it listens on none."""
    ports = listening_ports(pid)
    return ports[0] if ports else None


def listening_ports(pid: int) -> list[int]:
    """The TCP ports process ``pid`` listens on (a front end of a Ray
    cluster listens on Ray's ports too), in the order of the kernel's tables."""
    found: list[int] = []
    try:
        inodes = set()
        for fd in os.listdir(f"/proc/{pid}/fd"):
            try:
                target = os.readlink(f"/proc/{pid}/fd/{fd}")
            except OSError:  # closed meanwhile
                continue
            if target.startswith("socket:["):
                inodes.add(target[len("socket:[") : -1])
        for table in ("tcp", "tcp6"):
            for line in Path(f"/proc/{pid}/net/{table}").read_text().splitlines()[1:]:
                f = line.split()
                if f[3] == "0A" and f[9] in inodes:  # state LISTEN
                    found.append(int(f[1].rsplit(":", 1)[1], 16))
    except OSError:
        return found
    return found


class LiveServer:
    """``hybridmpm serve`` in a child process. ``env`` adds ``HYBRIDMPM_*`` settings
    (:meth:`ServiceConfig.from_env`; the per-client session quota is
    ``max_sessions`` unless ``env`` sets it: every request of a test comes
    from one address); ``args`` more ``serve`` arguments (``["--log-level",
    "info"]``); ``port``, ``url`` and ``ws_url`` are known once it is started
    (:meth:`start`, or entering the ``with``)."""

    def __init__(
        self,
        max_sessions: int = 100,
        ttl: float = 600.0,
        env: dict[str, str] | None = None,
        log: Path | None = None,
        args: list[str] | None = None,
    ) -> None:
        self.port = 0
        self.url = self.ws_url = ""
        cmd = [
            sys.executable,
            "-m",
            "hybridmpm",
            "serve",
            "--host",
            "127.0.0.1",
            "--port",
            "0",
            "--max-sessions",
            str(max_sessions),
            "--ttl",
            str(ttl),
            *(args or []),
        ]
        full_env = {**os.environ, "HYBRIDMPM_MAX_SESSIONS_PER_CLIENT": str(max_sessions), **(env or {})}
        self._log = open(log, "wb") if log is not None else subprocess.DEVNULL  # noqa: SIM115 - closed in stop()
        self.proc = subprocess.Popen(cmd, env=full_env, stdout=self._log, stderr=self._log)

    def start(self, timeout: float = 60.0) -> LiveServer:
        t_end = time.monotonic() + timeout
        while time.monotonic() < t_end:
            if self.proc.poll() is not None:
                raise RuntimeError(f"server exited with {self.proc.returncode}")
            for port in [self.port] if self.port else listening_ports(self.proc.pid):
                try:
                    with urllib.request.urlopen(f"http://127.0.0.1:{port}/healthz", timeout=1) as r:
                        if r.status == 200:
                            self.port = port
                            self.url = f"http://127.0.0.1:{port}"
                            self.ws_url = f"ws://127.0.0.1:{port}"
                            return self
                except (OSError, http.client.HTTPException):  # not up yet, or another listener (Ray's) of the process
                    continue
            time.sleep(0.1)
        self.stop()
        raise RuntimeError("server did not start in time")

    def rss(self) -> int:
        """Resident memory of the server process [bytes]."""
        for line in Path(f"/proc/{self.proc.pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) * 1024
        return 0

    def threads(self) -> int:
        return len(os.listdir(f"/proc/{self.proc.pid}/task"))

    def stop(self) -> None:
        if self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(10)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(5)
        if hasattr(self._log, "close"):
            self._log.close()

    def __enter__(self) -> LiveServer:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()


def cpu_seconds(pids: list[int]) -> float:
    """CPU time (user + system) the processes ``pids`` have used [s] (Linux:
    ``/proc/PID/stat``); a process gone meanwhile counts 0."""
    return sum(_stat_cpu(f"/proc/{pid}/stat") for pid in pids)


def thread_cpu_seconds(pid: int, tid: int | None = None) -> float:
    """CPU time (user + system) thread ``tid`` of process ``pid`` has used [s]
    (default its main thread: a server's event loop); 0 once it is gone."""
    return _stat_cpu(f"/proc/{pid}/task/{pid if tid is None else tid}/stat")


def _stat_cpu(path: str) -> float:
    try:
        f = Path(path).read_text().rsplit(")", 1)[1].split()
    except OSError:
        return 0.0
    return (int(f[11]) + int(f[12])) / os.sysconf("SC_CLK_TCK")


def children() -> dict[int, list[int]]:
    """Every process's children (Linux: ``/proc/PID/stat``)."""
    out: dict[int, list[int]] = {}
    for d in os.listdir("/proc"):
        if d.isdigit():
            try:
                ppid = int(Path(f"/proc/{d}/stat").read_text().rsplit(")", 1)[1].split()[1])
            except (OSError, IndexError, ValueError):
                continue
            out.setdefault(ppid, []).append(int(d))
    return out


def descendants(roots: list[int]) -> list[int]:
    """``roots`` and every process below them, parents before children."""
    kids = children()
    seen: list[int] = []
    todo = list(roots)
    while todo:
        p = todo.pop(0)
        if p not in seen:
            seen.append(p)
            todo.extend(kids.get(p, []))
    return seen


def cmdline(pid: int) -> str:
    """Process ``pid``'s command line (its title: ``ray::SessionActor`` for a session's actor); "" once it is gone."""
    try:
        return Path(f"/proc/{pid}/cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace").strip()
    except OSError:
        return ""


def private_bytes(pid: int) -> int:
    """Memory only process ``pid`` holds (its private pages: what its end gives back) [bytes]; 0 once it is gone."""
    try:
        text = Path(f"/proc/{pid}/smaps_rollup").read_text()
    except OSError:
        return 0
    return sum(int(line.split()[1]) * 1024 for line in text.splitlines() if line.startswith(("Private_Clean:", "Private_Dirty:")))


class RayCluster:
    """A Ray cluster of ``nodes`` node processes on this machine (``ray start
    --block``: a head, then nodes joining it), each with ``num_cpus`` CPUs, on
    127.0.0.1, token authentication with ``token`` (also in :attr:`env`, for
    front ends: nothing is written to ``~/.ray``), Ray's files under ``root``
    (keep it short: Ray's socket paths live under it). :meth:`stop` kills, by
    their process ids, every process its commands started (``ray stop``
    would end every Ray process of the machine's user). Raises
    RuntimeError when a node does not come up within ``timeout`` seconds."""

    def __init__(self, root: Path, token: str, nodes: int = 2, num_cpus: int = 1, object_store_bytes: int = 100 << 20, timeout: float = 180.0) -> None:
        self.root, self.token, self.nodes, self.num_cpus = Path(root), token, nodes, num_cpus
        self.object_store_bytes, self.timeout = object_store_bytes, timeout
        self.env = {**os.environ, "RAY_AUTH_MODE": "token", "RAY_AUTH_TOKEN": token}
        self.procs: list[subprocess.Popen[bytes]] = []
        self.port = 0
        self.ray = shutil.which("ray") or str(Path(sys.executable).parent / "ray")

    @property
    def address(self) -> str:
        return f"127.0.0.1:{self.port}"

    def _node(self, name: str, args: list[str]) -> None:
        log = self.root / f"{name}.log"
        common = ["--node-ip-address", "127.0.0.1", "--num-cpus", str(self.num_cpus), "--temp-dir", str(self.root / "ray"), "--disable-usage-stats"]
        common += [
            "--object-store-memory",
            str(self.object_store_bytes),
            "--dashboard-agent-listen-port",
            str(free_port()),
            "--metrics-export-port",
            str(free_port()),
        ]
        with open(log, "wb") as f:
            proc = subprocess.Popen([self.ray, "start", *args, *common, "--block"], env=self.env, stdout=f, stderr=subprocess.STDOUT)
        self.procs.append(proc)
        deadline = time.monotonic() + self.timeout
        while b"block forever" not in log.read_bytes():
            if proc.poll() is not None or time.monotonic() > deadline:
                tail = log.read_text(errors="replace")[-2000:]
                self.stop()
                raise RuntimeError(f"ray start ({name}) did not come up: {tail}")
            time.sleep(0.2)

    def start(self) -> RayCluster:
        """Start the nodes (a new head port each time)."""
        self.root.mkdir(parents=True, exist_ok=True)
        self.port = free_port()
        self._node("head", ["--head", "--port", str(self.port), "--include-dashboard", "false", "--dashboard-port", str(free_port())])
        for i in range(1, self.nodes):
            self._node(f"node{i}", ["--address", self.address])
        return self

    def actor_pids(self, title: str = "ray::SessionActor") -> list[int]:
        """The processes of the cluster's actors whose title starts with ``title``."""
        return [p for p in descendants([q.pid for q in self.procs]) if cmdline(p).startswith(title)]

    def stop(self) -> None:
        """Kill every process the nodes started (SIGKILL, by process id) and wait for the commands."""
        for pid in reversed(descendants([p.pid for p in self.procs if p.poll() is None])):
            try:
                os.kill(pid, signal.SIGKILL)
            except ProcessLookupError:
                pass
        for p in self.procs:
            p.wait(60)
        self.procs = []

    def __enter__(self) -> RayCluster:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()


def new_session(client: Any, scene: str = "dam_break2d", solver: str = "mpm", seed: int = 0) -> dict[str, Any]:
    """``POST /v1/sessions`` through ``client`` (an httpx or test client): the new session's description.
    AssertionError when it does not answer 201."""
    r = client.post("/v1/sessions", json={"scene": scene, "solver": solver, "seed": seed})
    assert r.status_code == 201, r.text
    return dict(r.json())


def get_checkpoint(client: Any, sid: str) -> bytes:
    """``GET /v1/sessions/{sid}/checkpoint`` through ``client``: the checkpoint's bytes. AssertionError when it
    does not answer 200."""
    r = client.get(f"/v1/sessions/{sid}/checkpoint")
    assert r.status_code == 200, r.text
    return bytes(r.content)


def step_binary(client: Any, sid: str, frames: int) -> np.ndarray:
    """``POST /v1/sessions/{sid}/step`` with a binary answer through
    ``client`` (an httpx or test client): the positions, float32
    ``[steps, N, D]``. AssertionError when it does not answer 200."""
    r = client.post(f"/v1/sessions/{sid}/step", json={"frames": frames}, headers={"Accept": "application/octet-stream"})
    assert r.status_code == 200, r.text
    shape = tuple(int(x) for x in r.headers["x-shape"].split(","))
    return np.frombuffer(r.content, "<f4").reshape(shape)


def wait_saved(client: Any, sid: str, timeout_s: float) -> int:
    """The session's frame once its last save has reached it (``saved_frame ==
    frame``); AssertionError after ``timeout_s`` seconds."""
    deadline = time.monotonic() + timeout_s
    info: dict[str, Any] = {}
    while time.monotonic() < deadline:
        info = client.get(f"/v1/sessions/{sid}").json()
        if info["saved_frame"] == info["frame"]:
            return int(info["frame"])
        time.sleep(0.05)
    raise AssertionError(f"session not saved within {timeout_s} s: frame {info.get('frame')}, saved {info.get('saved_frame')}")


#: The soak's sessions: (scene, solver), cycled over its sessions (the witness is extra).
SOAK_MIX = [
    ("water2d", "mpm"),
    ("sand2d", "hybrid"),
    ("dam_break2d", "hybrid"),
    ("water_sand2d", "mpm"),
    ("water3d", "hybrid"),
    ("water2d", "neural"),
    ("sand2d", "mpm"),
    ("dam_break2d", "mpm"),
]
#: The soak's witness: a session only the soak's witness task steps, compared bitwise with an uninterrupted run.
SOAK_WITNESS = ("water2d", "mpm", 7)


async def soak(url: str, seconds: float, sessions: int = 16, workers: int = 6, seed: int = 0) -> dict[str, Any]:
    """A mixed load on the server at ``url`` for ``seconds``: ``sessions``
    sessions (:data:`SOAK_MIX`) that ``workers`` clients drive with random
    steps (JSON and binary), controls (every method), checkpoint round trips,
    trajectory downloads, short stream views and deletes 0.1-0.6 s into a
    1000-frame control (the session is replaced by a new one), plus a
    witness session (:data:`SOAK_WITNESS`) stepped in random chunks. At the
    end every session is deleted. Returns ``{"statuses": {code: count},
    "refusals": [method, route, status and text of each
    4xx other than 404], "deleted_controls": [codes of the controls whose
    session was deleted],
    "witness": float32 [T, N, D] (its steps in order), "memory_used_start",
    "memory_used_end", "ops": count}``."""
    import asyncio
    import random

    import httpx
    import websockets

    rng = random.Random(seed)
    statuses: dict[int, int] = {}
    deleted_controls: list[int] = []
    witness: list[np.ndarray] = []
    ops = 0
    arrow = {"kind": "arrow", "points": [[0.3, 0.3], [0.6, 0.4]]}

    refusals: list[str] = []

    def seen(r: httpx.Response) -> httpx.Response:
        statuses[r.status_code] = statuses.get(r.status_code, 0) + 1
        if r.status_code >= 400 and r.status_code != 404:
            refusals.append(f"{r.request.method} {r.request.url.path.split('/')[-1]}: {r.status_code} {r.text[:160]}")
        return r

    async with httpx.AsyncClient(base_url=url, timeout=600) as c:
        start_used = int((await c.get("/healthz")).json()["memory_used"])
        solver_of: dict[str, str] = {}

        async def create(k: int) -> str:
            scene, solver = SOAK_MIX[k % len(SOAK_MIX)]
            r = seen(await c.post("/v1/sessions", json={"scene": scene, "solver": solver, "seed": rng.randrange(1000)}))
            assert r.status_code == 201, r.text[:200]
            solver_of[str(r.json()["id"])] = solver
            return str(r.json()["id"])

        sids = [await create(k) for k in range(sessions)]
        wscene, wsolver, wseed = SOAK_WITNESS
        r = seen(await c.post("/v1/sessions", json={"scene": wscene, "solver": wsolver, "seed": wseed}))
        witness_id = str(r.json()["id"])
        busy: set[int] = set()
        t_end = time.monotonic() + seconds

        async def op(k: int) -> None:
            nonlocal ops
            sid = sids[k]
            kind = rng.choice(["step", "step", "binary", "control", "control", "delete_in_control", "checkpoint", "trajectory", "view", "info"])
            if kind == "delete_in_control" and solver_of[sid] == "neural":  # the network alone takes no control (a 422)
                kind = "step"
            ops += 1
            if kind == "step":
                seen(await c.post(f"/v1/sessions/{sid}/step", json={"frames": rng.randint(1, 30)}))
            elif kind == "binary":
                seen(await c.post(f"/v1/sessions/{sid}/step", json={"frames": rng.randint(1, 30)}, headers={"Accept": "application/octet-stream"}))
            elif kind == "control":
                body = {"method": rng.choice(["constant", "pd", "none", "diffusion"]), "sketch": arrow, "frames": rng.randint(30, 300)}
                seen(await c.post(f"/v1/sessions/{sid}/controls", json=body))
            elif kind == "delete_in_control":
                task = asyncio.create_task(c.post(f"/v1/sessions/{sid}/controls", json={"sketch": arrow, "frames": 1000}))
                await asyncio.sleep(rng.uniform(0.1, 0.6))
                seen(await c.delete(f"/v1/sessions/{sid}"))
                deleted_controls.append(seen(await task).status_code)
                sids[k] = await create(rng.randrange(len(SOAK_MIX)))
            elif kind == "checkpoint":
                got = seen(await c.get(f"/v1/sessions/{sid}/checkpoint"))
                if got.status_code == 200:
                    seen(await c.put(f"/v1/sessions/{sid}/checkpoint", content=got.content, headers={"Content-Type": "application/octet-stream"}))
            elif kind == "trajectory":
                seen(await c.get(f"/v1/sessions/{sid}/trajectory", params={"format": rng.choice(["npz", "ply"]), "frames": rng.randint(1, 20)}))
            elif kind == "view":
                ws_url = url.replace("http://", "ws://", 1) + f"/v1/sessions/{sid}/stream"
                async with websockets.connect(ws_url, max_size=None) as ws:
                    await asyncio.wait_for(ws.recv(), 60)
                    await ws.send('{"type": "play"}')
                    await asyncio.sleep(rng.uniform(0.1, 0.5))
                    await ws.send('{"type": "pause"}')
            else:
                seen(await c.get(f"/v1/sessions/{sid}"))

        async def worker() -> None:
            while time.monotonic() < t_end:
                free = [k for k in range(sessions) if k not in busy]
                if not free:
                    await asyncio.sleep(0.01)
                    continue
                k = rng.choice(free)
                busy.add(k)
                try:
                    await op(k)
                finally:
                    busy.discard(k)

        async def step_witness() -> None:
            while time.monotonic() < t_end:
                r = seen(await c.post(f"/v1/sessions/{witness_id}/step", json={"frames": rng.randint(1, 12)}, headers={"Accept": "application/octet-stream"}))
                if r.status_code == 200:
                    shape = tuple(int(x) for x in r.headers["x-shape"].split(","))
                    witness.append(np.frombuffer(r.content, "<f4").reshape(shape))
                await asyncio.sleep(rng.uniform(0.0, 0.2))

        await asyncio.gather(step_witness(), *(worker() for _ in range(workers)))
        for sid in (*sids, witness_id):
            seen(await c.delete(f"/v1/sessions/{sid}"))
        await asyncio.sleep(0.5)
        end_used = int((await c.get("/healthz")).json()["memory_used"])
    return {
        "statuses": statuses,
        "refusals": refusals,
        "deleted_controls": deleted_controls,
        "witness": np.concatenate(witness) if witness else np.zeros((0, 0, 2), np.float32),
        "memory_used_start": start_used,
        "memory_used_end": end_used,
        "ops": ops,
    }


__all__ = [
    "LiveServer",
    "RayCluster",
    "cmdline",
    "cpu_seconds",
    "descendants",
    "free_port",
    "listening_port",
    "listening_ports",
    "private_bytes",
    "soak",
    "step_binary",
    "thread_cpu_seconds",
    "wait_saved",
]
