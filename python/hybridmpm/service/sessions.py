"""Sessions: each owns one simulator, its lock, its viewers; a manager holds
them in memory (one process), caps their number and reaps idle ones.

All simulation work runs through :meth:`SessionManager.compute` — off the
event loop, on one capacity limiter sized to the cores — never in ``async``
code directly (a CPU-bound call there would stall every client).
"""

from __future__ import annotations

import asyncio
import collections
import contextlib
import logging
import math
import secrets
import time
import traceback
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from typing import Any, TypeVar

import anyio
import anyio.to_thread
import numpy as np
from starlette.websockets import WebSocket, WebSocketState

from hybridmpm.errors import HybridMpmError
from hybridmpm.service.config import ServiceConfig
from hybridmpm.service.frames import encode_frame
from hybridmpm.service.logs import SHOWN_ID_CHARS
from hybridmpm.sim import Frame, Simulator

log = logging.getLogger("hybridmpm.service")
T = TypeVar("T")

#: Controls kept per session (their trajectories can be fetched).
KEEP_CONTROLS = 8
#: What a session costs beyond its state arrays (simulator objects, grids, buffers) [bytes], for the memory budget.
SESSION_OVERHEAD = 4 << 20
#: Copies of its state a session's cost counts: the live simulator, the initial state kept for "reset", a step's working copy.
SESSION_STATE_COPIES = 3
#: Seconds a client is asked to wait (``Retry-After``) when the memory budget is full.
RETRY_AFTER_S = 5


class SessionCapError(Exception):
    """No room for another session (→ 503)."""


class QuotaError(Exception):
    """The client address holds its quota of sessions (→ 429)."""


class BudgetFullError(Exception):
    """The memory budget cannot hold an allocation (→ 503 with ``Retry-After``)."""

    def __init__(self, what: str, nbytes: int, used: int, total: int) -> None:
        from hybridmpm.limits import human

        super().__init__(f"{what} would need {human(nbytes)}; the server holds {human(used)} of its memory budget of {human(total)}; retry later")
        self.what, self.nbytes = what, nbytes


class MemoryBudget:
    """One memory budget for the process [bytes]: sessions, kept controls
    and the transient buffers of requests take from it before they
    allocate and give back when freed. Used from the event loop thread only
    (no lock needed)."""

    def __init__(self, total: int) -> None:
        self.total = int(total)
        self.used = 0

    def take(self, nbytes: float, what: str) -> int:
        """Reserve ``nbytes`` (rounded up) or raise :class:`BudgetFullError`; returns the bytes reserved."""
        n = max(0, int(math.ceil(nbytes)))
        if self.used + n > self.total:
            raise BudgetFullError(what, n, self.used, self.total)
        self.used += n
        return n

    def give(self, nbytes: int) -> None:
        self.used = max(0, self.used - int(nbytes))

    @contextlib.contextmanager
    def hold(self, nbytes: float, what: str) -> Iterator[int]:
        """Reserve ``nbytes`` for the ``with`` block (:class:`BudgetFullError` if it cannot)."""
        n = self.take(nbytes, what)
        try:
            yield n
        finally:
            self.give(n)


def tree_nbytes(tree: Any) -> int:
    """Bytes of the arrays and byte strings in a state tree (dicts, lists, arrays, bytes)."""
    if isinstance(tree, dict):
        return sum(tree_nbytes(v) for v in tree.values())
    if isinstance(tree, (list, tuple)):
        return sum(tree_nbytes(v) for v in tree)
    if isinstance(tree, np.ndarray):
        return int(tree.nbytes)
    if isinstance(tree, (bytes, bytearray)):
        return len(tree)
    return 0


class Viewer:
    """One WebSocket connection: a latest-frame slot (newer frames overwrite
    an unsent one — never a queue of frames) and a short bounded queue of
    JSON events (oldest dropped)."""

    def __init__(self, ws: WebSocket) -> None:
        self.ws = ws
        self.frame: bytes | None = None
        self.events: collections.deque[dict[str, Any]] = collections.deque(maxlen=16)
        self.wake = asyncio.Event()
        self.sent = 0
        self.dropped = 0
        self.closed = False

    def offer(self, data: bytes) -> None:
        if self.frame is not None:
            self.dropped += 1
        self.frame = data
        self.wake.set()

    def event(self, msg: dict[str, Any]) -> None:
        self.events.append(msg)
        self.wake.set()


@dataclass
class Control:
    id: str
    method: str
    positions: np.ndarray
    solver: list[str]
    response: dict[str, Any]
    cost: int = 0  # bytes taken from the memory budget while it is kept


