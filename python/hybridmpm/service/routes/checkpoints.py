"""Checkpoints: a session's whole state as npz (no pickle), written and restored."""

from __future__ import annotations

from typing import Any

from fastapi import APIRouter, Request
from fastapi.responses import Response

from hybridmpm.errors import CheckpointError, InvalidInputError
from hybridmpm.service import checkpoint as ckpt
from hybridmpm.service.backend import Session
from hybridmpm.service.deps import ConfigDep, ManagerDep, SessionDep
from hybridmpm.service.errors import FieldError
from hybridmpm.service.schemas import SessionInfo

OCTET = "application/octet-stream"
NPZ = "application/x-npz"

router = APIRouter()


def session_meta(s: Session) -> dict[str, Any]:
    return s.settings.meta()


@router.get(
    "/v1/sessions/{sid}/checkpoint",
    responses={
        200: {"content": {NPZ: {}}, "description": "the whole simulator state (npz of arrays + JSON, no pickle)"},
        404: {"description": "no such session"},
        503: {"description": "memory budget full (Retry-After)"},
    },
)
async def get_checkpoint(s: SessionDep, manager: ManagerDep) -> Response:
    data = await manager.checkpoint(s)
    return Response(data, media_type=NPZ, headers={"Content-Disposition": 'attachment; filename="checkpoint.npz"'})


@router.put(
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
async def put_checkpoint(s: SessionDep, request: Request, manager: ManagerDep, cfg: ConfigDep) -> dict[str, Any]:
    """Restore a checkpoint, all or nothing: a refused one (422 naming
    ``checkpoint``) leaves the session exactly as it was."""
    data = await request.body()
    need = await manager.compute(ckpt.decoded_nbytes, data)
    if need > cfg.max_checkpoint_bytes:  # refused before anything is reserved: retrying cannot help
        raise FieldError(
            ("body", "checkpoint"), f"checkpoint: its arrays declare {need} bytes once decompressed, more than the {cfg.max_checkpoint_bytes} allowed"
        )
    with manager.budget.hold(2 * need, "reading the checkpoint"):
        state, meta = await manager.compute(ckpt.loads, data, cfg.max_checkpoint_bytes)
        mine = session_meta(s)
        if meta != mine:
            differ = sorted(k for k in mine.keys() | meta.keys() if meta.get(k) != mine.get(k))[:4]
            shown = ", ".join(f"{k} {meta.get(k)!r} (this session: {mine.get(k)!r})" for k in differ)
            raise FieldError(("body", "checkpoint"), f"checkpoint: written for another session: {shown}")
        try:
            await manager.restore(s, state)  # the recent trajectory starts again at the restored state
        except (InvalidInputError, CheckpointError) as e:
            raise FieldError(("body", "checkpoint"), f"checkpoint: {e}") from None
        except (KeyError, TypeError, ValueError, AttributeError, IndexError, OverflowError) as e:
            raise FieldError(("body", "checkpoint"), f"checkpoint: malformed state ({type(e).__name__})") from None
        del state
    return await manager.info(s)
