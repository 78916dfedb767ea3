"""Blocks: ``POST /v1/sessions/{sid}/blocks`` pours a block of particles into
a session between frames (what the page's palette sends;
:func:`hybridmpm.sim.pour.pour_block`)."""

from __future__ import annotations

from typing import Any

from fastapi import APIRouter

from hybridmpm.errors import InvalidInputError
from hybridmpm.service.deps import ManagerDep, SessionDep
from hybridmpm.service.errors import ApiError, FieldError, field_error
from hybridmpm.service.schemas import BlockPour, BlockPoured

router = APIRouter()


@router.post(
    "/v1/sessions/{sid}/blocks",
    response_model=BlockPoured,
    status_code=201,
    responses={
        404: {"description": "no such session"},
        409: {"description": "a control is running on the session, or its solver is not MPM"},
        422: {
            "description": "a bad material or parameter, a block outside the walls, overlapping the particles there, "
            "or beyond the session's particle or memory budget (the field named; the session unchanged)"
        },
    },
)
async def pour_block(s: SessionDep, body: BlockPour, manager: ManagerDep) -> dict[str, Any]:
    """Add a block of particles (a scene file's block: ``material``, a model or
    a preset, and its parameters, in ``params`` or as flat keys, ``lo``, ``hi``,
    ``velocity``) at the
    session's current frame. Every viewer gets a ``particles`` event with the
    new count and particle types. A refused block changes nothing."""
    if s.controlling:
        raise ApiError(409, "a control is running on this session; pour after it")
    if s.settings.solver not in ("mpm", "realtime"):
        raise ApiError(409, f"this session's solver is {s.settings.solver!r}; only MPM runs every material: create the session with solver 'mpm' or 'realtime'")
    d = s.facts.dim
    for name in ("lo", "hi", "velocity"):
        v = getattr(body, name)
        if v is not None and len(v) != d:
            raise FieldError(("body", name), f"{name}: expected {d} numbers (the session is {d}D)")
    block = body.model_dump(exclude_none=True)
    params = block.pop("params", {})
    for k in params:
        if k in ("material", "lo", "hi", "velocity"):
            raise FieldError(("body", "params", k), f"params.{k}: not a material parameter (give {k} beside params)")
        if k in block:
            raise FieldError(("body", "params", k), f"params.{k}: given twice, in params and as the flat key {k}")
    try:
        out = await manager.pour(s, {**block, **params})
    except InvalidInputError as e:  # a parameter given in params is named there
        raise field_error(e, ("body", "params") if e.field in params else ("body",)) from None
    return {k: out[k] for k in ("added", "num_particles", "frame")}
