"""Sessions: create, read, delete."""

from __future__ import annotations

from typing import Any

from fastapi import APIRouter, Request, Response

from hybridmpm.service.backend import RETRY_AFTER_S, QuotaError, SessionCapError, StoreSaveError
from hybridmpm.service.capacity import RealtimeFullError
from hybridmpm.service.deps import ConfigDep, ManagerDep, SessionDep
from hybridmpm.service.errors import NO_SESSION, ApiError
from hybridmpm.service.facts import checked_integrator, checked_n_grid, checked_realtime
from hybridmpm.service.schemas import CreateSession, SessionInfo

router = APIRouter()


@router.post(
    "/v1/sessions",
    status_code=201,
    response_model=SessionInfo,
    responses={
        429: {"description": "this client address holds its quota of sessions (Retry-After)"},
        503: {
            "description": "session cap reached, memory budget full, real time full for a real-time session (how many play, at what cost), "
            "or the store could not save the new session (Retry-After)"
        },
        507: {"description": "the store is full: the new session could not be saved, and nothing was created"},
    },
)
async def create_session(body: CreateSession, request: Request, manager: ManagerDep, cfg: ConfigDep) -> dict[str, Any]:
    scene = body.scene.value if hasattr(body.scene, "value") else str(body.scene)
    client = request.client.host if request.client is not None else ""
    try:
        solver = checked_realtime(body.solver, body.realtime, body.n_grid, body.integrator, cfg.realtime)  # null: the server's default
        n_grid, integrator = checked_n_grid(scene, solver, body.n_grid), checked_integrator(solver, body.integrator)
        s = await manager.create(scene, body.seed, solver, body.r_c, client, n_grid=n_grid, integrator=integrator, when_full=body.when_full)
    except RealtimeFullError as e:
        raise ApiError(503, str(e), {"Retry-After": str(RETRY_AFTER_S)}) from None
    except SessionCapError:
        raise ApiError(503, f"the server holds its maximum of {cfg.max_sessions} sessions; retry later", {"Retry-After": "30"}) from None
    except QuotaError:
        msg = f"this client address holds its maximum of {cfg.max_sessions_per_client} sessions (per client); delete one or retry later"
        raise ApiError(429, msg, {"Retry-After": "30"}) from None
    except StoreSaveError as e:  # a 201 means the session is in the store
        if e.full:
            raise ApiError(507, f"store: full, the new session could not be saved ({e.why}); nothing was created") from None
        msg = f"store: the new session could not be saved ({e.why}); nothing was created, retry later"
        raise ApiError(503, msg, {"Retry-After": str(RETRY_AFTER_S)}) from None
    return await manager.info(s)


@router.get("/v1/sessions/{sid}", response_model=SessionInfo, responses={404: {"description": "no such session"}})
async def get_session(s: SessionDep, manager: ManagerDep) -> dict[str, Any]:
    return await manager.info(s)


@router.delete("/v1/sessions/{sid}", status_code=204, responses={404: {"description": "no such session"}})
async def delete_session(sid: str, manager: ManagerDep) -> Response:
    if not await manager.close(sid, 1000, "deleted"):
        raise ApiError(404, NO_SESSION)
    return Response(status_code=204)
