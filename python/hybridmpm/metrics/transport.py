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
  For a set and its translate by ``d`` it is ``|d|²`` exactly, for every ε
  (sets reduced on a lattice, which stays put as they move: to ~1e-5 of it).

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
* at most :data:`SINKHORN_MAX_POINTS` points per set: where either set of a
  frame has more particles, both are reduced on one lattice ``h·Z^D``
  (:func:`bin_width`: the finest ``h = blur·2^(k/2)``, ``k ≥ −12``, at which
  each set occupies at most that many cells), every occupied cell becoming one
  point at its particles' mass-weighted centroid, weighted by its mass share
  (:func:`binned_set`). The rule reads positions and masses, never indices:
  the particles are put in a canonical order (cell, position, mass) before any
  sum, so the reduced sets are bit for bit the same for any order of the
  particles: a set scores 0 against a permutation of itself, and against
  itself plus a few particles it scores what they change, not which particles
  a draw happened to pick. Sets within the limit are used whole. Measured
  floors (``python benchmarks/sinkhorn_floor.py``;
  ``benchmarks/results/sinkhorn_floor.md``): 2,000 particles against a
  permutation of themselves score 0 (2D and 3D); a block of 2,000 against the
  block plus 7 particles inside it 1.0-2.4e-7 m² in 2D and 1.4-1.9e-7 m² in 3D
  (the whole sets: ~1e-13); MPM at ``r_p`` against full-resolution MPM on
  water2d (400 frames, seeds 1000-1002) scores 4.5e-4 to 1.3e-3 m² (the
  reference against itself permuted: < 1e-18), so the floor is under 1/1000 of
  the signal (sand2d, which settles into nearly the same heap, scores 1.3e-5
  m²: 50x the floor; ``benchmarks/results/metric_floor.md``), and the reduced
  sets' value is that of the whole sets to 0.2% (seed 1000). A draw of 300
  particle indices instead (the script's "index" column) scores a permutation
  of the same 2,000 particles 4e-4 to 9e-4 m², the block plus 7 particles
  1.8e-4 (2D) and 4.7e-4 m² (3D), and MPM at ``r_p`` on water2d 2.0e-3 to
  3.1e-3 m²: a floor of the order of the signal;
* :data:`SINKHORN_FRAMES` frames per rollout, evenly spaced
  (:func:`sinkhorn_frames`); the rollout's score is their mean.

POT is imported when a divergence is first computed, with its PyTorch, JAX,
CuPy and TensorFlow backends switched off (``POT_BACKEND_DISABLE_*``, unless
already set): the metric runs on NumPy alone and importing
:mod:`hybridmpm.metrics` loads neither POT nor torch.
"""

from __future__ import annotations

import hashlib
import math
import os
import warnings
from collections.abc import Sequence
from typing import Any

import numpy as np
from threadpoolctl import threadpool_limits

from hybridmpm.errors import InvalidInputError
from hybridmpm.limits import check_allocation

#: Blur of the Sinkhorn divergence [m] (ε = blur²): 1/16 of the unit domain's side.
SINKHORN_BLUR = 1.0 / 16.0
#: Points per set at most (larger sets are reduced on a lattice, :func:`bin_width`, :func:`binned_set`).
SINKHORN_MAX_POINTS = 300
#: Frames of a rollout the divergence is computed on (evenly spaced, :func:`sinkhorn_frames`).
SINKHORN_FRAMES = 8
#: The finest lattice tried (:func:`bin_width`): ``blur·2^(_FINEST_LEVEL/2)`` = blur/64.
_FINEST_LEVEL = -12
#: ε-scaling (:func:`entropic_ot`): at most ``_MAX_ITER`` levels of at most ``_LEVEL_ITERS`` Sinkhorn iterations each;
#: it stops when the coupling's marginals miss ``a`` and ``b`` by ``_STOP_THR`` (2-norm).
_LEVEL_ITERS = 20
_STOP_THR = 1e-7
_MAX_ITER = 200
#: A coupling whose marginals miss ``a`` and ``b`` by more than this (L1, of 2) is a failed solve, redone in the log
#: domain (at most ``_LOG_MAX_ITER`` iterations). A level left unconverged misses by ~1e-3 at most on the scenes.
_MARGINAL_FAIL = 1e-2
_LOG_MAX_ITER = 10000


def _ot() -> Any:
    """POT with its GPU/autodiff backends off (NumPy only; see the module docstring)."""
    for backend in ("PYTORCH", "JAX", "CUPY", "TENSORFLOW"):
        os.environ.setdefault(f"POT_BACKEND_DISABLE_{backend}", "1")
    try:
        import ot
    except ImportError as e:  # a dependency of the package: only a broken install lacks it
        raise ImportError("the Sinkhorn divergence needs POT (pip install pot), a dependency of hybridmpm") from e
    return ot


def _max_points(max_points: Any) -> int:
    if isinstance(max_points, bool) or not isinstance(max_points, (int, np.integer)) or max_points < 1:
        raise InvalidInputError(f"max_points: must be an integer >= 1, got {max_points!r}", "max_points")
    return int(max_points)


def _cells(x: np.ndarray, width: float) -> np.ndarray:
    """The lattice cell of every position, float64 [N, D] of integers (``floor(x / width)``; one cell for an infinite width)."""
    return np.zeros_like(x) if math.isinf(width) else np.floor(x / width)


def _count_cells(x: np.ndarray, width: float) -> int:
    q = _cells(x, width)
    if len(q) < 2:
        return len(q)
    q -= q.min(axis=0)
    span = q.max(axis=0) + 1
    if float(np.prod(span)) < 2.0**62:  # one integer key a cell (a 1D sort, ~10x faster than lexsort on D columns)
        key = np.zeros(len(q), np.int64)
        for j in range(q.shape[1]):
            key = key * np.int64(span[j]) + q[:, j].astype(np.int64)
        return len(np.unique(key))
    q = q[np.lexsort(q.T[::-1])]
    return 1 + int(np.count_nonzero(np.any(q[1:] != q[:-1], axis=1)))


def bin_width(sets: Sequence[Any], max_points: int = SINKHORN_MAX_POINTS, blur: float = SINKHORN_BLUR) -> float:
    """The width [m] of the lattice the sets in ``sets`` (float positions [N_k, D]) are reduced on together
    (:func:`binned_set`): 0.0 (no reduction) when every set has at most ``max_points`` particles; else the
    finest ``blur·2^(k/2)``, ``k = -12, -11, …`` (from ``blur``/64 up), at which every set occupies at most
    ``max_points`` cells of the lattice ``width·Z^D``; ``inf`` (each set one point) where none does (``max_points``
    below ``2^D`` and sets straddling a cell corner at every width). It depends on the sets' positions alone,
    not on their order. Raises :class:`InvalidInputError` (``max_points``) unless it is an integer >= 1."""
    cap = _max_points(max_points)
    xs = [np.asarray(x, dtype=np.float64) for x in sets]
    if all(len(x) <= cap for x in xs):
        return 0.0
    extent = max(float(np.abs(x).max()) for x in xs if len(x))
    k = _FINEST_LEVEL
    while True:
        width = float(blur) * 2.0 ** (k / 2)
        if all(_count_cells(x, width) <= cap for x in xs):
            return width
        if width > 2.0 * extent:  # every set already within the 2^D cells around the origin
            return math.inf
        k += 1


def binned_set(x: Any, masses: Any, width: float) -> tuple[np.ndarray, np.ndarray]:
    """The weighted point set [m] the divergence sees for particles ``x`` (float [N, D]) of ``masses``
    (real [N], >= 0, not all zero): every cell of the lattice ``width·Z^D`` that holds mass becomes one point
    at its particles' mass-weighted centroid, weighted by its share of the mass (``width`` 0: every particle
    with mass as it is; ``inf``: one point). Returns (points float64 [K, D], weights float64 [K] summing to 1),
    sorted by cell, then position. The particles are put in a canonical order (cell, position, mass) before any
    sum, so the result is bit for bit the same for every order of the particles."""
    pos = np.asarray(x, dtype=np.float64)
    m = np.asarray(masses, dtype=np.float64)
    keep = m > 0
    pos, m = pos[keep], m[keep]
    if width == 0:
        order = np.lexsort((m, *pos.T[::-1]))
        w = m[order]
        return pos[order], w / w.sum()
    q = _cells(pos, width)
    order = np.lexsort((m, *pos.T[::-1], *q.T[::-1]))
    pos, m, q = pos[order], m[order], q[order]
    starts = np.flatnonzero(np.concatenate([[True], np.any(q[1:] != q[:-1], axis=1)]))
    mass = np.add.reduceat(m, starts)
    centroids = np.add.reduceat(pos * m[:, None], starts, axis=0) / mass[:, None]
    return centroids, mass / mass.sum()


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
        return np.ones(n)
    arr = np.asarray(w)
    if arr.dtype.kind not in "fiu" or arr.shape != (n,):
        raise InvalidInputError(f"{name}: expected a real array of shape [{n}], got {arr.dtype} {list(arr.shape)}", name)
    arr = arr.astype(np.float64)
    if not (np.isfinite(arr) & (arr >= 0)).all() or not arr.sum() > 0:
        raise InvalidInputError(f"{name}: must be finite, >= 0 and not all zero", name)
    return arr  # normalised by binned_set, after its canonical order (a sum in the given order would depend on it)


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
    but spends its time in SciPy's ``logsumexp`` (3-4x slower here); it is the
    fallback where the scaled solver's coupling misses the marginals by more than
    :data:`_MARGINAL_FAIL` (L1): on the 1,885 particles of a settled sand2d frame
    against themselves it returned a coupling of total mass ~1e-6 (a divergence
    2,000x the true one), which the log-domain solver settles in ~40 iterations.
    """
    ot = _ot()
    cost = ot.dist(x, y)  # squared Euclidean [N, M]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # a level left unconverged on purpose is not news
        plan = ot.bregman.sinkhorn_epsilon_scaling(
            a, b, cost, eps, numItermax=_MAX_ITER, epsilon0=max(float(cost.max()), eps), numInnerItermax=_LEVEL_ITERS, stopThr=_STOP_THR
        )
        if not np.abs(plan.sum(axis=1) - a).sum() + np.abs(plan.sum(axis=0) - b).sum() <= _MARGINAL_FAIL:
            plan = ot.sinkhorn(a, b, cost, eps, method="sinkhorn_log", numItermax=_LOG_MAX_ITER, stopThr=_STOP_THR)
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
    equal masses), normalised to sum 1. Where either set is larger than
    ``max_points``, both are reduced on one lattice (:func:`bin_width`,
    :func:`binned_set`): the value does not depend on the particles' order. Returns a float >= 0 (clipped at 0 where
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
    pick them with :func:`sinkhorn_frames`), each frame's pair reduced on its
    own lattice (:func:`bin_width`: the water spreads, the cells grow with it). Raises :class:`InvalidInputError` as :func:`sinkhorn_divergence`."""
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
    cap = _max_points(max_points)
    wp, wr = _mass("x_weights", pred_weights, p.shape[1]), _mass("y_weights", ref_weights, r.shape[1])
    kp, kr = wp > 0, wr > 0  # massless particles hold no distribution (and no logarithm)
    # the cost matrix, the coupling and their products, float64, for the largest of the three problems
    n = min(max(int(kp.sum()), int(kr.sum())), cap)
    check_allocation("max_points", 4 * 8.0 * n**2, f"Sinkhorn on {n} points")
    out = np.empty(p.shape[0], np.float64)
    eps = b * b
    # one BLAS thread: Sinkhorn's products on a few hundred² are too small to share, and two threads on a busy
    # machine took 15-30x longer each
    with threadpool_limits(limits=1, user_api="blas"):
        for t in range(p.shape[0]):
            xt, yt = _set("x", p[t])[kp], _set("y", r[t])[kr]
            width = bin_width((xt, yt), cap, b)
            (xs, a), (ys, c) = binned_set(xt, wp[kp], width), binned_set(yt, wr[kr], width)
            s = entropic_ot(xs, ys, a, c, eps) - 0.5 * (self_ot(xs, a, eps) + self_ot(ys, c, eps))
            out[t] = max(s, 0.0)
    return out
