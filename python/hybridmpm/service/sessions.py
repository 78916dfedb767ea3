"""Sessions of the local backend: each a :class:`~hybridmpm.service.core.SessionCore`
(its simulator, lock, recording, kept controls, play loop and saves,
written once for both backends) and, here, its viewers; a manager holds
them in memory (one process), caps their number and reaps idle ones.

All simulation work runs through :meth:`SessionManager.compute` — off the
event loop, on one capacity limiter sized to the cores — never in ``async``
code directly (a CPU-bound call there would stall every client). Each call
into a session's core waits first for the session's ``asyncio`` lock (fair:
requests queue in order without holding a worker).

:class:`SessionManager` implements :class:`~hybridmpm.service.backend.SessionBackend`
(what the routes call) over :class:`LocalSession` handles; the Ray backend
(:class:`hybridmpm.service.ray_backend.manager.RaySessionManager`) implements
it beside this one, running the same core in each session's Ray actor.
"""

from __future__ import annotations

import asyncio
import collections
import contextlib
import functools
import logging
import secrets
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from typing import Any, TypeVar

import anyio
import anyio.from_thread
import anyio.to_thread

from hybridmpm.errors import CheckpointError, InvalidInputError
from hybridmpm.service.backend import (
    RETRY_AFTER_S,
    QuotaError,
    SessionCapError,
    StoreSaveError,
    Viewer,
    close_viewers,
    close_ws,
    every,
    meta_message,
    offer_all,
    on_worker,
    open_store,
    stop_task,
)
from hybridmpm.service.budget import BudgetFullError, MemoryBudget, RecordedFrame, tree_nbytes
from hybridmpm.service.capacity import RealtimeFullError, admit_session, realtime_share
from hybridmpm.service.config import ServiceConfig
from hybridmpm.service.core import Control, SessionCore, SessionGoneError, session_threads
from hybridmpm.service.facts import SessionFacts, SessionSettings
from hybridmpm.service.frames import frame_message
from hybridmpm.service.logs import SHOWN_ID_CHARS
from hybridmpm.service.store import SHOWN_KEY_CHARS, SessionStore, load_unexpired, session_key
from hybridmpm.sim import Frame, RealtimeSimulator, Rollout

log = logging.getLogger("hybridmpm.service")
T = TypeVar("T")
#: A control gives the compute it holds to work that waits for it (another session's step) at most this often [s]:
#: such work starts within about this (plus the control's unit of work: a frame, or 10 frames of an MPC model
#: rollout), and the control pays one hand-over per period while others wait, none while nobody does.
SHARE_EVERY_S = 0.05


class ComputeShare:
    """The compute tokens one long call holds (a control: as many of the
    limiter's tokens as its session's MPM threads, taken as
    :meth:`SessionManager.compute_wide` takes them), and the hand-over its
    worker thread calls between units of work (:meth:`__call__`): when work
    waits for the compute and :data:`SHARE_EVERY_S` has passed since the
    last hand-over, it gives its tokens to the waiters (the limiter hands a
    freed token to the first in line) and queues for them again behind them.
    A control thus shares the cores with the other sessions instead of
    holding them for its whole plan and run."""

    def __init__(self, manager: SessionManager, width: int) -> None:
        self.manager = manager
        self.tokens = [object() for _ in range(max(1, int(width)))]
        self.held = 0
        self.last = time.monotonic()
        self.handovers = 0

    async def take(self) -> None:
        """Take every token (a wide call's one wide call at a time); cancelled meanwhile, it gives back those it took."""
        limiter = self.manager.limiter
        async with self.manager._wide if len(self.tokens) > 1 else contextlib.nullcontext():
            try:
                for t in self.tokens[self.held :]:
                    await limiter.acquire_on_behalf_of(t)
                    self.held += 1
            except BaseException:
                self.give()
                raise

    def give(self) -> None:
        """Give back the tokens it holds (event loop thread)."""
        while self.held:
            self.held -= 1
            self.manager.limiter.release_on_behalf_of(self.tokens[self.held])

    async def _hand_over(self) -> None:
        self.give()
        await self.take()

    def __call__(self) -> None:
        """From the worker thread between units of work: hand the compute over when work waits for it."""
        now = time.monotonic()
        if now - self.last < SHARE_EVERY_S:
            return
        self.last = now
        if not self.manager.limiter.statistics().tasks_waiting:
            return
        anyio.from_thread.run(self._hand_over)
        self.handovers += 1
        self.last = time.monotonic()


