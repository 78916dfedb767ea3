"""Typed dependencies of the routes: the application's session backend
(:class:`~hybridmpm.service.backend.SessionBackend`, either backend) and
configuration (``app.state``), and the session and control a path names
(404 if none). They are ``async``: FastAPI runs a plain function dependency
on its thread pool, these run on the event loop."""

from __future__ import annotations

from typing import Annotated, Any

from fastapi import Depends, Request

from hybridmpm.service.backend import Session, SessionBackend
from hybridmpm.service.config import ServiceConfig
from hybridmpm.service.core import Control
from hybridmpm.service.errors import NO_SESSION, ApiError


async def get_manager(request: Request) -> SessionBackend[Any]:
    return request.app.state.manager  # type: ignore[no-any-return]


async def get_config(request: Request) -> ServiceConfig:
    return request.app.state.config  # type: ignore[no-any-return]


ManagerDep = Annotated[SessionBackend[Any], Depends(get_manager)]
ConfigDep = Annotated[ServiceConfig, Depends(get_config)]


async def session_or_404(sid: str, manager: ManagerDep) -> Session:
    """The session ``sid`` (the path's), or a 404."""
    s = await manager.find(sid)
    if s is None:
        raise ApiError(404, NO_SESSION)
    return s


SessionDep = Annotated[Session, Depends(session_or_404)]


async def control_or_404(s: SessionDep, cid: str, manager: ManagerDep) -> Control:
    """The session's kept control ``cid`` (the path's), or a 404."""
    c = await manager.get_control(s, cid)
    if c is None:
        raise ApiError(404, "no such control (the last 8 are kept)")
    return c


ControlDep = Annotated[Control, Depends(control_or_404)]

__all__ = ["ConfigDep", "ControlDep", "ManagerDep", "SessionDep", "control_or_404", "get_config", "get_manager", "session_or_404"]
