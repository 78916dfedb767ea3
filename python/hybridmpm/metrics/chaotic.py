"""Scores of a whole rollout that stay fair on a chaotic flow.

Water is chaotic: a 1 µm change of its initial state moves full-resolution MPM
by a grid-mass error of ~0.24 over 400 frames, about half of what MPM at
``r_p`` scores, so a long-horizon pointwise error on water mostly measures
chaos (docs/benchmarks.md "Metrics for a chaotic flow"). Beside the
long-horizon grid-mass error (right for sand, which is deterministic), a
rollout is scored as LagrangeBench scores particle rollouts (Toshev et al.
2023, arXiv 2309.16342): over a short horizon, by the distribution of matter
and by its kinetic energy; the dam break also by its surge front against the
experiment (Martin & Moyce 1952). :func:`rollout_metrics` computes them all,
for ``hybridmpm bench``, ``hybridmpm evaluate`` and ``simulate --reference``:

* ``error_mean`` / ``error_last``: the grid-mass error
  (:func:`~hybridmpm.metrics.grid_mass_error`) mean over the frames and at the
  last one — the long-horizon error.
* ``short_error``: the same error's mean over the first
  :data:`SHORT_HORIZON_FRAMES` frames (:func:`short_horizon_error`).
* ``sinkhorn``: the debiased Sinkhorn divergence [m²] between the
  mass-weighted particle sets, mean over :data:`~hybridmpm.metrics.transport.SINKHORN_FRAMES`
  evenly spaced frames (:mod:`hybridmpm.metrics.transport`).
* ``ke_error``: the kinetic energy's relative error (:func:`kinetic_energy_error`).
* ``front_rms``: the dam break's surge front against Martin & Moyce
  (:func:`dam_break_front`); NaN for other scenes.
"""

from __future__ import annotations

import math
import time
from typing import Any

import numpy as np

from hybridmpm.conventions import DT_FRAME, G
from hybridmpm.errors import InvalidInputError
from hybridmpm.metrics.core import checked_frames, grid_mass_error, kinetic_energy
from hybridmpm.metrics.transport import sinkhorn_frames, sinkhorn_series
from hybridmpm.validation import dam_break_front_height, load_martin_moyce, score_dam_break

#: The short horizon [frames of DT_FRAME = 2.5 ms]: 0.125 s, over which a flow has not yet forgotten its start.
SHORT_HORIZON_FRAMES = 50
#: A frame whose reference kinetic energy is below this fraction of the reference's peak counts relative to that
#: fraction of the peak (:func:`kinetic_energy_error`): a flow at rest has no relative error to speak of.
KE_FLOOR = 0.05
#: The dam break's geometry that :func:`dam_break_front` needs (the scene's ``info``).
DAM_BREAK_KEYS = ("a", "x_wall", "y_floor", "spacing")
#: The experiment's last front point that the score uses (T = t·sqrt(2g/a), :func:`~hybridmpm.validation.score_dam_break`).
_FRONT_T_MAX = 3.33

#: The scores of a rollout (what ``bench`` records per configuration, draws a front for and ``tune --metric`` chooses
#: on): key -> what it is (the charts' axis label).
ROLLOUT_METRICS = {
    "error_mean": "grid-mass error (mean over the rollout)",
    "error_last": "grid-mass error (last frame)",
    "short_error": f"grid-mass error (mean over the first {SHORT_HORIZON_FRAMES} frames)",
    "sinkhorn": "Sinkhorn divergence [m²] (mean over sampled frames)",
    "ke_error": "kinetic energy's relative error (mean over frames)",
    "front_rms": "dam-break front against Martin & Moyce (RMS of x/a, best shift)",
}


def json_scores(scores: dict[str, Any]) -> dict[str, float | None]:
    """The :data:`ROLLOUT_METRICS` scores of :func:`rollout_metrics`' result as
    JSON: floats, None where undefined (JSON has no NaN)."""
    return {k: float(scores[k]) if math.isfinite(scores[k]) else None for k in ROLLOUT_METRICS}


def _times(name: str, times: Any, n: int) -> np.ndarray:
    t = np.asarray(times, dtype=np.float64)
    if t.shape != (n,) or not np.isfinite(t).all() or (n > 1 and not (np.diff(t) > 0).all()):
        raise InvalidInputError(f"{name}: expected {n} finite, increasing times [s], got shape {list(t.shape)}", name)
    return t