@dataclass
class Session:
    id: str
    scene: str
    seed: int
    solver_kind: str
    r_c: float
    sim: Simulator
    initial: dict[str, Any]
    lock: asyncio.Lock = field(default_factory=asyncio.Lock)
    last_used: float = field(default_factory=time.monotonic)
    viewers: set[Viewer] = field(default_factory=set)
    playing: bool = False
    play_task: asyncio.Task[None] | None = None
    controlling: bool = False
    controls: collections.OrderedDict[str, Control] = field(default_factory=collections.OrderedDict)
    closed: bool = False
    client: str = ""  # the address that created it (the per-client quota)
    cost: int = 0  # bytes taken from the memory budget (controls not included)

    def touch(self) -> None:
        self.last_used = time.monotonic()

    def info(self) -> dict[str, Any]:
        p = self.sim.particles
        d = p.dim
        return {
            "id": self.id,
            "scene": self.scene,
            "seed": self.seed,
            "solver": self.solver_kind,
            "r_c": self.r_c,
            "dim": d,
            "num_fluid": p.num_fluid,
            "num_particles": p.num_total,
            "particle_type": [int(t) for t in p.particle_type],
            "bounds": [[0.0] * d, [1.0] * d],
            "dt_frame": float(self.sim.dt_frame),
            "r_t": int(self.sim.r_t),
            "frame": int(self.sim.frame.frame),
            "viewers": len(self.viewers),
            "stream": f"/v1/sessions/{self.id}/stream",
        }

    def meta(self) -> dict[str, Any]:
        return {"type": "meta", **self.info(), "playing": self.playing, "header_bytes": 32}

    def publish(self, fr: Frame, control_frame: int = 0) -> None:
        """Offer a frame to every viewer (event loop thread only)."""
        if not self.viewers:
            return
        data = encode_frame(fr.positions, fr.frame, fr.time, fr.solver, fr.controlled, control_frame)
        for v in list(self.viewers):
            v.offer(data)

    def broadcast(self, msg: dict[str, Any]) -> None:
        for v in list(self.viewers):
            v.event(msg)


