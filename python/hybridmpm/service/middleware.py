"""The service's ASGI middleware: the request body cap (:class:`BodyLimit`) and
the trusted ``Host`` check (:class:`HostCheck`)."""

from __future__ import annotations

import asyncio
import ipaddress
import json
import time
from collections.abc import Awaitable, Callable, MutableMapping
from typing import Any

from starlette.middleware.trustedhost import TrustedHostMiddleware

from hybridmpm.service.backend import RETRY_AFTER_S
from hybridmpm.service.budget import BudgetFullError, MemoryBudget
from hybridmpm.service.config import LOOPBACK_HOSTS, ServiceConfig

Scope = MutableMapping[str, Any]
Receive = Callable[[], Awaitable[MutableMapping[str, Any]]]
Send = Callable[[MutableMapping[str, Any]], Awaitable[None]]


async def send_json(send: Send, status: int, body: dict[str, Any], headers: list[tuple[bytes, bytes]] = ()) -> None:  # type: ignore[assignment]
    data = json.dumps(body).encode()
    hdrs = [(b"content-type", b"application/json"), (b"content-length", str(len(data)).encode()), *headers]
    await send({"type": "http.response.start", "status": status, "headers": hdrs})
    await send({"type": "http.response.body", "body": data})


class BodyLimit:
    """Pure-ASGI request body cap (413), counting the bytes actually received
    (chunked bodies without ``Content-Length`` included): checkpoints up to
    ``max_checkpoint_bytes``, everything else ``max_json_bytes``. The body
    is counted against the memory budget while the request runs (503 with
    ``Retry-After`` when it is full) and must arrive within
    ``body_timeout_s`` (else 408). Also answers 415 for a raw image upload
    to ``/controls`` (a PNG sketch travels base64-encoded in the JSON body,
    ``sketch_png``)."""

    def __init__(self, app: Callable[[Scope, Receive, Send], Awaitable[None]], config: ServiceConfig, budget: MemoryBudget) -> None:
        self.app, self.config, self.budget = app, config, budget

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        path, method = scope["path"], scope["method"]
        limit = self.config.max_checkpoint_bytes if method == "PUT" and path.endswith("/checkpoint") else self.config.max_json_bytes
        headers = {k.lower(): v for k, v in scope.get("headers", [])}
        ctype = headers.get(b"content-type", b"").split(b";")[0].strip().lower()
        if method == "POST" and path.endswith("/controls") and (ctype.startswith(b"image/") or ctype == b"multipart/form-data"):
            msg = "sketch: send the sketch as JSON (a polyline in `sketch`, or a PNG base64-encoded in `sketch_png`), or the PNG itself to .../controls/png"
            await send_json(send, 415, {"detail": [{"loc": ["body", "sketch"], "msg": msg, "type": "unsupported_media_type"}]})
            return
        too_big = {"detail": [{"loc": ["body"], "msg": f"request body larger than {limit} bytes", "type": "too_large"}]}
        cl = headers.get(b"content-length")
        # a body without a length is chunked (HTTP/1.1): reserve the cap; no length and no chunks: no body
        expected = limit if b"chunked" in headers.get(b"transfer-encoding", b"").lower() else 0
        if cl is not None:
            try:
                n = int(cl)
            except ValueError:
                n = -1
            if n > limit:
                await send_json(send, 413, too_big)
                return
            expected = max(0, n)
        try:
            reserved = self.budget.take(expected, "this request's body")
        except BudgetFullError as e:
            await send_json(send, 503, {"detail": str(e)}, [(b"retry-after", str(RETRY_AFTER_S).encode())])
            return
        try:
            chunks: list[bytes] = []
            size = 0
            more = True
            deadline = time.monotonic() + self.config.body_timeout_s
            while more:
                try:
                    msg_ = await asyncio.wait_for(receive(), max(0.0, deadline - time.monotonic()))
                except asyncio.TimeoutError:
                    msg = f"request body not received within {self.config.body_timeout_s:g} s"
                    await send_json(send, 408, {"detail": [{"loc": ["body"], "msg": msg, "type": "timeout"}]}, [(b"connection", b"close")])
                    return
                if msg_["type"] == "http.disconnect":
                    return
                body = msg_.get("body", b"")
                size += len(body)
                if size > limit:
                    await send_json(send, 413, too_big)
                    return
                chunks.append(body)
                more = bool(msg_.get("more_body", False))
            data = b"".join(chunks)
            del chunks
            replayed = False

            async def replay() -> MutableMapping[str, Any]:
                nonlocal replayed
                if not replayed:
                    replayed = True
                    return {"type": "http.request", "body": data, "more_body": False}
                return await receive()

            await self.app(scope, replay, send)
        finally:
            self.budget.give(reserved)


class HostCheck:
    """Trusted ``Host`` headers (starlette's :class:`TrustedHostMiddleware`,
    400 otherwise): ``allowed_hosts`` when given; else the loopback names on
    a connection to a loopback address (a page of another site that reached
    the server through DNS rebinding names its own host) and any host on
    other addresses."""

    def __init__(self, app: Callable[[Scope, Receive, Send], Awaitable[None]], allowed_hosts: tuple[str, ...]) -> None:
        self.app = app
        self.explicit = TrustedHostMiddleware(app, allowed_hosts=list(allowed_hosts), www_redirect=False) if allowed_hosts else None
        self.loopback = TrustedHostMiddleware(app, allowed_hosts=list(LOOPBACK_HOSTS), www_redirect=False)

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] in ("http", "websocket"):
            if self.explicit is not None:
                await self.explicit(scope, receive, send)
                return
            server = scope.get("server")
            if server and is_loopback(str(server[0])):
                await self.loopback(scope, receive, send)
                return
        await self.app(scope, receive, send)


def is_loopback(host: str) -> bool:
    try:
        return ipaddress.ip_address(host.strip("[]")).is_loopback
    except ValueError:
        return host.lower() == "localhost"


__all__ = ["BodyLimit", "HostCheck"]
