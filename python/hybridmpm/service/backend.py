"""What the routes call of a session backend (:class:`SessionBackend`) and of
a session's handle (:class:`Session`), and the helpers both backends share.

Two backends implement the protocol side by side, neither inheriting the
other: the local one (:class:`hybridmpm.service.sessions.SessionManager`,
every session's :class:`~hybridmpm.service.core.SessionCore` in this
process) and the Ray one
(:class:`hybridmpm.service.ray_backend.manager.RaySessionManager`, each
session's core in its own Ray actor). What they share is written here once:
a viewer's latest-frame slot and event queue (:class:`Viewer`), closing its
socket (:func:`close_ws`, :func:`close_viewers`), the ``meta`` message a new
viewer gets first (:func:`meta_message`), a call on a worker thread
(:func:`on_worker`), a background loop that survives its errors
(:func:`every`), the store a manager opens (:func:`open_store`) and the
refusals of admission (:class:`SessionCapError`, :class:`QuotaError`,
:class:`StoreSaveError`). A frame's bytes for the viewers are
:func:`hybridmpm.service.frames.frame_message`'s, the record-expiry rule is
the store's (:func:`hybridmpm.service.store.load_unexpired`) and the saves
around a control the core's (:meth:`SessionCore.control
<hybridmpm.service.core.SessionCore.control>`).

The walk of a session on either backend is mapped in ``docs/architecture.md``.
"""

from __future__ import annotations

import asyncio
import collections
import contextlib
import errno
import logging
import traceback
from collections.abc import Awaitable, Callable, Iterable
from typing import Any, Protocol, TypeVar

import anyio
import anyio.to_thread
from starlette.websockets import WebSocket, WebSocketState

from hybridmpm.errors import HybridMpmError
from hybridmpm.service.budget import MemoryBudget, RecordedFrame
from hybridmpm.service.config import ServiceConfig
from hybridmpm.service.core import Control
from hybridmpm.service.facts import SessionFacts, SessionSettings
from hybridmpm.service.frames import HEADER_SIZE
from hybridmpm.service.store import SessionStore
from hybridmpm.sim import Rollout

log = logging.getLogger("hybridmpm.service")
T = TypeVar("T")
S = TypeVar("S", bound="Session")

#: Seconds a client is asked to wait (``Retry-After``) when the memory budget is full.
RETRY_AFTER_S = 5
#: What a failed save's errno says when the store is full (→ 507).
STORE_FULL_ERRNOS = frozenset({errno.ENOSPC, errno.EDQUOT, errno.EFBIG})


class StoreSaveError(Exception):
    """A create whose first save failed: nothing was created (→ 507 naming
    ``store`` when ``full``, else 503 with ``Retry-After``). ``why``: the
    save's error, :attr:`SessionCore.save_failure
    <hybridmpm.service.core.SessionCore.save_failure>`'s message."""

    def __init__(self, failure: tuple[int | None, str] | None) -> None:
        code, why = failure or (None, "unknown error")
        super().__init__(why)
        self.full = code in STORE_FULL_ERRNOS
        self.why = why


class SessionCapError(Exception):
    """No room for another session (→ 503)."""


class QuotaError(Exception):
    """The client address holds its quota of sessions (→ 429)."""


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

    def opening(self, msg: dict[str, Any]) -> None:
        """``msg`` (the ``meta`` message) first, before any event queued while it was made."""
        self.events.appendleft(msg)
        self.wake.set()


async def close_ws(v: Viewer, code: int, reason: str) -> None:
    """Close viewer ``v``'s socket with ``code`` and ``reason`` (at most 2 s; a socket already gone is left)."""
    v.closed = True
    v.wake.set()
    if v.ws.application_state == WebSocketState.CONNECTED:
        with contextlib.suppress(Exception):
            await asyncio.wait_for(v.ws.close(code=code, reason=reason), 2.0)


async def close_viewers(viewers: set[Viewer], code: int, reason: str) -> None:
    """Close every viewer of a session held here (:func:`close_ws`) and forget them."""
    for v in list(viewers):
        await close_ws(v, code, reason)
    viewers.clear()


