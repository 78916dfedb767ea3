"""The FastAPI application: routes under ``/v1``, the frame stream, the page at ``/``.

Errors: every bad field answers 422 in FastAPI's format
(``{"detail": [{"loc": ["body", FIELD], "msg": ..., "type": ...}]}``, the
message at most :data:`~hybridmpm.service.config.MAX_MESSAGE_CHARS`
characters and free of object reprs), a body over its cap 413, a body too
slow 408, an unknown session 404, a full server or a full memory budget 503
with ``Retry-After``, a second control on a session 409, too many controls at
once or a client over its session quota 429, a ``Host`` not served 400; an
unexpected error is logged (session ids redacted) and answers a plain 500
(the tests fuzz the API to keep that from happening). A refused request
changes nothing.
"""

from __future__ import annotations

import asyncio
import base64
import contextlib
import io
import ipaddress
import json
import logging
import math
import re
import secrets
import threading
import time
from collections.abc import AsyncIterator, Awaitable, Callable, MutableMapping
from pathlib import Path
from typing import Any
from urllib.parse import urlsplit

import numpy as np
from fastapi import FastAPI, Request, WebSocket, WebSocketDisconnect
from fastapi.exceptions import RequestValidationError
from fastapi.responses import FileResponse, JSONResponse, Response, StreamingResponse
from fastapi.staticfiles import StaticFiles
from starlette.exceptions import HTTPException as StarletteHTTPException
from starlette.middleware.trustedhost import TrustedHostMiddleware
from starlette.routing import Match

from hybridmpm.conventions import T_CTR
from hybridmpm.errors import CheckpointError, InvalidInputError
from hybridmpm.service import checkpoint as ckpt
from hybridmpm.service.config import LOOPBACK_HOSTS, MAX_MESSAGE_CHARS, ServiceConfig
from hybridmpm.service.frames import encode_frame
from hybridmpm.service.logs import SHOWN_ID_CHARS, install_log_filters
from hybridmpm.service.schemas import (
    ControlRequest,
    ControlResponse,
    CreateSession,
    Health,
    SceneInfo,
    SessionInfo,
    StepRequest,
    StepResponse,
    clean,
)
from hybridmpm.service.sessions import (
    RETRY_AFTER_S,
    BudgetFullError,
    Control,
    MemoryBudget,
    QuotaError,
    Session,
    SessionCapError,
    SessionManager,
    Viewer,
    close_ws,
    tree_nbytes,
)

log = logging.getLogger("hybridmpm.service")
STATIC = Path(__file__).parent / "static"
OCTET = "application/octet-stream"
NPZ = "application/x-npz"
CSP = "default-src 'self'; img-src 'self' data:; connect-src 'self'; style-src 'self'; script-src 'self'; object-src 'none'; base-uri 'none'"

#: Transient bytes per position value of a step's answer: JSON text, its pieces and the joined body; raw float32 and its copies.
JSON_BYTES_PER_VALUE = 64
BINARY_BYTES_PER_VALUE = 16
#: Values of a step's positions JSON-encoded at a time, the GIL handed over in between.
JSON_VALUES_PER_PIECE = 1024
#: Copies of a control's trajectory alive while it runs (its frames, the stacked array, the kept one).
CONTROL_COPIES = 3
#: Bytes per pixel while a PNG sketch is decoded (the decoded image, its RGB copy, the ink mask).
PNG_BYTES_PER_PIXEL = 8
#: How often a running control looks whether its client has left [s].
DISCONNECT_POLL_S = 0.25
#: Deepest JSON a WebSocket message may nest (the protocol's messages are flat objects).
WS_MAX_JSON_DEPTH = 4

Scope = MutableMapping[str, Any]
Receive = Callable[[], Awaitable[MutableMapping[str, Any]]]
Send = Callable[[MutableMapping[str, Any]], Awaitable[None]]
_REPR = re.compile(r"<[^<>]{0,200}? (?:object )?at 0x[0-9a-fA-F]+>")


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
    def __init__(self, status: int, detail: str, headers: dict[str, str] | None = None) -> None:
        detail = tidy(detail)
        super().__init__(detail)
        self.status, self.detail, self.headers = status, detail, headers


