"""The Ray actors of the ray backend (:mod:`hybridmpm.service.cluster`).

:class:`SessionActor` is one session: its simulator, its kept controls, its
play loop, its latest frame and events for the viewers of every front end,
and its saves to the store; :class:`Registry` counts the cluster's sessions
(the session cap and the per-client quota hold cluster-wide). Both are plain
classes that :mod:`~hybridmpm.service.cluster` turns into Ray actors; this
module imports no web framework, so that an actor starts quickly.

Every method of :class:`SessionActor` answers a tuple instead of raising
(Ray would wrap an error and lose its field): ``("ok", value)``, ``("err",
kind, message, field)`` for a refusal the front end raises again as the same
error (:func:`hybridmpm.service.cluster.unwrap`), ``("gone", reason)`` for a
session deleted, expired or that could not be restored, ``("busy",)`` for a
second control. Calls run at once in the actor's threads
(:data:`ACTOR_THREADS`); the simulation work takes the simulator's lock in
turn (as the local backend's session lock), beside the polls, descriptions
and events, the play loop and the saver thread.
"""

from __future__ import annotations

import collections
import contextlib
import functools
import logging
import os
import secrets
import threading
import time
import warnings
from collections.abc import Callable
from typing import Any, TypeVar, cast

import numpy as np
import ray

from hybridmpm.control import Controller, Sketch
from hybridmpm.errors import HybridMpmError, InvalidInputError
from hybridmpm.service import checkpoint as ckpt
from hybridmpm.service.budget import MemoryBudget, Recording, tree_nbytes
from hybridmpm.service.core import Pacer, encode_record, play_period, play_step, snapshot
from hybridmpm.service.episode import run_episode
from hybridmpm.service.facts import SessionFacts
from hybridmpm.service.frames import encode_frame
from hybridmpm.service.sessions import KEEP_CONTROLS, RECORD_STEPS, Control, Session
from hybridmpm.service.store import SHOWN_KEY_CHARS, SessionStore, rebuild
from hybridmpm.sim import Frame, make_simulator, rollout

log = logging.getLogger("hybridmpm.service")
_F = TypeVar("_F", bound=Callable[..., Any])

#: A session's actor is named this + its store key (the SHA-256 of its id: the id is no actor name).
ACTOR_PREFIX = "session-"
#: The name of the :class:`Registry` actor in the namespace.
REGISTRY_NAME = "registry"
#: Calls an actor runs at once (threads): the simulation work, which takes the simulator's lock
#: in turn, beside the polls of the front ends' streams, descriptions and events.
ACTOR_THREADS = 32
#: A front end's report of its viewers of a session counts for this long [s] (its stream polls renew it).
VIEWER_LEASE_S = 3.0
#: Events kept for the front ends' streams (the oldest dropped).
EVENTS_KEPT = 16
#: Seconds between the registry's looks for sessions whose actor is gone, and how old such an entry must be.
REGISTRY_PRUNE_S = 30.0
REGISTRY_GRACE_S = 120.0
#: Errors of the simulation that answer as refusals (the same types the local backend raises).
_REFUSALS = (HybridMpmError, KeyError, TypeError, ValueError, AttributeError, IndexError, OverflowError)


class Busy(Exception):
    """A control is already running on the session (→ 409)."""


class Gone(Exception):
    """The session was closed while the call waited or ran (→ 404)."""


def _wrap(method: _F, failed_is_error: bool = False, when_closed: bool = False) -> _F:
    """An actor method answering ``("ok", value)``, ``("err", kind, message,
    field)`` for a refusal, ``("busy",)``, or ``("gone", reason)`` once the
    session is closed (unless ``when_closed``) or failed to build (an ``err``
    with ``failed_is_error``)."""

    @functools.wraps(method)
    def wrapper(self: SessionActor, *args: Any, **kwargs: Any) -> tuple[Any, ...]:
        if self.failed is not None:
            return ("err", *self.failed) if failed_is_error else ("gone", self.failed[1])
        if self.closing is not None and not when_closed:
            return ("gone", self.closing[1])
        try:
            return ("ok", method(self, *args, **kwargs))
        except Busy:
            return ("busy",)
        except Gone:
            return ("gone", self.closing[1] if self.closing is not None else "closed")
        except _REFUSALS as e:
            return ("err", type(e).__name__, str(e), getattr(e, "field", None))

    return cast(_F, wrapper)


