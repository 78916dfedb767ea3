"""The frame stream: ``/v1/sessions/{sid}/stream``, a WebSocket that sends a
session's frames (binary, :mod:`~hybridmpm.service.frames`) and events (JSON
text) and takes ``play``, ``pause``, ``reset`` and ``ping``."""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import time
from typing import Any
from urllib.parse import urlsplit

from fastapi import APIRouter, WebSocket, WebSocketDisconnect

from hybridmpm.errors import InvalidInputError
from hybridmpm.files import loads_json
from hybridmpm.service.backend import Session, SessionBackend, Viewer, close_ws
from hybridmpm.service.config import ServiceConfig
from hybridmpm.service.core import SessionGoneError
from hybridmpm.service.schemas import clean

log = logging.getLogger("hybridmpm.service")
#: Deepest JSON a WebSocket message may nest (the protocol's messages are flat objects).
WS_MAX_JSON_DEPTH = 4

router = APIRouter()


def origin_ok(ws: WebSocket, config: ServiceConfig) -> bool:
    """Same origin as the page (``Origin``'s host:port equals ``Host``), or
    listed in ``allowed_origins``; no ``Origin`` (not a browser) is allowed."""
    origin = ws.headers.get("origin")
    if origin is None:
        return True
    if origin in config.allowed_origins:
        return True
    try:
        parts = urlsplit(origin)
    except ValueError:
        return False
    host = ws.headers.get("host", "")
    return parts.scheme in ("http", "https") and bool(parts.netloc) and parts.netloc.lower() == host.lower()


async def sender(v: Viewer, s: Session, cfg: ServiceConfig) -> None:
    gap = 1.0 / cfg.max_fps
    last = 0.0
    try:
        while not v.closed:
            await v.wake.wait()
            v.wake.clear()
            while v.events and not v.closed:
                await asyncio.wait_for(v.ws.send_text(json.dumps(clean(v.events.popleft()))), cfg.send_timeout_s)
            if v.frame is not None and not v.closed:
                wait = last + gap - time.monotonic()
                if wait > 0:
                    await asyncio.sleep(wait)  # frames arriving meanwhile overwrite the slot
                data, v.frame = v.frame, None
                if data is not None:
                    await asyncio.wait_for(v.ws.send_bytes(data), cfg.send_timeout_s)
                    v.sent += 1
                    last = time.monotonic()
    except asyncio.TimeoutError:
        log.info("stream of session %s…: send timed out; closing", s.id[:6])
        s.viewers.discard(v)
        await close_ws(v, 1011, "send timeout")
    except (asyncio.CancelledError, WebSocketDisconnect, RuntimeError, OSError):
        pass
    finally:
        v.closed = True
        s.viewers.discard(v)


@router.websocket("/v1/sessions/{sid}/stream")
async def stream(ws: WebSocket, sid: str) -> None:
    manager: SessionBackend[Any] = ws.app.state.manager
    cfg: ServiceConfig = ws.app.state.config
    if not origin_ok(ws, cfg):
        await ws.close(code=1008, reason="origin not allowed")
        return
    s = await manager.find(sid)
    if s is None:
        await ws.close(code=4004, reason="no such session")
        return
    await ws.accept()
    v = Viewer(ws)
    await manager.attach(s, v)  # its meta message and the current frame first
    task = asyncio.get_running_loop().create_task(sender(v, s, cfg))
    try:
        while not v.closed and not s.closed:
            m = await ws.receive()
            if m["type"] == "websocket.disconnect":
                break
            if m.get("text") is None:  # binary: not part of the protocol
                await close_ws(v, 1003, "send JSON text messages")
                break
            raw = str(m["text"])
            s.touch()
            msg: Any = None
            with contextlib.suppress(InvalidInputError):  # not JSON, or nested too deep: answered as an unknown message
                msg = loads_json(raw, "message", max_depth=WS_MAX_JSON_DEPTH)
            kind = msg.get("type") if isinstance(msg, dict) else None
            if kind in ("play", "pause"):
                await manager.set_playing(s, kind == "play")
            elif kind == "reset":
                await manager.reset(s)  # the recent trajectory starts again at the initial state
            elif kind == "ping":
                t = msg.get("t")
                v.event({"type": "pong", "t": t if isinstance(t, (int, float)) and not isinstance(t, bool) else None})
            else:
                v.event({"type": "error", "message": 'unknown message; send {"type": "play" | "pause" | "reset" | "ping"}'})
    except (WebSocketDisconnect, RuntimeError, KeyError):
        pass
    except SessionGoneError:  # deleted, expired or lost meanwhile (another front end of a cluster)
        await close_ws(v, 4004, "no such session")
    finally:
        v.closed = True
        v.wake.set()
        await manager.detach(s, v)
        task.cancel()
        with contextlib.suppress(asyncio.CancelledError, Exception):
            await task
