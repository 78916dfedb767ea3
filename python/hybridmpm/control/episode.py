"""One controlled episode: plan from the current state, apply it through the
simulator's forcing for ``T_ctr`` frames (MPM runs them), measure."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from hybridmpm.control.controller import Controller, Plan
from hybridmpm.control.metrics import control_metrics
from hybridmpm.control.sketch import Sketch
from hybridmpm.sim import Frame, Rollout, Simulator, rollout
from hybridmpm.sim.rollout import StopRule


@dataclass
class Episode:
    """A controlled rollout (``rollout``: ``T_ctr`` frames from the state the
    sketch was drawn on), its ``plan`` and ``metrics``."""

    rollout: Rollout
    plan: Plan
    metrics: dict[str, Any]


def control_episode(
    sim: Simulator,
    sketch: Sketch | None,
    controller: Controller,
    *,
    target: np.ndarray | None = None,
    progress: str | None = None,
    on_frame: Callable[[Frame], None] | None = None,
    on_plan: Callable[[Plan], None] | None = None,
    stop: StopRule | None = None,
    between: Callable[[], bool] | None = None,
) -> Episode:
    """Plan with ``controller`` on ``sim``'s current state and ``sketch``, run
    the ``controller.frames`` frames with the plan as ``sim.forcing`` (cleared
    afterwards, whatever happens), and measure (:func:`~hybridmpm.control.metrics.control_metrics`;
    ``target`` fluid positions [M, D] for the final-shape error). ``on_frame``
    and ``stop`` are :func:`~hybridmpm.sim.rollout`'s (called with every
    controlled frame; a reason ends the episode early); ``on_plan`` gets the
    plan once it is made, before the first frame (it knows its own centroid
    path, :meth:`~hybridmpm.control.controller.Plan.centroid_path`). The
    simulator continues from the controlled state. ``between()`` is called
    between units of work, inside a long plan (``"mpc"``'s model rollouts)
    and after every controlled frame: it may block while other work uses the
    compute (a server's other sessions), and True stops the episode: a plan
    in progress raises :class:`~hybridmpm.control.mpc.PlanStopped` (``sim``
    untouched), a run ends at that frame (failure ``"stopped"``)."""
    plan = controller.plan(sim, sketch, between)
    if on_plan is not None:
        on_plan(plan)

    def run_stop(fr: Frame, s: Simulator) -> str | None:
        if between is not None and between():
            return "stopped"
        return stop(fr, s) if stop is not None else None

    sim.forcing = plan
    try:
        ro = rollout(sim, controller.frames, progress=progress, on_frame=on_frame, stop=run_stop if between is not None else stop)
    finally:
        sim.forcing = None
    fluid = ro.fluid_positions
    metrics = control_metrics(fluid[0], fluid[-1], sketch, plan.applied, target, sim.scene.params.resolved_n_grid())
    metrics.update({"plan_ms": plan.seconds * 1e3, "episode_ms": float(ro.seconds.sum()) * 1e3, "frames": ro.frames_done, "failure": ro.failure})
    metrics["network"] = plan.network  # whether a network made the plan (not in free flight, Controller.plan)
    return Episode(ro, plan, metrics)


__all__ = ["Episode", "control_episode"]
