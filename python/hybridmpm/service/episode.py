"""A control episode as the service runs it, written once for both
backends: the local one runs it on a worker thread
(:meth:`hybridmpm.service.sessions.SessionManager.run_control`), the Ray one
inside the session's actor (:meth:`hybridmpm.service.actor.SessionActor.run_control`).

Around :func:`~hybridmpm.control.control_episode` it adds what the streams
show: every controlled frame, the plan's centroid path once the plan is
known (its first frame), and a stop within a frame when the client leaves.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from typing import Any

import numpy as np

from hybridmpm.control import Controller, Sketch, control_episode
from hybridmpm.control.controller import Plan
from hybridmpm.control.targets import pd_targets
from hybridmpm.service.schemas import clean
from hybridmpm.sim import Frame, Rollout, Simulator

log = logging.getLogger("hybridmpm.service")
#: Most points of a plan's centroid path in an answer or a stream event.
PLAN_POINTS = 101


def plan_start(sim: Any) -> dict[str, np.ndarray]:
    """The fluid's ``x``, ``v``, ``m`` and gravity ``g`` of ``sim`` when a plan is made (:func:`plan_info`'s ``start``)."""
    p = sim.particles
    return {
        "x": np.asarray(p.fluid(sim.positions), np.float64),
        "v": np.asarray(sim.velocities, np.float64),
        "m": np.asarray(p.masses, np.float64),
        "g": sim.scene.params.resolved_gravity(),
    }


def plan_info(plan: Any, start: dict[str, np.ndarray], sketch: Sketch | None, dt_frame: float, settle: float) -> dict[str, Any] | None:
    """Where ``plan`` (a :class:`~hybridmpm.control.controller.Plan`) takes the
    fluid's centroid (mass-weighted) over its horizon: a planned method's path
    averaged over the particles; the constant force's centroid kinematics (it
    lands on the target); PD's critically damped approach to its targets'
    centroid (gravity fed forward). ``start``: the fluid's ``x``, ``v``, ``m``
    when the plan was made. None for no control."""
    if not isinstance(plan, Plan) or sketch is None or plan.method == "none":
        return None
    x, v, m = start["x"], start["v"], start["m"]
    w = m / m.sum()
    c0, v0 = w @ x, w @ v
    frames = int(plan.frames)
    stride = max(1, -(-frames // (PLAN_POINTS - 1)))
    k = np.arange(0, frames + 1, stride)
    if k[-1] != frames:
        k = np.append(k, frames)
    t = (k * dt_frame)[:, None]
    if plan.path is not None:  # a planned method: its particles' paths
        path = np.asarray(plan.path, np.float64)
        path = np.einsum("fnd,n->fd", path, w)[np.minimum(k, len(path) - 1)]
    elif plan.accelerations is not None:  # the constant force: a free cloud's centroid under gravity + a
        a = np.asarray(plan.accelerations[0], np.float64)
        path = c0 + v0 * t + 0.5 * (w @ a + start["g"]) * t * t
    elif plan.method == "pd":
        cy = w @ pd_targets(x, sketch)
        omega = 2.0 * np.pi / (settle * frames * dt_frame)
        e0 = c0 - cy
        path = cy + (e0 + (v0 + omega * e0) * t) * np.exp(-omega * t)
    else:
        return None
    target = c0[:2] + sketch.vector if sketch.kind == "arrow" else sketch.ellipse()[0]
    return {
        "method": plan.method,
        "frames": frames,
        "stride": stride,
        "centroid_path": clean(np.round(path, 5).tolist()),
        "target": clean(np.round(target, 5).tolist()),
    }


def run_episode(
    sim: Simulator,
    sketch: Sketch | None,
    controller: Controller,
    cid: str,
    publish: Callable[[Frame, int], None],
    event: Callable[[dict[str, Any]], None],
    cancelled: Callable[[], bool],
) -> tuple[Rollout, dict[str, Any], dict[str, Any] | None, float | None]:
    """Plan and run control ``cid`` on ``sim`` (the caller holds the
    session's lock; this runs on a worker thread). ``publish(frame,
    control_frame)`` gets every controlled frame and ``event(msg)`` the
    ``plan`` event (its :func:`plan_info`) at the first one, both from this
    thread; ``cancelled()`` true stops the episode within a frame. Returns
    ``(rollout, metrics, plan summary or None, time.perf_counter() of the
    first controlled frame or None)``."""
    start = plan_start(sim)
    k0 = int(sim.frame.frame_index)
    first: list[float] = []
    planned: list[dict[str, Any] | None] = []

    def on_frame(fr: Frame) -> None:
        if not first:
            first.append(time.perf_counter())
        if not planned:  # the first controlled frame: the plan is the simulator's forcing
            try:
                planned.append(plan_info(sim.forcing, start, sketch, float(sim.dt_frame), controller.settle))
            except Exception:  # noqa: BLE001 - a summary for display must not stop the control
                log.exception("control %s: the plan's centroid path", cid)
                planned.append(None)
            if planned[0] is not None:
                event({"type": "plan", "id": cid, **planned[0]})
        publish(fr, int(fr.frame_index) - k0)

    def client_left(fr: Frame, sim_: Any) -> str | None:
        return "cancelled: the client left" if cancelled() else None

    ep = control_episode(sim, sketch, controller, on_frame=on_frame, stop=client_left)
    return ep.rollout, ep.metrics, (planned[0] if planned else None), (first[0] if first else None)


__all__ = ["PLAN_POINTS", "plan_info", "plan_start", "run_episode"]
