"""Sessions on a Ray cluster (``hybridmpm serve --backend ray``).

Each session is a named, detached Ray actor
(:class:`~hybridmpm.service.ray_backend.actor.SessionActor`, named ``session-`` + the
SHA-256 of its id, in the namespace ``ServiceConfig.ray_namespace``) that
runs its :class:`~hybridmpm.service.core.SessionCore` (the same core the
local backend runs: simulator, kept controls, play loop, saves), placed
by Ray with ``ServiceConfig.ray_num_cpus`` CPUs. This process is a *front
end*: :class:`RaySessionManager` implements
:class:`~hybridmpm.service.backend.SessionBackend` (what the routes call;
the local :class:`~hybridmpm.service.sessions.SessionManager` implements it
beside this one) over :class:`RaySession` handles, by finding a
session's actor by name and running the routes' work there (a step, a
control episode, a checkpoint, a restore, a reset), so any number of front
ends serve every session. The session cap and the per-client quota count the
whole cluster (:class:`~hybridmpm.service.ray_backend.registry.Registry`); a session that
does not fit on the cluster's CPUs answers 503 with ``Retry-After``. The
handles, joining the cluster (:func:`connect`) and an actor's refusal raised
again (:func:`error_from`) are :mod:`~hybridmpm.service.ray_backend.front`'s.

Streams: for each session with viewers here, one task pulls the actor's
latest frame (at most ``max_fps`` a second, long polls) and its events, and
offers the same bytes to every viewer's latest-frame slot (no copy per client).

Durable sessions: with ``--store`` (shared by every node) each actor saves
itself; when its process or its node dies, Ray builds it again on a live
node from its last save (``max_restarts``), and a request meanwhile waits
for it; a session whose actor is gone while its record is still in the store
(a restarted cluster) is built again from it when a request names it, and a
front end restores every unexpired record at start. Errors: a session
deleted, expired or lost answers 404 (:class:`SessionGoneError`); one that
does not come back within :data:`REVIVE_TIMEOUT_S` 503.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import secrets
import time
from collections.abc import Callable
from typing import Any, TypeVar

import anyio
import anyio.to_thread
import ray
import ray.exceptions

from hybridmpm.control import Sketch
from hybridmpm.errors import HybridMpmError, InvalidInputError
from hybridmpm.service.backend import (
    QuotaError,
    SessionCapError,
    Viewer,
    close_viewers,
    every,
    meta_message,
    offer_all,
    on_worker,
    open_store,
    stop_task,
)
from hybridmpm.service.budget import MemoryBudget, RecordedFrame
from hybridmpm.service.config import ServiceConfig
from hybridmpm.service.core import Control, SessionGoneError
from hybridmpm.service.errors import ApiError
from hybridmpm.service.facts import SessionFacts, SessionSettings
from hybridmpm.service.logs import SHOWN_ID_CHARS
from hybridmpm.service.ray_backend.actor import ACTOR_THREADS, SessionActor
from hybridmpm.service.ray_backend.front import BUILTIN_ERRORS, RaySession, connect, error_from
from hybridmpm.service.ray_backend.registry import ACTOR_PREFIX, REGISTRY_NAME, Registry
from hybridmpm.service.store import SHOWN_KEY_CHARS, StoredSession, load_unexpired, session_key
from hybridmpm.sim import Rollout

log = logging.getLogger("hybridmpm.service")
T = TypeVar("T")

#: How long creating a session waits for its actor to be placed and built [s] (then 503).
PLACE_TIMEOUT_S = 120.0
#: How long a request waits for a session's actor to come back after its process died [s] (then 503).
REVIVE_TIMEOUT_S = 60.0
#: Longest wait of one poll of a session's frames and events [s].
POLL_WAIT_S = 1.0
#: ``Retry-After`` of a 503 for a cluster without room or a session not back yet [s].
RETRY_S = 5
#: A session's description in this front end is dropped after this long unused (its actor stays) [s].
FORGET_AFTER_S = 600.0


class RaySessionManager:
    """The session backend of a front end of a Ray cluster (module doc; :class:`~hybridmpm.service.backend.SessionBackend` over
    :class:`RaySession`). Raises :class:`InvalidInputError` naming ``ray_address`` when it cannot join the cluster, ``store`` when
    the store cannot be written."""

    #: Sessions run in the cluster's actors, which save and expire themselves.
    remote = True
    #: Temporary files of torn saves older than this are removed when the store opens [s]
    #: (other front ends' and actors' saves may be in progress).
    store_clean_after_s = 60.0

    def __init__(self, config: ServiceConfig) -> None:
        self.config = config
        self.budget = MemoryBudget(config.memory_budget_bytes)  # this front end's buffers (checkpoints, controls' answers)
        self.limiter = anyio.CapacityLimiter(config.compute_threads)  # this front end's own work (decoding, encoding)
        self.io_limiter = anyio.CapacityLimiter(1)
        self.controls_running = 0
        self._reaper: asyncio.Task[None] | None = None
        self.store = open_store(config, self.store_clean_after_s)
        connect(config)
        self.ns = config.ray_namespace
        self.front_id = secrets.token_hex(6)
        self.cache: dict[str, RaySession] = {}
        self._announcing: set[asyncio.Future[None]] = set()  # events sent to actors being restored
        self.actor_class = ray.remote(SessionActor)
        store_url = None
        if self.store is not None:
            store_url = self.store.root if self.store.local else self.store.url  # an absolute path: every node's actors
        self.settings = {
            "store": store_url,
            "save_every_s": config.save_every_s,
            "idle_ttl_s": config.idle_ttl_s,
            "max_checkpoint_bytes": config.max_checkpoint_bytes,
            "memory_budget": config.memory_budget_bytes,
            "namespace": self.ns,
        }
        self.registry: Any = (
            ray.remote(Registry)
            .options(
                name=REGISTRY_NAME,
                namespace=self.ns,
                lifetime="detached",
                get_if_exists=True,
                num_cpus=0,
                max_restarts=-1,
                resources={"node:__internal_head__": 0.001},  # on the head node: it lives as long as the cluster
            )
            .remote(store_url if self.store is not None and self.store.local else None, self.ns)
        )
        if self.store is not None and self.store.local:  # the registry holds the store's lock for every front end
            registry: Any = self.registry
            refused = ray.get(registry.claim_store.remote(store_url), timeout=PLACE_TIMEOUT_S)
            if refused is not None:
                raise InvalidInputError(str(refused), "store")

    # ------------------------------------------------------------ actors
    def _spawn(
        self, key: str, scene: str, seed: int, solver: str, r_c: float, client: str, restore: bool, n_grid: int | None = None, integrator: str | None = None
    ) -> Any:
        """The session actor of ``key`` (created, or the one already there). Blocks: call it off the event loop."""
        return self.actor_class.options(
            name=ACTOR_PREFIX + key,
            namespace=self.ns,
            lifetime="detached",
            get_if_exists=True,
            num_cpus=self.config.ray_num_cpus,
            max_restarts=-1 if self.store is not None else 0,
            max_task_retries=0,
            max_concurrency=ACTOR_THREADS,
            scheduling_strategy="SPREAD",
        ).remote(key, scene, seed, solver, r_c, client, self.settings, restore, n_grid, integrator)

    def _lookup(self, key: str) -> Any:
        """The live actor of ``key``, or None. Blocks."""
        try:
            return ray.get_actor(ACTOR_PREFIX + key, namespace=self.ns)
        except ValueError:
            return None

    async def compute(self, fn: Callable[..., T], *args: Any) -> T:
        """``fn(*args)`` on a worker thread of this front end (:func:`~hybridmpm.service.backend.on_worker`)."""
        return await on_worker(self.limiter, fn, *args)

    async def _end(self, key: str, actor: Any | None) -> None:
        """The one way a session leaves the cluster from a front end: its actor
        (if any) is killed, not to be restarted, and the registry no longer
        counts ``key``. Errors (an actor or registry already gone) are ignored."""
        if actor is not None:
            with contextlib.suppress(Exception):
                await anyio.to_thread.run_sync(lambda: ray.kill(actor, no_restart=True))
        with contextlib.suppress(Exception):
            await self.registry.release.remote(key)

    async def _reserve(self, key: str, client: str, restoring: bool = False) -> None:
        verdict = await self.registry.reserve.remote(key, client, self.config.max_sessions, self.config.max_sessions_per_client, restoring)
        if verdict == "cap":
            raise SessionCapError()
        if verdict == "quota":
            raise QuotaError()

    async def _room(self) -> None:
        """503 when the cluster has no CPU left for another session's actor."""
        free = await anyio.to_thread.run_sync(ray.available_resources)
        if float(free.get("CPU", 0.0)) + 1e-9 < self.config.ray_num_cpus:
            msg = f"the cluster has no free CPU for another session (each takes {self.config.ray_num_cpus:g}); add a node or retry later"
            raise ApiError(503, msg, {"Retry-After": str(RETRY_S)})

    async def _ready(self, actor: Any, timeout: float) -> dict[str, Any]:
        """The actor's facts once it is built; its construction's error raised
        (:func:`error_from`); :class:`SessionGoneError` if it died or cannot be reached in time."""
        deadline = time.monotonic() + timeout
        while True:
            try:
                out = await asyncio.wait_for(actor.ready.remote(), max(0.1, deadline - time.monotonic()))
            except asyncio.TimeoutError:
                raise SessionGoneError() from None
            except ray.exceptions.ActorUnavailableError:
                if time.monotonic() > deadline:
                    raise SessionGoneError() from None
                await asyncio.sleep(0.05)
                continue
            except ray.exceptions.RayActorError:
                raise SessionGoneError() from None
            if out[0] == "ok":
                return dict(out[1])
            if out[0] == "err":
                raise error_from(*out[1:])
            raise SessionGoneError()

    def _session(self, sid: str, key: str, actor: Any, ready: dict[str, Any]) -> RaySession:
        """The handle of a session whose actor answered ``ready`` (:meth:`SessionActor.ready <hybridmpm.service.ray_backend.actor.SessionActor.ready>`)."""
        settings, facts = SessionSettings(**ready["settings"]), SessionFacts.from_dict(ready["facts"])
        s = RaySession(sid, key, settings, facts, client=ready["client"], at_frame=int(ready["frame"]))
        s.actor, s.name, s.state_nbytes = actor, ACTOR_PREFIX + key, int(ready["state_nbytes"])
        s.touched_remote = s.last_used
        return s

    async def _from_store(self, key: str) -> Any:
        """Build ``key``'s actor again from its stored record (a restarted
        cluster, or an actor Ray did not restart); None when there is no
        loadable, unexpired record. An expired one is removed."""
        store = self.store
        if store is None or not await anyio.to_thread.run_sync(store.has, key, limiter=self.io_limiter):
            return None
        try:
            max_bytes, ttl = self.config.max_checkpoint_bytes, self.config.idle_ttl_s
            rec: StoredSession | None = await anyio.to_thread.run_sync(load_unexpired, store, key, max_bytes, ttl, limiter=self.io_limiter)
        except InvalidInputError as e:
            log.warning("%s; not restored", e)
            return None
        if rec is None:
            return None
        await self._reserve(key, rec.client, restoring=True)
        try:
            return await anyio.to_thread.run_sync(self._spawn, key, rec.scene, rec.seed, rec.solver, rec.r_c, rec.client, True, rec.n_grid, rec.integrator)
        except Exception:
            await self._end(key, None)
            raise

    async def _restore(self, key: str) -> Any:
        """:meth:`_from_store` for a request: a cluster at its cap answers 503 (the session waits in the store)."""
        try:
            return await self._from_store(key)
        except SessionCapError:
            msg = f"the cluster holds its maximum of {self.config.max_sessions} sessions; this one waits in the store, retry later"
            raise ApiError(503, msg, {"Retry-After": str(RETRY_S)}) from None

    async def _revive(self, s: RaySession) -> bool:
        """``s``'s actor died: the one Ray builds again, or one built from the store. False when the session is gone."""
        actor = await anyio.to_thread.run_sync(self._lookup, s.key)
        if actor is None:
            actor = await self._restore(s.key)
        if actor is None:
            return False
        s.actor = actor
        return True

    async def _forget(self, s: RaySession, code: int = 4004, reason: str = "no such session") -> None:
        s.closed = True
        if self.cache.get(s.id) is s:
            del self.cache[s.id]
        await close_viewers(s.viewers, code, reason)

    async def _call(self, s: RaySession, method: str, *args: Any, retry: bool = True) -> Any:
        """Run ``method`` of ``s``'s actor and answer its value. A refusal is
        raised as its own type, a second control as a 409; a session deleted,
        expired or lost as :class:`SessionGoneError`. When the actor's process
        died, the call waits for it to come back (Ray's restart, or the store)
        and runs again — unless ``retry`` is False (a control: 503)."""
        deadline = time.monotonic() + REVIVE_TIMEOUT_S
        while True:
            try:
                out = await getattr(s.actor, method).remote(*args)
            except ray.exceptions.ActorUnavailableError:  # its process died a moment ago; Ray is restarting it
                if not retry or time.monotonic() > deadline:
                    raise ApiError(
                        503, "the session's process was lost; it is being restored from its last save, retry", {"Retry-After": str(RETRY_S)}
                    ) from None
                await asyncio.sleep(0.05)
                continue
            except ray.exceptions.RayActorError:
                if time.monotonic() > deadline or not await self._revive(s):
                    await self._forget(s)
                    raise SessionGoneError() from None
                if not retry:
                    raise ApiError(
                        503, "the session's process was lost; it is being restored from its last save, retry", {"Retry-After": str(RETRY_S)}
                    ) from None
                continue
            kind = out[0]
            if kind == "ok":
                return out[1]
            if kind == "err":
                raise error_from(*out[1:])
            if kind == "busy":
                raise ApiError(409, "a control is already running on this session")
            await self._end(s.key, s.actor)  # closed, or it could not be restored: its actor goes
            await self._forget(s)
            raise SessionGoneError()

    # ------------------------------------------------------------ lifecycle
    async def held(self) -> int:
        """Sessions of the whole cluster (the registry's count)."""
        return int(await self.registry.count.remote())

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
    ) -> RaySession:
        """A new session in its own actor (``solver`` ``realtime``: real-time mode, as the route resolved the
        request's ``realtime``, :func:`~hybridmpm.service.facts.checked_realtime`; the actor's frames and events
        carry it; ``when_full`` is not used: the cluster admits no real-time session by capacity, each playing one
        takes its share of its node, :mod:`~hybridmpm.service.ray_backend.shares`). Raises :class:`SessionCapError` /
        :class:`QuotaError` (counted over the cluster), :class:`ApiError` 503
        when the cluster has no CPU for it, and the simulator's
        :class:`InvalidInputError` for bad settings."""
        sid = secrets.token_urlsafe(24)  # 192 bits
        key = session_key(sid)
        await self._reserve(key, client)
        actor = None
        try:
            await self._room()
            actor = await anyio.to_thread.run_sync(self._spawn, key, scene, seed, solver, r_c, client, False, n_grid, integrator)
            try:
                facts = await self._ready(actor, PLACE_TIMEOUT_S)
            except SessionGoneError:
                raise ApiError(503, "no node of the cluster took the new session in time; retry later", {"Retry-After": str(RETRY_S)}) from None
        except BaseException:
            await self._end(key, actor)
            raise
        s = self._session(sid, key, actor, facts)
        self.cache[sid] = s
        return s

    async def find(self, sid: str) -> RaySession | None:
        """The session ``sid``: this front end's handle, or its actor found by
        name (or built again from the store); None when there is none."""
        s = self.cache.get(sid)
        if s is not None and not s.closed:
            s.touch()
            return s
        if len(sid) >= 256:
            return None
        key = session_key(sid)
        actor = await anyio.to_thread.run_sync(self._lookup, key)
        if actor is None:
            actor = await self._restore(key)
            if actor is None:
                return None
        try:
            facts = await self._ready(actor, REVIVE_TIMEOUT_S)
        except SessionGoneError:
            return None
        except (HybridMpmError, *BUILTIN_ERRORS.values()) as e:  # its record could not be restored
            log.warning("session %s… cannot be restored: %s", sid[:SHOWN_ID_CHARS], e)
            await self._end(key, actor)
            return None
        s = self.cache.get(sid)  # another request may have found it meanwhile
        if s is None or s.closed:
            s = self._session(sid, key, actor, facts)
            self.cache[sid] = s
        s.touch()
        return s

    async def close(self, sid: str, code: int = 1000, reason: str = "closed", forget: bool = True) -> bool:
        """Delete session ``sid`` in the cluster (its record too), closing its sockets here."""
        s = await self.find(sid)
        if s is None:
            return False
        with contextlib.suppress(SessionGoneError):
            await self._call(s, "delete", code, reason)
        await self._end(s.key, s.actor)
        await self._forget(s, code, reason)
        return True

    async def reap_once(self) -> list[str]:
        """Drop this front end's handles unused for :data:`FORGET_AFTER_S` (the actors expire themselves)."""
        now = time.monotonic()
        stale = [sid for sid, s in self.cache.items() if not s.viewers and now - s.last_used > max(FORGET_AFTER_S, self.config.idle_ttl_s)]
        for sid in stale:
            self.cache.pop(sid, None)
        return stale

    def start(self) -> None:
        """Start the reaper of this front end's handles (every ``reap_interval_s``; the actors save and expire themselves)."""
        if self._reaper is None:
            self._reaper = asyncio.get_running_loop().create_task(every(float(self.config.reap_interval_s or 30.0), self.reap_once, "reaper"))

    async def stop(self) -> None:
        """Close this front end's sockets (1001) and leave the cluster; the sessions stay in it."""
        await stop_task(self._reaper)
        self._reaper = None
        for s in list(self.cache.values()):
            if s.pump is not None:
                s.pump.cancel()
            await close_viewers(s.viewers, 1001, "server shutting down")
        self.cache.clear()
        with contextlib.suppress(Exception):
            await anyio.to_thread.run_sync(ray.shutdown)

    async def restore_all(self) -> int:
        """Build the actor of every unexpired record of the store that has
        none (a restarted cluster), all at once; expired records are removed.
        Returns the number of sessions restored."""
        store = self.store
        if store is None:
            return 0
        keys = await anyio.to_thread.run_sync(store.keys, limiter=self.io_limiter)
        alive = set(await anyio.to_thread.run_sync(ray.util.list_named_actors))
        pending = []
        for key in keys:
            if ACTOR_PREFIX + key in alive:
                continue
            try:
                actor = await self._from_store(key)
            except SessionCapError:
                log.warning("store: session %s… not restored: the cluster holds its maximum of %d sessions", key[:SHOWN_KEY_CHARS], self.config.max_sessions)
                continue
            if actor is not None:
                pending.append((key, actor))
        restored = 0
        for key, actor in pending:
            try:
                facts = await self._ready(actor, PLACE_TIMEOUT_S)
            except (SessionGoneError, HybridMpmError, *BUILTIN_ERRORS.values()) as e:
                log.warning("store: session %s… not restored: %s", key[:SHOWN_KEY_CHARS], e or "its actor did not start")
                await self._end(key, actor)
                continue
            restored += 1
            log.info("store: session %s… restored at frame %d", key[:SHOWN_KEY_CHARS], facts["frame"])
        return restored

    # ------------------------------------------------------------ the work of the routes, in the actors
    async def info(self, s: RaySession) -> dict[str, Any]:
        """``s``'s description, from its actor (the viewers of every front end counted)."""
        d, _, _ = await self._described(s)
        return d

    async def _described(self, s: RaySession) -> tuple[dict[str, Any], str, int]:
        """``s``'s description and where its actor's events stood when it was taken: ``(info, epoch, event seq)``."""
        d = dict(await self._call(s, "info", self.front_id, len(s.viewers)))
        epoch, eseq = str(d.pop("_epoch", "")), int(d.pop("_event_seq", -1))
        d.update(id=s.id, stream=f"/v1/sessions/{s.id}/stream")
        s.at_frame = int(d["frame"])
        s.playing = bool(d.pop("playing", False))
        return d, epoch, eseq

    async def rollout(self, s: RaySession, frames: int) -> Rollout:
        ro: Rollout = await self._call(s, "rollout", frames)
        if len(ro.frame_index):
            s.at_frame = int(ro.frame_index[-1])
        return ro

    async def run_control(self, s: RaySession, sketch: Sketch | None, method: str, frames: int, left: Any, first: list[float], cid: str) -> Any:
        """Control ``cid`` in ``s``'s actor (:meth:`SessionActor.run_control`,
        :func:`hybridmpm.service.episode.run_episode`); a client that leaves
        (``left`` set) cancels it there. Returns ``(rollout, metrics, plan summary)``."""
        t0 = time.perf_counter()
        call = asyncio.ensure_future(
            self._call(
                s,
                "run_control",
                method,
                int(frames),
                sketch.to_json() if sketch is not None else None,
                cid,
                retry=False,
            )
        )
        cancelled = False
        try:
            while not call.done():
                await asyncio.wait({call}, timeout=0.1)
                if left.is_set() and not cancelled and not call.done():
                    cancelled = True
                    with contextlib.suppress(Exception):
                        await s.actor.cancel_control.remote()
        except asyncio.CancelledError:
            with contextlib.suppress(Exception):
                s.actor.cancel_control.remote()
            raise
        try:
            ro, metrics, planned, first_after, _ = call.result()
        except ApiError as e:
            if e.status == 503:  # the actor was lost during the control: every front end's viewers see it end
                task = asyncio.ensure_future(self._announce(s, {"type": "control", "status": "failed", "id": cid}))
                self._announcing.add(task)
                task.add_done_callback(self._announcing.discard)
            raise
        if first_after is not None:
            first.append(t0 + first_after)
        if len(ro.frame_index):
            s.at_frame = int(ro.frame_index[-1])
        return ro, metrics, planned

    async def _announce(self, s: RaySession, msg: dict[str, Any]) -> None:
        """``msg`` for the viewers of every front end, through ``s``'s actor once it is back (a lost actor's
        restart is waited for; a session that is gone has no viewers left)."""
        with contextlib.suppress(Exception):
            await self._call(s, "event", msg)

    async def checkpoint(self, s: RaySession) -> bytes:
        with self.budget.hold(2 * s.state_nbytes, "writing the checkpoint"):
            data: bytes = await self._call(s, "checkpoint")
        return data

    async def restore(self, s: RaySession, state: dict[str, Any]) -> None:
        s.facts = SessionFacts.from_dict(await self._call(s, "restore", state))  # a state before or after a pour: its own particles

    async def reset(self, s: RaySession) -> None:
        s.facts = SessionFacts.from_dict(await self._call(s, "reset"))  # its scene's particles again after a pour

    async def pour(self, s: RaySession, block: dict[str, Any]) -> dict[str, Any]:
        s.facts = SessionFacts.from_dict((out := await self._call(s, "pour", block))["facts"])
        return dict(out)

    async def add_body(self, s: RaySession, body: dict[str, Any]) -> dict[str, Any]:
        s.facts = SessionFacts.from_dict((out := await self._call(s, "add_body", body))["facts"])
        return dict(out)

    async def remove_body(self, s: RaySession, index: int) -> dict[str, Any]:
        s.facts = SessionFacts.from_dict((out := await self._call(s, "remove_body", index))["facts"])
        return dict(out)

    async def move_obstacle(self, s: RaySession, index: int, center: list[float], velocity: list[float] | None) -> int:
        return int(await self._call(s, "move_obstacle", index, center, velocity))

    async def keep_control(self, s: RaySession, c: Control) -> None:
        """Kept by the actor (the last 8); its cost leaves this front end's budget."""
        try:
            await self._call(s, "keep_control", c)
        finally:
            self.budget.give(c.cost)
            c.cost = 0

    async def recorded(self, s: RaySession, count: int) -> list[RecordedFrame]:
        """The actor's recent trajectory (its latest ``count`` frames)."""
        held: list[RecordedFrame] = await self._call(s, "recorded", count)
        return held

    async def get_control(self, s: RaySession, cid: str) -> Control | None:
        c: Control | None = await self._call(s, "get_control", cid)
        return c

    # ------------------------------------------------------------ streams
    async def attach(self, s: RaySession, v: Viewer) -> None:
        """A new viewer of ``s``: its ``meta`` message (the description, a running control included) and the current frame first,
        then every event the actor emits after that description: a feeder started here polls from the description's event count, a
        running one delivers to the viewer from now on (an event between the two may come twice, never not at all)."""
        s.viewers.add(v)
        try:
            info, epoch, eseq = await self._described(s)
            v.opening(meta_message(info, s.playing))
        except BaseException:
            s.viewers.discard(v)
            raise
        if s.last_frame is not None:
            v.offer(s.last_frame)
        if s.pump is None or s.pump.done():
            s.pump = asyncio.get_running_loop().create_task(self._pump(s, epoch, eseq))

    async def detach(self, s: RaySession, v: Viewer) -> None:
        s.viewers.discard(v)

    async def set_playing(self, s: RaySession, playing: bool) -> None:
        await self._call(s, "set_playing", playing, self.front_id, len(s.viewers))
        s.playing = playing

    async def _pump(self, s: RaySession, epoch: str = "", eseq: int = -1) -> None:
        """Feed the viewers of ``s`` here: the actor's latest frame (at most
        ``max_fps`` a second; newer ones replace an unsent one in each
        viewer's slot, the same bytes for all) and its events after event
        ``eseq`` of the actor's ``epoch`` (an empty epoch: from now), until no
        viewer is left, the session closes (its code and reason) or it is gone (4004)."""
        fseq = -1
        gap = 1.0 / float(self.config.max_fps)
        try:
            while s.viewers and not s.closed:
                try:
                    epoch_now, frame, fseq, events, eseq, closing = await self._call(s, "poll", self.front_id, len(s.viewers), epoch, fseq, eseq, POLL_WAIT_S)
                except SessionGoneError:
                    break
                except ApiError:  # its process is coming back
                    await asyncio.sleep(0.2)
                    continue
                epoch = epoch_now
                for msg in events:
                    s.deliver(msg)
                if frame is not None:
                    s.last_frame = frame
                    offer_all(s.viewers, frame)
                if closing is not None:
                    self.cache.pop(s.id, None)
                    await self._forget(s, int(closing[0]), str(closing[1]))
                    break
                if frame is not None:
                    await asyncio.sleep(gap)
        except asyncio.CancelledError:
            pass
        except Exception:  # noqa: BLE001 - a stream's feeder must not take the server down
            log.exception("stream of session %s…", s.id[:SHOWN_ID_CHARS])
        finally:
            if not s.closed:
                with contextlib.suppress(Exception):
                    s.actor.poll.remote(self.front_id, len(s.viewers), epoch, fseq, eseq, 0.0)  # this front end's viewers now


__all__ = ["POLL_WAIT_S", "REVIVE_TIMEOUT_S", "RaySession", "RaySessionManager", "connect", "error_from"]
