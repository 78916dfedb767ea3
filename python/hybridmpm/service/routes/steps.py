"""Stepping a session: ``POST /v1/sessions/{sid}/step`` answers the frames as
JSON (encoded a piece at a time) or raw float32.

The raw answer is the positions float32 [K, N, D] (``X-Shape``), the bytes
every client reads whole. A session's rigid bodies (docs/bodies.md) are
appended only when the client asks (``?bodies=1``): then, after the
positions, float32 [K, B, D + D²] (``X-Bodies: K,B,D+D²``), each body's
centre [m] and its rotation row-major at each frame's end, as the stream's
binary frame carries them (:func:`hybridmpm.service.frames.body_poses`). A
client that reads the whole answer as ``X-Shape`` (the docs' example) is
never handed bytes it does not expect; without bodies ``?bodies=1`` changes
nothing."""

from __future__ import annotations

import json
import math
import time
from collections.abc import AsyncIterator
from typing import Any

import numpy as np
from fastapi import APIRouter, Query, Request
from fastapi.responses import Response, StreamingResponse

from hybridmpm.service.deps import ConfigDep, ManagerDep, SessionDep
from hybridmpm.service.errors import FieldError
from hybridmpm.service.frames import body_poses
from hybridmpm.service.schemas import StepRequest, StepResponse, clean

OCTET = "application/octet-stream"
#: Transient bytes per position value of a step's answer: JSON text, its pieces and the joined body; raw float32 and its copies.
JSON_BYTES_PER_VALUE = 64
BINARY_BYTES_PER_VALUE = 16
#: Values of a step's positions JSON-encoded at a time, the GIL handed over in between.
JSON_VALUES_PER_PIECE = 1024

router = APIRouter()


def json_floats(a: np.ndarray) -> str:
    """``a`` float [n, d] as a JSON array of arrays (what ``json.dumps(a.tolist())``
    writes), formatted a few thousand values at a time with no list per row
    (nothing for the garbage collector), handing the GIL over between pieces:
    a worker thread running this stalls the event loop by one piece at most."""
    if not np.isfinite(a).all():
        return json.dumps(clean(a.tolist()))
    n, d = a.shape
    row = "[" + ", ".join(["%r"] * d) + "]"
    step = max(1, JSON_VALUES_PER_PIECE // d)
    pieces = []
    for i in range(0, n, step):
        block = a[i : i + step]
        pieces.append(", ".join([row] * len(block)) % tuple(block.reshape(-1).tolist()))
        time.sleep(0)
    return "[" + ", ".join(pieces) + "]"


def step_json(
    pos: np.ndarray,
    frames: list[int],
    solvers: list[str],
    seconds: list[float],
    r_t: int,
    dt: float,
    failure: str | None,
    latency: float,
    bodies: tuple[np.ndarray, np.ndarray] | None = None,
) -> list[bytes]:
    """The JSON answer of a step as its pieces (one per frame), encoded in a
    worker thread (:func:`json_floats`), which lets the event loop run in
    between; sent one piece at a time, never joined into one buffer. With
    ``bodies`` (centres [K, B, D] and rotations [K, B, D, D]) each frame
    carries ``bodies: [{center, rotation}]``; without, no such key."""
    parts = [b'{"frames": [']
    for k in range(len(pos)):
        fr = frames[k]
        head = {"step": fr // r_t, "frame": fr, "time": fr * dt, "solver": solvers[k], "seconds": seconds[k], "controlled": False}
        if bodies is not None:
            head["bodies"] = [{"center": c.tolist(), "rotation": r.tolist()} for c, r in zip(bodies[0][k], bodies[1][k], strict=True)]
        item = json.dumps(clean(head), allow_nan=False)[:-1] + ', "positions": ' + json_floats(pos[k]) + "}"
        parts.append(((", " if k else "") + item).encode())
    parts.append(("], " + json.dumps({"failure": failure, "latency_ms": latency})[1:]).encode())
    return parts


@router.post(
    "/v1/sessions/{sid}/step",
    response_model=StepResponse,
    responses={
        200: {
            "content": {OCTET: {"schema": {"type": "string", "format": "binary"}}},
            "description": "JSON, or float32 [K, N, D] with Accept: application/octet-stream (X-Shape, X-Solvers, X-Seconds headers);"
            " with ?bodies=1 and bodies in the session, float32 [K, B, D + D²] body poses after the positions (X-Bodies)",
        },
        404: {"description": "no such session"},
    },
)
async def step(
    s: SessionDep,
    body: StepRequest,
    request: Request,
    manager: ManagerDep,
    cfg: ConfigDep,
    bodies_after: bool = Query(False, alias="bodies", description="binary answer: append the bodies' poses after the positions (X-Bodies)"),
) -> Any:
    if body.frames > cfg.max_frames:
        raise FieldError(("body", "frames"), f"frames: at most {cfg.max_frames} per request")
    binary = OCTET in request.headers.get("accept", "")
    values = math.ceil(body.frames / s.facts.r_t) * s.facts.num_total * s.facts.dim
    with manager.budget.hold(values * (BINARY_BYTES_PER_VALUE if binary else JSON_BYTES_PER_VALUE), f"a step of {body.frames} frames"):
        t0 = time.perf_counter()
        ro = await manager.rollout(s, body.frames)
        latency = (time.perf_counter() - t0) * 1e3
        s.touch()
        pos = np.asarray(ro.positions[1:], np.float32)
        solvers = [str(x) for x in list(ro.solver)[1:]]
        seconds = [float(x) for x in np.asarray(ro.seconds)[1:]]
        frames_ = [int(x) for x in np.asarray(ro.frame_index)[1:]]
        failure = None if ro.failure is None else str(ro.failure)
        bodies = None
        if ro.bodies is not None:  # the rollout's bodies (its frames share them), the first entry (the start) left out
            bodies = (ro.bodies.center[1:], ro.bodies.rotation[1:])
        del ro
        if binary:
            headers = {
                "X-Shape": ",".join(str(x) for x in pos.shape),
                "X-Solvers": ",".join(solvers),
                "X-Seconds": ",".join(f"{x:.6g}" for x in seconds),
                "X-Frames": ",".join(str(x) for x in frames_),
                "X-Latency-Ms": f"{latency:.3f}",
            }
            if failure:
                headers["X-Failure"] = failure
            poses = None
            if bodies_after and bodies is not None:
                k, b, d = bodies[0].shape
                flat = body_poses(bodies[0].reshape(k * b, d), bodies[1].reshape(k * b, d, d), d)
                if flat is not None:  # None: no frame stepped
                    poses = flat.reshape(k, b, d + d * d)
                    headers["X-Bodies"] = ",".join(str(x) for x in poses.shape)

            def raw() -> bytes:
                data = np.ascontiguousarray(pos, "<f4").tobytes()
                return data if poses is None else data + poses.tobytes()

            return Response(await manager.compute(raw), media_type=OCTET, headers=headers)
        parts = await manager.compute(step_json, pos, frames_, solvers, seconds, s.facts.r_t, s.facts.dt_frame, failure, latency, bodies)

        async def pieces() -> AsyncIterator[bytes]:
            while parts:
                yield parts.pop(0)

        size = str(sum(len(x) for x in parts))
        return StreamingResponse(pieces(), media_type="application/json", headers={"Content-Length": size})