def offer_all(viewers: Iterable[Viewer], data: bytes) -> None:
    """The same frame bytes in every viewer's latest-frame slot (no copy per viewer)."""
    for v in list(viewers):
        v.offer(data)


def meta_message(info: dict[str, Any], playing: bool) -> dict[str, Any]:
    """The first message a new viewer gets: the session's description ``info`` (``GET /v1/sessions/{id}``),
    whether it plays, and the size of a binary frame's header (:mod:`~hybridmpm.service.frames`)."""
    return {"type": "meta", **info, "playing": bool(playing), "header_bytes": HEADER_SIZE}


async def on_worker(limiter: anyio.CapacityLimiter, fn: Callable[..., T], *args: Any) -> T:
    """``fn(*args)`` in a worker thread under ``limiter``. A refusal
    (:class:`~hybridmpm.errors.HybridMpmError`) comes back with the locals of
    its traceback's frames cleared: the answer keeps no decoded image or
    state alive while it lingers."""
    try:
        return await anyio.to_thread.run_sync(fn, *args, limiter=limiter)
    except HybridMpmError as e:
        traceback.clear_frames(e.__traceback__)
        raise


async def every(interval: float, fn: Callable[[], Awaitable[Any] | None], what: str) -> None:
    """Call ``fn`` (awaiting what it returns) every ``interval`` seconds, forever;
    an error is logged under ``what`` and the loop goes on (a reaper, a saver)."""
    while True:
        await asyncio.sleep(interval)
        try:
            out = fn()
            if out is not None:
                await out
        except Exception:  # noqa: BLE001 - a background loop must survive
            log.exception(what)


async def stop_task(task: asyncio.Task[Any] | None) -> None:
    """Cancel ``task`` (if any) and wait for it to end."""
    if task is not None:
        task.cancel()
        with contextlib.suppress(asyncio.CancelledError, Exception):
            await task


def open_store(config: ServiceConfig, clean_after_s: float | None) -> SessionStore | None:
    """The durable store of ``config.store`` opened (torn saves older than ``clean_after_s`` removed;
    :meth:`SessionStore.open`), or None without one."""
    return None if config.store is None else SessionStore(config.store).open(clean_after_s)


class Session(Protocol):
    """A session as the routes hold it, on either backend: its ``id``, store
    ``key``, plain ``settings`` and ``facts`` (what routes read), the client
    address that created it, the viewers connected to this process, whether a
    control admitted here runs (``controlling``: the route's 409) and whether
    it is closed."""

    id: str
    key: str
    settings: SessionSettings
    facts: SessionFacts
    client: str
    viewers: set[Viewer]
    controlling: bool
    closed: bool

    @property
    def frame_index(self) -> int:
        """The frame the session is at (as last known here)."""
        ...

    def touch(self) -> None:
        """Used now: its idle clock starts again."""

    def broadcast(self, msg: dict[str, Any]) -> None:
        """An event for every viewer of the session."""

    def republish(self) -> None:
        """Offer the current frame to the viewers again (after a control that stopped early)."""