#: What a session costs beyond its state arrays (simulator objects, grids, buffers) [bytes], for the memory budget.
SESSION_OVERHEAD = 4 << 20
#: Copies of its state a session's cost counts: the live simulator, the initial state kept for "reset", a step's working copy.
SESSION_STATE_COPIES = 3


@dataclass(eq=False)
class LocalSession:
    """A session of this process as the routes hold it (a
    :class:`~hybridmpm.service.backend.Session`): its ``id``, store ``key``,
    plain ``settings`` and ``facts``, the client address that created it, its
    :class:`~hybridmpm.service.core.SessionCore` (``core``) and its viewers."""

    id: str
    key: str
    settings: SessionSettings
    facts: SessionFacts
    core: SessionCore
    client: str = ""
    lock: asyncio.Lock = field(default_factory=asyncio.Lock)  # calls into the core queue here, in order
    save_lock: asyncio.Lock = field(default_factory=asyncio.Lock)
    last_used: float = field(default_factory=time.monotonic)
    viewers: set[Viewer] = field(default_factory=set)
    play_task: asyncio.Task[None] | None = None
    controlling: bool = False  # a control admitted here is running (the route's 409)
    closed: bool = False
    cost: int = 0  # bytes taken from the memory budget (controls not included)

    @property
    def frame_index(self) -> int:
        """The frame the session is at."""
        return self.core.frame_index

    def touch(self) -> None:
        self.last_used = time.monotonic()
        self.core.touch()

    def republish(self) -> None:
        """Offer the current frame to the viewers again (after a control that stopped early)."""
        self.core.republish()

    def offer(self, fr: Frame, control_frame: int = 0, realtime: dict[str, Any] | None = None) -> None:
        """Offer a frame to every viewer (event loop thread only); ``realtime``: a real-time session's
        :meth:`~hybridmpm.service.core.SessionCore.realtime_info` when the frame was made (its header's factor)."""
        if self.viewers:
            offer_all(self.viewers, frame_message(fr, control_frame, realtime))

    def broadcast(self, msg: dict[str, Any]) -> None:
        """An event for every viewer (event loop thread only)."""
        for v in list(self.viewers):
            v.event(msg)

    def bind(self, loop: asyncio.AbstractEventLoop) -> None:
        """Hand the core's frames and events to this process's viewers, on ``loop``."""

        def on_frame(fr: Frame, control_frame: int) -> None:
            # read here, under the core's lock in the thread that stepped it: the factor of the frame's own step
            loop.call_soon_threadsafe(self.offer, fr, control_frame, self.core.realtime_info())

        def on_event(msg: dict[str, Any]) -> None:
            loop.call_soon_threadsafe(self.broadcast, msg)

        self.core.on_frame, self.core.on_event = on_frame, on_event
        self.core.has_viewers = lambda: bool(self.viewers)


