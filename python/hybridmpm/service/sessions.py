"""Sessions: each owns one simulator, its lock, its viewers; a manager holds
them in memory (one process), caps their number and reaps idle ones.

All simulation work runs through :meth:`SessionManager.compute` — off the
event loop, on one capacity limiter sized to the cores — never in ``async``
code directly (a CPU-bound call there would stall every client).

The routes reach a session's simulator through the manager's ``async``
methods (:meth:`SessionManager.find`, :meth:`~SessionManager.rollout`,
:meth:`~SessionManager.checkpoint`, :meth:`~SessionManager.restore`,
:meth:`~SessionManager.reset`, :meth:`~SessionManager.info`,
:meth:`~SessionManager.attach`, ...; a control runs its episode itself where
``manager.remote`` is False): the seam where
:class:`hybridmpm.service.cluster.RaySessionManager` runs the same work in
each session's Ray actor instead of in this process.
"""

from __future__ import annotations

import asyncio
import collections
import contextlib
import functools
import logging
import secrets
import threading
import time
import traceback
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, TypeVar

import anyio
import anyio.to_thread
import numpy as np
from starlette.websockets import WebSocket, WebSocketState

from hybridmpm.errors import CheckpointError, HybridMpmError, InvalidInputError
from hybridmpm.service import checkpoint as ckpt
from hybridmpm.service.budget import BudgetFullError, MemoryBudget, Recording, tree_nbytes
from hybridmpm.service.config import ServiceConfig
from hybridmpm.service.core import Pacer, encode_record, play_period, play_step, snapshot
from hybridmpm.service.facts import SessionFacts, scene_geometry
from hybridmpm.service.frames import encode_frame
from hybridmpm.service.logs import SHOWN_ID_CHARS
from hybridmpm.service.store import SHOWN_KEY_CHARS, SessionStore, rebuild, session_key
from hybridmpm.sim import Frame, Rollout, Simulator, rollout

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
#: Coarse steps of its recent trajectory a session keeps for download (``GET .../trajectory``).
RECORD_STEPS = 300


class SessionCapError(Exception):
    """No room for another session (→ 503)."""


class QuotaError(Exception):
    """The client address holds its quota of sessions (→ 429)."""


class SessionGoneError(Exception):
    """The session was deleted, expired or lost while a request used it (→ 404)."""


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
    recording: Recording | None = None  # its latest frames, for download
    n_grid: int | None = None  # the grid it was asked to run on (None: the scene's)
    control_stop: threading.Event | None = None  # set stops the running control within a frame (a delete sets it)
    _facts: SessionFacts | None = None

    @property
    def facts(self) -> SessionFacts:
        """The session's fixed facts, what routes read (:class:`~hybridmpm.service.facts.SessionFacts`)."""
        if self._facts is None:
            self._facts = SessionFacts.of(self.sim)
        return self._facts

    @property
    def frame_index(self) -> int:
        """The frame the session is at."""
        return int(self.sim.frame.frame_index)

    def republish(self) -> None:
        """Offer the current frame to the viewers again (after a step or control that stopped early)."""
        self.publish(self.sim.frame)

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
            **scene_geometry(self.sim),
            "obstacle_centers": np.round(np.asarray(getattr(self.sim, "obstacle_centers", np.zeros((0, d))), np.float64), 7).tolist(),
            "recorded_frames": len(self.recording) if self.recording is not None else 0,
        }

    def meta(self) -> dict[str, Any]:
        return {"type": "meta", **self.info(), "playing": self.playing, "header_bytes": 32}

    def record(self, fr: Frame) -> None:
        """Keep ``fr`` in the session's recent trajectory (event loop thread
        only); nothing once the session is closed (its budget was given back)."""
        if self.recording is not None and not self.closed:
            self.recording.add(fr.frame_index, fr.positions, fr.solver, fr.controlled)

    def publish(self, fr: Frame, control_frame: int = 0) -> None:
        """Record a frame and offer it to every viewer (event loop thread only)."""
        self.record(fr)
        if not self.viewers:
            return
        data = encode_frame(fr.positions, fr.frame_index, fr.time, fr.solver, fr.controlled, control_frame)
        for v in list(self.viewers):
            v.offer(data)

    def broadcast(self, msg: dict[str, Any]) -> None:
        for v in list(self.viewers):
            v.event(msg)

    def settings(self) -> dict[str, Any]:
        """What a checkpoint of the session is written for (its ``meta``): scene, seed, solver, ``r_c`` (and ``n_grid`` when asked)."""
        d: dict[str, Any] = {"scene": self.scene, "seed": self.seed, "solver": self.solver_kind, "r_c": self.r_c}
        if self.n_grid is not None:
            d["n_grid"] = self.n_grid
        return d