def short_horizon_error(per_frame: Any, times: Any, horizon: int = SHORT_HORIZON_FRAMES) -> float:
    """Mean of a per-frame error (float [F]) over the frames at times (float [F],
    [s] from the start) in ``(0, horizon·DT_FRAME]``: the first ``horizon``
    frames the solver made (the start, shared by both rollouts, is not one
    of them). NaN when no frame lies there. Raises :class:`InvalidInputError`
    (``per_frame``, ``times``)."""
    e = np.asarray(per_frame, dtype=np.float64)
    if e.ndim != 1 or e.size == 0:
        raise InvalidInputError(f"per_frame: expected a non-empty 1-D series, got shape {list(e.shape)}", "per_frame")
    t = _times("times", times, len(e))
    keep = (t > 0.5 * DT_FRAME) & (t <= (horizon + 0.5) * DT_FRAME)
    return float(e[keep].mean()) if keep.any() else float("nan")


def kinetic_energy_error(pred: Any, ref: Any, times: Any) -> tuple[float, np.ndarray, np.ndarray]:
    """The kinetic energy's relative error of ``pred`` against ``ref``.

    ``pred`` float [F, N, D] and ``ref`` float [F, M, D] [m] at the same
    ``times`` (float [F], evenly spaced [s]); velocities by finite differences
    between those frames (:func:`~hybridmpm.metrics.kinetic_energy`), every
    particle of mass ``1/N`` (specific energy [J/kg], so particle counts
    compare). Returns ``(mean_t |KE_pred(t) − KE_ref(t)| / max(KE_ref(t),
    KE_FLOOR·max KE_ref), KE_pred [F − 1], KE_ref [F − 1])``; the error is NaN
    with fewer than 2 frames or a reference that never moves. Raises
    :class:`InvalidInputError` (``pred``, ``ref``, ``times``).
    """
    p, r = checked_frames("pred", pred), checked_frames("ref", ref)
    if p.shape[0] != r.shape[0]:
        raise InvalidInputError(f"ref: has {r.shape[0]} frames but pred has {p.shape[0]}", "ref")
    t = _times("times", times, p.shape[0])
    if len(t) < 2:
        return float("nan"), np.zeros(0), np.zeros(0)
    dt = np.diff(t)
    if not np.allclose(dt, dt[0], rtol=1e-6):
        raise InvalidInputError("times: the frames must be evenly spaced (finite differences over one interval)", "times")
    kp, kr = kinetic_energy(p, float(dt[0])), kinetic_energy(r, float(dt[0]))
    peak = float(kr.max())
    if not peak > 0:
        return float("nan"), kp, kr
    return float(np.mean(np.abs(kp - kr) / np.maximum(kr, KE_FLOOR * peak))), kp, kr


def dam_break_geometry(info: Any) -> dict[str, float] | None:
    """The dam break's geometry (:data:`DAM_BREAK_KEYS` [m]) from a scene's
    ``info``, or None for a scene that is not a dam break."""
    if not isinstance(info, dict) or not all(k in info for k in DAM_BREAK_KEYS):
        return None
    return {k: float(info[k]) for k in DAM_BREAK_KEYS}


def dam_break_front(positions: Any, times: Any, geometry: dict[str, float]) -> dict[str, Any]:
    """The surge front over time against Martin & Moyce (1952).

    ``positions`` float [F, N, D] [m] of the water at ``times`` (float [F],
    [s] since the release); ``geometry`` the scene's :data:`DAM_BREAK_KEYS`
    (:func:`dam_break_geometry`). The front is
    :func:`~hybridmpm.validation.dam_break_front_height`'s (``Z = x_front/a``),
    its score :func:`~hybridmpm.validation.score_dam_break`'s: the RMS of
    ``Z_sim(T − dT) − Z_exp(T)`` over the experiment's points
    ``1.19 <= T <= 3.33`` (``T = t·sqrt(2g/a)``) at the best shift
    ``dT ∈ [0, 0.5]``. Returns ``{"rms", "shift", "front", "reason"}``:
    ``rms`` None (and ``reason`` why) when the rollout ends before ``T = 3.33``.
    """
    x = checked_frames("positions", positions)
    t = _times("times", times, x.shape[0])
    a = float(geometry["a"])
    z, h = dam_break_front_height(x, a, geometry["x_wall"], geometry["y_floor"], geometry["spacing"])
    out: dict[str, Any] = {"rms": None, "shift": None, "front": [float(v) for v in z], "reason": None}
    t_max = float(t[-1]) * math.sqrt(2.0 * G / a)
    if t_max < _FRONT_T_MAX:
        out["reason"] = f"the rollout ends at T = {t_max:.2f}, before the experiment's T = {_FRONT_T_MAX} (T = t·sqrt(2g/a))"
        return out
    score = score_dam_break(t, z, h, a, load_martin_moyce())
    out["rms"], out["shift"] = float(score.rms_front_shifted), float(score.best_shift)
    return out


