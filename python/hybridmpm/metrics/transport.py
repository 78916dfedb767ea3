"""The Sinkhorn divergence between two mass-weighted particle sets: a distance
between the *distributions* of matter, blind to which particle went where, so a
chaotic flow that puts the same water in the same places scores near zero.

For particle sets ``α = Σ a_i δ(x_i)`` and ``β = Σ b_j δ(y_j)`` (weights summing
to 1) and the cost ``C(x, y) = |x − y|²`` [m²]:

* ``OT_ε(α, β) = min_π ⟨π, C⟩ + ε·KL(π ‖ α⊗β)`` over couplings ``π`` with
  marginals ``a`` and ``b`` (entropic optimal transport, Cuturi 2013), solved
  by Sinkhorn's iterations in POT (Flamary et al. 2021, JMLR 22(78),
  ``ot.sinkhorn``, log domain) with ε-scaling (:func:`entropic_ot`);
* ``S_ε(α, β) = OT_ε(α, β) − ½·OT_ε(α, α) − ½·OT_ε(β, β)`` — the debiased
  Sinkhorn divergence (Genevay, Peyré & Cuturi 2018; Feydy et al. 2019, AISTATS,
  "Interpolating between optimal transport and MMD using Sinkhorn divergences"):
  0 for identical distributions, symmetric, ≥ 0, and → ``W₂²(α, β)`` as ε → 0.
  For a set and its translate by ``d`` it is ``|d|²`` exactly, for every ε.

LagrangeBench (Toshev et al. 2023, arXiv 2309.16342) scores particle rollouts
with it. Its settings live here and only here:

* ``ε = blur²`` with ``blur`` = :data:`SINKHORN_BLUR` [m] = 1/16 of the
  domain's side (every scene's domain is the unit box ``[0, 1]^D``): 8 cells
  of the 2D scenes' 128² grid, 4 of the 3D scenes' 64³, about a block's
  size. Mass moved farther than the blur counts as ``|d|²``; rearrangements
  within it (the grains of a chaotic splash) are smoothed out: it says
  whether the water is in the right places, the grid-mass error says more.
  On 2 cores a finer blur costs more than the rollout it scores: where water
  spreads over the floor, Sinkhorn at 1/32 needed ~10⁴ iterations
  (docs/benchmarks.md "Metrics for a chaotic flow").
* at most :data:`SINKHORN_MAX_POINTS` particles per set: a larger set is
  subsampled once per trajectory (the same particles in every frame) by a
  fixed-seed draw without replacement (:func:`subsample`), and the drawn
  particles' masses renormalised (an unbiased estimate of the mass
  distribution; two sets of different sizes carry a sampling floor of
  ~1e-5 m² at 300 particles, two of the same size none);
* :data:`SINKHORN_FRAMES` frames per rollout, evenly spaced
  (:func:`sinkhorn_frames`); the rollout's score is their mean.

POT is imported when a divergence is first computed, with its PyTorch, JAX,
CuPy and TensorFlow backends switched off (``POT_BACKEND_DISABLE_*``, unless
already set): the metric runs on NumPy alone and importing
:mod:`hybridmpm.metrics` loads neither POT nor torch.
"""

from __future__ import annotations

import hashlib
import os
import warnings
from typing import Any

import numpy as np
from threadpoolctl import threadpool_limits

from hybridmpm.errors import InvalidInputError
from hybridmpm.limits import check_allocation

#: Blur of the Sinkhorn divergence [m] (ε = blur²): 1/16 of the unit domain's side.
SINKHORN_BLUR = 1.0 / 16.0
#: Particles per set at most (larger sets are subsampled, :func:`subsample`).
SINKHORN_MAX_POINTS = 300
#: Frames of a rollout the divergence is computed on (evenly spaced, :func:`sinkhorn_frames`).
SINKHORN_FRAMES = 8
#: Seed of the subsampling draw: fixed, so a set's subsample depends on its size alone.
_SUBSAMPLE_SEED = 0
#: ε-scaling (:func:`entropic_ot`): at most ``_MAX_ITER`` levels of at most ``_LEVEL_ITERS`` Sinkhorn iterations each;
#: it stops when the coupling's marginals miss ``a`` and ``b`` by ``_STOP_THR`` (2-norm).
_LEVEL_ITERS = 20
_STOP_THR = 1e-7
_MAX_ITER = 200


def _ot() -> Any:
    """POT with its GPU/autodiff backends off (NumPy only; see the module docstring)."""
    for backend in ("PYTORCH", "JAX", "CUPY", "TENSORFLOW"):
        os.environ.setdefault(f"POT_BACKEND_DISABLE_{backend}", "1")
    try:
        import ot
    except ImportError as e:  # a dependency of the package: only a broken install lacks it
        raise ImportError("the Sinkhorn divergence needs POT (pip install pot), a dependency of hybridmpm") from e
    return ot


