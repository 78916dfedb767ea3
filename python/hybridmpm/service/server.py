"""Running the application on uvicorn with the connection limits of
:class:`~hybridmpm.service.config.ServiceConfig` (``hybridmpm serve``).

uvicorn closes idle keep-alive connections (``timeout_keep_alive``) and caps
the request line and headers (``h11_max_incomplete_event_size``), but waits
without limit for a request's headers to be completed: a client can hold a
connection open by sending them a byte at a time. :func:`header_timeout_protocol`
is uvicorn's h11 protocol with a deadline for them: a connection whose
request line and headers are not complete ``header_timeout_s`` after it
opened, or after its last response, is closed.
"""

from __future__ import annotations

import asyncio
from typing import Any

import h11
from uvicorn.protocols.http.h11_impl import H11Protocol

from hybridmpm.service.config import ServiceConfig


def header_timeout_protocol(header_timeout_s: float) -> type[H11Protocol]:
    """uvicorn's h11 protocol closing connections whose request headers are
    not complete within ``header_timeout_s`` seconds [s] of the connection's
    start or of the previous response's end."""

    class HeaderTimeoutH11(H11Protocol):
        _header_timer: asyncio.TimerHandle | None = None

        def _arm(self) -> None:
            self._disarm()
            self._header_timer = self.loop.call_later(header_timeout_s, self._header_deadline)

        def _disarm(self) -> None:
            if self._header_timer is not None:
                self._header_timer.cancel()
                self._header_timer = None

        def _header_deadline(self) -> None:
            self._header_timer = None
            t = self.transport
            if t is None or t.is_closing() or t.get_protocol() is not self:  # closed, or upgraded to a WebSocket
                return
            if self.conn.their_state is h11.IDLE and (self.cycle is None or self.cycle.response_complete):
                t.close()  # no complete request head in time (a partial one, or none)

        def connection_made(self, transport: Any) -> None:
            super().connection_made(transport)
            self._arm()

        def on_response_complete(self) -> None:
            super().on_response_complete()
            if self.transport is not None and not self.transport.is_closing():
                self._arm()

        def connection_lost(self, exc: Exception | None) -> None:
            self._disarm()
            super().connection_lost(exc)

    return HeaderTimeoutH11


def run(app: Any, host: str, port: int, config: ServiceConfig, log_level: str = "warning") -> None:
    """Serve ``app`` with uvicorn, one worker, with ``config``'s header,
    idle and size limits (WebSocket messages at most 64 KiB), and without
    WebSocket compression (permessage-deflate): a frame is float32 positions,
    which deflate shrinks little, and compressing one of the default 3D
    scene's (23,520 particles, 282 KB) took about 9 ms of the event loop per
    frame, which halved the frames a playing session streams (docs/page.md)."""
    import uvicorn

    uvicorn.run(
        app,
        host=host,
        port=port,
        workers=1,
        log_level=log_level,
        http=header_timeout_protocol(config.header_timeout_s),
        timeout_keep_alive=max(1, round(config.keep_alive_s)),
        h11_max_incomplete_event_size=config.max_header_bytes,
        ws_max_size=1 << 16,
        ws_per_message_deflate=False,
    )


__all__ = ["header_timeout_protocol", "run"]