def _answer(method: _F) -> _F:
    """:func:`_wrap` with its defaults."""
    return _wrap(method)


class SessionActor:
    """One session in a Ray actor (named :data:`ACTOR_PREFIX` + ``key``).

    Built from ``scene``, ``seed``, ``solver``, ``r_c`` for the client address
    ``client`` — or, with ``restore`` or when Ray restarts the actor after
    its process died, from its last save in the store. ``settings``: ``store``
    (URL or None), ``save_every_s``, ``idle_ttl_s``, ``max_checkpoint_bytes``,
    ``memory_budget`` (bytes for its recent frames), ``namespace``. A
    construction that fails (bad settings, no loadable save) is kept as
    :attr:`failed`: :meth:`ready` answers it, every other method ``gone``.

    With a store the actor saves itself (:mod:`hybridmpm.service.store`'s
    format and atomic write) when it is built, after each control (before
    the control is answered) and at most ``save_every_s`` after any other
    change; idle for ``idle_ttl_s`` it removes its record and ends itself.
    """

    def __init__(
        self,
        key: str,
        scene: str,
        seed: int,
        solver: str,
        r_c: float,
        client: str,
        settings: dict[str, Any],
        restore: bool = False,
        n_grid: int | None = None,
    ) -> None:
        self.key = key
        self.client_addr = client
        self.settings = dict(settings)
        self.epoch = secrets.token_hex(4)  # this incarnation (a restarted actor has another)
        self.failed: tuple[str, str, str | None] | None = None  # (kind, message, field) of a failed construction
        self.closing: tuple[int, str] | None = None  # (WebSocket close code, reason) once deleted or expired
        self.lock = threading.RLock()  # the simulator
        self.save_lock = threading.Lock()
        self.cond = threading.Condition()  # frames and events, for the polls
        self.frame_seq = 0
        self.frame_bytes = b""
        self.event_seq = 0
        self.events: collections.deque[tuple[int, dict[str, Any]]] = collections.deque(maxlen=EVENTS_KEPT)
        self.viewers: dict[str, tuple[int, float]] = {}
        self.playing = False
        self.play_thread: threading.Thread | None = None
        self.controlling = False
        self.cancel = threading.Event()
        self.dirty = False
        self.last_used = time.monotonic()
        self.store: SessionStore | None = None
        self.sess: Session | None = None
        url = self.settings.get("store")
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            reconstructed = bool(ray.get_runtime_context().was_current_actor_reconstructed)
        try:
            if url is not None:
                self.store = SessionStore(url).open(clean_after_s=None)  # other actors' saves may be in progress
            if restore or reconstructed:
                self._load()
            else:
                self._build(scene, seed, solver, r_c, n_grid)
        except _REFUSALS as e:
            self.failed = (type(e).__name__, str(e), getattr(e, "field", None))
            log.warning("session %s…: %s", key[:SHOWN_KEY_CHARS], e)
            return
        threading.Thread(target=self._keeper, name="saver", daemon=True).start()

    # ------------------------------------------------------------ building
    def _session(self, scene: str, seed: int, solver: str, r_c: float, sim: Any, initial: dict[str, Any], n_grid: int | None) -> Session:
        sess = Session(self.key, scene, seed, solver, r_c, sim, initial, client=self.client_addr, key=self.key, n_grid=n_grid)
        budget = MemoryBudget(int(self.settings.get("memory_budget") or 1 << 30))
        sess.recording = Recording(budget, RECORD_STEPS, int(sim.r_t))
        return sess

    def _build(self, scene: str, seed: int, solver: str, r_c: float, n_grid: int | None) -> None:
        sim = make_simulator(scene, solver, r_c=r_c, seed=seed, threads=1, nn_threads=1, n_grid=n_grid)
        self.sess = self._session(scene, seed, solver, r_c, sim, sim.state(), n_grid)
        self._publish(sim.frame)
        if self.store is not None:
            self.dirty = True
            self._save()

    def _load(self) -> None:
        if self.store is None:
            raise HybridMpmError("the session's process was lost and there is no store to restore it from")
        rec = self.store.load(self.key, int(self.settings["max_checkpoint_bytes"]))
        sim, initial = rebuild(rec)
        self.client_addr = rec.client
        self.sess = self._session(rec.scene, rec.seed, rec.solver, rec.r_c, sim, initial, rec.n_grid)
        frame = int(sim.frame.frame_index)
        self.sess.saved_frame = self.sess.restored_from_frame = frame
        self.last_used = time.monotonic() - max(0.0, time.time() - rec.last_used_at)
        self._publish(sim.frame)
        log.info("store: session %s… restored at frame %d (pid %d)", self.key[:SHOWN_KEY_CHARS], frame, os.getpid())

    @property
    def sim(self) -> Any:
        assert self.sess is not None
        return self.sess.sim

    # ------------------------------------------------------------ frames and events
    def _publish(self, fr: Frame, control_frame: int = 0) -> None:
        """Record ``fr`` and make it the latest frame of every front end's stream."""
        if self.sess is not None:
            self.sess.record(fr)
        data = encode_frame(fr.positions, fr.frame_index, fr.time, fr.solver, fr.controlled, control_frame)
        with self.cond:
            self.frame_seq += 1
            self.frame_bytes = data
            self.cond.notify_all()

    def _event(self, msg: dict[str, Any]) -> None:
        with self.cond:
            self.event_seq += 1
            self.events.append((self.event_seq, msg))
            self.cond.notify_all()

    def _lease(self, front: str, viewers: int) -> None:
        self.viewers[front] = (int(viewers), time.monotonic())

    def _viewer_count(self) -> int:
        now = time.monotonic()
        return sum(n for n, t in list(self.viewers.values()) if now - t < VIEWER_LEASE_S)

    def _touch(self) -> None:
        self.last_used = time.monotonic()

    # ------------------------------------------------------------ the simulation work (under the lock)
    @functools.partial(_wrap, failed_is_error=True)
    def ready(self) -> dict[str, Any]:
        """The session's fixed facts (what the front end's view of the simulator holds)."""
        return self._describe()

    def _describe(self) -> dict[str, Any]:
        sim = self.sim
        assert self.sess is not None
        return {
            "scene": self.sess.scene,
            "seed": self.sess.seed,
            "solver": self.sess.solver_kind,
            "r_c": self.sess.r_c,
            "client": self.client_addr,
            **SessionFacts.of(sim).to_dict(),
            "state_nbytes": tree_nbytes(self.sess.initial),
            "frame": self._frame_facts(),
        }

    def _frame_facts(self) -> tuple[int, float, str, bool]:
        fr = self.sim.frame
        return int(fr.frame_index), float(fr.time), str(fr.solver), bool(fr.controlled)

    @_answer
    def rollout(self, frames: int) -> Any:
        """Advance ``frames`` frames (:func:`hybridmpm.sim.rollout`); the last one goes to the streams."""
        with self.lock:
            ro = rollout(self.sim, frames)
            self.dirty = True
            self._touch()
            rec = self.sess.recording if self.sess is not None else None
            if rec is not None:
                for k in range(1, len(ro.frame_index)):
                    rec.add(int(ro.frame_index[k]), ro.positions[k], str(ro.solver[k]), False)
            if len(ro.frame_index) > 1:
                self._publish(self.sim.frame)
        return ro

    @_answer
    def run_control(
        self, method: str, frames: int, sketch_json: dict[str, Any] | None, cid: str
    ) -> tuple[Any, dict[str, Any], dict[str, Any] | None, float | None, bool]:
        """Plan and run control ``cid`` here (its forcing is a closure over
        this simulator; :func:`hybridmpm.service.episode.run_episode`):
        ``(rollout, metrics, plan summary, seconds to the first controlled
        frame, cancelled)``. Saved before it answers; :meth:`cancel_control`
        stops it within a frame."""
        with self.cond:  # a close sets `closing` under this lock, then the cancel flag: a control never clears a close's cancel
            if self.controlling:
                raise Busy()  # refused: no viewer is told of it
            if self.closing is not None:
                raise Gone()
            self.controlling = True
            self.cancel.clear()
        t0 = time.perf_counter()
        try:
            sketch = Sketch.from_json(sketch_json) if sketch_json is not None else None
            controller = Controller.for_scene(self.sim.scene.name, method, frames=frames)
            self._save()  # the steps answered before it are durable (before it is announced running)
            self._event({"type": "control", "status": "running", "id": cid, "method": method})
            with self.lock:
                ro, metrics, plan, t_first = run_episode(self.sim, sketch, controller, cid, self._publish, self._event, self.cancel.is_set)
                self.dirty = True
                self._touch()
            if self.closing is not None:  # deleted while it ran (it stopped within a frame)
                raise Gone()
            self._save()  # a control is saved before it is answered
            return ro, metrics, plan, ((t_first - t0) if t_first is not None else None), self.cancel.is_set()
        finally:
            self.controlling = False

    @_answer
    def checkpoint(self) -> bytes:
        """The whole state as a checkpoint (:func:`hybridmpm.service.checkpoint.dumps`)."""
        assert self.sess is not None
        with self.lock:
            state = self.sim.state()
        self._touch()
        return ckpt.dumps(state, self.sess.settings())

    @_answer
    def restore(self, state: dict[str, Any]) -> None:
        """Restore ``state``, all or nothing (the simulator validates it whole first)."""
        with self.lock:
            self.sim.restore(state)
            self.dirty = True
            self._touch()
            if self.sess is not None and self.sess.recording is not None:
                self.sess.recording.clear()  # the recent trajectory starts again at the restored state
            self._publish(self.sim.frame)

    @_answer
    def reset(self) -> None:
        """Back to the initial condition; the streams get the frame and a ``reset`` event."""
        assert self.sess is not None
        with self.lock:
            self.sim.restore(self.sess.initial)
            self.dirty = True
            self._touch()
            if self.sess.recording is not None:
                self.sess.recording.clear()  # the recent trajectory starts again at the initial state
            self._publish(self.sim.frame)
        self._event({"type": "reset", "frame": int(self.sim.frame.frame_index)})

    @_answer
    def move_obstacle(self, index: int, center: list[float], velocity: list[float] | None) -> int:
        """Move obstacle ``index`` to ``center`` over the next step (the simulator's ``move_obstacle``); the streams get an ``obstacle`` event."""
        with self.lock:
            self.sim.move_obstacle(index, center, velocity)  # type: ignore[attr-defined]
            frame = int(self.sim.frame.frame_index)
        self._touch()
        self._event({"type": "obstacle", "index": int(index), "center": [float(x) for x in center]})
        return frame

    @_answer
    def keep_control(self, c: Control) -> None:
        """Keep ``c`` (the last :data:`~hybridmpm.service.sessions.KEEP_CONTROLS`)."""
        assert self.sess is not None
        self.sess.controls[c.id] = c
        while len(self.sess.controls) > KEEP_CONTROLS:
            self.sess.controls.popitem(last=False)

    @_answer
    def delete(self, code: int = 1000, reason: str = "deleted") -> None:
        """Close the session: its record leaves the store, the streams get ``(code, reason)``."""
        self._close(code, reason)

    def _close(self, code: int, reason: str) -> None:
        self.playing = False
        with self.cond:
            self.closing = (code, reason)
            self.cancel.set()  # a control running here stops within a frame (after `closing`: see run_control)
            self.cond.notify_all()
        with self.save_lock:  # a save under way ends first: no record outlives its session
            if self.store is not None:
                self.store.delete(self.key)
        with contextlib.suppress(Exception):
            ray.get_actor(REGISTRY_NAME, namespace=self.settings["namespace"]).release.remote(self.key)

    # ------------------------------------------------------------ beside the work
    @functools.partial(_wrap, when_closed=True)
    def poll(self, front: str, viewers: int, epoch: str, fseq: int, eseq: int, wait_s: float) -> tuple[Any, ...]:
        """What a front end's stream has not seen: ``(epoch, frame or None,
        frame seq, events, event seq, closing)``, waiting up to ``wait_s``
        for something new. ``viewers`` the front end's viewers of the session
        (kept for :data:`VIEWER_LEASE_S`); an empty ``epoch`` (a stream's
        first poll) answers the current frame and no past event, another
        actor's (a restarted one) everything since this one started."""
        self._lease(front, viewers)
        if not epoch:  # a stream's first poll: the current frame, no past events
            fseq, eseq = -1, self.event_seq
        elif epoch != self.epoch:  # a restarted actor: everything since it started
            fseq = eseq = -1
        deadline = time.monotonic() + max(0.0, min(float(wait_s), 10.0))
        with self.cond:
            while self.frame_seq == fseq and self.event_seq == eseq and self.closing is None:
                left = deadline - time.monotonic()
                if left <= 0:
                    break
                self.cond.wait(left)
            frame = self.frame_bytes if self.frame_seq != fseq else None
            events = [m for q, m in self.events if q > eseq]
            return self.epoch, frame, self.frame_seq, events, self.event_seq, self.closing

    @_answer
    def info(self, front: str, viewers: int) -> dict[str, Any]:
        """The session's description (``GET /v1/sessions/{id}``; ``id`` and
        ``stream`` are the front end's), with the viewers of every front end."""
        assert self.sess is not None
        self._lease(front, viewers)
        self._touch()
        d = self.sess.info()
        d.update(viewers=self._viewer_count(), playing=self.playing)
        return d

    @_answer
    def set_playing(self, playing: bool, front: str, viewers: int) -> None:
        """Play (one coarse step at a time, no faster than real time, while
        any front end has viewers) or pause."""
        self._lease(front, viewers)
        self._touch()
        self.playing = bool(playing)
        if self.playing and (self.play_thread is None or not self.play_thread.is_alive()):
            self.play_thread = threading.Thread(target=self._play, name="play", daemon=True)
            self.play_thread.start()

    @_answer
    def event(self, msg: dict[str, Any]) -> None:
        """An event for the viewers of every front end (``control`` running/done/cancelled)."""
        self._event(msg)

    @_answer
    def touch(self) -> None:
        self._touch()

    @_answer
    def cancel_control(self) -> None:
        """Stop the running control within a frame (its client left)."""
        self.cancel.set()

    @_answer
    def recorded(self, count: int) -> list[tuple[int, np.ndarray, str, bool]]:
        """The latest ``count`` frames of the recent trajectory, oldest first (``GET /v1/sessions/{id}/trajectory``)."""
        assert self.sess is not None
        self._touch()
        with self.lock:
            return self.sess.recording.last(count) if self.sess.recording is not None else []

    @_answer
    def get_control(self, cid: str) -> Control | None:
        assert self.sess is not None
        self._touch()
        return self.sess.controls.get(cid)

    @_answer
    def pid(self) -> int:
        """The actor's process id (tests and benchmarks: which process to stop)."""
        return os.getpid()

    @_answer
    def client(self) -> str:
        """The client address that created the session (the registry's quota)."""
        return self.client_addr

    # ------------------------------------------------------------ threads
    def _play(self) -> None:
        pacer = Pacer(play_period(self.sim))
        while self.playing and self.closing is None and self._viewer_count() > 0:
            with self.lock:
                if not self.playing:
                    break
                try:
                    fr = play_step(self.sim)
                except Exception as e:  # noqa: BLE001 - a failed step pauses the stream with a message
                    self.playing = False
                    self._event({"type": "error", "message": f"simulation stopped: {e}"})
                    break
                self.dirty = True
                self._touch()
                self._publish(fr)
            time.sleep(pacer.delay())

    def _save(self) -> bool:
        """Write the checkpoint to the store if it changed since the last save;
        False when it could not (logged; it stays changed and is tried again)."""
        if self.store is None or self.sess is None:
            return True
        with self.save_lock:
            if self.closing is not None or not self.dirty:
                return True
            t0 = time.perf_counter()
            with self.lock:
                self.dirty = False
                state, frame = snapshot(self.sim)
            try:
                data = encode_record(state, self.sess.settings(), self.last_used, self.client_addr)
                del state
                self.store.write(self.key, data)
            except Exception as e:  # noqa: BLE001 - a failed save must not fail the session
                self.dirty = True
                log.warning("store: saving session %s… failed: %s", self.key[:SHOWN_KEY_CHARS], e)
                return False
            self.sess.saved_frame = frame
            log.debug(
                "store: session %s… saved at frame %d: %d bytes in %.1f ms", self.key[:SHOWN_KEY_CHARS], frame, len(data), (time.perf_counter() - t0) * 1e3
            )
            return True

    def _keeper(self) -> None:
        """Save at most every ``save_every_s``; end the session once idle for ``idle_ttl_s``."""
        every = float(self.settings.get("save_every_s") or 1.0)
        ttl = float(self.settings["idle_ttl_s"])
        tick = min(every, max(0.05, ttl / 4))
        while self.closing is None:
            time.sleep(tick)
            try:
                self._save()
                if not self.controlling and time.monotonic() - self.last_used > ttl:
                    self._expire()
                    return
            except Exception:  # noqa: BLE001 - the keeper must survive
                log.exception("session %s…: keeper", self.key[:SHOWN_KEY_CHARS])

    def _expire(self) -> None:
        log.info("session %s… (store key) expired", self.key[:SHOWN_KEY_CHARS])
        self._close(4000, "expired")
        time.sleep(2 * VIEWER_LEASE_S / 3)  # the streams' polls see the closing first
        ray.kill(ray.get_runtime_context().current_actor, no_restart=True)


