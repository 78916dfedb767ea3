"""Rigid bodies: ``POST /v1/sessions/{sid}/bodies`` adds one to an MPM
session between frames and ``DELETE /v1/sessions/{sid}/bodies/{index}``
removes one (docs/bodies.md "Using bodies";
:meth:`hybridmpm.sim.MpmSimulator.add_body`)."""

from __future__ import annotations

import re
from typing import Any

from fastapi import APIRouter

from hybridmpm.errors import InvalidInputError
from hybridmpm.service.backend import Session
from hybridmpm.service.deps import ManagerDep, SessionDep
from hybridmpm.service.errors import ApiError, FieldError
from hybridmpm.service.schemas import BodyAdd, BodyAdded

router = APIRouter()
#: The simulator names a body's field ``bodies[i].density``; the request's is ``density``.
_BODY_FIELD = re.compile(r"^bodies\[\d+\]\.")


def _refuse_if_busy(s: Session) -> None:
    if s.controlling:
        raise ApiError(409, "a control is running on this session; add or remove bodies after it")
    if s.facts.kind != "mpm":
        raise ApiError(409, f"this session runs the {s.facts.kind} simulator, which holds no rigid bodies: create the session with solver 'mpm'")


@router.post(
    "/v1/sessions/{sid}/bodies",
    response_model=BodyAdded,
    status_code=201,
    responses={
        404: {"description": "no such session"},
        409: {"description": "a control is running on the session, or its simulator is not MPM"},
        422: {"description": "a bad shape, size, pose, density or mass, a body outside the walls, or one too many (the field named; the session unchanged)"},
    },
)
async def add_body(s: SessionDep, body: BodyAdd, manager: ManagerDep) -> dict[str, Any]:
    """Add a rigid body (a scene file's ``[[bodies]]`` table: ``shape``,
    ``center``, ``half_extents`` or ``radius``, ``angle_deg`` or ``rotation``,
    ``density`` or ``mass``, ``velocity``, ``angular_velocity``, ``friction``)
    at the session's current frame. Every viewer gets a ``bodies`` event with
    the session's bodies as given. A refused body changes nothing."""
    _refuse_if_busy(s)
    d = s.facts.dim
    for name in ("center", "half_extents", "velocity"):
        v = getattr(body, name)
        if v is not None and len(v) != d:
            raise FieldError(("body", name), f"{name}: expected {d} numbers (the session is {d}D)")
    try:
        out = await manager.add_body(s, body.model_dump(exclude_none=True))
    except InvalidInputError as e:
        raise FieldError(("body", _BODY_FIELD.sub("", str(e.field or "body"))), str(e)) from None
    return {k: out[k] for k in ("index", "num_bodies", "frame")}


@router.delete(
    "/v1/sessions/{sid}/bodies/{index}",
    response_model=BodyAdded,
    responses={
        404: {"description": "no such session, or no body of that index (named)"},
        409: {"description": "a control is running on the session, or its simulator is not MPM"},
    },
)
async def remove_body(s: SessionDep, index: int, manager: ManagerDep) -> dict[str, Any]:
    """Remove body ``index`` (its place in the session's ``bodies``; the
    later ones move down one). Every viewer gets a ``bodies`` event."""
    _refuse_if_busy(s)
    try:
        out = await manager.remove_body(s, index)
    except InvalidInputError as e:
        raise FieldError(("path", "index"), str(e), status=404) from None
    return {k: out[k] for k in ("index", "num_bodies", "frame")}