def subsample(n: int, max_points: int = SINKHORN_MAX_POINTS) -> np.ndarray:
    """Indices (int64, sorted) of the particles of an ``n``-particle set that the
    divergence uses: all of them when ``n <= max_points``, else ``max_points``
    drawn without replacement by a generator of fixed seed, so the same ``n``
    always gives the same subsample. Raises :class:`InvalidInputError`
    (``max_points``) unless it is an integer >= 1."""
    if isinstance(max_points, bool) or not isinstance(max_points, (int, np.integer)) or max_points < 1:
        raise InvalidInputError(f"max_points: must be an integer >= 1, got {max_points!r}", "max_points")
    if n <= max_points:
        return np.arange(n, dtype=np.int64)
    return np.sort(np.random.default_rng(_SUBSAMPLE_SEED).choice(n, int(max_points), replace=False)).astype(np.int64)


def sinkhorn_frames(frame_index: Any, count: int = SINKHORN_FRAMES) -> np.ndarray:
    """Positions (int64, increasing, distinct) into ``frame_index`` (int [F],
    increasing) of the frames the divergence is computed on: for ``k = 1 … count``
    the stored frame nearest to ``first + k·(last − first)/count`` (the first
    frame is the shared start; the last frame is always included). Fewer when
    frames are fewer; empty for a single frame."""
    f = np.asarray(frame_index, dtype=np.float64)
    if f.ndim != 1 or len(f) < 2:
        return np.zeros(0, np.int64)
    targets = f[0] + (f[-1] - f[0]) * np.arange(1, int(count) + 1) / int(count)
    pos = np.abs(f[None, :] - targets[:, None]).argmin(axis=1)
    return np.unique(pos[pos > 0]).astype(np.int64)


def _set(name: str, x: Any) -> np.ndarray:
    arr = np.asarray(x)
    if arr.dtype.kind != "f" or arr.ndim != 2 or arr.shape[1] not in (2, 3) or arr.shape[0] < 1:
        raise InvalidInputError(f"{name}: expected float positions [N, D] with N >= 1 and D in {{2, 3}}, got {arr.dtype} {list(arr.shape)}", name)
    if not np.isfinite(arr).all():
        raise InvalidInputError(f"{name}: positions must be finite", name)
    return arr.astype(np.float64)


def _mass(name: str, w: Any, n: int) -> np.ndarray:
    if w is None:
        return np.full(n, 1.0 / n)
    arr = np.asarray(w)
    if arr.dtype.kind not in "fiu" or arr.shape != (n,):
        raise InvalidInputError(f"{name}: expected a real array of shape [{n}], got {arr.dtype} {list(arr.shape)}", name)
    arr = arr.astype(np.float64)
    if not (np.isfinite(arr) & (arr >= 0)).all() or not arr.sum() > 0:
        raise InvalidInputError(f"{name}: must be finite, >= 0 and not all zero", name)
    return arr / arr.sum()


def entropic_ot(x: np.ndarray, y: np.ndarray, a: np.ndarray, b: np.ndarray, eps: float) -> float:
    """``OT_ε`` [m²] between the weighted sets ``(x, a)`` and ``(y, b)``
    (float64 [N, D], [M, D]; weights [N], [M] summing to 1, all > 0).

    POT's ε-scaled Sinkhorn (``ot.bregman.sinkhorn_epsilon_scaling``: Schmitzer
    2019's scaling with log-absorption of large scalings, in the plain domain):
    ε starts at the largest cost and falls geometrically to ``eps``, each level
    warm-started from the last, at most :data:`_LEVEL_ITERS` inner iterations a
    level and :data:`_MAX_ITER` levels, until the marginals meet to
    :data:`_STOP_THR`. The value is the primal ``⟨π, C⟩ + ε·KL(π ‖ a⊗b)`` of the
    returned coupling. Plain Sinkhorn needed thousands of iterations where water
    spreads over the domain (1.5e4 at blur 1/32); the scaling bounds the work. The
    log-domain solver (``method="sinkhorn_log"``) gives the same values to ~1e-6 m²
    but spends its time in SciPy's ``logsumexp`` (3-4x slower here).
    """
    ot = _ot()
    cost = ot.dist(x, y)  # squared Euclidean [N, M]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # a level left unconverged on purpose is not news
        plan = ot.bregman.sinkhorn_epsilon_scaling(
            a, b, cost, eps, numItermax=_MAX_ITER, epsilon0=max(float(cost.max()), eps), numInnerItermax=_LEVEL_ITERS, stopThr=_STOP_THR
        )
    nz = plan > 0
    kl = float(np.sum(plan[nz] * np.log(plan[nz] / np.outer(a, b)[nz])))
    return float(np.sum(plan * cost)) + eps * kl


#: ``OT_ε(α, α)`` of the sets seen last (:func:`self_ot`): a benchmark scores every method against the same
#: reference frames, whose self-term is then computed once.
_SELF_CACHE: dict[bytes, float] = {}
_SELF_CACHE_MAX = 512