def _budget_error(e: BudgetFullError) -> ApiError:
    return ApiError(503, str(e), {"Retry-After": str(RETRY_AFTER_S)})


def _field_error(e: InvalidInputError | CheckpointError, prefix: tuple[str, ...] = ("body",), default: str = "body") -> FieldError:
    name = getattr(e, "field", None) or default
    return FieldError((*prefix, str(name)), str(e))


async def _send_json(send: Send, status: int, body: dict[str, Any], headers: list[tuple[bytes, bytes]] = ()) -> None:  # type: ignore[assignment]
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
            await _send_json(send, 415, {"detail": [{"loc": ["body", "sketch"], "msg": msg, "type": "unsupported_media_type"}]})
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
                await _send_json(send, 413, too_big)
                return
            expected = max(0, n)
        try:
            reserved = self.budget.take(expected, "this request's body")
        except BudgetFullError as e:
            await _send_json(send, 503, {"detail": str(e)}, [(b"retry-after", str(RETRY_AFTER_S).encode())])
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
                    await _send_json(send, 408, {"detail": [{"loc": ["body"], "msg": msg, "type": "timeout"}]}, [(b"connection", b"close")])
                    return
                if msg_["type"] == "http.disconnect":
                    return
                body = msg_.get("body", b"")
                size += len(body)
                if size > limit:
                    await _send_json(send, 413, too_big)
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
            if server and _is_loopback(str(server[0])):
                await self.loopback(scope, receive, send)
                return
        await self.app(scope, receive, send)


def _is_loopback(host: str) -> bool:
    try:
        return ipaddress.ip_address(host.strip("[]")).is_loopback
    except ValueError:
        return host.lower() == "localhost"


def _scene_list() -> list[dict[str, Any]]:
    from hybridmpm.models import shipped_models
    from hybridmpm.scenes import DOMAINS

    ships = shipped_models()
    out = []
    for name, gen in sorted(DOMAINS.items()):
        spec = gen(seed=0)
        doc = (gen.__doc__ or "").strip().split("\n\n")[0].replace("\n", " ")
        has = name in ships
        out.append(
            {
                "name": name,
                "dim": int(spec.params.dim),
                "frames": int(spec.frames),
                "seeded": name != "dam_break2d",
                "doc": " ".join(doc.split()),
                "solvers": ["hybrid", "mpm", "neural"] if has else ["mpm"],
                "model": has,
            }
        )
    return out


