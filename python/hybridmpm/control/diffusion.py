"""The numpy half of the Fluid ControlNet: the temporal basis of the control
field, the diffusion schedule, the closed-form DDIM update, and the
onnxruntime sampler that turns a sketch and the fluid state into a field
(paper Sec. 3.2, App. B; ``docs/control.md``).

Serving needs numpy and onnxruntime only; the torch model that is trained
and exported lives in :mod:`hybridmpm.train.control.model`.

The sample (what is diffused) is, per particle, the coefficients of its
planned displacement over the horizon on a temporal basis:
``y_i(k) − x_i = Σ_j c_ij B_j(k)`` for the ``T_ctr`` frames, ``B`` clamped
cubic B-splines on uniform knots that vanish at frame 0 (:func:`path_basis`),
``K_b`` of them, so a particle's whole-horizon plan is ``K_b·D`` numbers,
normalised per (basis, dimension) by the training set's mean and std. The
controller turns the plan into accelerations frame by frame with a tracking
law (:func:`hybridmpm.control.controller.track_path`); ``docs/control.md``
explains why the plan, not the acceleration field, is what is diffused.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from hybridmpm.control.prior import prior_path
from hybridmpm.control.sketch import render_sketch
from hybridmpm.control.targets import GEOMETRY_SCALE, sketch_geometry, smoothstep
from hybridmpm.errors import InvalidInputError, as_f32
from hybridmpm.files import loads_json
from hybridmpm.graph import radius_graph
from hybridmpm.materials import refuse_untrained

#: Diffusion steps of training (the schedule's length).
DIFFUSION_STEPS = 100
#: DDIM steps at sampling time (trailing spacing). One step returns the network's x̂0 from pure noise — its estimate of the
#: mean plan, not a draw — and on validation seeds 4000–4015 (``docs/control.md``) it tracks as well as 4 steps on
#: water2d (1.005 both) and better on sand2d (1.026 against 1.048), at a quarter of the head's time.
SAMPLE_STEPS = 1


# --------------------------------------------------------------------- basis
def temporal_basis(frames: int, k: int) -> np.ndarray:
    """Clamped cubic B-spline basis on uniform knots: float64 [frames, k]
    (``k ≥ 4``), rows sum to 1; frame ``f`` sits at ``u = f/(frames − 1)``
    in [0, 1]. Cox–de Boor recursion (de Boor 1978); ``tests/test_control_diffusion.py``
    checks it against scipy's ``BSpline.design_matrix``."""
    if not 4 <= k <= frames:
        raise InvalidInputError(f"k: basis size must be in [4, {frames}], got {k!r}", "k")
    degree = 3
    inner = np.linspace(0.0, 1.0, k - degree + 1)
    knots = np.concatenate([np.zeros(degree), inner, np.ones(degree)])
    u = np.linspace(0.0, 1.0, frames)
    # degree 0: indicator of [t_i, t_{i+1}), the last non-empty span closed at 1
    b = np.zeros((frames, len(knots) - 1))
    for i in range(len(knots) - 1):
        if knots[i + 1] > knots[i]:
            b[:, i] = (u >= knots[i]) & (u < knots[i + 1])
    last = np.nonzero(knots[1:] > knots[:-1])[0][-1]
    b[u >= 1.0, last] = 1.0
    for p in range(1, degree + 1):
        nb = np.zeros((frames, len(knots) - 1 - p))
        for i in range(len(knots) - 1 - p):
            d1, d2 = knots[i + p] - knots[i], knots[i + p + 1] - knots[i + 1]
            left = (u - knots[i]) / d1 * b[:, i] if d1 > 0 else 0.0
            right = (knots[i + p + 1] - u) / d2 * b[:, i + 1] if d2 > 0 else 0.0
            nb[:, i] = left + right
        b = nb
    return b


def path_basis(frames: int, k: int) -> np.ndarray:
    """The basis of a planned displacement: the clamped cubic B-spline basis
    of ``k + 1`` functions (:func:`temporal_basis`) without its first, so
    every combination is 0 at frame 0 (a plan starts where the fluid is).
    float64 [frames, k], ``k ≥ 3``."""
    return temporal_basis(frames, k + 1)[:, 1:]


