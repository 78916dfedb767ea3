"""What a front end of the Ray backend holds besides its
:class:`~hybridmpm.service.ray_backend.manager.RaySessionManager`: joining
the cluster (:func:`connect`), a session's handle (:class:`RaySession`, a
:class:`~hybridmpm.service.backend.Session` whose core runs in an actor) and
an actor's refusal raised again here as its own type (:func:`error_from`).
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import os
import socket
import time
from dataclasses import dataclass, field
from typing import Any

import ray

from hybridmpm.errors import CheckpointError, HybridMpmError, InvalidInputError, SimulationError
from hybridmpm.service.backend import StoreSaveError, Viewer
from hybridmpm.service.config import ServiceConfig
from hybridmpm.service.errors import tidy
from hybridmpm.service.facts import SessionFacts, SessionSettings

#: How long joining the cluster waits for its head's port to answer [s].
CONNECT_TIMEOUT_S = 5.0
#: The built-in errors an actor's refusal is raised again as, by name (:func:`error_from`).
BUILTIN_ERRORS = {c.__name__: c for c in (KeyError, TypeError, ValueError, AttributeError, IndexError, OverflowError)}


def connect(config: ServiceConfig) -> None:
    """Join the Ray cluster at ``config.ray_address`` as a driver in
    ``config.ray_namespace``; :class:`InvalidInputError` naming
    ``ray_address`` when there is none (or its token is refused)."""
    os.environ.setdefault("RAY_IGNORE_UNHANDLED_ERRORS", "1")  # events are sent without waiting for their answer
    if ray.is_initialized():
        return
    hint = "start one with `ray start --head` (and set RAY_AUTH_MODE=token with the cluster's token where it has one)"
    if config.ray_address != "auto":  # Ray itself retries a closed port for minutes
        host, port = config.ray_address.rsplit(":", 1)
        try:
            socket.create_connection((host.strip("[]"), int(port)), timeout=CONNECT_TIMEOUT_S).close()
        except OSError as e:
            raise InvalidInputError(
                f"ray_address: no Ray cluster answers at {config.ray_address} ({e.strerror or type(e).__name__}); {hint}", "ray_address"
            ) from None
    try:
        ray.init(address=config.ray_address, namespace=config.ray_namespace, logging_level=logging.WARNING, log_to_driver=False)
    except Exception as e:  # noqa: BLE001 - ray raises ConnectionError, RuntimeError, ValueError, AuthenticationError...
        raise InvalidInputError(f"ray_address: no Ray cluster at {config.ray_address!r}: {tidy(str(e), 160)}; {hint}", "ray_address") from None


def error_from(kind: str, message: str, name: str | None) -> Exception:
    """The error an actor answered (``("err", kind, message, field)``), raised again here as its type."""
    if kind == "InvalidInputError":
        return InvalidInputError(message, name)
    if kind == "CheckpointError":
        return CheckpointError(message)
    if kind == "SimulationError":
        return SimulationError(message)
    if kind == "StoreSaveError":  # the new session's first save failed; ``name`` carries the errno
        return StoreSaveError((int(name) if name and name.lstrip("-").isdigit() else None, message))
    if kind in BUILTIN_ERRORS:
        return BUILTIN_ERRORS[kind](message)
    return HybridMpmError(message)


@dataclass(eq=False)
class RaySession:
    """A session whose core runs in a Ray actor, as a front end's routes hold it (a :class:`~hybridmpm.service.backend.Session`):
    its ``id``, store ``key``, settings and facts (sent by the actor), the client address that created it, the front end's handle
    of its actor (``actor``), the frame it was last known at (``at_frame``), whether it plays, the viewers connected here and the
    task that feeds them (``pump``)."""

    id: str
    key: str
    settings: SessionSettings
    facts: SessionFacts
    client: str = ""
    actor: Any = None
    playing: bool = False
    at_frame: int = 0
    name: str = ""
    state_nbytes: int = 0
    last_frame: bytes | None = None
    pump: asyncio.Task[None] | None = None
    last_used: float = field(default_factory=time.monotonic)
    touched_remote: float = 0.0
    viewers: set[Viewer] = field(default_factory=set)
    controlling: bool = False  # a control admitted here is running (the route's 409; the actor refuses a second from any front end)
    closed: bool = False

    @property
    def frame_index(self) -> int:
        return self.at_frame

    def republish(self) -> None:
        """Nothing: the actor publishes its frames to every front end's stream."""

    def broadcast(self, msg: dict[str, Any]) -> None:
        """An event for the viewers of every front end (through the actor; not awaited)."""
        with contextlib.suppress(Exception):
            self.actor.event.remote(msg)

    def deliver(self, msg: dict[str, Any]) -> None:
        for v in list(self.viewers):
            v.event(msg)

    def touch(self) -> None:
        self.last_used = time.monotonic()
        if self.last_used - self.touched_remote > 1.0:  # the actor's idle clock (expiry), at most once a second
            self.touched_remote = self.last_used
            with contextlib.suppress(Exception):
                self.actor.touch.remote()


__all__ = ["BUILTIN_ERRORS", "CONNECT_TIMEOUT_S", "RaySession", "connect", "error_from"]
