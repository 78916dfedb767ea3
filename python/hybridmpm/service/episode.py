"""A control episode as the service runs it, written once for both
backends: a session's core runs it
(:meth:`hybridmpm.service.core.SessionCore.control`), on a worker thread of
this process (the local backend) or in the session's Ray actor.

Around :func:`~hybridmpm.control.control_episode` it adds what the streams
show: the plan's centroid path once the plan is made (the plan's own
summary), every controlled frame, and a stop within a frame when the client
leaves.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from typing import Any

from hybridmpm.control import Controller, PlanStopped, Sketch, control_episode
from hybridmpm.control.controller import Plan
from hybridmpm.service.schemas import clean
from hybridmpm.sim import Frame, Rollout, Simulator, rollout

log = logging.getLogger("hybridmpm.service")


def run_episode(
    sim: Simulator,
    sketch: Sketch | None,
    controller: Controller,
    cid: str,
    publish: Callable[[Frame, int], None],
    event: Callable[[dict[str, Any]], None],
    cancelled: Callable[[], bool],
    share: Callable[[], None] | None = None,
) -> tuple[Rollout, dict[str, Any], dict[str, Any] | None, float | None]:
    """Plan and run control ``cid`` on ``sim`` (the caller holds the
    session's lock; this runs on a worker thread). ``event(msg)`` gets the
    ``plan`` event (the plan's :meth:`~hybridmpm.control.controller.Plan.summary`:
    its centroid path and target) once the plan is made, and
    ``publish(frame, control_frame)`` every controlled frame, both from this
    thread; ``cancelled()`` true stops the episode within a frame, or within
    :data:`~hybridmpm.control.mpc.BETWEEN_FRAMES` frames of a model rollout
    while it plans (a stopped plan answers a rollout of no frame, its metrics'
    ``failure`` saying so). ``share()`` (a backend's hand-over of its compute
    to work that waits for it) is called between the same units of work.
    Returns ``(rollout, metrics, plan summary or None, time.perf_counter() of
    the first controlled frame or None)``."""
    k0 = int(sim.frame.frame_index)
    first: list[float] = []
    planned: list[dict[str, Any] | None] = []

    def on_plan(plan: Plan) -> None:
        try:
            summary = plan.summary()
            planned.append(clean(summary) if summary is not None else None)
        except Exception:  # noqa: BLE001 - a summary for display must not stop the control
            log.exception("control %s: the plan's centroid path", cid)
            planned.append(None)
        if planned[0] is not None:
            event({"type": "plan", "id": cid, **planned[0]})

    def on_frame(fr: Frame) -> None:
        if not first:
            first.append(time.perf_counter())
        publish(fr, int(fr.frame_index) - k0)

    def client_left(fr: Frame, sim_: Any) -> str | None:
        return "cancelled: the client left" if cancelled() else None

    def between() -> bool:
        if share is not None:
            share()
        return cancelled()

    try:
        ep = control_episode(sim, sketch, controller, on_frame=on_frame, on_plan=on_plan, stop=client_left, between=between)
    except PlanStopped:
        log.info("control %s: stopped while it planned", cid)
        return rollout(sim, 0), {"frames": 0, "failure": "cancelled while planning"}, None, None
    return ep.rollout, ep.metrics, (planned[0] if planned else None), (first[0] if first else None)


__all__ = ["run_episode"]
