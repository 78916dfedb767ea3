"""The HTTP service and its web page (``hybridmpm serve``; the ``service`` extra).

A FastAPI application that holds simulation *sessions* in memory — each owns
one simulator (:func:`hybridmpm.sim.make_simulator`) — steps them on request,
streams their frames to browsers over a binary WebSocket, and applies sketches
(:mod:`hybridmpm.control`) as controlled trajectories. Sessions live in one
process: run it with one worker (``uvicorn --workers 1``; ``hybridmpm serve``
does) — or, with ``hybridmpm serve --backend ray``, each in a named actor of a
Ray cluster that any number of front ends serve (:mod:`hybridmpm.service.ray_backend`).
See ``docs/service.md``.

>>> from hybridmpm.service import ServiceConfig, create_app
>>> app = create_app(ServiceConfig(max_sessions=10))   # an ASGI app for uvicorn

FastAPI is imported only here, and only when ``create_app`` is first named:
``import hybridmpm`` never needs it, nor does a session's Ray actor
(:mod:`hybridmpm.service.ray_backend.actor`), which imports the modules it uses alone.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from hybridmpm.service.config import ServiceConfig
from hybridmpm.service.frames import HEADER, HEADER_SIZE, decode_frame, encode_frame

if TYPE_CHECKING:
    from hybridmpm.service.app import create_app


def __getattr__(name: str) -> Any:
    if name == "create_app":
        # import time: the web framework loads when the application is made, not with the package
        from hybridmpm.service.app import create_app

        return create_app
    raise AttributeError(f"module 'hybridmpm.service' has no attribute {name!r}")


__all__ = ["HEADER", "HEADER_SIZE", "ServiceConfig", "create_app", "decode_frame", "encode_frame"]
