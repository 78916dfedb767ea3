"""A control as the service runs it, once admitted by the route
(:mod:`hybridmpm.service.routes.controls`): the memory it reserves and gives
back, the watch for a client that leaves, the saves before and after, the
events its viewers see (running → done, cancelled or failed), the answer's
metrics and the kept control.
"""

from __future__ import annotations

import asyncio
import base64
import io
import logging
import math
import secrets
import threading
import time
from typing import Any

import numpy as np
from fastapi import Request

from hybridmpm.control import Sketch, render_sketch
from hybridmpm.control.controller import shipped_control_model
from hybridmpm.errors import InvalidInputError
from hybridmpm.service.backend import Session, SessionBackend
from hybridmpm.service.budget import BudgetFullError
from hybridmpm.service.core import Control, SessionGoneError
from hybridmpm.service.errors import ApiError
from hybridmpm.service.logs import SHOWN_ID_CHARS
from hybridmpm.service.schemas import clean

log = logging.getLogger("hybridmpm.service")
#: Copies of a control's trajectory alive at its peak (its frames, the stacked array, the kept one, the plan's
#: arrays): measured with tracemalloc at 2.4 (constant) and 4.1 (diffusion) for a 1000-frame water3d hybrid
#: control, once the effort and smoothness metrics stopped keeping every applied field.
CONTROL_COPIES = 5
#: How often a running control looks whether its client has left [s].
DISCONNECT_POLL_S = 0.25


def check_method(scene: str, method: str) -> None:
    """Refuse a method the session's scene cannot run, without loading any
    model: the diffusion method needs the scene's shipped controller.
    Raises :class:`InvalidInputError` naming ``method``."""
    if method == "diffusion":
        try:
            shipped_control_model(scene)
        except InvalidInputError as e:
            raise InvalidInputError(f"method: {e}".replace("scene: ", "", 1), "method") from None


def png_base64(img: np.ndarray) -> str:
    from PIL import Image

    buf = io.BytesIO()
    Image.fromarray(img).save(buf, format="PNG")
    return base64.b64encode(buf.getvalue()).decode()


async def run_control(
    manager: SessionBackend[Any], s: Session, sketch: Sketch | None, method: str, frames: int, request: Request, t_req: float
) -> dict[str, Any]:
    """Run an admitted control of ``frames`` frames with ``method`` on ``s``
    (the backend's :meth:`~hybridmpm.service.backend.SessionBackend.run_control`,
    whose core saves the session before the control is announced and before it answers)
    and answer it (:class:`~hybridmpm.service.schemas.ControlResponse`'s
    fields; ``t_req`` when the request came, ``time.perf_counter()``).
    Reserves :data:`CONTROL_COPIES` copies of its trajectory for the run
    (:class:`BudgetFullError` when the budget cannot) and the kept
    trajectory after, giving back each exactly once whatever ends it. A
    client that leaves stops it within a frame (408; the session keeps the
    frames computed); a session deleted meanwhile answers 404
    (:class:`SessionGoneError`)."""
    frame_bytes = s.facts.frame_bytes
    steps = math.ceil(frames / s.facts.r_t)
    transient = manager.budget.take(CONTROL_COPIES * (steps + 1) * frame_bytes, f"a control of {frames} frames")
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
        # the backend tells the viewers "running" once the control has really started (a refused one, never)
        try:
            ro, metrics, plan = await manager.run_control(s, sketch, method, frames, left, first, cid)
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
            "method": method,
            "frames": int(frames),
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
        kept = Control(cid, method, pos, solver_names, resp)
        kept.cost = manager.budget.take(pos.nbytes + len(png or "") + 4096, "keeping the control")
        if s.closed:
            manager.budget.give(kept.cost)
        else:
            await manager.keep_control(s, kept)
        s.broadcast({"type": "control", "status": "done", "id": cid, "metrics": resp["metrics"]})
        s.touch()
        return resp
    finally:
        left.set()
        watcher.cancel()
        manager.budget.give(transient)
        s.controlling = False
        manager.controls_running -= 1


__all__ = ["CONTROL_COPIES", "DISCONNECT_POLL_S", "check_method", "png_base64", "run_control"]