def project(field: np.ndarray, basis: np.ndarray) -> np.ndarray:
    """Least-squares coefficients of ``field`` float [F, N, D] on ``basis``
    [F, K]: float32 [N, K, D]."""
    f = np.asarray(field, np.float64)
    coef = np.linalg.pinv(basis) @ f.reshape(len(f), -1)  # [K, F] pseudo-inverse once, then one matrix product
    return coef.reshape(basis.shape[1], f.shape[1], f.shape[2]).transpose(1, 0, 2).astype(np.float32)


def expand(coefficients: np.ndarray, basis: np.ndarray) -> np.ndarray:
    """The field of ``coefficients`` [N, K, D] on ``basis`` [F, K]: float32 [F, N, D]."""
    c = np.asarray(coefficients, np.float64)
    n, k, d = c.shape
    return (np.asarray(basis, np.float64) @ c.transpose(1, 0, 2).reshape(k, n * d)).reshape(len(basis), n, d).astype(np.float32)


# --------------------------------------------------------------------- schedule and DDIM
def cosine_alpha_bar(steps: int = DIFFUSION_STEPS, max_beta: float = 0.999) -> np.ndarray:
    """``ᾱ_t`` for t = 0 … steps − 1 of the cosine schedule (Nichol & Dhariwal
    2021, Eq. 17; diffusers' ``squaredcos_cap_v2``: ``β_t = min(1 −
    f((t+1)/T)/f(t/T), max_beta)``, ``f(s) = cos²((s + 0.008)/1.008·π/2)``,
    ``ᾱ_t = Π_{i≤t}(1 − β_i)``). float64 [steps]."""

    def f(s: float) -> float:
        return math.cos((s + 0.008) / 1.008 * math.pi / 2) ** 2

    betas = np.array([min(1 - f((i + 1) / steps) / f(i / steps), max_beta) for i in range(steps)])
    return np.cumprod(1.0 - betas)


def trailing_timesteps(steps: int = SAMPLE_STEPS, train_steps: int = DIFFUSION_STEPS) -> np.ndarray:
    """DDIM sampling timesteps with trailing spacing (Lin et al. 2024, Table 2;
    the first step is ``train_steps − 1``, pure noise): int64 [steps], decreasing."""
    if not 1 <= steps <= train_steps:
        raise InvalidInputError(f"steps: must be in [1, {train_steps}], got {steps!r}", "steps")
    ratio = train_steps / steps
    return (np.round(np.arange(train_steps, 0, -ratio)) - 1).astype(np.int64)


def add_noise(x0: np.ndarray, noise: np.ndarray, alpha_bar_t: float) -> np.ndarray:
    """The forward process ``x_t = √ᾱ_t·x0 + √(1 − ᾱ_t)·ε`` (DDPM, Ho et al. 2020, Eq. 4)."""
    return math.sqrt(alpha_bar_t) * x0 + math.sqrt(1.0 - alpha_bar_t) * noise


def ddim_step(x_t: np.ndarray, x0: np.ndarray, alpha_bar_t: float, alpha_bar_prev: float) -> np.ndarray:
    """One deterministic DDIM update (η = 0; Song et al. 2021, Eq. 12) from a
    predicted ``x0``: ``ε̂ = (x_t − √ᾱ_t·x0)/√(1 − ᾱ_t)``,
    ``x_prev = √ᾱ_prev·x0 + √(1 − ᾱ_prev)·ε̂``. No clipping of ``x0``."""
    eps = (x_t - math.sqrt(alpha_bar_t) * x0) / math.sqrt(1.0 - alpha_bar_t)
    return math.sqrt(alpha_bar_prev) * x0 + math.sqrt(1.0 - alpha_bar_prev) * eps


