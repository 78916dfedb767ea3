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

from hybridmpm.errors import CheckpointError, HybridMpmError, InvalidInputError
from hybridmpm.service import checkpoint as ckpt
from hybridmpm.service.config import ServiceConfig
from hybridmpm.service.frames import encode_frame
from hybridmpm.service.logs import SHOWN_ID_CHARS
from hybridmpm.service.store import SHOWN_KEY_CHARS, SessionStore, StoredSession, session_key
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
    key: str = ""  # its name in the store (SHA-256 of the id; the id is never stored)
    dirty: bool = False  # changed since its last save
    saved_frame: int | None = None  # frame of its last save (None: no store, or not saved yet)
    restored_from_frame: int | None = None  # the frame it resumed from after a restart
    save_lock: asyncio.Lock = field(default_factory=asyncio.Lock)

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
            "frame": int(self.sim.frame.frame_index),
            "viewers": len(self.viewers),
            "stream": f"/v1/sessions/{self.id}/stream",
            "saved_frame": self.saved_frame,
            "restored_from_frame": self.restored_from_frame,
        }

    def meta(self) -> dict[str, Any]:
        return {"type": "meta", **self.info(), "playing": self.playing, "header_bytes": 32}

    def publish(self, fr: Frame, control_frame: int = 0) -> None:
        """Offer a frame to every viewer (event loop thread only)."""
        if not self.viewers:
            return
        data = encode_frame(fr.positions, fr.frame_index, fr.time, fr.solver, fr.controlled, control_frame)
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
        self._saver: asyncio.Task[None] | None = None
        #: Durable sessions (None without ``config.store``).
        self.store: SessionStore | None = None
        #: Sessions restored from the store whose id no request has named yet, by key.
        self.unclaimed: dict[str, Session] = {}
        self.io_limiter = anyio.CapacityLimiter(1)
        if config.store is not None:
            self.store = SessionStore(config.store).open()

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
    def count(self) -> int:
        """Sessions held (restored ones no request has named yet included)."""
        return len(self.sessions) + len(self.unclaimed)

    def sessions_of(self, client: str) -> int:
        """Sessions held or being built for the client address ``client``."""
        held = sum(1 for s in (*self.sessions.values(), *self.unclaimed.values()) if s.client == client)
        return held + self.reserved_by[client]

    async def create(self, scene: str, seed: int, solver: str, r_c: float, client: str = "") -> Session:
        """Build a session for the client address ``client``. Raises
        :class:`SessionCapError` when the server is full,
        :class:`QuotaError` when the client holds its quota,
        :class:`BudgetFullError` when the memory budget cannot hold it (its
        cost: :data:`SESSION_STATE_COPIES` × its state + :data:`SESSION_OVERHEAD`,
        known once it is built; a session that does not fit is dropped), and
        the simulator's :class:`InvalidInputError` for bad settings."""
        if self.count() + self.reserved >= self.config.max_sessions:
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
            sess = Session(sid, scene, seed, solver, r_c, sim, initial, client=client, cost=cost, key=session_key(sid))
            self.sessions[sid] = sess
            if self.store is not None:
                sess.dirty = True
                await self.save(sess)
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
        if s is None and self.unclaimed and len(sid) < 256:
            s = self.unclaimed.pop(session_key(sid), None)
            if s is not None:  # a restored session, named for the first time since the restart
                s.id = sid
                self.sessions[sid] = s
        if s is not None:
            s.touch()
        return s

    async def close(self, sid: str, code: int = 1000, reason: str = "closed", forget: bool = True) -> bool:
        """Remove session ``sid``, closing its sockets; ``forget``: its stored
        record too (a delete or an expiry; not a shutdown, which keeps it for the next start)."""
        s = self.get(sid) if self.unclaimed else self.sessions.get(sid)
        if s is None:
            return False
        del self.sessions[sid]
        await self._drop(s, code, reason, forget)
        return True

    async def _drop(self, s: Session, code: int, reason: str, forget: bool) -> None:
        s.closed = True
        if forget and self.store is not None:
            store = self.store
            async with s.save_lock:  # a save under way ends first, so that no record outlives its session
                await anyio.to_thread.run_sync(store.delete, s.key, limiter=self.io_limiter)
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

    async def reap_once(self) -> list[str]:
        now = time.monotonic()
        ttl = self.config.idle_ttl_s
        stale = [sid for sid, s in self.sessions.items() if now - s.last_used > ttl and not s.lock.locked()]
        for sid in stale:
            await self.close(sid, 4000, "expired")
            log.info("session %s… expired", sid[:SHOWN_ID_CHARS])
        for key in [k for k, s in self.unclaimed.items() if now - s.last_used > ttl]:
            await self._drop(self.unclaimed.pop(key), 4000, "expired", True)
            log.info("restored session %s… (store key) expired", key[:SHOWN_KEY_CHARS])
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
        if self.store is not None and self._saver is None:
            self._saver = asyncio.get_running_loop().create_task(self._save_forever())

    async def stop(self) -> None:
        for task in (self._reaper, self._saver):
            if task is not None:
                task.cancel()
                with contextlib.suppress(asyncio.CancelledError, Exception):
                    await task
        self._reaper = self._saver = None
        if self.store is not None:
            await self.save_all()  # a clean stop loses nothing
        for sid in list(self.sessions):
            await self.close(sid, 1001, "server shutting down", forget=False)
        for key in list(self.unclaimed):
            await self._drop(self.unclaimed.pop(key), 1001, "server shutting down", False)

    # ------------------------------------------------------------ durable sessions
    def changed(self, s: Session) -> None:
        """``s``'s state changed (a step, a control, a reset, a restored checkpoint): the saver writes it."""
        if self.store is not None:
            s.dirty = True

    async def save(self, s: Session) -> bool:
        """Write ``s``'s checkpoint to the store if it changed since its last
        save; False when it could not (logged; it stays marked changed and
        the saver tries again)."""
        store = self.store
        if store is None or s.closed or not s.dirty:
            return True
        async with s.save_lock:
            if s.closed or not s.dirty:
                return True
            t0 = time.perf_counter()
            try:
                with self.budget.hold(2 * tree_nbytes(s.initial), "saving a session"):
                    async with s.lock:
                        if s.closed:
                            return True
                        s.dirty = False
                        state = await self.compute(s.sim.state)
                        frame = int(s.sim.frame.frame_index)
                    meta = {
                        "scene": s.scene,
                        "seed": s.seed,
                        "solver": s.solver_kind,
                        "r_c": s.r_c,
                        "last_used_at": time.time() - (time.monotonic() - s.last_used),
                        "client": s.client[: ckpt.MAX_META_CHARS],
                    }
                    data = await self.compute(ckpt.dumps, state, meta)
                    del state
                    await anyio.to_thread.run_sync(store.write, s.key, data, limiter=self.io_limiter)
            except Exception as e:  # noqa: BLE001 - a failed save must not fail the request or the saver
                s.dirty = True
                log.warning("store: saving session %s… failed: %s", s.id[:SHOWN_ID_CHARS], e)
                return False
            s.saved_frame = frame
            log.debug("store: session %s… saved at frame %d: %d bytes in %.1f ms", s.id[:SHOWN_ID_CHARS], frame, len(data), (time.perf_counter() - t0) * 1e3)
            return True

    async def save_all(self) -> None:
        for s in list(self.sessions.values()):
            await self.save(s)

    async def _save_forever(self) -> None:
        interval = float(self.config.save_every_s)
        while True:
            await asyncio.sleep(interval)
            try:
                await self.save_all()
            except Exception:  # noqa: BLE001 - the saver must survive
                log.exception("saver")

    async def restore_all(self) -> int:
        """Bring back every unexpired session of the store (once, at start;
        each waits, unclaimed, for the first request that names its id).
        Expired records are removed; a record that cannot be loaded is
        logged (naming the field) and left in the store. Returns the number restored."""
        store = self.store
        if store is None:
            return 0
        from hybridmpm.sim import make_simulator

        keys = await anyio.to_thread.run_sync(store.keys, limiter=self.io_limiter)
        restored = 0
        for key in keys:
            shown = key[:SHOWN_KEY_CHARS]
            try:
                rec = await anyio.to_thread.run_sync(store.load, key, self.config.max_checkpoint_bytes, limiter=self.io_limiter)
            except InvalidInputError as e:
                log.warning("%s; not restored", e)
                continue
            idle = time.time() - rec.last_used_at
            if idle > self.config.idle_ttl_s:
                await anyio.to_thread.run_sync(store.delete, key, limiter=self.io_limiter)
                log.info("store: session %s… expired while the server was down; removed", shown)
                continue
            if self.count() >= self.config.max_sessions:
                log.warning("store: session %s… not restored: the server holds its maximum of %d sessions", shown, self.config.max_sessions)
                continue
            try:
                with self.budget.hold(SESSION_OVERHEAD + 2 * tree_nbytes(rec.state), "restoring a session"):

                    def build(rec: StoredSession = rec) -> tuple[Simulator, dict[str, Any]]:
                        sim = make_simulator(rec.scene, rec.solver, r_c=rec.r_c, seed=rec.seed, threads=1, nn_threads=1)
                        initial = sim.state()
                        sim.restore(rec.state)
                        return sim, initial

                    sim, initial = await self.compute(build)
                cost = self.budget.take(SESSION_STATE_COPIES * tree_nbytes(initial) + SESSION_OVERHEAD, "a restored session")
            except BudgetFullError as e:
                log.warning("store: session %s… not restored: %s", shown, e)
                continue
            except (InvalidInputError, CheckpointError) as e:
                log.warning("store: session %s…: checkpoint: %s; not restored", shown, e)
                continue
            except (KeyError, TypeError, ValueError, AttributeError, IndexError, OverflowError) as e:
                log.warning("store: session %s…: checkpoint: malformed state (%s); not restored", shown, type(e).__name__)
                continue
            frame = int(sim.frame.frame_index)
            s = Session(key, rec.scene, rec.seed, rec.solver, rec.r_c, sim, initial, client=rec.client, cost=cost, key=key)
            s.last_used = time.monotonic() - max(0.0, idle)
            s.saved_frame = s.restored_from_frame = frame
            self.unclaimed[key] = s
            restored += 1
            log.info("store: session %s… restored at frame %d", shown, frame)
        return restored

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
                self.changed(s)
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