class SessionManager:
    """The local backend (:class:`~hybridmpm.service.backend.SessionBackend`
    over :class:`LocalSession`): the sessions of this process (a plain dict),
    the compute limiter, the reaper and, with a store, the periodic saver."""

    #: Sessions run here (the Ray backend's run in actors).
    remote = False
    #: Temporary files of torn saves older than this are removed when the store opens [s]
    #: (:meth:`SessionStore.open`; one process writes this store, so all of them).
    store_clean_after_s: float | None = 0.0

    def __init__(self, config: ServiceConfig) -> None:
        self.config = config
        self.sessions: dict[str, LocalSession] = {}
        self.reserved = 0
        self.reserved_by: collections.Counter[str] = collections.Counter()
        self.budget = MemoryBudget(config.memory_budget_bytes)
        self.limiter = anyio.CapacityLimiter(config.compute_threads)
        self._wide = asyncio.Lock()  # one wide call takes its tokens at a time (compute_wide)
        self._unlimited = anyio.CapacityLimiter(max(1, config.max_sessions) + config.compute_threads)  # a wide call's thread: its tokens are held
        self.controls_running = 0
        self._reaper: asyncio.Task[None] | None = None
        self._saver: asyncio.Task[None] | None = None
        self._saving: dict[str, asyncio.Task[bool]] = {}  # the periodic saver's save in progress, per session key
        #: Durable sessions (None without ``config.store``).
        self.store: SessionStore | None
        #: Sessions restored from the store whose id no request has named yet, by key.
        self.unclaimed: dict[str, LocalSession] = {}
        self.io_limiter = anyio.CapacityLimiter(1)
        self.store = open_store(config, self.store_clean_after_s)

    # ------------------------------------------------------------ compute
    async def compute(self, fn: Callable[..., T], *args: Any) -> T:
        """Run ``fn(*args)`` in a worker thread under the compute limiter (:func:`~hybridmpm.service.backend.on_worker`)."""
        return await on_worker(self.limiter, fn, *args)

    # ------------------------------------------------------------ lifecycle
    def count(self) -> int:
        """Sessions held (restored ones no request has named yet included)."""
        return len(self.sessions) + len(self.unclaimed)

    def sessions_of(self, client: str) -> int:
        """Sessions held or being built for the client address ``client``."""
        held = sum(1 for s in (*self.sessions.values(), *self.unclaimed.values()) if s.client == client)
        return held + self.reserved_by[client]

    async def create(
        self,
        scene: str,
        seed: int,
        solver: str,
        r_c: float,
        client: str = "",
        *,
        n_grid: int | None = None,
        integrator: str | None = None,
        when_full: str = "refuse",
    ) -> LocalSession:
        """Build a session for the client address ``client`` (``n_grid``: MPM
        on a coarser grid of the scene, :func:`~hybridmpm.service.facts.checked_n_grid`;
        ``integrator``: what its MPM steps with, :func:`~hybridmpm.service.facts.checked_integrator`;
        ``solver`` ``realtime``: real-time mode, :func:`~hybridmpm.service.facts.checked_realtime`, admitted
        at the rung the playing ones leave room for, ``when_full`` saying what a full server does:
        :func:`~hybridmpm.service.capacity.admit`).
        With a store the session is saved before it is answered; when that
        save fails the session is dropped and :class:`StoreSaveError` raised
        (nothing already saved changes).
        Raises :class:`SessionCapError` when the server is full,
        :class:`~hybridmpm.service.capacity.RealtimeFullError` when real time is,
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
            sid = secrets.token_urlsafe(24)  # 192 bits
            settings = SessionSettings(scene, int(seed), solver, float(r_c), n_grid, integrator)
            with self.budget.hold(SESSION_OVERHEAD, "a new session"):
                threads = await self.compute(session_threads, settings, self.config.compute_threads)
                core = await self.compute(functools.partial(SessionCore.build, session_key(sid), settings, client, self.budget, threads))
            try:  # a real-time session: the rung it starts on, or the 503
                admit_session(core, [x.core for x in self.sessions.values()], self.config.compute_threads, when_full)
            except RealtimeFullError:
                core.close()
                raise
            try:
                cost = self.budget.take(SESSION_STATE_COPIES * tree_nbytes(core.initial) + SESSION_OVERHEAD, "a new session")
            except BudgetFullError:
                core.close()
                raise
            sess = self._adopt(sid, core, cost)
            self.sessions[sid] = sess
            if self.store is not None:
                core.dirty = True
                if not await self.save(sess):  # a 201 means the session is durable: one that is not is not created
                    failure = core.save_failure
                    del self.sessions[sid]
                    await self._drop(sess, 1011, "not saved", True)
                    raise StoreSaveError(failure)
            return sess
        finally:
            self.reserved -= 1
            self.reserved_by[client] -= 1
            if self.reserved_by[client] <= 0:
                del self.reserved_by[client]

    def _adopt(self, sid: str, core: SessionCore, cost: int) -> LocalSession:
        """The routes' handle of ``core``, its frames and events bound to this process's viewers."""
        s = LocalSession(sid, core.key, core.settings, core.facts, client=core.client, core=core, cost=cost)
        s.last_used = core.last_used
        s.bind(asyncio.get_running_loop())
        return s

    @staticmethod
    def core_of(s: LocalSession) -> SessionCore:
        """``s``'s core."""
        return s.core

    async def compute_wide(self, width: int, fn: Callable[..., T], *args: Any) -> T:
        """:meth:`compute` for work on ``width`` threads: it holds ``width``
        of the compute limiter's tokens while it runs. The tokens are taken
        one wide call at a time (a narrow call holds one and always ends), so
        two wide calls never each hold part of what the other waits for; a call
        cancelled while it takes them gives back those it took."""
        if width <= 1:
            return await self.compute(fn, *args)
        tokens = [object() for _ in range(width)]
        async with self._wide:
            taken = 0
            try:
                for t in tokens:
                    await self.limiter.acquire_on_behalf_of(t)
                    taken += 1
            except BaseException:  # cancelled while it waits for a token (its session deleted): give back what it took
                for t in tokens[:taken]:
                    self.limiter.release_on_behalf_of(t)
                raise
        try:
            return await on_worker(self._unlimited, fn, *args)
        finally:
            for t in tokens:
                self.limiter.release_on_behalf_of(t)

    async def on_core(self, s: LocalSession, fn: Callable[..., T], *args: Any) -> T:
        """Run ``fn(*args)`` (a method of ``s``'s core) on a worker, after
        the calls queued before it on ``s``, holding as many compute tokens
        as the session's MPM threads (:meth:`compute_wide`);
        :class:`SessionGoneError` when ``s`` was closed meanwhile."""
        async with s.lock:
            if s.closed:
                raise SessionGoneError()
            return await self.compute_wide(self.core_of(s).threads, fn, *args)

    async def keep_control(self, s: LocalSession, c: Control) -> None:
        """Keep ``c`` on ``s`` (its cost already taken from the budget),
        dropping the oldest beyond :data:`~hybridmpm.service.core.KEEP_CONTROLS` and giving their cost back."""
        for old in self.core_of(s).keep_control(c):
            self.budget.give(old.cost)
            old.cost = 0

    async def get_control(self, s: LocalSession, cid: str) -> Control | None:
        """The kept control ``cid`` of ``s``, or None."""
        return self.core_of(s).get_control(cid)

    async def recorded(self, s: LocalSession, count: int) -> list[RecordedFrame]:
        """The latest ``count`` frames of ``s``'s recent trajectory, oldest first."""
        return self.core_of(s).recorded(count)

    async def find(self, sid: str) -> LocalSession | None:
        """The session ``sid`` (touched), or None: what a request names."""
        return self.get(sid)

    async def held(self) -> int:
        """Sessions held (``/healthz``)."""
        return self.count()

    def get(self, sid: str) -> LocalSession | None:
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

    async def _drop(self, s: LocalSession, code: int, reason: str, forget: bool) -> None:
        s.closed = True
        core = self.core_of(s)
        core.close()  # a control running on it stops within a frame and answers 404
        if forget and self.store is not None:
            async with s.save_lock:  # a save under way ends first (and the core writes no record once closed)
                await anyio.to_thread.run_sync(core.close, self.store, limiter=self.io_limiter)
        self.budget.give(s.cost + sum(c.cost for c in core.controls.values()))
        s.cost = 0
        for c in core.controls.values():
            c.cost = 0
        if s.play_task is not None:
            s.play_task.cancel()
        await close_viewers(s.viewers, code, reason)

    async def reap_once(self) -> list[str]:
        ttl = self.config.idle_ttl_s
        stale = [sid for sid, s in self.sessions.items() if self.core_of(s).expired(ttl) and not s.lock.locked()]
        for sid in stale:
            await self.close(sid, 4000, "expired")
            log.info("session %s… expired", sid[:SHOWN_ID_CHARS])
        for key in [k for k, s in self.unclaimed.items() if self.core_of(s).expired(ttl)]:
            await self._drop(self.unclaimed.pop(key), 4000, "expired", True)
            log.info("restored session %s… (store key) expired", key[:SHOWN_KEY_CHARS])
        return stale

    def start(self) -> None:
        """Start the reaper (every ``reap_interval_s``) and, with a store, the periodic saver (every ``save_every_s``)."""
        loop = asyncio.get_running_loop()
        if self._reaper is None:
            self._reaper = loop.create_task(every(float(self.config.reap_interval_s or 30.0), self.reap_once, "reaper"))
        if self.store is not None and self._saver is None:
            self._saver = loop.create_task(every(float(self.config.save_every_s), self.save_round, "saver"))

    async def stop(self) -> None:
        """Stop the loops, save every changed session (a clean stop loses nothing) and close them, keeping their records."""
        await stop_task(self._reaper)
        await stop_task(self._saver)
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
    async def save(self, s: LocalSession) -> bool:
        """Write ``s``'s checkpoint to the store if it changed since its last
        save; False when it could not (logged; it stays marked changed and
        the saver tries again). The snapshot
        (:meth:`~hybridmpm.service.core.SessionCore.snapshot`) waits for the
        session's lock, so it is taken at a step boundary (a step or control
        running is waited for: the lock is fair, so the next step queues
        behind the snapshot); taking it and writing it run on the store's
        I/O thread, not the compute workers, so busy sessions do not delay it."""
        store, core = self.store, self.core_of(s)
        if store is None or s.closed or not core.dirty:
            return True
        async with s.save_lock:
            if s.closed or not core.dirty:
                return True
            with self.budget.hold(2 * tree_nbytes(core.initial), "saving a session"):
                async with s.lock:
                    if s.closed:
                        return True
                    snap = await anyio.to_thread.run_sync(core.snapshot, limiter=self.io_limiter)
                if snap is None:
                    return True
                ok: bool = await anyio.to_thread.run_sync(core.write, store, *snap, limiter=self.io_limiter)
                del snap
                return ok

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
            if self.core_of(s).dirty and not s.closed and s.key not in self._saving:
                task = asyncio.get_running_loop().create_task(self.save(s))
                self._saving[s.key] = task
                task.add_done_callback(functools.partial(self._saved, s.key))

    def _saved(self, key: str, _task: asyncio.Task[bool]) -> None:
        self._saving.pop(key, None)

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
                rec = await anyio.to_thread.run_sync(
                    load_unexpired, store, key, self.config.max_checkpoint_bytes, self.config.idle_ttl_s, limiter=self.io_limiter
                )
            except InvalidInputError as e:
                log.warning("%s; not restored", e)
                continue
            if rec is None:
                continue
            if self.count() >= self.config.max_sessions:
                log.warning("store: session %s… not restored: the server holds its maximum of %d sessions", shown, self.config.max_sessions)
                continue
            try:
                with self.budget.hold(SESSION_OVERHEAD + 2 * tree_nbytes(rec.state), "restoring a session"):
                    core = await self.compute(SessionCore.load, rec, self.budget, self.config.compute_threads)
                try:
                    cost = self.budget.take(SESSION_STATE_COPIES * tree_nbytes(core.initial) + SESSION_OVERHEAD, "a restored session")
                except BudgetFullError:
                    core.close()
                    raise
            except BudgetFullError as e:
                log.warning("store: session %s… not restored: %s", shown, e)
                continue
            except (InvalidInputError, CheckpointError) as e:
                log.warning("store: session %s…: checkpoint: %s; not restored", shown, e)
                continue
            except (KeyError, TypeError, ValueError, AttributeError, IndexError, OverflowError) as e:
                log.warning("store: session %s…: checkpoint: malformed state (%s); not restored", shown, type(e).__name__)
                continue
            self.unclaimed[key] = self._adopt(key, core, cost)
            restored += 1
            log.info("store: session %s… restored at frame %d", shown, core.frame_index)
        return restored

    # ------------------------------------------------------------ the work of the routes
    async def info(self, s: LocalSession) -> dict[str, Any]:
        """``s``'s description (``GET /v1/sessions/{id}``)."""
        return {"id": s.id, **self.core_of(s).info(), "viewers": len(s.viewers), "stream": f"/v1/sessions/{s.id}/stream"}

    async def rollout(self, s: LocalSession, frames: int) -> Rollout:
        """Advance ``s`` by ``frames`` frames (:meth:`SessionCore.rollout <hybridmpm.service.core.SessionCore.rollout>`);
        :class:`SessionGoneError` when it was closed meanwhile."""
        return await self.on_core(s, self.core_of(s).rollout, frames)

    async def run_control(
        self, s: LocalSession, sketch: Any, method: str, frames: int, left: Any, first: list[float], cid: str
    ) -> tuple[Rollout, dict[str, Any], Any]:
        """Control ``cid`` on ``s`` with ``method`` for ``frames`` frames
        (:meth:`SessionCore.control <hybridmpm.service.core.SessionCore.control>`
        on a worker thread), its frames and plan offered to the viewers as
        they come; ``left`` (a :class:`threading.Event`) set stops it within
        a frame, and so does closing ``s`` (a delete, an expiry), a plan in
        progress too (between its model rollouts' frames). It holds the
        session's share of the compute (:class:`ComputeShare`) and hands it
        to other sessions' work that waits for it, so a long control (an MPC
        plan, a 1000-frame run) never stalls them. Appends the
        time of the first controlled frame to ``first``; returns ``(rollout,
        metrics, plan summary)``; :class:`SessionGoneError` when it was
        closed before or during the control. With a store the core saves it
        before the control is announced and after it ends (its save policy)."""
        core = self.core_of(s)
        async with s.lock:
            if s.closed:
                raise SessionGoneError()
            share = ComputeShare(self, core.threads)
            await share.take()
            try:
                ro, metrics, plan, t_first = await on_worker(self._unlimited, core.control, method, frames, sketch, cid, left.is_set, self.store, share)
            finally:
                share.give()
        if t_first is not None:
            first.append(t_first)
        return ro, metrics, plan

    async def checkpoint(self, s: LocalSession) -> bytes:
        """``s``'s whole state as a checkpoint (:func:`hybridmpm.service.checkpoint.dumps`);
        :class:`BudgetFullError` when the budget cannot hold two copies of it."""
        with self.budget.hold(2 * tree_nbytes(self.core_of(s).initial), "writing the checkpoint"):
            return await self.on_core(s, self.core_of(s).checkpoint)

    async def restore(self, s: LocalSession, state: dict[str, Any]) -> None:
        """Restore ``state`` into ``s``, all or nothing: the simulator's
        refusal (:class:`InvalidInputError`, :class:`CheckpointError`, or a
        ``KeyError``/``TypeError``/... of a malformed tree) leaves it as it was."""
        await self.on_core(s, self.core_of(s).restore, state)
        s.facts = self.core_of(s).facts  # a state taken before or after a pour has its own particles

    async def reset(self, s: LocalSession) -> None:
        """Back to the initial condition; the viewers get the frame and a ``reset`` event."""
        await self.on_core(s, self.core_of(s).reset)
        s.facts = self.core_of(s).facts  # a session that was poured into has its scene's particles again

    async def pour(self, s: LocalSession, block: dict[str, Any]) -> dict[str, Any]:
        """Add ``block`` to ``s`` between frames (:meth:`SessionCore.pour
        <hybridmpm.service.core.SessionCore.pour>`); every viewer gets a
        ``particles`` event. Returns its answer."""
        # at call time: the simulators' modules load with the first pour, and a test lowers the bound
        from hybridmpm.scenes.core import BYTES_PER_PARTICLE
        from hybridmpm.sim.pour import MAX_POUR_PARTICLES

        # the most a pour can add taken from the service's budget first (a full budget refuses it, the session
        # unchanged); what it did not add given back, what it added counted in the session's cost until it goes
        per = SESSION_STATE_COPIES * BYTES_PER_PARTICLE
        held = self.budget.take(per * MAX_POUR_PARTICLES, "a poured block")
        try:
            out = await self.on_core(s, self.core_of(s).pour, block)
        except BaseException:
            self.budget.give(held)
            raise
        used = min(held, per * int(out["added"]))
        self.budget.give(held - used)
        s.cost += used
        s.facts = self.core_of(s).facts
        s.touch()
        return dict(out)

    async def add_body(self, s: LocalSession, body: dict[str, Any]) -> dict[str, Any]:
        """Add rigid body ``body`` to ``s`` between frames (:meth:`SessionCore.add_body
        <hybridmpm.service.core.SessionCore.add_body>`); every viewer gets a ``bodies``
        event. A body's state is a few hundred bytes: nothing is charged to the budget."""
        out = await self.on_core(s, self.core_of(s).add_body, body)
        s.facts = self.core_of(s).facts
        s.touch()
        return dict(out)

    async def remove_body(self, s: LocalSession, index: int) -> dict[str, Any]:
        """Remove rigid body ``index`` of ``s`` between frames (:meth:`SessionCore.remove_body
        <hybridmpm.service.core.SessionCore.remove_body>`); every viewer gets a ``bodies`` event."""
        out = await self.on_core(s, self.core_of(s).remove_body, index)
        s.facts = self.core_of(s).facts
        s.touch()
        return dict(out)

    async def move_obstacle(self, s: LocalSession, index: int, center: list[float], velocity: list[float] | None) -> int:
        """Move obstacle ``index`` of ``s`` to ``center`` over its next step
        (:meth:`SessionCore.move_obstacle <hybridmpm.service.core.SessionCore.move_obstacle>`);
        every viewer gets an ``obstacle`` event. Returns the session's frame."""
        frame = await self.on_core(s, self.core_of(s).move_obstacle, index, center, velocity)
        s.touch()
        return frame

    async def attach(self, s: LocalSession, v: Viewer) -> None:
        """A new viewer of ``s``: its ``meta`` message (the description, a
        running control included) and the current frame are offered first,
        then every event emitted after the description (the core sets a
        control's state before it emits its ``running`` event: one in
        between may come twice, never not at all)."""
        s.viewers.add(v)
        core = self.core_of(s)
        v.opening(meta_message(await self.info(s), core.playing))
        v.offer(frame_message(core.sim.frame, 0, core.realtime_info()))

    async def detach(self, s: LocalSession, v: Viewer) -> None:
        s.viewers.discard(v)

    async def set_playing(self, s: LocalSession, playing: bool) -> None:
        """Play (one coarse step at a time, no faster than real time, while it has viewers) or pause ``s``."""
        self.core_of(s).playing = playing
        if playing:
            self.ensure_playing(s)

    # ------------------------------------------------------------ play loop
    def ensure_playing(self, s: LocalSession) -> None:
        if self.core_of(s).playing and s.viewers and (s.play_task is None or s.play_task.done()):
            s.play_task = asyncio.get_running_loop().create_task(self._play(s))

    async def _play(self, s: LocalSession) -> None:
        """Run ``s``'s play loop (:meth:`SessionCore.play <hybridmpm.service.core.SessionCore.play>`):
        each step on a worker after the calls queued on ``s``, the wait between steps on the event loop."""
        steps: Iterator[float] = self.core_of(s).play()
        try:
            while not s.closed:
                async with s.lock:
                    if s.closed:
                        break
                    core = self.core_of(s)
                    if isinstance(core.sim, RealtimeSimulator):  # its part of the machine's real time (capacity.py)
                        core.sim.set_share(realtime_share([x.core for x in self.sessions.values()], self.config.compute_threads))
                    delay = await self.compute_wide(core.threads, next, steps, None)
                if delay is None:
                    break
                await asyncio.sleep(delay)
        except asyncio.CancelledError:
            pass


__all__ = [
    "RETRY_AFTER_S",
    "LocalSession",
    "QuotaError",
    "LocalSession",
    "SessionCapError",
    "SessionManager",
    "StoreSaveError",
    "Viewer",
    "close_ws",
]