class SessionManager:
    """The sessions of this process (a plain dict) and the compute limiter."""

    def __init__(self, config: ServiceConfig) -> None:
        self.config = config
        self.sessions: dict[str, Session] = {}
        self.reserved = 0
        self.reserved_by: collections.Counter[str] = collections.Counter()
        self.budget = MemoryBudget(config.memory_budget_bytes)
        self.limiter = anyio.CapacityLimiter(config.compute_threads)
        self.controls_running = 0
        self._reaper: asyncio.Task[None] | None = None

    # ------------------------------------------------------------ compute
    async def compute(self, fn: Callable[..., T], *args: Any) -> T:
        """Run ``fn(*args)`` in a worker thread under the compute limiter.
        A refusal (:class:`~hybridmpm.errors.HybridMpmError`) comes back with
        the locals of its traceback's frames cleared: the answer keeps no
        decoded image or state alive while it lingers."""
        try:
            return await anyio.to_thread.run_sync(fn, *args, limiter=self.limiter)
        except HybridMpmError as e:
            traceback.clear_frames(e.__traceback__)
            raise

    # ------------------------------------------------------------ lifecycle
    def sessions_of(self, client: str) -> int:
        """Sessions held or being built for the client address ``client``."""
        return sum(1 for s in self.sessions.values() if s.client == client) + self.reserved_by[client]

    async def create(self, scene: str, seed: int, solver: str, r_c: float, client: str = "") -> Session:
        """Build a session for the client address ``client``. Raises
        :class:`SessionCapError` when the server is full,
        :class:`QuotaError` when the client holds its quota,
        :class:`BudgetFullError` when the memory budget cannot hold it (its
        cost: :data:`SESSION_STATE_COPIES` × its state + :data:`SESSION_OVERHEAD`,
        known once it is built; a session that does not fit is dropped), and
        the simulator's :class:`InvalidInputError` for bad settings."""
        if len(self.sessions) + self.reserved >= self.config.max_sessions:
            raise SessionCapError()
        if self.sessions_of(client) >= self.config.max_sessions_per_client:
            raise QuotaError()
        self.reserved += 1
        self.reserved_by[client] += 1
        try:
            with self.budget.hold(SESSION_OVERHEAD, "a new session"):

                def build() -> tuple[Simulator, dict[str, Any]]:
                    from hybridmpm.sim import make_simulator

                    sim = make_simulator(scene, solver, r_c=r_c, seed=seed, threads=1, nn_threads=1)
                    return sim, sim.state()

                sim, initial = await self.compute(build)
            cost = self.budget.take(SESSION_STATE_COPIES * tree_nbytes(initial) + SESSION_OVERHEAD, "a new session")
            sid = secrets.token_urlsafe(24)  # 192 bits
            sess = Session(sid, scene, seed, solver, r_c, sim, initial, client=client, cost=cost)
            self.sessions[sid] = sess
            return sess
        finally:
            self.reserved -= 1
            self.reserved_by[client] -= 1
            if self.reserved_by[client] <= 0:
                del self.reserved_by[client]

    def keep_control(self, s: Session, c: Control) -> None:
        """Keep ``c`` on ``s`` (its cost already taken from the budget),
        dropping the oldest beyond :data:`KEEP_CONTROLS` and giving their cost back."""
        s.controls[c.id] = c
        while len(s.controls) > KEEP_CONTROLS:
            _, old = s.controls.popitem(last=False)
            self.budget.give(old.cost)

    def get(self, sid: str) -> Session | None:
        s = self.sessions.get(sid)
        if s is not None:
            s.touch()
        return s

    async def close(self, sid: str, code: int = 1000, reason: str = "closed") -> bool:
        s = self.sessions.pop(sid, None)
        if s is None:
            return False
        s.closed = True
        self.budget.give(s.cost + sum(c.cost for c in s.controls.values()))
        s.cost = 0
        for c in s.controls.values():
            c.cost = 0
        s.playing = False
        if s.play_task is not None:
            s.play_task.cancel()
        for v in list(s.viewers):
            await close_ws(v, code, reason)
        s.viewers.clear()
        return True

    async def reap_once(self) -> list[str]:
        now = time.monotonic()
        ttl = self.config.idle_ttl_s
        stale = [sid for sid, s in self.sessions.items() if now - s.last_used > ttl and not s.lock.locked()]
        for sid in stale:
            await self.close(sid, 4000, "expired")
            log.info("session %s… expired", sid[:SHOWN_ID_CHARS])
        return stale

    async def _reap_forever(self) -> None:
        interval = float(self.config.reap_interval_s or 30.0)
        while True:
            await asyncio.sleep(interval)
            try:
                await self.reap_once()
            except Exception:  # noqa: BLE001 - the reaper must survive
                log.exception("reaper")

    def start(self) -> None:
        if self._reaper is None:
            self._reaper = asyncio.get_running_loop().create_task(self._reap_forever())

    async def stop(self) -> None:
        if self._reaper is not None:
            self._reaper.cancel()
            with contextlib.suppress(asyncio.CancelledError, Exception):
                await self._reaper
            self._reaper = None
        for sid in list(self.sessions):
            await self.close(sid, 1001, "server shutting down")

    # ------------------------------------------------------------ play loop
    def ensure_playing(self, s: Session) -> None:
        if s.playing and s.viewers and (s.play_task is None or s.play_task.done()):
            s.play_task = asyncio.get_running_loop().create_task(self._play(s))

    async def _play(self, s: Session) -> None:
        """Advance a playing session one coarse step at a time (no faster than
        real time) while it has viewers; frames go to the viewers' slots."""
        period = float(s.sim.dt_frame) * int(s.sim.r_t)
        next_t = time.monotonic()
        try:
            while s.playing and s.viewers and not s.closed:
                async with s.lock:
                    if not s.playing or s.closed:
                        break
                    try:
                        fr = await self.compute(s.sim.advance)
                    except Exception as e:  # noqa: BLE001 - a failed step pauses the stream with a message
                        s.playing = False
                        s.broadcast({"type": "error", "message": f"simulation stopped: {e}"})
                        break
                s.touch()
                s.publish(fr)
                next_t = max(next_t + period, time.monotonic() - 0.25)
                await asyncio.sleep(max(0.0, next_t - time.monotonic()))
        except asyncio.CancelledError:
            pass


async def close_ws(v: Viewer, code: int, reason: str) -> None:
    v.closed = True
    v.wake.set()
    if v.ws.application_state == WebSocketState.CONNECTED:
        with contextlib.suppress(Exception):
            await asyncio.wait_for(v.ws.close(code=code, reason=reason), 2.0)


__all__ = [
    "KEEP_CONTROLS",
    "RETRY_AFTER_S",
    "BudgetFullError",
    "Control",
    "MemoryBudget",
    "QuotaError",
    "Session",
    "SessionCapError",
    "SessionManager",
    "Viewer",
    "close_ws",
    "tree_nbytes",
]