def _json_floats(a: np.ndarray) -> str:
    """``a`` float [n, d] as a JSON array of arrays (what ``json.dumps(a.tolist())``
    writes), formatted a few thousand values at a time with no list per row
    (nothing for the garbage collector), handing the GIL over between pieces:
    a worker thread running this stalls the event loop by one piece at most."""
    if not np.isfinite(a).all():
        return json.dumps(clean(a.tolist()))
    n, d = a.shape
    row = "[" + ", ".join(["%r"] * d) + "]"
    step = max(1, JSON_VALUES_PER_PIECE // d)
    pieces = []
    for i in range(0, n, step):
        block = a[i : i + step]
        pieces.append(", ".join([row] * len(block)) % tuple(block.reshape(-1).tolist()))
        time.sleep(0)
    return "[" + ", ".join(pieces) + "]"


def _step_json(
    pos: np.ndarray, frames: list[int], solvers: list[str], seconds: list[float], r_t: int, dt: float, failure: str | None, latency: float
) -> list[bytes]:
    """The JSON answer of a step as its pieces (one per frame), encoded in a
    worker thread (:func:`_json_floats`), which lets the event loop run in
    between; sent one piece at a time, never joined into one buffer."""
    parts = [b'{"frames": [']
    for k in range(len(pos)):
        fr = frames[k]
        head = {"step": fr // r_t, "frame": fr, "time": fr * dt, "solver": solvers[k], "seconds": seconds[k], "controlled": False}
        item = json.dumps(head, allow_nan=False)[:-1] + ', "positions": ' + _json_floats(pos[k]) + "}"
        parts.append(((", " if k else "") + item).encode())
    parts.append(("], " + json.dumps({"failure": failure, "latency_ms": latency})[1:]).encode())
    return parts


def _png(img: np.ndarray) -> str:
    from PIL import Image

    buf = io.BytesIO()
    Image.fromarray(img).save(buf, format="PNG")
    return base64.b64encode(buf.getvalue()).decode()


def _origin_ok(ws: WebSocket, config: ServiceConfig) -> bool:
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


def create_app(config: ServiceConfig | None = None) -> FastAPI:
    """The ASGI application (``uvicorn --factory hybridmpm.service:create_app``
    reads :meth:`ServiceConfig.from_env`)."""
    cfg = config if config is not None else ServiceConfig.from_env()
    manager = SessionManager(cfg)
    scenes_cache: list[dict[str, Any]] = []

    @contextlib.asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        install_log_filters()  # again: uvicorn's logging configuration may have come after create_app
        n = await manager.restore_all()
        if manager.store is not None:
            log.warning("store %s: %d sessions restored; saving every %g s", cfg.store, n, cfg.save_every_s)
        manager.start()
        try:
            yield
        finally:
            await manager.stop()

    from hybridmpm import __version__

    app = FastAPI(
        title="hybridmpm service",
        version=__version__,
        description="Sessions of the hybrid neural/MLS-MPM simulator: step, stream, control by sketch. Sessions live in one process, in memory, and in a store with `hybridmpm serve --store`.",
        lifespan=lifespan,
    )
    app.state.manager = manager
    app.state.config = cfg
    install_log_filters()
    app.add_middleware(BodyLimit, config=cfg, budget=manager.budget)  # type: ignore[arg-type]
    app.add_middleware(HostCheck, allowed_hosts=cfg.allowed_hosts)  # type: ignore[arg-type]

    # ------------------------------------------------------------ errors
    @app.exception_handler(RequestValidationError)
    async def on_validation(request: Request, exc: RequestValidationError) -> JSONResponse:
        detail = [
            {"loc": [tidy(str(x), 80) for x in e.get("loc", ())], "msg": tidy(str(e.get("msg", ""))), "type": tidy(str(e.get("type", "value_error")), 80)}
            for e in exc.errors()[:8]
        ]
        return JSONResponse({"detail": detail}, status_code=422)

    @app.exception_handler(StarletteHTTPException)
    async def on_http(request: Request, exc: StarletteHTTPException) -> JSONResponse:
        headers = dict(exc.headers or {})
        if exc.status_code == 405:  # every method the path answers, not only the first route's
            methods: set[str] = set()
            for route in app.router.routes:
                match, _ = route.matches({**request.scope, "method": "\x00"})
                if match != Match.NONE:
                    methods |= set(getattr(route, "methods", None) or ())
            headers["Allow"] = ", ".join(sorted(methods))
        return JSONResponse({"detail": tidy(str(exc.detail))}, status_code=exc.status_code, headers=headers)

    @app.exception_handler(BudgetFullError)
    async def on_budget(request: Request, exc: BudgetFullError) -> JSONResponse:
        return await on_api(request, _budget_error(exc))

    @app.exception_handler(FieldError)
    async def on_field(request: Request, exc: FieldError) -> JSONResponse:
        return JSONResponse({"detail": [{"loc": list(exc.loc), "msg": exc.msg, "type": exc.typ}]}, status_code=exc.status)

    @app.exception_handler(InvalidInputError)
    async def on_invalid(request: Request, exc: InvalidInputError) -> JSONResponse:
        return await on_field(request, _field_error(exc))

    @app.exception_handler(ApiError)
    async def on_api(request: Request, exc: ApiError) -> JSONResponse:
        return JSONResponse({"detail": exc.detail}, status_code=exc.status, headers=exc.headers)

    @app.exception_handler(Exception)
    async def on_unexpected(request: Request, exc: Exception) -> JSONResponse:
        log.error("unexpected error on %s %s", request.method, request.url.path, exc_info=exc)  # ids redacted by the log filter
        return JSONResponse({"detail": "internal error (logged)"}, status_code=500)

    def session_or_404(sid: str) -> Session:
        s = manager.get(sid)
        if s is None:
            raise ApiError(404, "no such session (unknown, deleted or expired)")
        return s

    # ------------------------------------------------------------ page
    @app.get("/", include_in_schema=False)
    async def page() -> FileResponse:
        return FileResponse(STATIC / "index.html", headers={"Content-Security-Policy": CSP, "Cache-Control": "no-cache"})

    app.mount("/static", StaticFiles(directory=STATIC), name="static")

    @app.get("/healthz", response_model=Health)
    async def healthz() -> dict[str, Any]:
        return {
            "status": "ok",
            "sessions": manager.count(),
            "max_sessions": cfg.max_sessions,
            "memory_used": manager.budget.used,
            "memory_budget": manager.budget.total,
            "version": __version__,
        }

    @app.get("/v1/scenes", response_model=list[SceneInfo])
    async def scenes() -> list[dict[str, Any]]:
        if not scenes_cache:
            scenes_cache.extend(await manager.compute(_scene_list))
        return scenes_cache

    # ------------------------------------------------------------ sessions
    @app.post(
        "/v1/sessions",
        status_code=201,
        response_model=SessionInfo,
        responses={
            429: {"description": "this client address holds its quota of sessions (Retry-After)"},
            503: {"description": "session cap reached or memory budget full (Retry-After)"},
        },
    )
    async def create_session(body: CreateSession, request: Request) -> dict[str, Any]:
        scene = body.scene.value if hasattr(body.scene, "value") else str(body.scene)
        client = request.client.host if request.client is not None else ""
        try:
            s = await manager.create(scene, body.seed, body.solver, body.r_c, client)
        except SessionCapError:
            raise ApiError(503, f"the server holds its maximum of {cfg.max_sessions} sessions; retry later", {"Retry-After": "30"}) from None
        except QuotaError:
            msg = f"this client address holds its maximum of {cfg.max_sessions_per_client} sessions (per client); delete one or retry later"
            raise ApiError(429, msg, {"Retry-After": "30"}) from None
        return s.info()

    @app.get("/v1/sessions/{sid}", response_model=SessionInfo, responses={404: {"description": "no such session"}})
    async def get_session(sid: str) -> dict[str, Any]:
        return session_or_404(sid).info()

    @app.delete("/v1/sessions/{sid}", status_code=204, responses={404: {"description": "no such session"}})
    async def delete_session(sid: str) -> Response:
        if not await manager.close(sid, 1000, "deleted"):
            raise ApiError(404, "no such session (unknown, deleted or expired)")
        return Response(status_code=204)

    @app.post(
        "/v1/sessions/{sid}/step",
        response_model=StepResponse,
        responses={
            200: {
                "content": {OCTET: {"schema": {"type": "string", "format": "binary"}}},
                "description": "JSON, or float32 [K, N, D] with Accept: application/octet-stream (X-Shape, X-Solvers, X-Seconds headers)",
            },
            404: {"description": "no such session"},
        },
    )
    async def step(sid: str, body: StepRequest, request: Request) -> Any:
        from hybridmpm.sim import rollout

        s = session_or_404(sid)
        if body.frames > cfg.max_frames:
            raise FieldError(("body", "frames"), f"frames: at most {cfg.max_frames} per request")
        binary = OCTET in request.headers.get("accept", "")
        values = math.ceil(body.frames / int(s.sim.r_t)) * s.sim.particles.num_total * s.sim.particles.dim
        with manager.budget.hold(values * (BINARY_BYTES_PER_VALUE if binary else JSON_BYTES_PER_VALUE), f"a step of {body.frames} frames"):
            t0 = time.perf_counter()
            async with s.lock:
                if s.closed:
                    raise ApiError(404, "no such session (unknown, deleted or expired)")
                ro = await manager.compute(rollout, s.sim, body.frames)
                manager.changed(s)
            latency = (time.perf_counter() - t0) * 1e3
            s.touch()
            pos = np.asarray(ro.positions[1:], np.float32)
            solvers = [str(x) for x in list(ro.solver)[1:]]
            seconds = [float(x) for x in np.asarray(ro.seconds)[1:]]
            frames_ = [int(x) for x in np.asarray(ro.frame_index)[1:]]
            failure = None if ro.failure is None else str(ro.failure)
            del ro
            if len(pos):
                s.publish(s.sim.frame)
            if binary:
                headers = {
                    "X-Shape": ",".join(str(x) for x in pos.shape),
                    "X-Solvers": ",".join(solvers),
                    "X-Seconds": ",".join(f"{x:.6g}" for x in seconds),
                    "X-Frames": ",".join(str(x) for x in frames_),
                    "X-Latency-Ms": f"{latency:.3f}",
                }
                if failure:
                    headers["X-Failure"] = failure
                return Response(await manager.compute(lambda: np.ascontiguousarray(pos, "<f4").tobytes()), media_type=OCTET, headers=headers)
            parts = await manager.compute(_step_json, pos, frames_, solvers, seconds, int(s.sim.r_t), float(s.sim.dt_frame), failure, latency)

            async def pieces() -> AsyncIterator[bytes]:
                while parts:
                    yield parts.pop(0)

            size = str(sum(len(x) for x in parts))
            return StreamingResponse(pieces(), media_type="application/json", headers={"Content-Length": size})

    # ------------------------------------------------------------ controls
    @app.post(
        "/v1/sessions/{sid}/controls",
        response_model=ControlResponse,
        responses={
            404: {"description": "no such session"},
            409: {"description": "a control is already running on this session"},
            415: {"description": "a raw image body (use sketch_png, or POST .../controls/png)"},
            429: {"description": "too many controls running (Retry-After)"},
        },
    )
    async def control(sid: str, body: ControlRequest, request: Request) -> dict[str, Any]:
        """Runs the control; when the client leaves before the answer, the
        control stops within a frame: the session keeps the frames already
        computed (as after a step), the control is not kept, its slots are freed."""
        from hybridmpm.control import Controller, Sketch, render_sketch

        t_req = time.perf_counter()
        s = session_or_404(sid)
        sketch = None
        if body.sketch is not None and body.sketch_png is not None:
            raise FieldError(("body", "sketch_png"), "sketch_png: give the sketch either as `sketch` or as `sketch_png`, not both")
        if body.sketch_png is not None:
            import base64
            import binascii

            from hybridmpm.control import sketch_from_png
            from hybridmpm.control.sketch import MAX_IMAGE_PIXELS

            try:
                data = base64.b64decode(body.sketch_png, validate=True)
            except (binascii.Error, ValueError):
                raise FieldError(("body", "sketch_png"), "sketch_png: not base64") from None
            try:
                with manager.budget.hold(MAX_IMAGE_PIXELS * PNG_BYTES_PER_PIXEL, "decoding the sketch image"):
                    sketch = await manager.compute(sketch_from_png, data)
            except InvalidInputError as e:
                raise FieldError(("body", "sketch_png"), str(e).replace("sketch:", "sketch_png:", 1)) from None
        if body.sketch is not None:
            try:
                sketch = Sketch.from_json(body.sketch.model_dump(exclude_none=True))
            except InvalidInputError as e:
                raise _field_error(e, ("body", "sketch"), "points") from None
            n_grid = int(s.sim.scene.params.resolved_n_grid())
            if float(np.linalg.norm(sketch.points.max(0) - sketch.points.min(0))) < 2.0 / n_grid:
                raise FieldError(("body", "sketch", "points"), f"points: the stroke must span at least 2 grid cells ({2.0 / n_grid:.4g} m)")
        if body.frames > cfg.max_control_frames:
            raise FieldError(("body", "frames"), f"frames: at most {cfg.max_control_frames}")
        try:
            controller = Controller.for_scene(s.sim.scene.name, body.method, frames=body.frames)
        except InvalidInputError as e:
            if e.field == "scene":  # no diffusion controller ships for this session's scene
                raise FieldError(("body", "method"), f"method: {e}".replace("scene: ", "", 1)) from None
            raise _field_error(e, default="method") from None
        if sketch is None and body.method != "none":
            raise FieldError(("body", "sketch"), f"sketch: the {body.method} method needs a sketch")
        if s.controlling:
            raise ApiError(409, "a control is already running on this session")
        if manager.controls_running >= cfg.max_controls:
            raise ApiError(429, "too many controls running; retry shortly", {"Retry-After": "2"})
        p = s.sim.particles
        frame_bytes = p.num_total * p.dim * 4
        steps = math.ceil(body.frames / int(s.sim.r_t))
        transient = manager.budget.take(CONTROL_COPIES * (steps + 1) * frame_bytes, f"a control of {body.frames} frames")
        s.controlling = True
        manager.controls_running += 1
        cid = secrets.token_urlsafe(9)
        loop = asyncio.get_running_loop()
        first: list[float] = []
        left = threading.Event()  # set when the client has gone

        async def watch() -> None:
            while not left.is_set():
                if await request.is_disconnected():
                    left.set()
                    return
                await asyncio.sleep(DISCONNECT_POLL_S)

        watcher = loop.create_task(watch())
        try:
            s.broadcast({"type": "control", "status": "running", "id": cid, "method": body.method})
            async with s.lock:
                if s.closed:
                    raise ApiError(404, "no such session (unknown, deleted or expired)")

                def run() -> tuple[Any, Any, dict[str, Any]]:
                    from hybridmpm.control import control_metrics
                    from hybridmpm.sim import rollout

                    plan = controller.plan(s.sim, sketch)
                    k0 = int(s.sim.frame.frame)

                    def on_frame(fr: Any) -> None:
                        if not first:
                            first.append(time.perf_counter())
                        loop.call_soon_threadsafe(s.publish, fr, int(fr.frame) - k0)

                    def client_left(fr: Any, sim: Any) -> str | None:
                        return "cancelled: the client left" if left.is_set() else None

                    s.sim.forcing = plan
                    try:
                        ro = rollout(s.sim, controller.frames, on_frame=on_frame, stop=client_left)
                    finally:
                        s.sim.forcing = None
                    if left.is_set():
                        return ro, plan, {}
                    fluid = ro.fluid_positions
                    m = control_metrics(fluid[0], fluid[-1], sketch, plan.applied, None, s.sim.scene.params.resolved_n_grid())
                    m.update(
                        {
                            "plan_ms": plan.seconds * 1e3,
                            "episode_ms": float(np.asarray(ro.seconds).sum()) * 1e3,
                            "frames": ro.frames_done,
                            "failure": ro.failure,
                            "network": plan.network,
                        }
                    )
                    c0, c1 = fluid[0].mean(0), fluid[-1].mean(0)
                    m["centroid_start"] = c0.tolist()
                    m["centroid_end"] = c1.tolist()
                    m["centroid_displacement"] = (c1 - c0).tolist()
                    return ro, plan, m

                ro, plan, metrics = await manager.compute(run)
                manager.changed(s)
            if left.is_set():
                log.info("control %s on session %s… cancelled: its client left", cid, sid[:SHOWN_ID_CHARS])
                s.broadcast({"type": "control", "status": "cancelled", "id": cid})
                s.publish(s.sim.frame)
                raise ApiError(408, "control cancelled: the client left")
            png = await manager.compute(lambda: _png(render_sketch(sketch))) if sketch is not None else None
            pos = np.asarray(ro.positions, np.float32)
            solver_names = [str(x) for x in ro.solver]
            t_end = time.perf_counter()
            resp = {
                "id": cid,
                "method": body.method,
                "frames": int(controller.frames),
                "shape": list(pos.shape),
                "start_frame": int(np.asarray(ro.frame_index)[0]),
                "end_frame": int(s.sim.frame.frame),
                "metrics": clean(metrics),
                "sketch": clean(sketch.to_json()) if sketch is not None else None,
                "sketch_png": png,
                "first_frame_ms": ((first[0] if first else t_end) - t_req) * 1e3,
                "total_ms": (t_end - t_req) * 1e3,
                "trajectory": f"/v1/sessions/{sid}/controls/{cid}/trajectory",
            }
            del ro
            manager.budget.give(transient)  # the kept trajectory is smaller than what was reserved for the run
            transient = 0
            kept = Control(cid, body.method, pos, solver_names, resp)
            kept.cost = manager.budget.take(pos.nbytes + len(png or "") + 4096, "keeping the control")
            if s.closed:
                manager.budget.give(kept.cost)
            else:
                manager.keep_control(s, kept)
            await manager.save(s)  # a control is saved before it is answered
            s.broadcast({"type": "control", "status": "done", "id": cid, "metrics": resp["metrics"]})
            s.touch()
            return resp
        finally:
            left.set()
            watcher.cancel()
            manager.budget.give(transient)
            s.controlling = False
            manager.controls_running -= 1

    @app.post(
        "/v1/sessions/{sid}/controls/png",
        response_model=ControlResponse,
        openapi_extra={"requestBody": {"required": True, "content": {"image/png": {"schema": {"type": "string", "format": "binary"}}}}},
        responses={
            404: {"description": "no such session"},
            409: {"description": "a control is already running on this session"},
            413: {"description": "image larger than the body cap"},
            415: {"description": "not image/png"},
            422: {"description": "no readable sketch in the image, or a bad query parameter"},
        },
    )
    async def control_png(sid: str, request: Request, method: str = "constant", frames: int = T_CTR) -> dict[str, Any]:
        """The controls route with the sketch as a raw PNG body (``Content-Type:
        image/png``; the image spans the domain, y up); ``method`` and
        ``frames`` as query parameters."""
        from pydantic import ValidationError

        ctype = request.headers.get("content-type", "").split(";")[0].strip().lower()
        if ctype != "image/png":
            raise ApiError(415, "send the sketch image with Content-Type: image/png")
        data = await request.body()
        try:
            body = ControlRequest(sketch_png=base64.b64encode(data).decode(), method=method, frames=frames)  # type: ignore[arg-type]
        except ValidationError as e:
            err = e.errors()[0]
            loc = ("query", str(err["loc"][0])) if err["loc"] and err["loc"][0] in ("method", "frames") else ("body",)
            raise FieldError(loc, f"{'.'.join(str(x) for x in err['loc'])}: {err['msg']}") from None
        return await control(sid, body, request)

    @app.get("/v1/sessions/{sid}/controls/{cid}", response_model=ControlResponse, responses={404: {"description": "no such session or control"}})
    async def get_control(sid: str, cid: str) -> dict[str, Any]:
        c = session_or_404(sid).controls.get(cid)
        if c is None:
            raise ApiError(404, "no such control (the last 8 are kept)")
        return c.response

    @app.get(
        "/v1/sessions/{sid}/controls/{cid}/trajectory",
        responses={
            200: {
                "content": {NPZ: {}, OCTET: {}},
                "description": "npz (positions [T+1, N, D], solver, particle_type), or float32 with Accept: application/octet-stream",
            },
            404: {"description": "no such session or control"},
        },
    )
    async def get_trajectory(sid: str, cid: str, request: Request) -> Response:
        s = session_or_404(sid)
        c = s.controls.get(cid)
        if c is None:
            raise ApiError(404, "no such control (the last 8 are kept)")
        with manager.budget.hold(2 * c.positions.nbytes, "the trajectory's file"):
            if OCTET in request.headers.get("accept", ""):
                data = await manager.compute(lambda: np.ascontiguousarray(c.positions, "<f4").tobytes())
                return Response(data, media_type=OCTET, headers={"X-Shape": ",".join(str(x) for x in c.positions.shape)})
            ptype = np.asarray(s.sim.particles.particle_type)

            def npz() -> bytes:
                buf = io.BytesIO()
                np.savez(buf, positions=c.positions, solver=np.array(c.solver), particle_type=ptype)
                return buf.getvalue()

            data = await manager.compute(npz)
        return Response(data, media_type=NPZ, headers={"Content-Disposition": f'attachment; filename="control-{cid}.npz"'})

    # ------------------------------------------------------------ checkpoints
    def _meta(s: Session) -> dict[str, Any]:
        return {"scene": s.scene, "seed": s.seed, "solver": s.solver_kind, "r_c": s.r_c}

    @app.get(
        "/v1/sessions/{sid}/checkpoint",
        responses={
            200: {"content": {NPZ: {}}, "description": "the whole simulator state (npz of arrays + JSON, no pickle)"},
            404: {"description": "no such session"},
            503: {"description": "memory budget full (Retry-After)"},
        },
    )
    async def get_checkpoint(sid: str) -> Response:
        s = session_or_404(sid)
        with manager.budget.hold(2 * tree_nbytes(s.initial), "writing the checkpoint"):
            async with s.lock:
                state = await manager.compute(s.sim.state)
            data = await manager.compute(ckpt.dumps, state, _meta(s))
            del state
        return Response(data, media_type=NPZ, headers={"Content-Disposition": 'attachment; filename="checkpoint.npz"'})

    @app.put(
        "/v1/sessions/{sid}/checkpoint",
        status_code=200,
        response_model=SessionInfo,
        openapi_extra={"requestBody": {"required": True, "content": {OCTET: {"schema": {"type": "string", "format": "binary"}}}}},
        responses={
            404: {"description": "no such session"},
            413: {"description": "checkpoint too large"},
            422: {"description": "not a checkpoint of this session, or a malformed one (the session is unchanged)"},
            503: {"description": "memory budget full (Retry-After)"},
        },
    )
    async def put_checkpoint(sid: str, request: Request) -> dict[str, Any]:
        """Restore a checkpoint, all or nothing: a refused one (422 naming
        ``checkpoint``) leaves the session exactly as it was."""
        s = session_or_404(sid)
        data = await request.body()
        need = await manager.compute(ckpt.decoded_nbytes, data)
        with manager.budget.hold(2 * need, "reading the checkpoint"):
            state, meta = await manager.compute(ckpt.loads, data, cfg.max_checkpoint_bytes)
            mine = _meta(s)
            if meta != mine:
                differ = sorted(k for k in mine.keys() | meta.keys() if meta.get(k) != mine.get(k))[:4]
                shown = ", ".join(f"{k} {meta.get(k)!r} (this session: {mine.get(k)!r})" for k in differ)
                raise FieldError(("body", "checkpoint"), f"checkpoint: written for another session: {shown}")
            async with s.lock:
                try:
                    await manager.compute(s.sim.restore, state)
                except (InvalidInputError, CheckpointError) as e:
                    raise FieldError(("body", "checkpoint"), f"checkpoint: {e}") from None
                except (KeyError, TypeError, ValueError, AttributeError, IndexError, OverflowError) as e:
                    raise FieldError(("body", "checkpoint"), f"checkpoint: malformed state ({type(e).__name__})") from None
                manager.changed(s)
            del state
        s.publish(s.sim.frame)
        return s.info()

    # ------------------------------------------------------------ stream
    async def sender(v: Viewer, s: Session) -> None:
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

    @app.websocket("/v1/sessions/{sid}/stream")
    async def stream(ws: WebSocket, sid: str) -> None:
        if not _origin_ok(ws, cfg):
            await ws.close(code=1008, reason="origin not allowed")
            return
        s = manager.get(sid)
        if s is None:
            await ws.close(code=4004, reason="no such session")
            return
        await ws.accept()
        v = Viewer(ws)
        s.viewers.add(v)
        v.event(s.meta())
        fr = s.sim.frame
        v.offer(encode_frame(fr.positions, fr.frame, fr.time, fr.solver, fr.controlled))
        task = asyncio.get_running_loop().create_task(sender(v, s))
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
                if ckpt.json_depth(raw.encode()) <= WS_MAX_JSON_DEPTH:
                    with contextlib.suppress(ValueError):
                        msg = json.loads(raw)
                kind = msg.get("type") if isinstance(msg, dict) else None
                if kind == "play":
                    s.playing = True
                    manager.ensure_playing(s)
                elif kind == "pause":
                    s.playing = False
                elif kind == "reset":
                    async with s.lock:
                        await manager.compute(s.sim.restore, s.initial)
                        manager.changed(s)
                    s.publish(s.sim.frame)
                    s.broadcast({"type": "reset", "frame": int(s.sim.frame.frame)})
                elif kind == "ping":
                    t = msg.get("t")
                    v.event({"type": "pong", "t": t if isinstance(t, (int, float)) and not isinstance(t, bool) else None})
                else:
                    v.event({"type": "error", "message": 'unknown message; send {"type": "play" | "pause" | "reset" | "ping"}'})
        except (WebSocketDisconnect, RuntimeError, KeyError):
            pass
        finally:
            v.closed = True
            v.wake.set()
            s.viewers.discard(v)
            task.cancel()
            with contextlib.suppress(asyncio.CancelledError, Exception):
                await task

    return app


__all__ = ["ApiError", "BodyLimit", "FieldError", "create_app"]
