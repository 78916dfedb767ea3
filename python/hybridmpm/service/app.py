"""The FastAPI application: routes under ``/v1``, the frame stream, the page at ``/``.

:func:`create_app` wires the pieces: the middleware
(:mod:`~hybridmpm.service.middleware`), the error handlers
(:mod:`~hybridmpm.service.errors`) and one router per resource
(:mod:`~hybridmpm.service.routes`), whose dependencies
(:mod:`~hybridmpm.service.deps`) read the session manager and the
configuration from ``app.state``.

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

import contextlib
import logging
from collections.abc import AsyncIterator
from typing import Any

from fastapi import FastAPI
from fastapi.staticfiles import StaticFiles

from hybridmpm import __version__
from hybridmpm.errors import InvalidInputError
from hybridmpm.service.backend import SessionBackend
from hybridmpm.service.config import ServiceConfig
from hybridmpm.service.errors import ApiError, FieldError, install_error_handlers
from hybridmpm.service.logs import install_log_filters
from hybridmpm.service.middleware import BodyLimit, HostCheck
from hybridmpm.service.routes import ROUTERS
from hybridmpm.service.routes.health import STATIC
from hybridmpm.service.sessions import SessionManager

log = logging.getLogger("hybridmpm.service")


def session_manager(cfg: ServiceConfig) -> SessionBackend[Any]:
    """The session backend of ``cfg.backend``: this process's (``local``,
    :class:`hybridmpm.service.sessions.SessionManager`), or a Ray cluster's
    (``ray``, :class:`hybridmpm.service.ray_backend.manager.RaySessionManager`).
    Raises :class:`InvalidInputError` naming ``backend`` when Ray is not
    installed, ``ray_address`` when no cluster answers there."""
    if cfg.backend == "local":
        return SessionManager(cfg)
    try:
        # import time: Ray loads for the ray backend only
        from hybridmpm.service.ray_backend.manager import RaySessionManager
    except ImportError as e:
        raise InvalidInputError(f"backend: 'ray' needs Ray (pip install 'hybridmpm[cluster]'): {e}", "backend") from None
    return RaySessionManager(cfg)


def create_app(config: ServiceConfig | None = None) -> FastAPI:
    """The ASGI application (``uvicorn --factory hybridmpm.service:create_app``
    reads :meth:`ServiceConfig.from_env`). Raises :class:`InvalidInputError`
    naming the field of a bad setting (:func:`session_manager`, the store)."""
    cfg = config if config is not None else ServiceConfig.from_env()
    manager = session_manager(cfg)
    if manager.store is not None and not manager.remote:
        manager.store.claim()  # one server per store: a second is refused here, naming the first's pid

    @contextlib.asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        install_log_filters()  # again: uvicorn's logging configuration may have come after create_app
        n = await manager.restore_all()
        if manager.store is not None:
            log.warning("store %s: %d sessions restored; saving every %g s", cfg.store, n, cfg.save_every_s)
        if manager.remote:
            log.warning("sessions in the Ray cluster at %s (namespace %s, %g CPU each)", cfg.ray_address, cfg.ray_namespace, cfg.ray_num_cpus)
        manager.start()
        try:
            yield
        finally:
            await manager.stop()

    app = FastAPI(
        title="hybridmpm service",
        version=__version__,
        description="Sessions of the hybrid neural/MLS-MPM simulator: step, stream, control by sketch. Sessions live in one process, in memory, "
        "and in a store with `hybridmpm serve --store`; with `--backend ray`, each in an actor of a Ray cluster that every front end serves.",
        lifespan=lifespan,
    )
    app.state.manager = manager
    app.state.config = cfg
    app.state.scenes = []  # the scene list, made on first request
    install_log_filters()
    app.add_middleware(BodyLimit, config=cfg, budget=manager.budget)  # type: ignore[arg-type]
    app.add_middleware(HostCheck, allowed_hosts=cfg.allowed_hosts)  # type: ignore[arg-type]
    app.state.routers = ROUTERS  # the 405 handler's list of every route
    install_error_handlers(app)
    app.mount("/static", StaticFiles(directory=STATIC), name="static")
    for router in ROUTERS:
        app.include_router(router)
    return app


__all__ = ["ApiError", "BodyLimit", "FieldError", "create_app", "session_manager"]
