"""The HTTP service and its web page (``hybridmpm serve``; the ``service`` extra).

A FastAPI application that holds simulation *sessions* in memory — each owns
one simulator (:func:`hybridmpm.sim.make_simulator`) — steps them on request,
streams their frames to browsers over a binary WebSocket, and applies sketches
(:mod:`hybridmpm.control`) as controlled trajectories. Sessions live in one
process: run it with one worker (``uvicorn --workers 1``; ``hybridmpm serve``
does). See ``docs/service.md``.

>>> from hybridmpm.service import ServiceConfig, create_app
>>> app = create_app(ServiceConfig(max_sessions=10))   # an ASGI app for uvicorn

FastAPI is imported only here: ``import hybridmpm`` never needs it.
"""

from hybridmpm.service.app import create_app
from hybridmpm.service.config import ServiceConfig
from hybridmpm.service.frames import HEADER, HEADER_SIZE, decode_frame, encode_frame

__all__ = ["HEADER", "HEADER_SIZE", "ServiceConfig", "create_app", "decode_frame", "encode_frame"]
