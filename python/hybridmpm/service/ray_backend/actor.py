"""A session in a Ray actor (:class:`SessionActor`): the session's
:class:`~hybridmpm.service.core.SessionCore` run in place, its latest frame
and events kept for the streams of every front end, its saves and its
expiry. :mod:`~hybridmpm.service.ray_backend.manager` turns it into a Ray
actor; this module imports no web framework, so that an actor starts quickly.

Every method answers a tuple instead of raising (Ray would wrap an error and
lose its field): ``("ok", value)``, ``("err", kind, message, field)`` for a
refusal the front end raises again as the same error
(:func:`hybridmpm.service.ray_backend.front.error_from`), ``("gone",
reason)`` for a session deleted, expired or that could not be restored,
``("busy",)`` for a second control. Calls run at once in the actor's threads
(:data:`ACTOR_THREADS`); the simulation work takes the core's lock in turn,
beside the polls, descriptions and events, the play loop and the keeper.
"""

from __future__ import annotations

import collections
import contextlib
import dataclasses
import functools
import logging
import os
import secrets
import threading
import time
import warnings
from collections.abc import Callable
from typing import Any, TypeVar, cast

import ray

from hybridmpm.control import Sketch
from hybridmpm.errors import HybridMpmError
from hybridmpm.service.budget import MemoryBudget, RecordedFrame, tree_nbytes
from hybridmpm.service.core import BusyError, Control, SessionCore, SessionGoneError
from hybridmpm.service.facts import SessionSettings
from hybridmpm.service.frames import frame_message
from hybridmpm.service.ray_backend.registry import REGISTRY_NAME
from hybridmpm.service.ray_backend.shares import ShareReporter
from hybridmpm.service.store import SHOWN_KEY_CHARS, SessionStore
from hybridmpm.sim import Frame, RealtimeSimulator, Rollout

log = logging.getLogger("hybridmpm.service")
_F = TypeVar("_F", bound=Callable[..., Any])

#: Calls an actor runs at once (threads): the simulation work, which takes the core's lock
#: in turn, beside the polls of the front ends' streams, descriptions and events.
ACTOR_THREADS = 32
#: A front end's report of its viewers of a session counts for this long [s] (its stream polls renew it).
VIEWER_LEASE_S = 3.0
#: Events kept for the front ends' streams (the oldest dropped).
EVENTS_KEPT = 16
#: Errors of the simulation that answer as refusals (the same types the local backend raises).
_REFUSALS = (HybridMpmError, KeyError, TypeError, ValueError, AttributeError, IndexError, OverflowError)


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
        except BusyError:
            return ("busy",)
        except SessionGoneError:
            return ("gone", self.closing[1] if self.closing is not None else "closed")
        except _REFUSALS as e:
            return ("err", type(e).__name__, str(e), getattr(e, "field", None))

    return cast(_F, wrapper)


def _answer(method: _F) -> _F:
    """:func:`_wrap` with its defaults."""
    return _wrap(method)