class SessionManager:
    """The sessions of this process (a plain dict) and the compute limiter."""

    #: Whether sessions run elsewhere (a Ray actor each: :class:`hybridmpm.service.cluster.RaySessionManager`).
    remote = False
    #: Temporary files of torn saves older than this are removed when the store opens [s]
    #: (:meth:`SessionStore.open`; one process writes this store, so all of them).
    store_clean_after_s: float | None = 0.0

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
        self._saving: dict[str, asyncio.Task[bool]] = {}  # the periodic saver's save in progress, per session key
        #: Durable sessions (None without ``config.store``).
        self.store: SessionStore | None = None
        #: Sessions restored from the store whose id no request has named yet, by key.
        self.unclaimed: dict[str, Session] = {}
        self.io_limiter = anyio.CapacityLimiter(1)
        if config.store is not None:
            self.store = SessionStore(config.store).open(self.store_clean_after_s)

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

    async def create(self, scene: str, seed: int, solver: str, r_c: float, client: str = "", *, n_grid: int | None = None) -> Session:
        """Build a session for the client address ``client`` (``n_grid``: MPM
        on a coarser grid of the scene, :func:`checked_n_grid`). Raises
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

                    sim = make_simulator(scene, solver, r_c=r_c, seed=seed, threads=1, nn_threads=1, n_grid=n_grid)
                    return sim, sim.state()

                sim, initial = await self.compute(build)
            cost = self.budget.take(SESSION_STATE_COPIES * tree_nbytes(initial) + SESSION_OVERHEAD, "a new session")
            sid = secrets.token_urlsafe(24)  # 192 bits
            sess = Session(sid, scene, seed, solver, r_c, sim, initial, client=client, cost=cost, key=session_key(sid), n_grid=n_grid)
            sess.recording = Recording(self.budget, RECORD_STEPS, int(sim.r_t))
            sess.record(sim.frame)
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

    async def keep_control(self, s: Session, c: Control) -> None:
        """Keep ``c`` on ``s`` (its cost already taken from the budget),
        dropping the oldest beyond :data:`KEEP_CONTROLS` and giving their cost back."""
        s.controls[c.id] = c
        while len(s.controls) > KEEP_CONTROLS:
            _, old = s.controls.popitem(last=False)
            self.budget.give(old.cost)

    async def get_control(self, s: Session, cid: str) -> Control | None:
        """The kept control ``cid`` of ``s``, or None."""
        return s.controls.get(cid)

    async def recorded(self, s: Session, count: int) -> list[tuple[int, np.ndarray, str, bool]]:
        """The latest ``count`` frames of ``s``'s recent trajectory, oldest first (none when it records none)."""
        return s.recording.last(count) if s.recording is not None else []

    async def find(self, sid: str) -> Session | None:
        """The session ``sid`` (touched), or None: what a request names."""
        return self.get(sid)

    async def held(self) -> int:
        """Sessions held (``/healthz``)."""
        return self.count()

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
        if s.control_stop is not None:  # a control running on it stops within a frame and answers 404
            s.control_stop.set()
        if forget and self.store is not None:
            store = self.store
            async with s.save_lock:  # a save under way ends first, so that no record outlives its session
                await anyio.to_thread.run_sync(store.delete, s.key, limiter=self.io_limiter)
        self.budget.give(s.cost + sum(c.cost for c in s.controls.values()))
        if s.recording is not None:
            s.recording.release()
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
        if self._saving:
            await asyncio.gather(*self._saving.values(), return_exceptions=True)
        if self.store is not None:
            await self.save_all()  # a clean stop loses nothing
        for sid in list(self.sessions):
            await self.close(sid, 1001, "server shutting down", forget=False)
        for key in list(self.unclaimed):
            await self._drop(self.unclaimed.pop(key), 1001, "server shutting down", False)
        if self.store is not None:
            self.store.release()

    # ------------------------------------------------------------ durable sessions
    def changed(self, s: Session) -> None:
        """``s``'s state changed (a step, a control, a reset, a restored checkpoint): the saver writes it."""
        if self.store is not None:
            s.dirty = True

    async def save(self, s: Session) -> bool:
        """Write ``s``'s checkpoint to the store if it changed since its last
        save; False when it could not (logged; it stays marked changed and
        the saver tries again). The state is taken under the session's lock,
        so at a step boundary (a step or control running is waited for: the
        lock is fair, so the next step queues behind the snapshot); taking it
        and encoding it run on the store's I/O thread, not the compute
        workers, so busy sessions do not delay it."""
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
                        state, frame = await anyio.to_thread.run_sync(snapshot, s.sim, limiter=self.io_limiter)
                    data = await anyio.to_thread.run_sync(encode_record, state, s.settings(), s.last_used, s.client, limiter=self.io_limiter)
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
        """Save every changed session (:meth:`save`), each waiting only for its own lock."""
        await asyncio.gather(*(self.save(s) for s in list(self.sessions.values())))

    def save_round(self) -> None:
        """One round of the periodic saver: a save task (:meth:`save`) for every
        changed session that has none running. Returns at once: a session
        busy in a long control or step delays only its own save (whose
        steps answered before the control were saved when it started), never
        another session's."""
        for s in list(self.sessions.values()):
            if s.dirty and not s.closed and s.key not in self._saving:
                task = asyncio.get_running_loop().create_task(self.save(s))
                self._saving[s.key] = task
                task.add_done_callback(functools.partial(self._saved, s.key))

    def _saved(self, key: str, _task: asyncio.Task[bool]) -> None:
        self._saving.pop(key, None)

    async def _save_forever(self) -> None:
        interval = float(self.config.save_every_s)
        while True:
            await asyncio.sleep(interval)
            try:
                self.save_round()
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
                    sim, initial = await self.compute(rebuild, rec)
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
            s = Session(key, rec.scene, rec.seed, rec.solver, rec.r_c, sim, initial, client=rec.client, cost=cost, key=key, n_grid=rec.n_grid)
            s.last_used = time.monotonic() - max(0.0, idle)
            s.saved_frame = s.restored_from_frame = frame
            s.recording = Recording(self.budget, RECORD_STEPS, int(sim.r_t))
            s.record(sim.frame)
            self.unclaimed[key] = s
            restored += 1
            log.info("store: session %s… restored at frame %d", shown, frame)
        return restored

    # ------------------------------------------------------------ the work of the routes
    async def info(self, s: Session) -> dict[str, Any]:
        """``s``'s description (``GET /v1/sessions/{id}``)."""
        return s.info()

    async def rollout(self, s: Session, frames: int) -> Rollout:
        """Advance ``s`` by ``frames`` frames under its lock (:func:`hybridmpm.sim.rollout`);
        :class:`SessionGoneError` when it was closed meanwhile."""
        async with s.lock:
            if s.closed:
                raise SessionGoneError()
            ro = await self.compute(rollout, s.sim, frames)
            self.changed(s)
        return ro

    async def run_control(
        self, s: Session, sketch: Any, method: str, frames: int, left: Any, first: list[float], cid: str
    ) -> tuple[Rollout, dict[str, Any], Any]:
        """Control ``cid`` on ``s`` with ``method`` for ``frames`` frames
        (the scene's :class:`~hybridmpm.control.Controller`, built on the
        worker; :func:`hybridmpm.service.episode.run_episode`)
        on a worker thread under its lock, its frames and plan event offered
        to the viewers as they come; ``left`` (a :class:`threading.Event`) set
        stops it within a frame, and so does closing ``s`` (a delete, an
        expiry). Appends the time of the first controlled frame to ``first``;
        returns ``(rollout, metrics, plan summary)``; :class:`SessionGoneError`
        when it was closed before or during the control."""
        from hybridmpm.control import Controller  # import time: the controllers load only when a control runs
        from hybridmpm.service.episode import run_episode

        loop = asyncio.get_running_loop()

        def publish(fr: Frame, control_frame: int) -> None:
            loop.call_soon_threadsafe(s.publish, fr, control_frame)

        def event(msg: dict[str, Any]) -> None:
            loop.call_soon_threadsafe(s.broadcast, msg)

        async with s.lock:
            if s.closed:
                raise SessionGoneError()
            s.control_stop = left
            controller = await self.compute(functools.partial(Controller.for_scene, s.facts.scene_name, method, frames=frames))
            s.broadcast({"type": "control", "status": "running", "id": cid, "method": method})
            try:
                ro, metrics, plan, t_first = await self.compute(run_episode, s.sim, sketch, controller, cid, publish, event, left.is_set)
            finally:
                s.control_stop = None
            if s.closed:
                raise SessionGoneError()
            self.changed(s)
        if t_first is not None:
            first.append(t_first)
        return ro, metrics, plan

    async def checkpoint(self, s: Session) -> bytes:
        """``s``'s whole state as a checkpoint (:func:`hybridmpm.service.checkpoint.dumps`);
        :class:`BudgetFullError` when the budget cannot hold two copies of it."""
        with self.budget.hold(2 * tree_nbytes(s.initial), "writing the checkpoint"):
            async with s.lock:
                state = await self.compute(s.sim.state)
            data = await self.compute(ckpt.dumps, state, s.settings())
            del state
        return data

    async def restore(self, s: Session, state: dict[str, Any]) -> None:
        """Restore ``state`` into ``s``, all or nothing: the simulator's
        refusal (:class:`InvalidInputError`, :class:`CheckpointError`, or a
        ``KeyError``/``TypeError``/... of a malformed tree) leaves it as it was."""
        async with s.lock:
            if s.closed:
                raise SessionGoneError()
            await self.compute(s.sim.restore, state)
            self.changed(s)
            if s.recording is not None:
                s.recording.clear()  # the recent trajectory starts again at the restored state
        s.publish(s.sim.frame)

    async def reset(self, s: Session) -> None:
        """Back to the initial condition; the viewers get the frame and a ``reset`` event."""
        async with s.lock:
            await self.compute(s.sim.restore, s.initial)
            self.changed(s)
            if s.recording is not None:
                s.recording.clear()  # the recent trajectory starts again at the initial state
        s.publish(s.sim.frame)
        s.broadcast({"type": "reset", "frame": int(s.sim.frame.frame_index)})

    async def move_obstacle(self, s: Session, index: int, center: list[float], velocity: list[float] | None) -> int:
        """Move obstacle ``index`` of ``s`` to ``center`` over its next step
        (:meth:`hybridmpm.sim.MpmSimulator.move_obstacle`; the errors it raises
        name ``index``, ``center``, ``velocity``); every viewer gets an
        ``obstacle`` event. Returns the session's frame."""
        async with s.lock:
            await self.compute(s.sim.move_obstacle, index, center, velocity)  # type: ignore[attr-defined] # MPM and hybrid (the route refuses the network alone)
            frame = int(s.sim.frame.frame_index)
        s.touch()
        s.broadcast({"type": "obstacle", "index": int(index), "center": [float(x) for x in center]})
        return frame

    async def attach(self, s: Session, v: Viewer) -> None:
        """A new viewer of ``s``: its ``meta`` message and the current frame are offered first."""
        s.viewers.add(v)
        v.event(s.meta())
        fr = s.sim.frame
        v.offer(encode_frame(fr.positions, fr.frame_index, fr.time, fr.solver, fr.controlled))

    async def detach(self, s: Session, v: Viewer) -> None:
        s.viewers.discard(v)

    async def set_playing(self, s: Session, playing: bool) -> None:
        """Play (one coarse step at a time, no faster than real time, while it has viewers) or pause ``s``."""
        s.playing = playing
        if playing:
            self.ensure_playing(s)

    # ------------------------------------------------------------ play loop
    def ensure_playing(self, s: Session) -> None:
        if s.playing and s.viewers and (s.play_task is None or s.play_task.done()):
            s.play_task = asyncio.get_running_loop().create_task(self._play(s))

    async def _play(self, s: Session) -> None:
        """Advance a playing session one coarse step at a time (no faster than
        real time) while it has viewers; frames go to the viewers' slots."""
        pacer = Pacer(play_period(s.sim))
        try:
            while s.playing and s.viewers and not s.closed:
                async with s.lock:
                    if not s.playing or s.closed:
                        break
                    try:
                        fr = await self.compute(play_step, s.sim)
                    except Exception as e:  # noqa: BLE001 - a failed step pauses the stream with a message
                        s.playing = False
                        s.broadcast({"type": "error", "message": f"simulation stopped: {e}"})
                        break
                s.touch()
                self.changed(s)
                s.publish(fr)
                await asyncio.sleep(pacer.delay())
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
    "RECORD_STEPS",
    "RETRY_AFTER_S",
    "Control",
    "QuotaError",
    "Session",
    "SessionCapError",
    "SessionGoneError",
    "SessionManager",
    "Viewer",
    "close_ws",
]
