"""The per-frame measures of a rollout against a reference rollout, and the
checks of their inputs: :func:`grid_mass_error`, :func:`position_mse`,
:func:`kinetic_energy`, :func:`rollout_summary`, :func:`align_frames` and
:func:`fluid_mask` (the package's docstring says what each is)."""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from hybridmpm.conventions import GNS_KINEMATIC
from hybridmpm.errors import InvalidInputError
from hybridmpm.limits import check_allocation
from hybridmpm.mpm import grid_mass

#: Relative tolerance on "the ratio of the frame intervals is an integer".
_RATIO_RTOL = 1e-5
#: Largest ratio of two trajectories' frame intervals :func:`align_frames` pairs: 2^53 (beyond it a float
#: holds no integer exactly, and frame index × ratio stays within int64 below it).
MAX_INTERVAL_RATIO = float(2**53)


def checked_frames(name: str, x: Any) -> np.ndarray:
    """``x`` as float [T, N, D] (a single frame [N, D] becomes T = 1), finite;
    :class:`InvalidInputError` naming ``name`` otherwise."""
    arr = np.asarray(x)
    if arr.dtype.kind != "f":
        raise InvalidInputError(f"{name}: expected a floating-point array, got dtype {arr.dtype}", name)
    if arr.ndim == 2:
        arr = arr[None]
    if arr.ndim != 3 or arr.shape[2] not in (2, 3):
        raise InvalidInputError(f"{name}: expected shape [T, N, D] or [N, D] with D in {{2, 3}}, got {list(np.shape(x))}", name)
    if arr.shape[0] < 1 or arr.shape[1] < 1:
        raise InvalidInputError(f"{name}: need at least one frame and one particle, got shape {list(arr.shape)}", name)
    if not np.isfinite(arr).all():
        raise InvalidInputError(f"{name}: positions must be finite", name)
    return arr


def _weights(name: str, w: Any, n: int) -> np.ndarray | None:
    if w is None:
        return None
    arr = np.asarray(w)
    if arr.dtype.kind not in "fiu" or arr.shape != (n,):
        raise InvalidInputError(f"{name}: expected a real array of shape [{n}], got {arr.dtype} {list(arr.shape)}", name)
    arr = arr.astype(np.float32)
    if not (np.isfinite(arr) & (arr >= 0)).all() or not arr.sum() > 0:
        raise InvalidInputError(f"{name}: must be finite, >= 0 and not all zero", name)
    return arr


def checked_n_grid(n_grid: Any) -> int:
    """``n_grid`` as an int in [3, 4096]; :class:`InvalidInputError` (``n_grid``) otherwise."""
    if isinstance(n_grid, bool) or not isinstance(n_grid, (int, np.integer)) or not 3 <= int(n_grid) <= 4096:
        raise InvalidInputError(f"n_grid: must be an integer in [3, 4096], got {n_grid!r}", "n_grid")
    return int(n_grid)


def _positive(name: str, x: Any) -> float:
    try:
        v = float(x)
    except (TypeError, ValueError):
        raise InvalidInputError(f"{name}: must be a finite number > 0, got {x!r}", name) from None
    if not (math.isfinite(v) and v > 0):
        raise InvalidInputError(f"{name}: must be a finite number > 0, got {x!r}", name)
    return v


def fluid_mask(particle_type: Any) -> np.ndarray:
    """bool [N]: True for particles that count in the metrics, i.e. every
    particle whose GNS type (int [N]) is not kinematic (3: boundary / obstacle).

    Raises :class:`InvalidInputError` (``particle_type``) for a non-integer or
    non-1-D array.
    """
    pt = np.asarray(particle_type)
    if pt.dtype.kind not in "iu" or pt.ndim != 1:
        raise InvalidInputError(f"particle_type: expected an integer array [N], got {pt.dtype} {list(pt.shape)}", "particle_type")
    return np.asarray(pt != GNS_KINEMATIC)


