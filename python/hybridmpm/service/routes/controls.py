"""Controls: a sketch applied to a session as a controlled episode
(:func:`~hybridmpm.control.control_episode`), its frames streamed as they come;
the kept controls and their trajectories.

A running control stops within a frame when its client leaves: the session
keeps the frames already computed (as after a step), the control is not kept,
its slots are freed.
"""

from __future__ import annotations

import asyncio
import base64
import binascii
import io
import logging
import math
import secrets
import threading
import time
from typing import Any

import numpy as np
from fastapi import APIRouter, Request
from fastapi.responses import Response
from pydantic import ValidationError

from hybridmpm.control import Controller, Sketch, render_sketch, sketch_from_png
from hybridmpm.control.sketch import MAX_IMAGE_PIXELS
from hybridmpm.conventions import T_CTR
from hybridmpm.errors import InvalidInputError
from hybridmpm.service.budget import BudgetFullError
from hybridmpm.service.deps import ConfigDep, ControlDep, ManagerDep, SessionDep
from hybridmpm.service.errors import ApiError, FieldError, field_error
from hybridmpm.service.logs import SHOWN_ID_CHARS
from hybridmpm.service.schemas import ControlRequest, ControlResponse, clean
from hybridmpm.service.sessions import Control, SessionGoneError

log = logging.getLogger("hybridmpm.service")
OCTET = "application/octet-stream"
NPZ = "application/x-npz"
#: Copies of a control's trajectory alive at its peak (its frames, the stacked array, the kept one, the plan's
#: arrays): measured with tracemalloc at 2.4 (constant) and 4.1 (diffusion) for a 1000-frame water3d hybrid
#: control, once the effort and smoothness metrics stopped keeping every applied field.
CONTROL_COPIES = 5
#: Bytes per pixel while a PNG sketch is decoded (the decoded image, its RGB copy, the ink mask).
PNG_BYTES_PER_PIXEL = 8
#: How often a running control looks whether its client has left [s].
DISCONNECT_POLL_S = 0.25

router = APIRouter()


def png_base64(img: np.ndarray) -> str:
    from PIL import Image

    buf = io.BytesIO()
    Image.fromarray(img).save(buf, format="PNG")
    return base64.b64encode(buf.getvalue()).decode()


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
    try:
        controller = Controller.for_scene(s.facts.scene_name, body.method, frames=body.frames)
    except InvalidInputError as e:
        if e.field == "scene":  # no diffusion controller ships for this session's scene
            raise FieldError(("body", "method"), f"method: {e}".replace("scene: ", "", 1)) from None
        raise field_error(e, default="method") from None
    if sketch is None and body.method != "none":
        raise FieldError(("body", "sketch"), f"sketch: the {body.method} method needs a sketch")
    if s.controlling:
        raise ApiError(409, "a control is already running on this session")
    if s.solver_kind == "neural":
        raise ApiError(409, "this session's solver is the network alone, which takes no control (control runs on MPM); create it with solver 'hybrid' or 'mpm'")
    if manager.controls_running >= cfg.max_controls:
        raise ApiError(429, "too many controls running; retry shortly", {"Retry-After": "2"})
    frame_bytes = s.facts.frame_bytes
    steps = math.ceil(body.frames / s.facts.r_t)
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
        await manager.save(s)  # the steps answered before it are durable: the periodic saver skips a session in a control
        # the backend tells the viewers "running" once the control has really started (a refused one, never)
        try:
            ro, metrics, plan = await manager.run_control(s, sketch, controller, left, first, cid)
        except (ApiError, SessionGoneError, BudgetFullError):
            raise  # refused before it ran, or its session is gone (its viewers were closed)
        except Exception:
            s.broadcast({"type": "control", "status": "failed", "id": cid})  # it started: its viewers see it end
            raise
        if left.is_set():
            log.info("control %s on session %s… cancelled: its client left", cid, s.id[:SHOWN_ID_CHARS])
            s.broadcast({"type": "control", "status": "cancelled", "id": cid})
            s.republish()
            raise ApiError(408, "control cancelled: the client left")
        fluid = ro.fluid_positions
        c0, c1 = fluid[0].mean(0), fluid[-1].mean(0)
        metrics.update({"centroid_start": c0.tolist(), "centroid_end": c1.tolist(), "centroid_displacement": (c1 - c0).tolist()})
        del fluid
        png = await manager.compute(lambda: png_base64(render_sketch(sketch))) if sketch is not None else None
        pos = np.asarray(ro.positions, np.float32)
        solver_names = [str(x) for x in ro.solver]
        t_end = time.perf_counter()
        resp = {
            "id": cid,
            "method": body.method,
            "frames": int(controller.frames),
            "shape": list(pos.shape),
            "start_frame": int(np.asarray(ro.frame_index)[0]),
            "end_frame": s.frame_index,
            "metrics": clean(metrics),
            "sketch": clean(sketch.to_json()) if sketch is not None else None,
            "sketch_png": png,
            "first_frame_ms": ((first[0] if first else t_end) - t_req) * 1e3,
            "total_ms": (t_end - t_req) * 1e3,
            "trajectory": f"/v1/sessions/{s.id}/controls/{cid}/trajectory",
            "plan": plan,
        }
        del ro
        manager.budget.give(transient)  # the kept trajectory is smaller than what was reserved for the run
        transient = 0
        kept = Control(cid, body.method, pos, solver_names, resp)
        kept.cost = manager.budget.take(pos.nbytes + len(png or "") + 4096, "keeping the control")
        if s.closed:
            manager.budget.give(kept.cost)
        else:
            await manager.keep_control(s, kept)
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
async def control_png(s: SessionDep, request: Request, manager: ManagerDep, cfg: ConfigDep, method: str = "constant", frames: int = T_CTR) -> dict[str, Any]:
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