class Registry:
    """The cluster's sessions (their keys and client addresses), one actor
    per namespace: :meth:`reserve` enforces the session cap and the
    per-client quota for every front end at once. Built again after a
    restart from the session actors alive in the namespace; an entry whose
    actor is gone is dropped after :data:`REGISTRY_GRACE_S`.

    It also holds the cluster's local store (``store``, the path its first
    front end was given, and any other a front end asks for with
    :meth:`claim_store`): the store's lock (:meth:`SessionStore.claim`) is the
    registry's, taken again when Ray restarts it, so a plain server (or
    another cluster's front end) started on that store is refused while the
    cluster lives, and the cluster's front ends share it."""

    def __init__(self, store: str | None = None, namespace: str = "") -> None:
        self.held: dict[str, tuple[str, float]] = {}
        self.namespace = namespace
        self.stores: dict[str, SessionStore] = {}
        if store is not None:
            self.claim_store(store)  # refused: the front end's own call says why
        now = time.monotonic()
        with contextlib.suppress(Exception):
            for name in ray.util.list_named_actors():
                if isinstance(name, str) and name.startswith(ACTOR_PREFIX):
                    client = ""
                    with contextlib.suppress(Exception):
                        out: Any = ray.get(ray.get_actor(name).client.remote(), timeout=5)
                        client = out[1] if out[0] == "ok" else ""
                    self.held[name[len(ACTOR_PREFIX) :]] = (client, now)
        threading.Thread(target=self._prune_forever, name="prune", daemon=True).start()

    def reserve(self, key: str, client: str, max_sessions: int, max_per_client: int, restoring: bool = False) -> str | None:
        """Count ``key`` for ``client``: None, or ``"cap"`` (the cluster holds
        ``max_sessions``) or ``"quota"`` (the client holds ``max_per_client``;
        not for a session ``restoring`` from the store). A key already
        counted is accepted again."""
        if key in self.held:
            return None
        if len(self.held) >= max_sessions:
            return "cap"
        if not restoring and sum(1 for c, _ in self.held.values() if c == client) >= max_per_client:
            return "quota"
        self.held[key] = (client, time.monotonic())
        return None

    def release(self, key: str) -> None:
        self.held.pop(key, None)

    def claim_store(self, url: str) -> str | None:
        """Hold the store at ``url`` for this cluster (a no-op for a store
        that is not a local directory, or one already held): None, or why it
        is refused (another server holds it)."""
        if url in self.stores:
            return None
        store = SessionStore(url)
        try:
            store.claim(f"the Ray registry of namespace {self.namespace!r}")
        except InvalidInputError as e:
            return str(e)
        self.stores[url] = store
        return None

    def count(self) -> int:
        return len(self.held)

    def _prune_forever(self) -> None:
        while True:
            time.sleep(REGISTRY_PRUNE_S)
            with contextlib.suppress(Exception):
                alive = {n[len(ACTOR_PREFIX) :] for n in ray.util.list_named_actors() if isinstance(n, str) and n.startswith(ACTOR_PREFIX)}
                now = time.monotonic()
                for key, (_, since) in list(self.held.items()):
                    if key not in alive and now - since > REGISTRY_GRACE_S:
                        self.held.pop(key, None)


__all__ = ["ACTOR_PREFIX", "ACTOR_THREADS", "REGISTRY_NAME", "VIEWER_LEASE_S", "Registry", "SessionActor"]