def grid_mass_error(
    pred: np.ndarray,
    ref: np.ndarray,
    n_grid: int,
    *,
    pred_weights: np.ndarray | None = None,
    ref_weights: np.ndarray | None = None,
) -> np.ndarray:
    """Grid-mass error per frame (docs/design.md "Grid-mass error"; paper Sec. 3.1.1,
    ``RMSE_m̃``).

    For every frame ``t``: ``‖m̃_pred(t) − m̃_ref(t)‖₂ / ‖m̃_ref(t)‖₂`` where
    ``m̃ = grid_mass(positions, n_grid, weights)`` is the quadratic B-spline p2g
    of particle mass onto the nodes ``i/n_grid`` of ``[0, 1]^D``, normalised to
    sum 1 (particles outside the grid land on the border nodes).

    Parameters
    ----------
    pred, ref:
        Positions [m], float [T, N_pred, D] and [T, N_ref, D] (or single
        frames [N, D]): the particle counts may differ, T and D must match.
        Drop kinematic particles first (:func:`fluid_mask`).
    n_grid:
        Cells per dimension of the reference grid, 3 … 4096, and its grid
        within the memory budget (:mod:`hybridmpm.limits`).
    pred_weights, ref_weights:
        Optional particle masses [N] (any unit, only ratios matter); by
        default every particle weighs ``1/N`` as docs/design.md specifies.

    Returns
    -------
    float64 [T]; 0 for identical frames. Raises :class:`InvalidInputError`
    naming ``pred``, ``ref``, ``n_grid``, ``pred_weights`` or ``ref_weights``.
    """
    p = checked_frames("pred", pred)
    r = checked_frames("ref", ref)
    if p.shape[2] != r.shape[2]:
        raise InvalidInputError(f"ref: dimension {r.shape[2]} differs from pred's {p.shape[2]}", "ref")
    if p.shape[0] != r.shape[0]:
        raise InvalidInputError(f"ref: has {r.shape[0]} frames but pred has {p.shape[0]}; align them first (align_frames)", "ref")
    n = checked_n_grid(n_grid)
    # two float32 grids from Rust, their float64 copies and the difference: 28 bytes per node
    check_allocation("n_grid", 28.0 * (n + 1) ** p.shape[2], f"a {n}^{p.shape[2]} grid-mass grid")
    pw = _weights("pred_weights", pred_weights, p.shape[1])
    rw = _weights("ref_weights", ref_weights, r.shape[1])
    out = np.empty(p.shape[0], dtype=np.float64)
    for t in range(p.shape[0]):
        gp = grid_mass(np.asarray(p[t], dtype=np.float32), n, pw).astype(np.float64)
        gr = grid_mass(np.asarray(r[t], dtype=np.float32), n, rw).astype(np.float64)
        # sums of squares, not np.linalg.norm: BLAS's threads on a vector of a few 10^4 nodes cost more than the sum
        # (and on a busy machine ~10x more: its spinning workers wait for a core)
        out[t] = math.sqrt(float(np.square(gp - gr).sum()) / float(np.square(gr).sum()))
    return out


def position_mse(pred: np.ndarray, ref: np.ndarray) -> np.ndarray:
    """Mean squared position error per frame (GNS, Sanchez-Gonzalez et al. 2020).

    ``mean over particles i and dims d of (pred[t, i, d] − ref[t, i, d])²`` [m²],
    float64 [T]. ``pred`` and ``ref`` are float [T, N, D] (or [N, D]) of the
    *same* shape: particle ``i`` of one must be particle ``i`` of the other
    (no correspondence exists across resolutions: use
    :func:`grid_mass_error`). Raises :class:`InvalidInputError` (``pred`` /
    ``ref``) otherwise.
    """
    p = checked_frames("pred", pred)
    r = checked_frames("ref", ref)
    if p.shape != r.shape:
        raise InvalidInputError(f"ref: shape {list(r.shape)} differs from pred's {list(p.shape)}; position MSE needs the same frames and particles", "ref")
    diff = p.astype(np.float64) - r.astype(np.float64)
    return np.asarray(np.mean(diff * diff, axis=(1, 2)), dtype=np.float64)


def rollout_summary(per_frame: Any) -> dict[str, Any]:
    """``{"mean", "last", "per_frame"}`` of a per-frame error series (1-D,
    non-empty): its mean over the rollout, its last value, and the series as a
    list of floats (JSON-serialisable)."""
    arr = np.asarray(per_frame, dtype=np.float64)
    if arr.ndim != 1 or arr.size == 0:
        raise InvalidInputError(f"per_frame: expected a non-empty 1-D series, got shape {list(arr.shape)}", "per_frame")
    return {"mean": float(arr.mean()), "last": float(arr[-1]), "per_frame": [float(v) for v in arr]}