class SessionBackend(Protocol[S]):
    """What the routes, the control runner (:mod:`hybridmpm.service.controls`)
    and the application call of a session manager, with ``S`` its
    :class:`Session` handle. Errors: :class:`~hybridmpm.service.core.SessionGoneError`
    for a session closed meanwhile (→ 404), the simulator's
    :class:`~hybridmpm.errors.InvalidInputError` for bad input (→ 422), and
    those each method names."""

    #: Whether sessions run elsewhere (the Ray backend: the store's lock is the cluster's, sessions save themselves).
    remote: bool
    config: ServiceConfig
    budget: MemoryBudget
    store: SessionStore | None
    #: Controls running through this process (the route's 429 at ``config.max_controls``).
    controls_running: int

    async def compute(self, fn: Callable[..., T], *args: Any) -> T:
        """``fn(*args)`` on a worker thread under the compute limiter (:func:`on_worker`)."""
        ...

    # ------------------------------------------------------------ lifecycle
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
    ) -> S:
        """A new session for ``client`` (``n_grid``, ``integrator``: its MPM's, None: the scene's; ``solver``
        ``realtime``: real-time mode, the request's ``realtime`` resolved by the route, ``when_full`` what a
        server whose real time is full does, :mod:`hybridmpm.service.capacity`):
        :class:`SessionCapError`, :class:`QuotaError`, :class:`~hybridmpm.service.capacity.RealtimeFullError`,
        :class:`~hybridmpm.service.budget.BudgetFullError`, :class:`StoreSaveError`, the simulator's refusal."""
        ...

    async def find(self, sid: str) -> S | None:
        """The session ``sid`` (touched), or None."""
        ...

    async def held(self) -> int:
        """Sessions held (``/healthz``)."""
        ...

    async def close(self, sid: str, code: int = 1000, reason: str = "closed", forget: bool = True) -> bool:
        """Remove session ``sid`` (its record too with ``forget``), closing its sockets; False when there is none."""
        ...

    async def restore_all(self) -> int:
        """Bring back the store's unexpired sessions (once, at start); the number restored."""
        ...

    def start(self) -> None:
        """Start the background loops (reaper, saver)."""

    async def stop(self) -> None:
        """Stop them and close this process's sockets (1001)."""

    # ------------------------------------------------------------ the work of the routes
    async def info(self, s: S) -> dict[str, Any]:
        """``s``'s description (``GET /v1/sessions/{id}``)."""
        ...

    async def rollout(self, s: S, frames: int) -> Rollout:
        """Advance ``s`` by ``frames`` frames."""
        ...

    async def run_control(self, s: S, sketch: Any, method: str, frames: int, left: Any, first: list[float], cid: str) -> tuple[Rollout, dict[str, Any], Any]:
        """Control ``cid`` on ``s``: ``(rollout, metrics, plan summary)``; ``left`` set stops it within a frame."""
        ...

    async def keep_control(self, s: S, c: Control) -> None:
        """Keep ``c`` on ``s`` (its budget cost handled)."""

    async def get_control(self, s: S, cid: str) -> Control | None:
        """The kept control ``cid`` of ``s``, or None."""
        ...

    async def recorded(self, s: S, count: int) -> list[RecordedFrame]:
        """The latest ``count`` frames of ``s``'s recent trajectory, oldest first."""
        ...

    async def checkpoint(self, s: S) -> bytes:
        """``s``'s whole state as a checkpoint."""
        ...

    async def restore(self, s: S, state: dict[str, Any]) -> None:
        """Restore ``state`` into ``s``, all or nothing."""

    async def reset(self, s: S) -> None:
        """Back to the initial condition; the viewers get the frame and a ``reset`` event."""

    async def move_obstacle(self, s: S, index: int, center: list[float], velocity: list[float] | None) -> int:
        """Move obstacle ``index`` of ``s`` over its next step; the session's frame."""
        ...

    async def pour(self, s: S, block: dict[str, Any]) -> dict[str, Any]:
        """Add a block of particles to ``s`` between frames (its facts follow); ``{"added", "num_particles", "frame", "facts"}``."""
        ...

    async def add_body(self, s: S, body: dict[str, Any]) -> dict[str, Any]:
        """Add a rigid body to ``s`` between frames; ``{"index", "num_bodies", "frame", "facts"}``."""
        ...

    async def remove_body(self, s: S, index: int) -> dict[str, Any]:
        """Remove rigid body ``index`` of ``s`` between frames; ``{"index", "num_bodies", "frame", "facts"}``."""
        ...

    # ------------------------------------------------------------ streams
    async def attach(self, s: S, v: Viewer) -> None:
        """A new viewer of ``s``: its :func:`meta_message` and the current frame first."""

    async def detach(self, s: S, v: Viewer) -> None:
        """Viewer ``v`` of ``s`` left."""

    async def set_playing(self, s: S, playing: bool) -> None:
        """Play (real time, while it has viewers) or pause ``s``."""


__all__ = [
    "RETRY_AFTER_S",
    "QuotaError",
    "Session",
    "SessionBackend",
    "SessionCapError",
    "StoreSaveError",
    "Viewer",
    "close_viewers",
    "close_ws",
    "every",
    "meta_message",
    "offer_all",
    "on_worker",
    "open_store",
    "stop_task",
]