def self_ot(x: np.ndarray, a: np.ndarray, eps: float) -> float:
    """``OT_ε((x, a), (x, a))`` [m²] (:func:`entropic_ot` of a set with itself), remembered for the last
    :data:`_SELF_CACHE_MAX` sets by a digest of their positions, weights and ε (the same values, not the same objects)."""
    key = hashlib.blake2b(np.ascontiguousarray(x).tobytes() + np.ascontiguousarray(a).tobytes() + np.float64(eps).tobytes(), digest_size=16).digest()
    if key not in _SELF_CACHE:
        if len(_SELF_CACHE) >= _SELF_CACHE_MAX:
            _SELF_CACHE.pop(next(iter(_SELF_CACHE)))
        _SELF_CACHE[key] = entropic_ot(x, x, a, a, eps)
    return _SELF_CACHE[key]


def sinkhorn_divergence(
    x: Any,
    y: Any,
    x_weights: Any = None,
    y_weights: Any = None,
    *,
    blur: float = SINKHORN_BLUR,
    max_points: int = SINKHORN_MAX_POINTS,
) -> float:
    """The debiased Sinkhorn divergence ``S_ε`` [m²] between two particle sets
    (module docstring; ε = ``blur``²).

    ``x``, ``y``: positions [m], float [N, D] and [M, D] (N and M may differ);
    ``x_weights``, ``y_weights``: particle masses [N], [M] (any unit; default
    equal masses), normalised to sum 1. Sets larger than ``max_points`` are
    subsampled (:func:`subsample`). Returns a float >= 0 (clipped at 0 where
    the solvers' tolerance leaves a few 1e-12 below it). Raises
    :class:`InvalidInputError` naming ``x``, ``y``, ``x_weights``,
    ``y_weights``, ``blur`` or ``max_points``.
    """
    return float(sinkhorn_series(np.asarray(x)[None], np.asarray(y)[None], x_weights, y_weights, blur=blur, max_points=max_points)[0])


def sinkhorn_series(
    pred: Any,
    ref: Any,
    pred_weights: Any = None,
    ref_weights: Any = None,
    *,
    blur: float = SINKHORN_BLUR,
    max_points: int = SINKHORN_MAX_POINTS,
) -> np.ndarray:
    """:func:`sinkhorn_divergence` frame by frame, float64 [F] [m²], for
    ``pred`` float [F, N, D] and ``ref`` float [F, M, D] (the frames to compare:
    pick them with :func:`sinkhorn_frames`), with one subsample of each set for
    every frame. Raises :class:`InvalidInputError` as :func:`sinkhorn_divergence`."""
    p, r = np.asarray(pred), np.asarray(ref)
    for name, arr in (("x", p), ("y", r)):
        if arr.ndim != 3 or arr.shape[0] < 1:
            raise InvalidInputError(f"{name}: expected float positions [F, N, D], got {list(arr.shape)}", name)
    if p.shape[0] != r.shape[0] or p.shape[2] != r.shape[2]:
        raise InvalidInputError(f"y: {list(r.shape)} does not match x's frames and dimension {list(p.shape)}", "y")
    try:
        b = float(blur)
    except (TypeError, ValueError):
        b = float("nan")
    if not (np.isfinite(b) and b > 0):
        raise InvalidInputError(f"blur: must be a finite length > 0 [m], got {blur!r}", "blur")
    ip, ir = subsample(p.shape[1], max_points), subsample(r.shape[1], max_points)
    a = _mass("x_weights", pred_weights, p.shape[1])[ip]
    c = _mass("y_weights", ref_weights, r.shape[1])[ir]
    for name, w in (("x_weights", a), ("y_weights", c)):
        if not w.sum() > 0:
            raise InvalidInputError(f"{name}: the subsampled particles carry no mass", name)
    ip, ir = ip[a > 0], ir[c > 0]  # massless particles hold no distribution (and no logarithm)
    a, c = a[a > 0] / a.sum(), c[c > 0] / c.sum()
    n, m = len(ip), len(ir)
    # the cost matrix, the coupling and their products, float64, for the largest of the three problems
    check_allocation("max_points", 4 * 8.0 * max(n, m) ** 2, f"Sinkhorn on {max(n, m)} particles")
    out = np.empty(p.shape[0], np.float64)
    # one BLAS thread: Sinkhorn's products on a few hundred² are too small to share, and two threads on a busy
    # machine took 15-30x longer each
    with threadpool_limits(limits=1, user_api="blas"):
        for t in range(p.shape[0]):
            xs, ys = _set("x", p[t][ip]), _set("y", r[t][ir])
            eps = b * b
            s = entropic_ot(xs, ys, a, c, eps) - 0.5 * (self_ot(xs, a, eps) + self_ot(ys, c, eps))
            out[t] = max(s, 0.0)
    return out