def kinetic_energy(positions: np.ndarray, dt: float, masses: np.ndarray | None = None) -> np.ndarray:
    """Kinetic energy from finite differences, float64 [T − 1].

    Velocities ``v = (p[t+1] − p[t]) / dt`` [m/s] are those at the midpoints
    ``(t + ½)·dt`` (exact there for motion quadratic in time, e.g. free fall).

    * ``masses`` [N] [kg] given: total kinetic energy ``Σ_i ½ m_i |v_i|²`` [J]
      (in 2D the solver's masses are per unit depth, so J/m).
    * ``masses=None``: *specific* kinetic energy, ``mean_i ½ |v_i|²`` [J/kg],
      which compares across resolutions.

    ``positions`` float [T, N, D] with T >= 2, ``dt`` [s] the time between its
    frames. Raises :class:`InvalidInputError` (``positions``, ``dt``, ``masses``).
    """
    p = checked_frames("positions", positions)
    if np.ndim(positions) != 3 or p.shape[0] < 2:
        raise InvalidInputError(f"positions: need [T, N, D] with T >= 2 frames, got shape {list(np.shape(positions))}", "positions")
    h = _positive("dt", dt)
    v = np.diff(p.astype(np.float64), axis=0) / h
    e = 0.5 * np.sum(v * v, axis=2)  # [T-1, N]
    if masses is None:
        return np.asarray(e.mean(axis=1), dtype=np.float64)
    m = np.asarray(masses)
    if m.dtype.kind not in "fiu" or m.shape != (p.shape[1],) or not (np.isfinite(m) & (m >= 0)).all():
        raise InvalidInputError(f"masses: expected finite masses >= 0 of shape [{p.shape[1]}], got {m.dtype} {list(m.shape)}", "masses")
    return np.asarray(e @ m.astype(np.float64), dtype=np.float64)


def align_frames(pred_dt: float, pred_len: int, ref_dt: float, ref_len: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Frame pairs of two rollouts at their common times.

    Both rollouts start at t = 0 and store a frame every ``pred_dt`` /
    ``ref_dt`` seconds; the longer interval must be an integer multiple ``k``
    of the shorter (relative tolerance 1e-5), e.g. a neural rollout at
    ``r_t = 2`` (5 ms) against MPM frames (2.5 ms) pairs pred frames 0, 1, 2, …
    with ref frames 0, 2, 4, … . The pairs stop where either rollout ends.

    Returns ``(pred_idx, ref_idx, times)``: int64, int64 and float64 [F]
    (``times = ref_idx · ref_dt`` [s]), F >= 1 (frame 0 always pairs).
    Raises :class:`InvalidInputError` (``pred_dt``, ``ref_dt``, ``pred_len``,
    ``ref_len``) for non-positive or non-finite values, a non-integer interval
    ratio or one above :data:`MAX_INTERVAL_RATIO` (2^53), checked before any
    integer arithmetic.
    """
    pdt = _positive("pred_dt", pred_dt)
    rdt = _positive("ref_dt", ref_dt)
    for name, n in (("pred_len", pred_len), ("ref_len", ref_len)):
        if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or n < 1:
            raise InvalidInputError(f"{name}: must be an integer >= 1, got {n!r}", name)
    ratio = pdt / rdt
    big = max(ratio, 1.0 / ratio) if ratio > 0 else math.inf  # the quotient of two finite positive floats may underflow to 0 or overflow
    if not big <= MAX_INTERVAL_RATIO:  # before any integer arithmetic: a frame index times k must stay within int64
        raise InvalidInputError(
            f"pred_dt: the frame intervals {pdt:g} s (pred) and {rdt:g} s (ref) differ by a factor of {big:g}, more than {MAX_INTERVAL_RATIO:.0f} (2^53)",
            "pred_dt",
        )
    k = round(big)
    if k < 1 or abs(big - k) > _RATIO_RTOL * k:
        raise InvalidInputError(
            f"pred_dt: the frame intervals {pdt:g} s (pred) and {rdt:g} s (ref) are not integer multiples of each other (ratio {ratio:g})",
            "pred_dt",
        )
    if ratio >= 1.0:  # pred is the coarser: every pred frame i is ref frame k·i
        f = min(int(pred_len), (int(ref_len) - 1) // k + 1)
        pred_idx = np.arange(f, dtype=np.int64)
        ref_idx = pred_idx * k
    else:  # ref is the coarser: every ref frame j is pred frame k·j
        f = min(int(ref_len), (int(pred_len) - 1) // k + 1)
        ref_idx = np.arange(f, dtype=np.int64)
        pred_idx = ref_idx * k
    return pred_idx, ref_idx, ref_idx.astype(np.float64) * rdt
