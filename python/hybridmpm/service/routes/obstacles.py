"""Obstacles: ``PUT /v1/sessions/{sid}/obstacles/{index}`` moves one over
the session's next step, pushing the fluid (what the page's drag sends;
:meth:`hybridmpm.sim.MpmSimulator.move_obstacle`, translation only)."""

from __future__ import annotations

from typing import Any

from fastapi import APIRouter

from hybridmpm.errors import InvalidInputError
from hybridmpm.service.deps import ManagerDep, SessionDep
from hybridmpm.service.errors import ApiError, FieldError, field_error
from hybridmpm.service.schemas import ObstacleMove, ObstacleMoved

router = APIRouter()


@router.put(
    "/v1/sessions/{sid}/obstacles/{index}",
    response_model=ObstacleMoved,
    responses={
        404: {"description": "no such session"},
        409: {"description": "a control is running on the session, or its solver is the network alone"},
        422: {"description": "no such obstacle, one that follows its scene's path, or a centre or velocity out of range (named)"},
    },
)
async def move_obstacle(s: SessionDep, index: int, body: ObstacleMove, manager: ManagerDep) -> dict[str, Any]:
    """Obstacle ``index`` (its place in the session's ``obstacles``) reaches
    ``center`` at the end of the session's next step; its boundary condition
    pushes the fluid meanwhile. Every viewer gets an ``obstacle`` event. A
    refused move changes nothing."""
    if s.controlling:
        raise ApiError(409, "a control is running on this session; move its obstacles after it")
    if s.settings.solver == "neural":
        raise ApiError(409, "this session's solver is the network alone, which moves no obstacle; create it with solver 'hybrid' or 'mpm'")
    if len(body.center) != s.facts.dim or (body.velocity is not None and len(body.velocity) != s.facts.dim):
        bad = "center" if len(body.center) != s.facts.dim else "velocity"
        raise FieldError(("body", bad), f"{bad}: expected {s.facts.dim} numbers (the session is {s.facts.dim}D)")
    try:
        frame = await manager.move_obstacle(s, index, list(body.center), None if body.velocity is None else list(body.velocity))
    except InvalidInputError as e:
        raise field_error(e, ("path",) if e.field == "index" else ("body",)) from None
    return {"index": index, "center": list(body.center), "frame": frame}
