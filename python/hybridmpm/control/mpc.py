"""Sampling-based model-predictive control of a sketch (``"mpc"``), and the
offline optimiser (the teacher) that uses the same force field against the
full simulation.

**The force field** (:data:`FIELD_SIZE` = 16 numbers): per quarter of the
horizon ``τ = T_ctr·Δt``, a uniform push (x, y; in g), a pull of every
particle toward its own sketch target ``y_i``
(:func:`~hybridmpm.control.targets.pd_targets`: the arrow added, or the
cloud's ±2σ ellipse mapped onto the oval) and a velocity damping::

    a_i(k) = G·push_q + ω_q² (y_i − x_i) − δ_q v_i,   q = ⌊4k / T_ctr⌋,
    ω_q = pull_q · 2π/τ,   δ_q = damp_q · 4π/τ,

clipped at :data:`~hybridmpm.control.reverse.A_MAX`. PD attraction with
gravity fed forward (``Controller("pd")``) is the point push = −g/G,
pull = damp = 1 in every quarter (:func:`pd_field`), so the family holds the
classical controller and every search starts there. Classical fluid control
applies driving and gathering forces of this kind (Fattal & Lischinski,
SIGGRAPH 2004; Shi & Yu, SCA 2005).

**The optimiser**: the cross-entropy method (:func:`cem`; Rubinstein 1999;
as a sampling MPC, Williams et al. 2017 for MPPI): rounds of Gaussian samples
around a mean, the best ``elite`` share refits the mean and spread, the best
sample ever seen is kept (the start, PD, is the first one evaluated).

**The model**: MPC rolls the field out on the cheap model of
:func:`~hybridmpm.control.prior.coarse_model` (every 4th particle on a grid
twice as coarse, CFL 0.8), the whole horizon per rollout, and scores the end
(:func:`field_score`); the teacher (``benchmarks/control_teacher.py``) rolls
it out on the full simulation. The plan is the best field, applied in closed
loop to every particle (it reads the state each frame).
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from hybridmpm.control.metrics import AppliedStats, oval_adherence
from hybridmpm.control.prior import coarse_model, material_of
from hybridmpm.control.reverse import A_MAX, clip_norm
from hybridmpm.control.sketch import Sketch
from hybridmpm.control.targets import pd_targets
from hybridmpm.conventions import G
from hybridmpm.errors import InvalidInputError

#: Frames of a model rollout between two calls of a plan's ``between`` (its chance to share the compute or stop).
BETWEEN_FRAMES = 10


class PlanStopped(Exception):
    """A plan stopped while it was made: its ``between`` callback answered True
    (the control's session closed or its client left)."""


#: Quarters of the horizon, and the field's numbers per quarter (push x, push y, pull, damping).
QUARTERS = 4
PER_QUARTER = 4
FIELD_SIZE = QUARTERS * PER_QUARTER
#: Bounds of a quarter's numbers: push [g], pull and damping (1 = PD's).
FIELD_LO = np.array([-5.0, -5.0, 0.0, 0.0])
FIELD_HI = np.array([5.0, 5.0, 3.0, 3.0])
#: The search's first spread per quarter's number.
FIELD_STD = np.array([0.5, 0.5, 0.4, 0.4])
#: Effort weight of the score (per g of mean effort), as in the note's crude optimiser.
EFFORT_WEIGHT = 0.02


def pd_field(gravity: np.ndarray) -> np.ndarray:
    """The field's numbers float64 [16] of PD attraction with gravity fed
    forward (``gravity`` [D] m/s²): push = −g/G (x–y), pull = damping = 1."""
    q = np.zeros(PER_QUARTER)
    q[:2] = -np.asarray(gravity, np.float64)[:2] / G
    q[2:] = 1.0
    return np.tile(q, QUARTERS)


def field_feedback(theta: np.ndarray, targets: np.ndarray, frames: int, dt_frame: float) -> Callable[[int, np.ndarray, np.ndarray], np.ndarray]:
    """The closed-loop field of ``theta`` float [16] (module doc) toward the
    per-particle ``targets`` float [N, D] m over ``frames`` frames of
    ``dt_frame`` s: ``feedback(k, x, v)`` → float32 [N, D] m/s² (unclipped;
    a :class:`~hybridmpm.control.controller.Plan` clips it)."""
    th = np.clip(np.asarray(theta, np.float64).reshape(QUARTERS, PER_QUARTER), FIELD_LO, FIELD_HI)
    y = np.asarray(targets, np.float64)
    tau = frames * dt_frame
    push = np.zeros((QUARTERS, y.shape[1]))
    push[:, :2] = th[:, :2] * G
    kp = (th[:, 2] * 2.0 * math.pi / tau) ** 2
    kd = th[:, 3] * 4.0 * math.pi / tau

    def feedback(k: int, positions: np.ndarray, velocities: np.ndarray) -> np.ndarray:
        q = min(QUARTERS * int(k) // max(frames, 1), QUARTERS - 1)
        x = np.asarray(positions, np.float64)
        v = np.asarray(velocities, np.float64)
        return (push[q] + kp[q] * (y - x) - kd[q] * v).astype(np.float32)

    return feedback


def adherence(start: np.ndarray, end: np.ndarray, sketch: Sketch, n_grid: int) -> float:
    """What the optimisers maximise of a sketch (besides effort): an arrow —
    minus the centroid's miss of the arrow's tip relative to its length
    (0 = on the tip; x–y); an oval — the IoU of the ``n_grid``² occupied
    cells with it (:func:`~hybridmpm.control.metrics.oval_adherence`)."""
    if sketch.kind == "arrow":
        v = np.asarray(sketch.vector, np.float64)
        d = np.asarray(end, np.float64)[:, :2].mean(0) - np.asarray(start, np.float64)[:, :2].mean(0)
        return -float(np.linalg.norm(d - v) / max(float(np.linalg.norm(v)), 1e-9))
    return oval_adherence(end, sketch, n_grid)["iou"]


def field_score(adh: float, effort_mean_g: float, effort_weight: float) -> float:
    """The score of a rollout: ``adh − effort_weight·effort_mean_g``."""
    return float(adh - effort_weight * effort_mean_g)


@dataclass
class FieldRollout:
    """One field rolled out: end fluid positions float64 [N, D], the applied
    statistics, its adherence and the centroid path float64 [frames + 1, D]."""

    end: np.ndarray
    applied: AppliedStats
    adherence: float
    centroids: np.ndarray


def roll_field(
    sim: Any,
    state: dict[str, Any],
    theta: np.ndarray,
    targets: np.ndarray,
    sketch: Sketch,
    frames: int,
    n_grid: int,
    between: Callable[[], bool] | None = None,
) -> FieldRollout:
    """Restore ``sim`` (an :class:`~hybridmpm.sim.MpmSimulator`) to ``state``,
    apply the field ``theta`` toward ``targets`` for ``frames`` frames (clipped
    at ``A_MAX``), and measure (:func:`adherence` on ``n_grid``² cells). The
    simulator is left at the end. ``between()`` is called every
    :data:`BETWEEN_FRAMES` frames (it may block while other work uses the
    compute); True raises :class:`PlanStopped`."""
    sim.restore(state)
    fb = field_feedback(theta, targets, frames, sim.dt_frame)
    applied = AppliedStats()
    start_frame = int(sim.frame.frame_index)

    def forcing(frame: int, x: np.ndarray, v: np.ndarray) -> np.ndarray | None:
        k = frame - start_frame
        if not 0 <= k < frames:
            return None
        a = clip_norm(fb(k, x, v), A_MAX)
        applied.add(a)
        return a

    x0 = np.asarray(sim.fluid_positions, np.float64)
    cents = [x0.mean(0)]
    sim.forcing = forcing
    try:
        for k in range(frames):
            if between is not None and k % BETWEEN_FRAMES == 0 and between():
                raise PlanStopped()
            sim.advance()
            cents.append(np.asarray(sim.fluid_positions, np.float64).mean(0))
    finally:
        sim.forcing = None
    end = np.asarray(sim.fluid_positions, np.float64)
    return FieldRollout(end, applied, adherence(x0, end, sketch, n_grid), np.array(cents))


def cem(
    objective: Callable[[np.ndarray], float],
    mean: np.ndarray,
    *,
    rollouts: int,
    rounds: int,
    std: np.ndarray | None = None,
    elite: float = 0.25,
    rng: np.random.Generator,
    lo: np.ndarray | None = None,
    hi: np.ndarray | None = None,
    on_round: Callable[[int, np.ndarray, float], None] | None = None,
) -> tuple[np.ndarray, float]:
    """The cross-entropy method: maximise ``objective(theta)`` over float
    [P] vectors with ``rollouts`` evaluations in ``rounds`` rounds (the first
    evaluation is ``mean`` itself), samples ``N(mean, std²)`` clipped to
    ``[lo, hi]``; the best ``elite`` share (at least 2) refits mean and spread
    (spread at least 5% of the first). Returns ``(best theta, best score)``;
    ``on_round(round, best, score)`` after each round."""
    mean = np.asarray(mean, np.float64).copy()
    std0 = np.full_like(mean, 0.5) if std is None else np.asarray(std, np.float64).copy()
    std = std0.copy()
    lo_ = np.full_like(mean, -np.inf) if lo is None else lo
    hi_ = np.full_like(mean, np.inf) if hi is None else hi
    per = max(1, rollouts // rounds)
    best, best_s = mean.copy(), -math.inf
    done = 0
    for r in range(rounds):
        n = per if r < rounds - 1 else rollouts - done
        if n <= 0:
            break
        xs = np.clip(mean + std * rng.standard_normal((n, len(mean))), lo_, hi_)
        if r == 0:
            xs[0] = np.clip(mean, lo_, hi_)
        scores = np.array([objective(x) for x in xs])
        done += n
        i = int(np.argmax(scores))
        if scores[i] > best_s:
            best, best_s = xs[i].copy(), float(scores[i])
        k = max(2, int(round(elite * n))) if n >= 2 else 1
        top = xs[np.argsort(scores)[::-1][:k]]
        mean = top.mean(0)
        std = np.maximum(top.std(0) if k > 1 else std, 0.05 * std0)
        if on_round is not None:
            on_round(r, best, best_s)
    return best, best_s


@dataclass(frozen=True)
class MpcSettings:
    """Settings of the ``"mpc"`` method: ``rollouts`` of the cheap model per
    plan (the budget, 1–4096), in ``rounds`` CEM rounds (1–``rollouts``),
    ``effort_weight`` (≥ 0, per g of mean effort) and the sampler's ``seed``.
    Raises :class:`InvalidInputError` naming the field."""

    rollouts: int = 16
    rounds: int = 4
    effort_weight: float = EFFORT_WEIGHT
    seed: int = 0

    def __post_init__(self) -> None:
        for name, hi in (("rollouts", 4096), ("rounds", 4096), ("seed", 2**32 - 1)):
            v = getattr(self, name)
            lo = 0 if name == "seed" else 1
            if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or not lo <= int(v) <= hi:
                raise InvalidInputError(f"{name}: must be an integer in [{lo}, {hi}], got {v!r}", name)
        if self.rounds > self.rollouts:
            raise InvalidInputError(f"rounds: must be at most rollouts ({self.rollouts}), got {self.rounds}", "rounds")
        w = self.effort_weight
        if isinstance(w, bool) or not isinstance(w, (int, float)) or not math.isfinite(w) or not 0.0 <= w <= 100.0:
            raise InvalidInputError(f"effort_weight: must be a number in [0, 100], got {w!r}", "effort_weight")


@dataclass
class MpcResult:
    """A plan of the ``"mpc"`` method: the field ``theta`` float64 [16], the
    targets float64 [N, D] of every particle, the model's ``score`` and the
    centroid path float64 [frames + 1, D] it predicts, the ``seconds`` it took."""

    theta: np.ndarray
    targets: np.ndarray
    score: float
    centroids: np.ndarray
    seconds: float


def mpc_plan(sim: Any, sketch: Sketch, frames: int, settings: MpcSettings, between: Callable[[], bool] | None = None) -> MpcResult:
    """Plan the field for ``sketch`` from ``sim``'s fluid now (any
    :class:`~hybridmpm.sim.Simulator`) by the cross-entropy method on the cheap
    model (module doc), starting from PD's field. ``between()`` is called
    within every model rollout (:func:`roll_field`): it may block while other
    work uses the compute, and True stops the plan (:class:`PlanStopped`,
    ``sim`` untouched: the rollouts run on the model's own simulator)."""
    t0 = time.perf_counter()
    p = sim.particles
    x = np.asarray(p.fluid(sim.positions), np.float64)
    v = np.asarray(sim.velocities, np.float64)
    g = sim.scene.params.resolved_gravity()
    targets = pd_targets(x, sketch)
    model, idx, _ = coarse_model(x, v, material_of(p.particle_type[: p.num_fluid]), sim.scene.params, dt_frame=sim.dt_frame, frames=frames)
    state = model.state()
    n_grid = int(model.solver.n_grid)
    best: dict[str, Any] = {}

    def objective(theta: np.ndarray) -> float:
        ro = roll_field(model, state, theta, targets[idx], sketch, frames, n_grid, between)
        s = field_score(ro.adherence, ro.applied.effort()["effort_mean_g"], settings.effort_weight)
        if s > best.get("score", -math.inf):
            best.update(score=s, centroids=ro.centroids)
        return s

    rng = np.random.default_rng(settings.seed)
    theta, score = cem(
        objective, pd_field(g), rollouts=settings.rollouts, rounds=settings.rounds, std=np.tile(FIELD_STD, QUARTERS), rng=rng,
        lo=np.tile(FIELD_LO, QUARTERS), hi=np.tile(FIELD_HI, QUARTERS),
    )  # fmt: skip
    return MpcResult(theta, targets, score, best["centroids"], time.perf_counter() - t0)


__all__ = [
    "BETWEEN_FRAMES",
    "EFFORT_WEIGHT",
    "FIELD_SIZE",
    "FieldRollout",
    "MpcResult",
    "MpcSettings",
    "PlanStopped",
    "adherence",
    "cem",
    "field_feedback",
    "field_score",
    "mpc_plan",
    "pd_field",
    "roll_field",
]