def rollout_metrics(
    pred: Any,
    ref: Any,
    times: Any,
    n_grid: int,
    *,
    errors: Any = None,
    pred_weights: Any = None,
    ref_weights: Any = None,
    dam_break: dict[str, float] | None = None,
) -> dict[str, Any]:
    """Every score of :data:`ROLLOUT_METRICS` for a rollout against its reference.

    ``pred`` float [F, N, D] and ``ref`` float [F, M, D]: positions [m] of the
    fluid particles at the same ``times`` (float [F], evenly spaced [s] from the
    common start; the frames every compared method stores); ``n_grid`` the grid
    of the grid-mass error; ``errors`` that error per frame (float [F]) when
    the caller has it already; ``pred_weights`` / ``ref_weights`` the particle
    masses [N] / [M] of the Sinkhorn divergence (default equal); ``dam_break``
    the scene's :func:`dam_break_geometry` (None: ``front_rms`` is NaN).

    Returns the scores (floats; NaN where undefined), ``series`` (per-frame
    values: ``sinkhorn_times`` [s] and ``sinkhorn`` [m²], ``ke_times`` [s],
    ``ke_pred`` and ``ke_ref`` [J/kg], ``front`` (pred's ``x_front/a``) and
    ``front_reason`` for the dam break) and ``seconds``: the wall time of
    each metric. Raises :class:`InvalidInputError` naming the bad argument.
    """
    p, r = checked_frames("pred", pred), checked_frames("ref", ref)
    if p.shape[0] != r.shape[0]:
        raise InvalidInputError(f"ref: has {r.shape[0]} frames but pred has {p.shape[0]}", "ref")
    t = _times("times", times, p.shape[0])
    seconds: dict[str, float] = {}
    t0 = time.perf_counter()
    err = grid_mass_error(p, r, n_grid) if errors is None else np.asarray(errors, dtype=np.float64)
    if err.shape != (p.shape[0],):
        raise InvalidInputError(f"errors: expected {p.shape[0]} values, got shape {list(err.shape)}", "errors")
    seconds["grid_mass"] = time.perf_counter() - t0 if errors is None else 0.0
    t0 = time.perf_counter()
    sel = sinkhorn_frames(np.round(t / DT_FRAME).astype(np.int64))
    sk = sinkhorn_series(p[sel], r[sel], pred_weights, ref_weights) if len(sel) else np.zeros(0)
    seconds["sinkhorn"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    ke, kp, kr = kinetic_energy_error(p, r, t)
    seconds["kinetic_energy"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    front = dam_break_front(p, t, dam_break) if dam_break is not None else None
    seconds["front"] = time.perf_counter() - t0
    series: dict[str, Any] = {
        "sinkhorn_times": [float(v) for v in t[sel]],
        "sinkhorn": [float(v) for v in sk],
        "ke_times": [float(v) for v in 0.5 * (t[:-1] + t[1:])],
        "ke_pred": [float(v) for v in kp],
        "ke_ref": [float(v) for v in kr],
    }
    if front is not None:
        series["front"], series["front_reason"] = front["front"], front["reason"]
    return {
        "error_mean": float(err.mean()),
        "error_last": float(err[-1]),
        "short_error": short_horizon_error(err, t),
        "sinkhorn": float(sk.mean()) if len(sk) else float("nan"),
        "ke_error": ke,
        "front_rms": float(front["rms"]) if front is not None and front["rms"] is not None else float("nan"),
        "series": series,
        "seconds": seconds,
    }