def bilinear_sample(feature_map: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """Sample ``feature_map`` float [C, H, W] (row 0 = top = y 1, the image of
    :func:`~hybridmpm.control.sketch.render_sketch`) at domain points ``xy``
    [N, 2] (y up) bilinearly, pixel centres at ``(j + ½)/W``, zero outside
    (torch ``grid_sample(align_corners=False, padding_mode="zeros")``).
    Returns float32 [N, C]."""
    c, h, w = feature_map.shape
    fx = np.asarray(xy[:, 0], np.float64) * w - 0.5
    fy = (1.0 - np.asarray(xy[:, 1], np.float64)) * h - 0.5
    x0, y0 = np.floor(fx).astype(np.int64), np.floor(fy).astype(np.int64)
    out = np.zeros((len(xy), c), np.float64)
    for dy in (0, 1):
        for dx in (0, 1):
            xi, yi = x0 + dx, y0 + dy
            wgt = (1.0 - np.abs(fx - xi)) * (1.0 - np.abs(fy - yi))
            ok = (xi >= 0) & (xi < w) & (yi >= 0) & (yi < h)
            vals = np.zeros((len(xy), c))
            vals[ok] = feature_map[:, yi[ok], xi[ok]].T
            out += wgt[:, None] * vals
    return out.astype(np.float32)


def prior_coefficients(offset: np.ndarray, basis: np.ndarray) -> np.ndarray:
    """The sketch's geometric plan on ``basis`` [F, K]: every particle moved to
    its target point (``offset`` [N, D] in metres, see :func:`sketch_geometry`)
    along a smoothstep — float64 [N, K·D]. A cubic in time, so the B-spline
    basis holds it exactly. The diffusion sample is the plan minus this prior
    (``control.json`` ``"prior": "sketch_ramp"``): an untrained model plans the
    geometric mapping, and training learns how the fluid departs from it."""
    off = np.asarray(offset, np.float64)
    ramp = smoothstep(len(basis))[:, None, None] * off[None]
    return project(ramp, basis).astype(np.float64).reshape(len(off), -1)


def mirror_x(positions: np.ndarray, lower: float, upper: float) -> np.ndarray:
    """Positions [..., D] mirrored in x about the domain's centre (training augmentation)."""
    out = np.array(positions, copy=True)
    out[..., 0] = lower + upper - out[..., 0]
    return out


# --------------------------------------------------------------------- onnxruntime sampler
#: File names of an exported controller (a directory).
GRAPHS = ("sketch_encoder", "state_encoder", "denoiser_head")
META_FILE = "control.json"


@dataclass
class SampleResult:
    """A sampled plan: ``path`` float64 [F, N, D] the positions the fluid
    should pass through (``path[0]`` = now); ``seconds`` sketch → path."""

    path: np.ndarray
    seconds: float


class ControlModel:
    """An exported Fluid ControlNet run by onnxruntime (no torch).

    ``path`` a directory with :data:`GRAPHS` ``.onnx`` files and
    ``control.json`` (:func:`hybridmpm.train.control.train.export_control`);
    ``threads`` onnxruntime intra-op threads: 1, the only count allowed (the
    latency target's, and the graphs sum over particles with ``ScatterND``,
    which onnxruntime's CPU kernel runs without atomics and so loses updates
    on more threads: microsoft/onnxruntime#23396, ``hybridmpm.train.gns.onnx_graph``).
    Raises :class:`InvalidInputError` (field ``model``) for a missing or
    malformed model, (``threads``) for another thread count."""

    def __init__(self, path: str | Path, threads: int = 1) -> None:
        import onnxruntime as ort

        if isinstance(threads, bool) or threads != 1:
            raise InvalidInputError(f"threads: the control model's graphs sum with ScatterND, exact on 1 onnxruntime thread only; got {threads!r}", "threads")
        self.path = Path(path)
        try:
            self.meta: dict[str, Any] = loads_json((self.path / META_FILE).read_text(), "model")  # nesting checked before parsing
            cfg = self.meta["config"]
            self.dim = int(cfg["dim"])
            self.k_basis = int(cfg["k_basis"])
            self.frames = int(cfg["frames"])
            self.radius = float(cfg["radius"])
            self.coef_mean = np.asarray(cfg["coef_mean"], np.float64)
            self.coef_std = np.asarray(cfg["coef_std"], np.float64)
            opts = ort.SessionOptions()
            opts.intra_op_num_threads = 1
            opts.inter_op_num_threads = 1
            opts.add_session_config_entry("session.intra_op.allow_spinning", "0")
            self.sessions = {g: ort.InferenceSession(str(self.path / f"{g}.onnx"), opts, providers=["CPUExecutionProvider"]) for g in GRAPHS}
        except (OSError, KeyError, ValueError, TypeError) as e:
            raise InvalidInputError(f"model: {self.path} is not an exported control model ({e})", "model") from e
        except Exception as e:  # onnxruntime's own load errors
            raise InvalidInputError(f"model: {self.path} could not be loaded by onnxruntime ({e})", "model") from e
        if self.coef_mean.shape != (self.k_basis * self.dim,) or self.coef_std.shape != self.coef_mean.shape or (self.coef_std <= 0).any():
            raise InvalidInputError(f"model: {self.path} has malformed normalisation statistics", "model")
        #: DDIM steps when the caller names none: ``control.json``'s ``sample_steps``, else :data:`SAMPLE_STEPS`.
        self.sample_steps = self.meta.get("sample_steps", SAMPLE_STEPS)
        if isinstance(self.sample_steps, bool) or not isinstance(self.sample_steps, int) or not 1 <= self.sample_steps <= 100:
            raise InvalidInputError(f"model: {self.path} has sample_steps {self.sample_steps!r}, not an integer in [1, 100]", "model")
        self.basis = path_basis(self.frames, self.k_basis)
        self.alpha_bar = cosine_alpha_bar(int(self.meta.get("diffusion_steps", DIFFUSION_STEPS)))

    @property
    def needs_free(self) -> bool:
        """Whether :meth:`sample` needs the free-motion prior (``free``)."""
        return bool(self.meta.get("prior") == "free_sketch")

    def _encode_sketch(self, sketch: Any) -> tuple[np.ndarray, np.ndarray]:
        img = render_sketch(sketch).astype(np.float32).transpose(2, 0, 1)[None] / 255.0
        glob, local_map = self.sessions["sketch_encoder"].run(None, {"image": img})
        return glob, local_map[0]

    def sample(
        self,
        positions: np.ndarray,
        velocities: np.ndarray,
        particle_type: np.ndarray,
        sketch: Any,
        *,
        seed: int = 0,
        steps: int | None = None,
        guidance: float = 1.0,
        free: Any = None,
    ) -> SampleResult:
        """Sample a plan for the fluid ``positions`` [N, D] m, ``velocities``
        [N, D] m/s, ``particle_type`` int [N] (GNS codes) and ``sketch`` (None:
        blank). DDIM with ``steps`` trailing steps (None: :attr:`sample_steps`) from seeded Gaussian noise
        (``seed``: same inputs and seed → the same bits); ``guidance`` the
        classifier-free guidance scale ``s`` in
        ``x̂0 = x̂0_blank + s·(x̂0_sketch − x̂0_blank)`` (1: no blank pass).
        ``free`` float [F, N, D] (or a ``concurrent.futures.Future`` of it,
        waited for only when needed): the free-motion prior
        (:func:`~hybridmpm.control.prior.free_motion`), needed by a model whose
        ``prior`` is :data:`~hybridmpm.control.prior.PRIOR_FREE_SKETCH`
        (:attr:`needs_free`). Raises :class:`InvalidInputError` naming a bad argument."""
        t0 = time.perf_counter()
        x = as_f32("positions", positions)
        v = as_f32("velocities", velocities)
        if x.ndim != 2 or x.shape[1] != self.dim or v.shape != x.shape:
            raise InvalidInputError(
                f"positions: expected [N, {self.dim}] with velocities of the same shape, got {list(x.shape)} and {list(v.shape)}", "positions"
            )
        if not (isinstance(guidance, (int, float)) and 0.0 <= guidance <= 5.0):
            raise InvalidInputError(f"guidance: must be in [0, 5], got {guidance!r}", "guidance")
        ptype = np.asarray(particle_type, np.int64)
        refuse_untrained(ptype, "diffusion controller", gns=True)
        ts = trailing_timesteps(self.sample_steps if steps is None else steps, len(self.alpha_bar))
        s, r, _, _ = radius_graph(x, self.radius)
        h, edges = self.sessions["state_encoder"].run(None, {"positions": x, "velocities": v, "particle_type": ptype, "senders": s, "receivers": r})
        branches = [sketch] if guidance == 1.0 else [sketch, None]
        prior_kind = self.meta.get("prior", "none")
        x64 = x.astype(np.float64)
        if self.needs_free and free is None:
            raise InvalidInputError("free: this model plans relative to the free motion (control.json prior 'free_sketch'); pass free=", "free")
        conds = []
        for sk in branches:
            glob, local_map = self._encode_sketch(sk)
            geo, off = sketch_geometry(sk, x)
            conds.append((np.concatenate([glob, geo[None]], 1).astype(np.float32), bilinear_sample(local_map, x[:, :2]), off))

        def branch_priors() -> list[np.ndarray]:
            if self.needs_free:
                fm = free.result() if hasattr(free, "result") else free  # an array, or a Future computed meanwhile
                if np.shape(fm) != (self.frames, len(x), self.dim) or not np.isfinite(fm).all():
                    raise InvalidInputError(f"free: expected finite [{self.frames}, {len(x)}, {self.dim}], got {list(np.shape(fm))}", "free")
                return [project(prior_path(fm, x64, sk) - x64[None], self.basis).reshape(len(x), -1) for sk in branches]
            if prior_kind == "sketch_ramp":
                return [prior_coefficients(c[2] * GEOMETRY_SCALE, self.basis) for c in conds]
            return [np.zeros((len(x), self.k_basis * self.dim)) for _ in branches]

        # The loop runs relative to the first branch's prior, which one branch never needs inside it: with
        # guidance 1 the prior (and the free-motion rollout behind it) is only waited for at the end.
        priors = branch_priors() if len(branches) > 1 else None
        rng = np.random.default_rng(int(seed))
        xt = rng.standard_normal((len(x), self.k_basis * self.dim)).astype(np.float32)
        head = self.sessions["denoiser_head"]
        for i, t in enumerate(ts):
            ab = float(self.alpha_bar[t])
            relative = []  # each branch's x̂0 as plan coefficients [m] relative to the first branch's prior
            for b, (cond, local, off) in enumerate(conds):
                delta = 0.0 if b == 0 or priors is None else priors[0] - priors[b]
                shift = (math.sqrt(ab) * np.asarray(delta) / self.coef_std).astype(np.float32)
                feed = {"x_t": xt + shift, "h": h, "local": local, "offset": off, "edges": edges, "senders": s, "receivers": r}
                feed.update({"t": np.array([t / len(self.alpha_bar)], np.float32), "cond": cond})
                relative.append(head.run(None, feed)[0].astype(np.float64) * self.coef_std + self.coef_mean - delta)
            plan = relative[0] if len(relative) == 1 else relative[1] + guidance * (relative[0] - relative[1])
            x0 = (plan - self.coef_mean) / self.coef_std
            prev = self.alpha_bar[ts[i + 1]] if i + 1 < len(ts) else 1.0
            xt = ddim_step(xt.astype(np.float64), x0, ab, float(prev)).astype(np.float32)
        first_prior = (priors if priors is not None else branch_priors())[0]
        coef = (xt.astype(np.float64) * self.coef_std + self.coef_mean + first_prior).reshape(len(x), self.k_basis, self.dim)
        path = x.astype(np.float64)[None] + expand(coef, self.basis).astype(np.float64)
        if self.needs_free:
            # The sketch's end constraint, bent onto the plan as the prior bends the free motion (an arrow: where the
            # centroid ends; an oval: the end cloud's ±2σ ellipse, paper App. C). The network's x̂0 is a mean over what it
            # cannot tell apart, which shrinks the cloud: on validation seed 4007 (sand2d, an oval) it ended 17.5 cm long
            # where the oval and the truth say 34.2 (docs/control.md). No sketch: prior_path leaves the plan as it is.
            path = prior_path(path, x64, sketch)
        return SampleResult(path, time.perf_counter() - t0)


__all__ = [
    "DIFFUSION_STEPS",
    "GRAPHS",
    "META_FILE",
    "SAMPLE_STEPS",
    "ControlModel",
    "SampleResult",
    "add_noise",
    "bilinear_sample",
    "cosine_alpha_bar",
    "ddim_step",
    "expand",
    "mirror_x",
    "path_basis",
    "prior_coefficients",
    "project",
    "temporal_basis",
    "trailing_timesteps",
]
