"""Controls: a sketch applied to a session as a controlled episode
(:func:`~hybridmpm.control.control_episode`), its frames streamed as they come;
the kept controls and their trajectories.

A running control stops within a frame when its client leaves: the session
keeps the frames already computed (as after a step), the control is not kept,
its slots are freed.
"""

from __future__ import annotations

import base64
import binascii
import io
import logging
import time
from typing import Any

import numpy as np
from fastapi import APIRouter, Request
from fastapi.responses import Response
from pydantic import ValidationError

from hybridmpm.control import Sketch, sketch_from_png
from hybridmpm.control.controller import default_method
from hybridmpm.control.sketch import MAX_IMAGE_PIXELS
from hybridmpm.conventions import T_CTR
from hybridmpm.errors import InvalidInputError
from hybridmpm.service.controls import check_method, run_control
from hybridmpm.service.deps import ConfigDep, ControlDep, ManagerDep, SessionDep
from hybridmpm.service.errors import ApiError, FieldError, field_error
from hybridmpm.service.schemas import ControlRequest, ControlResponse

log = logging.getLogger("hybridmpm.service")
OCTET = "application/octet-stream"
NPZ = "application/x-npz"
#: Bytes per pixel while a PNG sketch is decoded (the decoded image, its RGB copy, the ink mask).
PNG_BYTES_PER_PIXEL = 8

router = APIRouter()


@router.post(
    "/v1/sessions/{sid}/controls",
    response_model=ControlResponse,
    responses={
        404: {"description": "no such session"},
        409: {"description": "a control is already running on this session, or its solver is the network alone"},
        415: {"description": "a raw image body (use sketch_png, or POST .../controls/png)"},
        429: {"description": "too many controls running (Retry-After)"},
    },
)
async def control(s: SessionDep, body: ControlRequest, request: Request, manager: ManagerDep, cfg: ConfigDep) -> dict[str, Any]:
    """Runs the control; when the client leaves before the answer, the
    control stops within a frame: the session keeps the frames already
    computed (as after a step), the control is not kept, its slots are freed."""
    t_req = time.perf_counter()
    sketch = None
    if body.sketch is not None and body.sketch_png is not None:
        raise FieldError(("body", "sketch_png"), "sketch_png: give the sketch either as `sketch` or as `sketch_png`, not both")
    if body.sketch_png is not None:
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
            raise field_error(e, ("body", "sketch"), "points") from None
        n_grid = s.facts.n_grid
        if float(np.linalg.norm(sketch.points.max(0) - sketch.points.min(0))) < 2.0 / n_grid:
            raise FieldError(("body", "sketch", "points"), f"points: the stroke must span at least 2 grid cells ({2.0 / n_grid:.4g} m)")
    if body.frames > cfg.max_control_frames:
        raise FieldError(("body", "frames"), f"frames: at most {cfg.max_control_frames}")
    method = body.method or default_method(s.facts.scene_name)  # none given: the scene's default (docs/control.md "Defaults")
    try:
        check_method(s.facts.scene_name, method)  # no model is loaded to validate a request
    except InvalidInputError as e:
        raise FieldError(("body", "method"), str(e)) from None
    if sketch is None and method != "none":
        raise FieldError(("body", "sketch"), f"sketch: the {method} method needs a sketch")
    if s.controlling:
        raise ApiError(409, "a control is already running on this session")
    if s.settings.solver == "neural":
        raise ApiError(409, "this session's solver is the network alone, which takes no control (control runs on MPM); create it with solver 'hybrid' or 'mpm'")
    if manager.controls_running >= cfg.max_controls:
        raise ApiError(429, "too many controls running; retry shortly", {"Retry-After": "2"})
    return await run_control(manager, s, sketch, method, body.frames, request, t_req)


@router.post(
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
async def control_png(s: SessionDep, request: Request, manager: ManagerDep, cfg: ConfigDep, method: str | None = None, frames: int = T_CTR) -> dict[str, Any]:
    """The controls route with the sketch as a raw PNG body (``Content-Type:
    image/png``; the image spans the domain, y up); ``method`` and
    ``frames`` as query parameters."""
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
    return await control(s, body, request, manager, cfg)


@router.get("/v1/sessions/{sid}/controls/{cid}", response_model=ControlResponse, responses={404: {"description": "no such session or control"}})
async def get_control(s: SessionDep, c: ControlDep) -> dict[str, Any]:  # s first: the schema lists sid before cid
    return c.response


@router.get(
    "/v1/sessions/{sid}/controls/{cid}/trajectory",
    responses={
        200: {
            "content": {NPZ: {}, OCTET: {}},
            "description": "npz (positions [T+1, N, D], solver, particle_type, dt_frame, n_grid: a hybridmpm trajectory), "
            "or float32 with Accept: application/octet-stream",
        },
        404: {"description": "no such session or control"},
    },
)
async def get_trajectory(s: SessionDep, c: ControlDep, request: Request, manager: ManagerDep) -> Response:
    with manager.budget.hold(2 * c.positions.nbytes, "the trajectory's file"):
        if OCTET in request.headers.get("accept", ""):
            data = await manager.compute(lambda: np.ascontiguousarray(c.positions, "<f4").tobytes())
            return Response(data, media_type=OCTET, headers={"X-Shape": ",".join(str(x) for x in c.positions.shape)})
        ptype, dt, n_grid = s.facts.particle_type, s.facts.step_dt, s.facts.n_grid

        def npz() -> bytes:  # a hybridmpm trajectory (hybridmpm.trajectory.Trajectory.load, hybridmpm evaluate)
            buf = io.BytesIO()
            np.savez(buf, positions=c.positions, solver=np.array(c.solver), particle_type=ptype, dt_frame=np.float64(dt), n_grid=np.int64(n_grid))
            return buf.getvalue()

        data = await manager.compute(npz)
    return Response(data, media_type=NPZ, headers={"Content-Disposition": f'attachment; filename="control-{c.id}.npz"'})