class SessionActor:
    """One session in a Ray actor (named ``ACTOR_PREFIX`` + ``key``).

    Built from ``scene``, ``seed``, ``solver``, ``r_c``, ``n_grid``, ``integrator`` for the
    client address ``client`` — or, with ``restore`` or when Ray restarts
    the actor after its process died, from its last save in the store.
    ``settings``: ``store`` (URL or None), ``save_every_s``, ``idle_ttl_s``,
    ``max_checkpoint_bytes``, ``memory_budget`` (bytes for its recent
    frames), ``namespace``. A construction that fails (bad settings, no
    loadable save) is kept as :attr:`failed`: :meth:`ready` answers it,
    every other method ``gone``.

    With a store the actor saves itself (:meth:`SessionCore.save
    <hybridmpm.service.core.SessionCore.save>`) when it is built, before a
    control is announced and after it (before it is answered), and at most
    ``save_every_s`` after any other change; idle for ``idle_ttl_s`` it
    removes its record and ends itself.
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
        integrator: str | None = None,
    ) -> None:
        self.key = key
        self.settings = dict(settings)
        self.epoch = secrets.token_hex(4)  # this incarnation (a restarted actor has another)
        self.failed: tuple[str, str, str | None] | None = None  # (kind, message, field) of a failed construction
        self.closing: tuple[int, str] | None = None  # (WebSocket close code, reason) once deleted or expired
        self.cond = threading.Condition()  # frames and events, for the polls
        self.frame_seq = 0
        self.frame_bytes = b""
        self.event_seq = 0
        self.events: collections.deque[tuple[int, dict[str, Any]]] = collections.deque(maxlen=EVENTS_KEPT)
        self.viewers: dict[str, tuple[int, float]] = {}
        self.play_thread: threading.Thread | None = None
        self.store: SessionStore | None = None
        budget = MemoryBudget(int(self.settings.get("memory_budget") or 1 << 30))
        url = self.settings.get("store")
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            reconstructed = bool(ray.get_runtime_context().was_current_actor_reconstructed)
        try:
            if url is not None:
                self.store = SessionStore(url).open(clean_after_s=None)  # other actors' saves may be in progress
            if restore or reconstructed:
                if self.store is None:
                    raise HybridMpmError("the session's process was lost and there is no store to restore it from")
                core = SessionCore.load(self.store.load(key, int(self.settings["max_checkpoint_bytes"])), budget)
                log.info("store: session %s… restored at frame %d (pid %d)", key[:SHOWN_KEY_CHARS], core.frame_index, os.getpid())
            else:
                core = SessionCore.build(key, SessionSettings(scene, int(seed), solver, float(r_c), n_grid, integrator), client, budget)
        except _REFUSALS as e:
            self.failed = (type(e).__name__, str(e), getattr(e, "field", None))
            log.warning("session %s…: %s", key[:SHOWN_KEY_CHARS], e)
            return
        self.core = core
        core.on_frame, core.on_event = self._publish, self._event
        core.has_viewers = lambda: self._viewer_count() > 0
        self._publish(core.sim.frame)
        if self.store is not None and not (restore or reconstructed):
            core.dirty = True
            if not core.save(self.store):  # a new session not in the store is not created (a 201 means it is durable)
                code, why = core.save_failure or (None, "unknown error")
                self.failed = ("StoreSaveError", why, None if code is None else str(code))
                core.close()
                return
        threading.Thread(target=self._keeper, name="saver", daemon=True).start()

    # ------------------------------------------------------------ frames and events
    def _publish(self, fr: Frame, control_frame: int = 0) -> None:
        """Make ``fr`` the latest frame of every front end's stream (the core records it; a real-time
        session's frame carries its real-time factor)."""
        data = frame_message(fr, control_frame, self.core.realtime_info())
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

    # ------------------------------------------------------------ the work (the core's)
    @functools.partial(_wrap, failed_is_error=True)
    def ready(self) -> dict[str, Any]:
        """The session's settings and fixed facts (what the front end's handle holds) and its frame."""
        core = self.core
        return {
            "settings": dataclasses.asdict(core.settings),
            "facts": core.facts.to_dict(),
            "client": core.client,
            "state_nbytes": tree_nbytes(core.initial),
            "frame": core.frame_index,
        }

    @_answer
    def rollout(self, frames: int) -> Rollout:
        """Advance ``frames`` frames (:meth:`SessionCore.rollout <hybridmpm.service.core.SessionCore.rollout>`)."""
        return self.core.rollout(frames)

    @_answer
    def run_control(
        self, method: str, frames: int, sketch_json: dict[str, Any] | None, cid: str
    ) -> tuple[Any, dict[str, Any], dict[str, Any] | None, float | None, bool]:
        """Plan and run control ``cid`` here (:meth:`SessionCore.control
        <hybridmpm.service.core.SessionCore.control>`, whose save policy
        saves it before it is announced and before it answers): ``(rollout, metrics, plan summary,
        seconds to the first controlled frame, cancelled)``;
        :meth:`cancel_control` stops it within a frame."""
        t0 = time.perf_counter()
        sketch = Sketch.from_json(sketch_json) if sketch_json is not None else None
        ro, metrics, plan, t_first = self.core.control(method, frames, sketch, cid, store=self.store)
        return ro, metrics, plan, ((t_first - t0) if t_first is not None else None), self.core.cancel.is_set()

    @_answer
    def checkpoint(self) -> bytes:
        """The whole state as a checkpoint (:func:`hybridmpm.service.checkpoint.dumps`)."""
        return self.core.checkpoint()

    @_answer
    def restore(self, state: dict[str, Any]) -> dict[str, Any]:
        """Restore ``state``, all or nothing (the simulator validates it whole first); the session's facts after it
        (a state taken before or after a pour holds its own particles)."""
        self.core.restore(state)
        return self.core.facts.to_dict()

    @_answer
    def reset(self) -> dict[str, Any]:
        """Back to the initial condition; the streams get the frame and a ``reset`` event. The session's facts after it
        (its scene's particles again after a pour)."""
        self.core.reset()
        return self.core.facts.to_dict()

    @_answer
    def pour(self, block: dict[str, Any]) -> dict[str, Any]:
        """Add a block between frames; the streams get a ``particles`` event."""
        return self.core.pour(block)

    @_answer
    def add_body(self, body: dict[str, Any]) -> dict[str, Any]:
        """Add a rigid body between frames; the streams get a ``bodies`` event."""
        return self.core.add_body(body)

    @_answer
    def remove_body(self, index: int) -> dict[str, Any]:
        """Remove rigid body ``index`` between frames; the streams get a ``bodies`` event."""
        return self.core.remove_body(index)

    @_answer
    def facts(self) -> dict[str, Any]:
        """The session's facts (its particles change with a pour and a reset after one)."""
        return self.core.facts.to_dict()

    @_answer
    def move_obstacle(self, index: int, center: list[float], velocity: list[float] | None) -> int:
        """Move obstacle ``index`` to ``center`` over the next step; the streams get an ``obstacle`` event."""
        return self.core.move_obstacle(index, center, velocity)

    @_answer
    def keep_control(self, c: Control) -> None:
        """Keep ``c`` (the last :data:`~hybridmpm.service.core.KEEP_CONTROLS`)."""
        self.core.keep_control(c)

    @_answer
    def get_control(self, cid: str) -> Control | None:
        return self.core.get_control(cid)

    @_answer
    def recorded(self, count: int) -> list[RecordedFrame]:
        """The latest ``count`` frames of the recent trajectory, oldest first (``GET /v1/sessions/{id}/trajectory``)."""
        return self.core.recorded(count)

    @_answer
    def delete(self, code: int = 1000, reason: str = "deleted") -> None:
        """Close the session: its record leaves the store, the streams get ``(code, reason)``."""
        self._close(code, reason)

    def _close(self, code: int, reason: str) -> None:
        with self.cond:
            self.closing = (code, reason)
            self.cond.notify_all()
        self.core.close(self.store)  # a running control stops within a frame; a save under way ends first
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
        ``stream`` are the front end's), with the viewers of every front end,
        and where the streams' events stood when it was taken (``_epoch``,
        ``_event_seq``: a new stream polls from there, so no event after the
        description, a control's ``running`` included, is missed)."""
        self._lease(front, viewers)
        self.core.touch()
        with self.cond:  # the description and the event count together: an event either shows in it or comes after it
            return {
                **self.core.info(),
                "viewers": self._viewer_count(),
                "playing": self.core.playing,
                "_epoch": self.epoch,
                "_event_seq": self.event_seq,
            }

    @_answer
    def set_playing(self, playing: bool, front: str, viewers: int) -> None:
        """Play (one coarse step at a time, no faster than real time, while
        any front end has viewers) or pause."""
        self._lease(front, viewers)
        self.core.touch()
        self.core.playing = bool(playing)
        if self.core.playing and (self.play_thread is None or not self.play_thread.is_alive()):
            self.play_thread = threading.Thread(target=self._play, name="play", daemon=True)
            self.play_thread.start()

    @_answer
    def event(self, msg: dict[str, Any]) -> None:
        """An event for the viewers of every front end (``control`` running/done/cancelled)."""
        self._event(msg)

    @_answer
    def touch(self) -> None:
        self.core.touch()

    @_answer
    def cancel_control(self) -> None:
        """Stop the running control within a frame (its client left)."""
        self.core.cancel.set()

    @_answer
    def pid(self) -> int:
        """The actor's process id (tests and benchmarks: which process to stop)."""
        return os.getpid()

    @_answer
    def client(self) -> str:
        """The client address that created the session (the registry's quota)."""
        return self.core.client

    # ------------------------------------------------------------ threads
    def _play(self) -> None:
        """The core's play loop (:meth:`SessionCore.play <hybridmpm.service.core.SessionCore.play>`), waiting in this thread;
        a real-time session's share of its node meanwhile (:class:`~hybridmpm.service.ray_backend.shares.ShareReporter`)."""
        shares = self._shares()
        try:
            for delay in self.core.play():
                if shares is not None:
                    shares.tick()
                time.sleep(delay)
        finally:
            if shares is not None:
                shares.stop()

    def _shares(self) -> ShareReporter | None:
        """The reporter of a real-time session's play to the registry, or None (another solver, or no registry)."""
        if not isinstance(self.core.sim, RealtimeSimulator):
            return None

        def apply(share: float) -> None:
            sim = self.core.sim  # a reset may have built another
            if isinstance(sim, RealtimeSimulator):
                sim.set_share(share)

        try:
            registry = ray.get_actor(REGISTRY_NAME, namespace=self.settings["namespace"])
        except Exception:  # noqa: BLE001 - no registry (yet): it plays on its own frame times
            return None
        return ShareReporter(registry, ray.get_runtime_context().get_node_id(), self.key, self.core.threads, apply)

    def _keeper(self) -> None:
        """Save at most every ``save_every_s``; end the session once idle for ``idle_ttl_s``."""
        every = float(self.settings.get("save_every_s") or 1.0)
        ttl = float(self.settings["idle_ttl_s"])
        tick = min(every, max(0.05, ttl / 4))
        while self.closing is None:
            time.sleep(tick)
            try:
                if self.store is not None:
                    self.core.save(self.store)
                if self.core.expired(ttl):
                    self._expire()
                    return
            except Exception:  # noqa: BLE001 - the keeper must survive
                log.exception("session %s…: keeper", self.key[:SHOWN_KEY_CHARS])

    def _expire(self) -> None:
        log.info("session %s… (store key) expired", self.key[:SHOWN_KEY_CHARS])
        self._close(4000, "expired")
        time.sleep(2 * VIEWER_LEASE_S / 3)  # the streams' polls see the closing first
        ray.kill(ray.get_runtime_context().current_actor, no_restart=True)


__all__ = ["ACTOR_THREADS", "EVENTS_KEPT", "VIEWER_LEASE_S", "SessionActor"]
