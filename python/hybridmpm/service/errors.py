"""The service's errors and their handlers.

Every bad field answers 422 in FastAPI's format (``{"detail": [{"loc":
["body", FIELD], "msg": ..., "type": ...}]}``, :class:`FieldError`); other
refusals answer ``{"detail": "..."}`` with their status (:class:`ApiError`).
Messages are at most :data:`~hybridmpm.service.config.MAX_MESSAGE_CHARS`
characters and free of object reprs (:func:`tidy`). An unexpected error is
logged (session ids redacted) and answers a plain 500.
"""

from __future__ import annotations

import logging
import re

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from starlette.exceptions import HTTPException as StarletteHTTPException
from starlette.routing import Match

from hybridmpm.errors import CheckpointError, InvalidInputError
from hybridmpm.service.backend import RETRY_AFTER_S
from hybridmpm.service.budget import BudgetFullError
from hybridmpm.service.config import MAX_MESSAGE_CHARS
from hybridmpm.service.core import SessionGoneError

log = logging.getLogger("hybridmpm.service")
_REPR = re.compile(r"<[^<>]{0,200}? (?:object )?at 0x[0-9a-fA-F]+>")
NO_SESSION = "no such session (unknown, deleted or expired)"


def tidy(msg: str, limit: int = MAX_MESSAGE_CHARS) -> str:
    """An error message fit for a client: object reprs (``<... at 0x...>``)
    replaced by ``<object>``, cut to ``limit`` characters with ``…``."""
    msg = _REPR.sub("<object>", str(msg)[: 4 * limit])
    return msg if len(msg) <= limit else msg[: limit - 1] + "…"


class FieldError(Exception):
    """A 422 naming the field at ``loc`` (FastAPI's error format); the message is :func:`tidy`."""

    def __init__(self, loc: tuple[str, ...], msg: str, status: int = 422, typ: str = "value_error") -> None:
        msg = tidy(msg)
        super().__init__(msg)
        self.loc, self.msg, self.status, self.typ = loc, msg, status, typ


class ApiError(Exception):
    """A refusal with ``status``, a :func:`tidy` ``detail`` and optional headers."""

    def __init__(self, status: int, detail: str, headers: dict[str, str] | None = None) -> None:
        detail = tidy(detail)
        super().__init__(detail)
        self.status, self.detail, self.headers = status, detail, headers


def budget_error(e: BudgetFullError) -> ApiError:
    return ApiError(503, str(e), {"Retry-After": str(RETRY_AFTER_S)})


def field_error(e: InvalidInputError | CheckpointError, prefix: tuple[str, ...] = ("body",), default: str = "body") -> FieldError:
    name = getattr(e, "field", None) or default
    return FieldError((*prefix, str(name)), str(e))


async def on_validation(request: Request, exc: RequestValidationError) -> JSONResponse:
    detail = [
        {"loc": [tidy(str(x), 80) for x in e.get("loc", ())], "msg": tidy(str(e.get("msg", ""))), "type": tidy(str(e.get("type", "value_error")), 80)}
        for e in exc.errors()[:8]
    ]
    return JSONResponse({"detail": detail}, status_code=422)


async def on_http(request: Request, exc: StarletteHTTPException) -> JSONResponse:
    headers = dict(exc.headers or {})
    if exc.status_code == 405:  # every method the path answers, not only the first route's
        methods: set[str] = set()
        routes = [*request.app.router.routes, *(r for router in request.app.state.routers for r in router.routes)]
        for route in routes:
            if getattr(route, "methods", None) and route.matches({**request.scope, "method": "\x00"})[0] != Match.NONE:
                methods |= set(route.methods)
        headers["Allow"] = ", ".join(sorted(methods))
    return JSONResponse({"detail": tidy(str(exc.detail))}, status_code=exc.status_code, headers=headers)


async def on_api(request: Request, exc: ApiError) -> JSONResponse:
    return JSONResponse({"detail": exc.detail}, status_code=exc.status, headers=exc.headers)


async def on_field(request: Request, exc: FieldError) -> JSONResponse:
    return JSONResponse({"detail": [{"loc": list(exc.loc), "msg": exc.msg, "type": exc.typ}]}, status_code=exc.status)


async def on_budget(request: Request, exc: BudgetFullError) -> JSONResponse:
    return await on_api(request, budget_error(exc))


async def on_gone(request: Request, exc: SessionGoneError) -> JSONResponse:
    return await on_api(request, ApiError(404, NO_SESSION))


async def on_invalid(request: Request, exc: InvalidInputError) -> JSONResponse:
    return await on_field(request, field_error(exc))


async def on_unexpected(request: Request, exc: Exception) -> JSONResponse:
    log.error("unexpected error on %s %s", request.method, request.url.path, exc_info=exc)  # ids redacted by the log filter
    return JSONResponse({"detail": "internal error (logged)"}, status_code=500)


def install_error_handlers(app: FastAPI) -> None:
    """The handlers above, each for its exception type."""
    app.add_exception_handler(RequestValidationError, on_validation)  # type: ignore[arg-type]
    app.add_exception_handler(StarletteHTTPException, on_http)  # type: ignore[arg-type]
    app.add_exception_handler(BudgetFullError, on_budget)  # type: ignore[arg-type]
    app.add_exception_handler(SessionGoneError, on_gone)  # type: ignore[arg-type]
    app.add_exception_handler(FieldError, on_field)  # type: ignore[arg-type]
    app.add_exception_handler(InvalidInputError, on_invalid)  # type: ignore[arg-type]
    app.add_exception_handler(ApiError, on_api)  # type: ignore[arg-type]
    app.add_exception_handler(Exception, on_unexpected)


__all__ = ["ApiError", "FieldError", "budget_error", "field_error", "install_error_handlers", "tidy"]
