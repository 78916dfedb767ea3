"""Controllers: a sketch and the current fluid state → external accelerations
over the next ``T_ctr`` frames (paper Sec. 3.2), applied by MPM through a
simulator's ``forcing``.

Methods (one code path, :meth:`Controller.plan`):

* ``"none"`` — no control (the ceiling of every error);
* ``"constant"`` — the paper's baseline: one acceleration for all particles
  and frames, solved from centroid kinematics so that a free cloud's centre
  of mass lands on the target after ``τ = T_ctr·Δt``:
  ``a = 2·(p̄_target − p̄_0 − v̄_0·τ)/τ² − g``;

An arrow is a displacement (the fluid's centroid should move by it, wherever
it is drawn: training arrows start at the centroid, paper App. C); an oval is
a place (its centre and shape);
* ``"pd"`` — classic non-learned control: each particle is attracted to its
  own target point (``y_i = p_i(0) +`` the arrow; for an oval, the cloud's
  ±2σ ellipse mapped affinely onto the drawn one), ``a_i = k_p (y_i − p_i)
  − k_d v_i − g``, critically damped (ω = 2π/τ);
* ``"oracle"`` — a given field replayed (the floor, when the true field is known);
* ``"diffusion"`` — the Fluid ControlNet (not shipped yet: refused with a clear error).

Every acceleration is clipped at :data:`~hybridmpm.control.reverse.A_MAX`.

>>> plan = Controller("constant").plan(sim, Sketch.arrow([0.3, 0.2], [0.7, 0.4]))
>>> sim.forcing = plan                                   # the next T_ctr frames are controlled
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from hybridmpm.control.reverse import A_MAX, clip_norm
from hybridmpm.control.sketch import Sketch
from hybridmpm.conventions import T_CTR
from hybridmpm.errors import InvalidInputError

#: Control methods.
METHODS = ("none", "constant", "pd", "oracle", "diffusion")


@dataclass
class Plan:
    """External accelerations for the ``frames`` frames after ``start_frame``:
    a simulator ``forcing`` (call it with a frame index → float32 [N, D] m/s²,
    None outside the horizon). Open loop (``accelerations`` [frames, N, D]) or
    closed loop (``feedback(k)`` computed from the state at control frame
    ``k``). ``applied`` keeps every field handed out (effort and smoothness
    metrics); ``seconds`` the time the plan took to make (sketch → field)."""

    method: str
    start_frame: int
    frames: int
    num_particles: int
    accelerations: np.ndarray | None = None
    feedback: Callable[[int], np.ndarray] | None = None
    seconds: float = 0.0
    sketch: Sketch | None = None
    applied: list[np.ndarray] = field(default_factory=list)

    def __call__(self, frame: int) -> np.ndarray | None:
        k = int(frame) - self.start_frame
        if not 0 <= k < self.frames or self.method == "none":
            return None
        a = self.accelerations[k] if self.accelerations is not None else self.feedback(k)  # type: ignore[misc]
        a = clip_norm(a, A_MAX)
        self.applied.append(a)
        return a


class Controller:
    """Makes :class:`Plan` s for a method (module doc).

    ``frames`` the horizon ``T_ctr`` (default 100 frames of 2.5 ms);
    ``settle`` the PD time scale as a fraction of the horizon (1: critically damped with ω = 2π/τ, within 1.3 % of the targets at the end);
    ``oracle`` the field [frames, N, D] of the ``"oracle"`` method. Raises
    :class:`InvalidInputError` (``method``) for an unknown method or one with
    no model."""

    def __init__(self, method: str = "constant", *, frames: int = T_CTR, settle: float = 1.0, oracle: np.ndarray | None = None) -> None:
        if method not in METHODS:
            raise InvalidInputError(f"method: must be one of {', '.join(METHODS)}, got {method!r}", "method")
        if method == "diffusion":
            raise InvalidInputError("method: no trained diffusion controller ships yet; use constant or pd", "method")
        if isinstance(frames, bool) or not isinstance(frames, int) or not 1 <= frames <= 10 * T_CTR:
            raise InvalidInputError(f"frames: must be an integer in [1, {10 * T_CTR}], got {frames!r}", "frames")
        if not (isinstance(settle, (int, float)) and 0.05 <= settle <= 1.0):
            raise InvalidInputError(f"settle: must be in [0.05, 1], got {settle!r}", "settle")
        if method == "oracle" and oracle is None:
            raise InvalidInputError("oracle: the oracle method replays a given field", "oracle")
        self.method = method
        self.frames = frames
        self.settle = float(settle)
        self.oracle = None if oracle is None else np.asarray(oracle, np.float32)

    @classmethod
    def for_scene(cls, scene: str, method: str = "constant", **kw: Any) -> Controller:
        """The controller of a registered scene (the diffusion model, once
        trained, is per scene; the baselines are the same for all)."""
        return cls(method, **kw)

    def plan(self, sim: Any, sketch: Sketch | None) -> Plan:
        """A plan from ``sim``'s current state (positions, velocities, masses,
        gravity; any :class:`~hybridmpm.sim.Simulator`) and ``sketch`` (None:
        no control). Raises :class:`InvalidInputError` naming ``sketch`` when
        the method needs one and none is given."""
        t0 = time.perf_counter()
        p = sim.particles
        n, d = p.num_fluid, p.dim
        start = int(sim.frame.frame)
        if self.method == "none":
            return Plan("none", start, self.frames, n, seconds=time.perf_counter() - t0, sketch=sketch)
        if self.method == "oracle":
            assert self.oracle is not None
            if self.oracle.shape[1:] != (n, d) or len(self.oracle) < self.frames:
                raise InvalidInputError(f"oracle: expected [>= {self.frames}, {n}, {d}], got {list(self.oracle.shape)}", "oracle")
            return Plan("oracle", start, self.frames, n, accelerations=self.oracle[: self.frames], seconds=time.perf_counter() - t0, sketch=sketch)
        if sketch is None:
            raise InvalidInputError(f"sketch: the {self.method} method needs a sketch", "sketch")
        x = p.fluid(sim.positions).astype(np.float64)
        v = np.asarray(sim.velocities, np.float64)
        m = p.masses.astype(np.float64)
        g = np.asarray(sim.scene.params.to_dict()["gravity"], np.float64)
        tau = self.frames * sim.dt_frame
        if self.method == "constant":
            com = (m[:, None] * x).sum(0) / m.sum()
            vel = (m[:, None] * v).sum(0) / m.sum()
            target = com + vel * tau  # depth (3D z) drifts freely: the sketch is drawn in x–y
            target[:2] = com[:2] + sketch.vector if sketch.kind == "arrow" else sketch.ellipse()[0]
            a = 2.0 * (target - com - vel * tau) / (tau * tau) - g
            field_ = np.broadcast_to(a.astype(np.float32), (self.frames, n, d))
            return Plan("constant", start, self.frames, n, accelerations=field_, seconds=time.perf_counter() - t0, sketch=sketch)
        # PD attraction to per-particle targets
        y = pd_targets(x, sketch)
        omega = 2.0 * math.pi / (self.settle * tau)
        kp, kd = omega * omega, 2.0 * omega

        src = getattr(sim, "mpm", sim)  # the hybrid applies control on its MPM, which has the state frame by frame

        def feedback(k: int) -> np.ndarray:
            xk = p.fluid(src.positions).astype(np.float64)
            vk = np.asarray(src.velocities, np.float64)
            return (kp * (y - xk) - kd * vk - g).astype(np.float32)

        return Plan("pd", start, self.frames, n, feedback=feedback, seconds=time.perf_counter() - t0, sketch=sketch)


def pd_targets(x: np.ndarray, sketch: Sketch) -> np.ndarray:
    """Per-particle targets of the PD controller, float64 [N, D]: arrow — each
    particle moved by the arrow (x–y); oval — the cloud's ±2σ ellipse (x–y
    principal axes) mapped affinely onto the drawn ellipse. Depth (3D z) is kept."""
    y = np.array(x, np.float64)
    if sketch.kind == "arrow":
        y[:, :2] += sketch.vector
        return y
    xy = x[:, :2]
    c0 = xy.mean(0)
    vals, vecs = np.linalg.eigh(np.cov((xy - c0).T) if len(xy) > 1 else np.eye(2) * 1e-8)
    order = np.argsort(vals)[::-1]
    r0 = 2.0 * np.sqrt(np.maximum(vals[order], 1e-10))
    r0_axes = vecs[:, order]
    c1, r1, angle = sketch.ellipse()
    r1_axes = np.array([[math.cos(angle), -math.sin(angle)], [math.sin(angle), math.cos(angle)]])
    local = (xy - c0) @ r0_axes / r0  # unit-ellipse coordinates along the cloud's axes
    y[:, :2] = c1 + (local * r1) @ r1_axes.T
    return y


__all__ = ["METHODS", "Controller", "Plan", "pd_targets"]
