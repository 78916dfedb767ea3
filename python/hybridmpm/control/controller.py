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
* ``"oracle"`` — a given field replayed open loop (``oracle=``), or a given
  path tracked (``oracle_path=``): the floors, when the truth is known;
* ``"mpc"`` — model-predictive control by sampling
  (:mod:`hybridmpm.control.mpc`): the cross-entropy method over a 16-number
  force field (per quarter of the horizon a push, a pull toward PD's targets
  and a damping), each candidate rolled out on the cheap coarse-grid model,
  starting from PD's field; the best field applied in closed loop;
* ``"diffusion"`` — the Fluid ControlNet (:mod:`hybridmpm.control.diffusion`):
  a sampled plan of the fluid's motion over the horizon (every particle's
  path, from the sketch and the state), tracked by the same law as
  ``oracle_path`` (:func:`track_path`).

Every acceleration is clipped at :data:`~hybridmpm.control.reverse.A_MAX`
(or the controller's lower ``cap_g``).

>>> plan = Controller("constant").plan(sim, Sketch.arrow([0.3, 0.2], [0.7, 0.4]))
>>> sim.forcing = plan                                   # the next T_ctr frames are controlled
"""

from __future__ import annotations

import contextlib
import math
import time
from collections.abc import Callable, Iterator
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from hybridmpm.control.diffusion import SAMPLE_STEPS, ControlModel
from hybridmpm.control.metrics import AppliedStats
from hybridmpm.control.mpc import MpcSettings, field_feedback, mpc_plan
from hybridmpm.control.prior import ballistic_path, free_motion_of, in_free_flight, prior_path
from hybridmpm.control.reverse import A_MAX, clip_norm
from hybridmpm.control.sketch import Sketch
from hybridmpm.control.targets import pd_targets
from hybridmpm.conventions import T_CTR, G
from hybridmpm.errors import InvalidInputError
from hybridmpm.mpm.bodies import refuse_bodies
from hybridmpm.sim import Simulator

#: Control methods.
METHODS = ("none", "constant", "pd", "mpc", "oracle", "diffusion")
#: Settling time of the path tracker as a fraction of the horizon (``docs/control.md``: on validation seeds 4000–4011 the
#: free-sketch diffusion plans land as close with 0.5 as with 0.25 at half the effort; the true path is followed more loosely).
TRACK_SETTLE = 0.5


#: Each registered scene's default method (``hybridmpm control``, :meth:`Controller.for_scene`, :func:`scene_methods`):
#: the best classical controller at live latency (plan p95 <= 150 ms) on the adherence-effort front of
#: ``benchmarks/bench_control_user.py`` (``docs/control.md``, "Defaults"); a scene not listed gets :data:`FALLBACK_METHOD`.
DEFAULT_METHODS: dict[str, str] = {"water2d": "pd", "sand2d": "pd", "water3d": "pd", "sand3d": "pd"}
FALLBACK_METHOD = "pd"
#: Methods a user can pick for any scene (``oracle`` needs the truth; ``diffusion`` needs a shipped model).
USER_METHODS = ("none", "constant", "pd", "mpc")


def default_method(scene: str) -> str:
    """The default control method of ``scene`` (a registered scene's name, or a scene file's stem): :data:`DEFAULT_METHODS`."""
    return DEFAULT_METHODS.get(str(scene), FALLBACK_METHOD)


def scene_methods(scene: str) -> dict[str, Any]:
    """What a viewer offers for ``scene``: ``{"methods": [names], "default": name}``
    — the methods of :data:`USER_METHODS`, plus ``"diffusion"`` where a
    controller ships for the scene (:func:`shipped_control_model`), and
    :func:`default_method`. Never raises for an unknown scene (it has the
    classical methods)."""
    methods = list(USER_METHODS)
    try:
        shipped_control_model(str(scene))
        methods.append("diffusion")
    except InvalidInputError:
        pass
    default = default_method(scene)
    return {"methods": methods, "default": default if default in methods else FALLBACK_METHOD}


def shipped_control_model(scene: str) -> Path:
    """Directory of the shipped controller of ``scene``. Raises
    :class:`InvalidInputError` (field ``scene``) when none ships."""
    path = Path(__file__).resolve().parent.parent / "models" / "control" / scene
    if not (path / "control.json").exists():
        have = sorted(p.name for p in path.parent.glob("*") if (p / "control.json").exists()) if path.parent.exists() else []
        raise InvalidInputError(f"scene: no diffusion controller ships for {scene!r} (shipped: {', '.join(have) or 'none'})", "scene")
    return path


_MODELS: dict[Path, ControlModel] = {}


def _cached_model(path: Path) -> ControlModel:
    """One onnxruntime model per shipped directory per process (sessions are thread-safe to run)."""
    if path not in _MODELS:
        _MODELS[path] = ControlModel(path)
    return _MODELS[path]


_BLAS: Any = None


@contextlib.contextmanager
def single_thread_blas() -> Iterator[None]:
    """BLAS (numpy's OpenBLAS) on one thread for the duration: a plan already
    keeps both cores busy (onnxruntime on this thread, the prior's MPM on a
    second), and OpenBLAS's spinning workers stole them — a plan took 128 ms
    instead of 89 ms on a quiet 2-core machine (``docs/control.md``). Process-wide
    while it lasts (BLAS has no per-thread setting); threadpoolctl restores it."""
    global _BLAS
    from threadpoolctl import ThreadpoolController

    if _BLAS is None:
        _BLAS = ThreadpoolController()
    with _BLAS.limit(limits=1, user_api="blas"):
        yield


def track_path(path: np.ndarray, omega: float, dt_frame: float, gravity: np.ndarray | None = None) -> Callable[[int, np.ndarray, np.ndarray], np.ndarray]:
    """The tracking law shared by PD and the planned methods: at control frame
    ``k`` the acceleration [m/s²] ``ω²(y_k − x) + 2ω(ẏ_k − v) − g_ff``, with
    ``y`` = ``path`` float [F, N, D] (``y_0`` the start; held at its last
    frame after the end), ``ẏ_k`` its central difference over frames of
    ``dt_frame`` s (one-sided at the ends, 0 after the end), ``x``, ``v`` the
    fluid's positions and velocities [N, D] at that frame (what the simulator
    applying the plan hands it, :data:`~hybridmpm.sim.ForcingFunction`);
    ``gravity`` the feed-forward ``g_ff`` (None: 0 — a plan already includes
    gravity's effect, so following the uncontrolled motion costs no effort:
    the central difference matches MPM's velocity to ``g·Δt/(2·substeps)`` on
    a ballistic path). Returns ``feedback(k, x, v)`` → float32 [N, D].
    Critically damped: settles in about ``2π/ω``."""
    y = np.asarray(path, np.float64)
    dt = dt_frame
    if len(y) > 2:
        vel = np.concatenate([(y[1:2] - y[:1]) / dt, (y[2:] - y[:-2]) / (2 * dt), (y[-1:] - y[-2:-1]) / dt])
    else:
        vel = np.zeros_like(y)
    g = np.zeros(y.shape[-1]) if gravity is None else np.asarray(gravity, np.float64)
    kp, kd = omega * omega, 2.0 * omega

    def feedback(k: int, positions: np.ndarray, velocities: np.ndarray) -> np.ndarray:
        xk = np.asarray(positions).astype(np.float64)
        vk = np.asarray(velocities, np.float64)
        target = y[min(k, len(y) - 1)]
        v_plan = vel[k] if k < len(y) - 1 else 0.0
        return (kp * (target - xk) + kd * (v_plan - vk) - g).astype(np.float32)

    return feedback


#: Most points of a plan's centroid path (:meth:`Plan.centroid_path`).
PLAN_POINTS = 101


@dataclass(frozen=True)
class PlanOrigin:
    """The fluid when a plan is made: ``weights`` float64 [N] (its particles'
    masses, normalised), ``centroid`` and ``velocity`` float64 [D] (mass-weighted,
    m and m/s), ``gravity`` [D] (m/s²) and the frame step ``dt_frame`` [s]."""

    weights: np.ndarray
    centroid: np.ndarray
    velocity: np.ndarray
    gravity: np.ndarray
    dt_frame: float

    @classmethod
    def of(cls, sim: Simulator) -> PlanOrigin:
        """``sim``'s fluid now (any :class:`~hybridmpm.sim.Simulator`)."""
        p = sim.particles
        x = np.asarray(p.fluid(sim.positions), np.float64)
        v = np.asarray(sim.velocities, np.float64)
        m = np.asarray(p.masses, np.float64)
        w = m / m.sum()
        return cls(w, w @ x, w @ v, np.asarray(sim.scene.params.resolved_gravity(), np.float64), float(sim.dt_frame))


@dataclass
class Plan:
    """External accelerations for the ``frames`` frames after ``start_frame``:
    a simulator ``forcing`` (:data:`~hybridmpm.sim.ForcingFunction`: call it
    with a frame index and the fluid's positions and velocities [N, D] →
    float32 [N, D] m/s², None outside the horizon). Open loop
    (``accelerations`` [frames, N, D]) or closed loop (``feedback(k, x, v)``
    computed from the state at control frame ``k``). ``applied`` takes every field handed out
    (:class:`~hybridmpm.control.metrics.AppliedStats`: effort and smoothness, one field in memory); ``seconds`` the time the plan took to make (sketch → field);
    ``path`` float64 [F, N, D] the planned motion of a planned method;
    ``network`` whether a network made it (False for a diffusion plan of a
    fluid in free flight, :func:`~hybridmpm.control.prior.in_free_flight`)."""

    method: str
    start_frame: int
    frames: int
    num_particles: int
    accelerations: np.ndarray | None = None
    feedback: Callable[[int, np.ndarray, np.ndarray], np.ndarray] | None = None
    seconds: float = 0.0
    sketch: Sketch | None = None
    applied: AppliedStats = field(default_factory=AppliedStats)
    path: np.ndarray | None = None
    network: bool = False
    origin: PlanOrigin | None = None
    omega: float = 0.0  # PD: the approach rate [1/s]
    pd_centroid: np.ndarray | None = None  # PD: its targets' centroid [D] [m]
    cap: float = A_MAX  # the clip of every acceleration [m/s²]
    model_centroids: np.ndarray | None = None  # MPC: the centroid path [frames + 1, D] its model predicts for the plan [m]

    def centroid_path(self, points: int = PLAN_POINTS) -> tuple[int, np.ndarray] | None:
        """Where the plan takes the fluid's (mass-weighted) centroid: ``(stride,
        path float64 [K, D] [m])`` at control frames 0, stride, …, ``frames``
        (at most ``points`` of them). A planned method (diffusion, an oracle
        path): its particles' paths averaged; the constant force: a free
        cloud's centroid under gravity and the force (it lands on the
        sketch's target); PD: the critically damped approach to its targets'
        centroid, gravity fed forward. None for no control (or a plan made
        without its origin)."""
        o = self.origin
        if o is None or self.sketch is None or self.method == "none":
            return None
        stride = max(1, -(-self.frames // (points - 1)))
        k = np.arange(0, self.frames + 1, stride)
        if k[-1] != self.frames:
            k = np.append(k, self.frames)
        t = (k * o.dt_frame)[:, None]
        if self.method == "mpc" and self.model_centroids is not None:
            path = self.model_centroids[np.minimum(k, len(self.model_centroids) - 1)]
        elif self.path is not None:
            path = np.einsum("fnd,n->fd", np.asarray(self.path, np.float64), o.weights)[np.minimum(k, len(self.path) - 1)]
        elif self.method == "constant" and self.accelerations is not None:
            a = np.asarray(self.accelerations[0], np.float64)
            path = o.centroid + o.velocity * t + 0.5 * (o.weights @ a + o.gravity) * t * t
        elif self.method == "pd" and self.pd_centroid is not None:
            e0 = o.centroid - self.pd_centroid
            path = self.pd_centroid + (e0 + (o.velocity + self.omega * e0) * t) * np.exp(-self.omega * t)
        else:
            return None
        return stride, path

    def summary(self, points: int = PLAN_POINTS) -> dict[str, Any] | None:
        """What a viewer draws of the plan: ``{"method", "frames", "stride",
        "centroid_path" [K][D], "target" [2]}`` (metres, 5 decimals;
        :meth:`centroid_path` and :meth:`Sketch.target`), or None."""
        cp = self.centroid_path(points)
        if cp is None or self.origin is None or self.sketch is None:
            return None
        stride, path = cp
        return {
            "method": self.method,
            "frames": int(self.frames),
            "stride": stride,
            "centroid_path": np.round(path, 5).tolist(),
            "target": np.round(self.sketch.target(self.origin.centroid), 5).tolist(),
        }

    def __call__(self, frame: int, positions: np.ndarray, velocities: np.ndarray) -> np.ndarray | None:
        k = int(frame) - self.start_frame
        if not 0 <= k < self.frames:
            return None
        if self.accelerations is not None:
            a = self.accelerations[k]
        elif self.feedback is not None:
            a = self.feedback(k, positions, velocities)
        else:  # "none", or no sketch
            return None
        a = clip_norm(a, self.cap)
        self.applied.add(a)
        return a


class Controller:
    """Makes :class:`Plan` s for a method (module doc).

    ``frames`` the horizon ``T_ctr`` (default 100 frames of 2.5 ms);
    ``settle`` the PD time scale as a fraction of the horizon (1: critically damped with ω = 2π/τ, within 1.3 % of the targets at the end);
    ``oracle`` the field [frames, N, D] of the ``"oracle"`` method, or
    ``oracle_path`` the path [F, N, D] it tracks instead; ``model`` the
    diffusion controller (a :class:`~hybridmpm.control.diffusion.ControlModel`
    or its directory; :meth:`for_scene` finds the shipped one), sampled with
    ``steps`` DDIM steps (None: the model's own, ``ControlModel.sample_steps``),
    guidance scale ``guidance`` and noise ``seed``; ``free_flight`` (default
    True) plans a fluid in free flight without the network (the parabola bent
    onto the sketch, :func:`~hybridmpm.control.prior.in_free_flight`; False
    always samples, for comparison); ``gain`` scales the constant force (a
    sweep of magnitudes, 1: the paper's), ``cap_g`` clips every acceleration
    at that many g (None: ``A_MAX``), ``mpc`` the
    :class:`~hybridmpm.control.mpc.MpcSettings` of the ``"mpc"`` method
    (None: the defaults, its sampler seeded by ``seed``).
    Raises :class:`InvalidInputError` naming the argument (``method`` for an
    unknown method, ``model`` for a diffusion controller without one)."""

    def __init__(
        self,
        method: str = "constant",
        *,
        frames: int = T_CTR,
        settle: float = 1.0,
        oracle: np.ndarray | None = None,
        oracle_path: np.ndarray | None = None,
        model: ControlModel | str | Path | None = None,
        steps: int | None = None,
        guidance: float = 1.0,
        seed: int = 0,
        free_flight: bool = True,
        gain: float = 1.0,
        cap_g: float | None = None,
        mpc: MpcSettings | None = None,
    ) -> None:
        if method not in METHODS:
            raise InvalidInputError(f"method: must be one of {', '.join(METHODS)}, got {method!r}", "method")
        if method == "diffusion" and model is None:
            raise InvalidInputError(
                "model: the diffusion method needs a trained model (Controller.for_scene(scene, 'diffusion') finds the shipped one)", "model"
            )
        if steps is not None and (isinstance(steps, bool) or not isinstance(steps, int) or not 1 <= steps <= 100):
            raise InvalidInputError(f"steps: must be an integer in [1, 100], got {steps!r}", "steps")
        if isinstance(guidance, bool) or not isinstance(guidance, (int, float)) or not 0.0 <= guidance <= 5.0:
            raise InvalidInputError(f"guidance: must be a number in [0, 5], got {guidance!r}", "guidance")
        if isinstance(seed, bool) or not isinstance(seed, int) or not 0 <= seed < 2**63:
            raise InvalidInputError(f"seed: must be an integer >= 0, got {seed!r}", "seed")
        if isinstance(frames, bool) or not isinstance(frames, int) or not 1 <= frames <= 10 * T_CTR:
            raise InvalidInputError(f"frames: must be an integer in [1, {10 * T_CTR}], got {frames!r}", "frames")
        if not (isinstance(settle, (int, float)) and 0.05 <= settle <= 1.0):
            raise InvalidInputError(f"settle: must be in [0.05, 1], got {settle!r}", "settle")
        if method == "oracle" and oracle is None and oracle_path is None:
            raise InvalidInputError("oracle: the oracle method replays a given field (oracle=) or tracks a given path (oracle_path=)", "oracle")
        if isinstance(gain, bool) or not isinstance(gain, (int, float)) or not 0.0 < gain <= 10.0:
            raise InvalidInputError(f"gain: must be a number in (0, 10], got {gain!r}", "gain")
        if cap_g is not None and (isinstance(cap_g, bool) or not isinstance(cap_g, (int, float)) or not 0.0 < cap_g <= A_MAX / G):
            raise InvalidInputError(f"cap_g: must be a number in (0, {A_MAX / G:g}] (g), got {cap_g!r}", "cap_g")
        if mpc is not None and not isinstance(mpc, MpcSettings):
            raise InvalidInputError("mpc: must be an MpcSettings", "mpc")
        self.method = method
        self.frames = frames
        self.gain = float(gain)
        self.cap = A_MAX if cap_g is None else float(cap_g) * G
        self.mpc = mpc if mpc is not None else MpcSettings(seed=seed % 2**32)
        self.settle = float(settle)
        self.oracle = None if oracle is None else np.asarray(oracle, np.float32)
        self.oracle_path = None if oracle_path is None else np.asarray(oracle_path, np.float64)
        self.model = ControlModel(model) if isinstance(model, (str, Path)) else model
        own = self.model.sample_steps if self.model is not None else SAMPLE_STEPS
        self.steps: int = own if steps is None else steps
        self.guidance, self.seed = float(guidance), seed
        self.free_flight = bool(free_flight)

    @classmethod
    def for_scene(cls, scene: str, method: str | None = None, **kw: Any) -> Controller:
        """The controller of a registered scene: ``method`` None is the
        scene's default (:func:`default_method`); for ``"diffusion"`` the
        shipped model of ``scene`` (:func:`shipped_control_model`; raises
        :class:`InvalidInputError` naming ``scene`` when none ships); the
        classical methods are the same for all scenes."""
        method = default_method(scene) if method is None else method
        if method == "diffusion" and kw.get("model") is None:
            kw["model"] = _cached_model(shipped_control_model(scene))
        return cls(method, **kw)

    def plan(self, sim: Simulator, sketch: Sketch | None, between: Callable[[], bool] | None = None) -> Plan:
        """A plan from ``sim``'s current state (positions, velocities, masses,
        gravity; any :class:`~hybridmpm.sim.Simulator`) and ``sketch`` (None:
        no control — for the diffusion method too, whose blank sketch is
        classifier-free guidance's unconditional branch inside the sampler,
        not a request to move the fluid). Raises :class:`InvalidInputError` naming ``sketch`` when
        the method needs one and none is given. A long plan (``"mpc"``: its
        model rollouts) calls ``between()`` as it goes: it may block while other
        work uses the compute, and True stops the plan
        (:class:`~hybridmpm.control.mpc.PlanStopped`, ``sim`` untouched)."""
        plan = self._plan(sim, sketch, between)
        plan.origin = PlanOrigin.of(sim)
        plan.cap = min(plan.cap, self.cap)
        return plan

    def _plan(self, sim: Simulator, sketch: Sketch | None, between: Callable[[], bool] | None = None) -> Plan:
        t0 = time.perf_counter()
        p = sim.particles
        n, d = p.num_fluid, p.dim
        start = int(sim.frame.frame_index)
        if self.method == "none":
            return Plan("none", start, self.frames, n, seconds=time.perf_counter() - t0, sketch=sketch)
        if self.method == "oracle" and self.oracle_path is not None:
            if self.oracle_path.shape[1:] != (n, d):
                raise InvalidInputError(f"oracle_path: expected [F, {n}, {d}], got {list(self.oracle_path.shape)}", "oracle_path")
            fb = track_path(self.oracle_path, self._track_omega(sim), sim.dt_frame)
            return Plan("oracle", start, self.frames, n, feedback=fb, seconds=time.perf_counter() - t0, sketch=sketch)
        if self.method == "oracle":
            assert self.oracle is not None
            if self.oracle.shape[1:] != (n, d) or len(self.oracle) < self.frames:
                raise InvalidInputError(f"oracle: expected [>= {self.frames}, {n}, {d}], got {list(self.oracle.shape)}", "oracle")
            return Plan("oracle", start, self.frames, n, accelerations=self.oracle[: self.frames], seconds=time.perf_counter() - t0, sketch=sketch)
        if self.method == "diffusion" and sketch is None:  # nothing drawn: nothing to steer to, the fluid flows freely
            return Plan("diffusion", start, self.frames, n, seconds=time.perf_counter() - t0, sketch=None)
        if self.method == "diffusion":
            assert self.model is not None
            refuse_bodies(len(sim.bodies) if hasattr(sim, "bodies") else len(sim.scene.params.bodies), "diffusion controller")
            if self.model.dim != d:
                raise InvalidInputError(f"model: a {self.model.dim}D controller cannot drive a {d}D scene", "model")
            x, v = p.fluid(sim.positions), sim.velocities
            network = True
            if self.model.needs_free:
                # the free-motion rollout (MPM, GIL released) runs on a second thread while the network denoises
                with single_thread_blas(), ThreadPoolExecutor(1) as pool:
                    free = pool.submit(free_motion_of, sim, self.model.frames - 1)
                    res = self.model.sample(x, v, p.particle_type[:n], sketch, seed=self.seed, steps=self.steps, guidance=self.guidance, free=free)
                    fm = free.result()
                # Free flight (no wall, pressure or friction acts over the horizon): the reverse path is the parabola,
                # exactly, and the network's correction could only add error; plan the parabola bent onto the sketch.
                # The network's plan, made meanwhile, is dropped: waiting for the rollout before sampling would add the
                # rollout's time to every plan to save it on the few in free flight.
                g = sim.scene.params.resolved_gravity() if self.free_flight else None
                if g is not None and in_free_flight(fm, x, v, g, sim.dt_frame):
                    res.path = prior_path(ballistic_path(x, v, g, self.model.frames - 1, sim.dt_frame), np.asarray(x, np.float64), sketch)
                    network = False
            else:
                res = self.model.sample(x, v, p.particle_type[:n], sketch, seed=self.seed, steps=self.steps, guidance=self.guidance)
            fb = track_path(res.path, self._track_omega(sim), sim.dt_frame)
            plan = Plan("diffusion", start, self.frames, n, feedback=fb, seconds=time.perf_counter() - t0, sketch=sketch)
            plan.path = res.path
            plan.network = network
            return plan
        if sketch is None:
            raise InvalidInputError(f"sketch: the {self.method} method needs a sketch", "sketch")
        x = p.fluid(sim.positions).astype(np.float64)
        v = np.asarray(sim.velocities, np.float64)
        m = p.masses.astype(np.float64)
        g = sim.scene.params.resolved_gravity()
        tau = self.frames * sim.dt_frame
        if self.method == "constant":
            com = (m[:, None] * x).sum(0) / m.sum()
            vel = (m[:, None] * v).sum(0) / m.sum()
            target = com + vel * tau  # depth (3D z) drifts freely: the sketch is drawn in x–y
            target[:2] = sketch.target(com)
            a = self.gain * (2.0 * (target - com - vel * tau) / (tau * tau) - g)
            field_ = np.broadcast_to(a.astype(np.float32), (self.frames, n, d))
            return Plan("constant", start, self.frames, n, accelerations=field_, seconds=time.perf_counter() - t0, sketch=sketch)
        if self.method == "mpc":
            best = mpc_plan(sim, sketch, self.frames, self.mpc, between)
            fb = field_feedback(best.theta, best.targets, self.frames, sim.dt_frame)
            plan = Plan("mpc", start, self.frames, n, feedback=fb, seconds=time.perf_counter() - t0, sketch=sketch)
            plan.model_centroids = best.centroids
            return plan
        # PD attraction to per-particle targets
        y = pd_targets(x, sketch)
        omega = 2.0 * math.pi / (self.settle * tau)
        feedback = track_path(y[None], omega, sim.dt_frame, gravity=g)
        plan = Plan("pd", start, self.frames, n, feedback=feedback, seconds=time.perf_counter() - t0, sketch=sketch, omega=omega)
        plan.pd_centroid = (m / m.sum()) @ y
        return plan

    def _track_omega(self, sim: Simulator) -> float:
        return 2.0 * math.pi / (TRACK_SETTLE * self.frames * sim.dt_frame)


__all__ = [
    "DEFAULT_METHODS",
    "FALLBACK_METHOD",
    "METHODS",
    "PLAN_POINTS",
    "TRACK_SETTLE",
    "USER_METHODS",
    "Controller",
    "Plan",
    "PlanOrigin",
    "default_method",
    "scene_methods",
    "shipped_control_model",
    "track_path",
]
