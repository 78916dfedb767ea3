"""``hybridmpm evaluate``: every metric of a predicted trajectory against a
reference trajectory, as one JSON-ready dict (:func:`evaluate`)."""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from hybridmpm.conventions import DEFAULT_N_GRID, GNS_KINEMATIC
from hybridmpm.errors import InvalidInputError
from hybridmpm.limits import check_allocation
from hybridmpm.metrics.chaotic import KE_FLOOR, SHORT_HORIZON_FRAMES, json_scores, rollout_metrics
from hybridmpm.metrics.core import align_frames, checked_n_grid, grid_mass_error, position_mse, rollout_summary
from hybridmpm.metrics.transport import SINKHORN_BLUR, SINKHORN_MAX_POINTS
from hybridmpm.trajectory import Trajectory

#: What :func:`evaluate` and writing its result as JSON hold per compared frame, whatever the particles
#: [bytes]: every per-frame series as Python floats (times, grid-mass errors, position MSEs, kinetic
#: energies, the dam break's front) and their JSON text (~170 B a frame). Measured with tracemalloc at
#: 1,234–1,238 B a frame (one particle, every series present); 1.24× that.
EVALUATE_BYTES_PER_FRAME = 1536
#: What :func:`evaluate` holds per position value of a compared frame, pred's and ref's, kinematic
#: particles included [bytes]: the frames it pairs, their float64 copies and differences. Measured with
#: tracemalloc at 14–18 B a value (2,000 and 20,000 particles); 1.33× that.
EVALUATE_BYTES_PER_VALUE = 24


def evaluate_bytes(frames: int, pred_particles: int, ref_particles: int, dim: int) -> float:
    """What :func:`evaluate` of ``frames`` compared frames needs at its peak [bytes], its JSON text
    included: ``frames · (EVALUATE_BYTES_PER_FRAME + EVALUATE_BYTES_PER_VALUE · (pred_particles +
    ref_particles) · dim)`` (particles: every particle of each trajectory, kinematic ones included)."""
    return float(frames) * (EVALUATE_BYTES_PER_FRAME + EVALUATE_BYTES_PER_VALUE * (int(pred_particles) + int(ref_particles)) * int(dim))


def check_evaluate_size(frames: int, pred_particles: int, ref_particles: int, dim: int, what: str = "pred and ref") -> None:
    """Refuse a comparison of ``frames`` frames of ``pred_particles`` and ``ref_particles``
    particles in ``dim`` D whose :func:`evaluate_bytes` exceed the memory budget
    (:func:`hybridmpm.limits.check_allocation`), before any frame is compared: raises
    :class:`InvalidInputError` naming ``frames`` (``what`` names the trajectories in the message)."""
    check_allocation(
        "frames",
        evaluate_bytes(frames, pred_particles, ref_particles, dim),
        f"comparing {frames} frames of {what} ({pred_particles} and {ref_particles} particles) and writing their metrics",
    )


def _finite(x: float) -> float | None:
    """``x``, or None where it is NaN or infinite (JSON has no NaN)."""
    return float(x) if math.isfinite(x) else None


def evaluate(pred: Trajectory, ref: Trajectory, n_grid: int | None = None, *, dam_break: dict[str, float] | None = None) -> dict[str, Any]:
    """Every metric of a predicted rollout against a reference rollout.

    Frames are paired with :func:`align_frames` (times that both store,
    frame 0 included); kinematic particles (GNS type 3) are dropped from both.

    * ``grid_mass_error``: :func:`rollout_summary` of :func:`grid_mass_error`
      with uniform particle weights (1/N, docs/design.md) on the grid ``n_grid`` (argument, else
      ``ref.n_grid``, else 128 in 2D / 64 in 3D).
    * ``grid_mass_error_mass_weighted``: the same with each particle's own mass
      (when both trajectories store positive ``masses``), else ``None``; it
      differs from the 1/N definition for unequal masses (k-means clusters).
    * ``position_mse_rollout``: summary of :func:`position_mse` when both have
      the same number of fluid particles (particle ``i`` assumed to be the same
      particle in both), else ``None`` and ``position_mse_rollout_reason`` says
      why.
    * ``position_mse_one_step``: the same for ``pred.extras["one_step_positions"]``
      (float [T_pred, N_pred, D], frame ``t`` predicted from ground-truth
      history); frames holding non-finite values (e.g. NaN for history frames
      with no prediction) are skipped and ``times`` lists those kept. ``None``
      with a reason when absent.
    * ``kinetic_energy``: specific kinetic energy [J/kg] of both
      (:func:`kinetic_energy` over the paired frames, velocities over the
      common frame interval) at the midpoint ``times``.
    * the scores of a chaotic flow (:func:`~hybridmpm.metrics.chaotic.rollout_metrics`
      over the paired frames): ``short_horizon_error`` (``mean`` over the first
      50 frames), ``sinkhorn_divergence`` (``mean`` [m²], ``per_frame`` at
      ``times``, with each particle's mass when both store positive masses),
      ``kinetic_energy_error`` (``mean``), ``dam_break_front`` (``rms``
      against Martin & Moyce, the predicted ``front``; None unless
      ``dam_break``, the scene's geometry from
      :func:`~hybridmpm.metrics.chaotic.dam_break_geometry`, is given),
      ``metrics`` (every :data:`~hybridmpm.metrics.chaotic.ROLLOUT_METRICS`
      score, None where undefined) and ``metric_seconds`` (their cost).
    * counts: ``frames_compared``, ``times`` [s], and for ``pred`` and ``ref``
      their ``frames``, ``dt_frame`` [s], fluid ``particles`` and
      ``kinematic_particles``; ``n_grid`` and ``dim``.

    The result holds only str, int, float, list, dict and None (JSON-ready).
    Before any frame is compared, the work is sized against the memory budget
    (:func:`check_evaluate_size`: the paired frames times
    :func:`evaluate_bytes`' cost per frame and per position value).
    Raises :class:`InvalidInputError` for mismatched dimensions, a
    non-integer frame-interval ratio (or one above 2^53), a bad ``n_grid``,
    ``frames`` for a comparison beyond the memory budget, no fluid particles or
    a malformed ``one_step_positions``.
    """
    for name, tr in (("pred", pred), ("ref", ref)):
        if not isinstance(tr, Trajectory):
            raise InvalidInputError(f"{name}: expected a Trajectory, got {type(tr).__name__}", name)
    if pred.dim != ref.dim:
        raise InvalidInputError(f"ref: dimension {ref.dim} differs from pred's {pred.dim}", "ref")
    n = checked_n_grid(n_grid if n_grid is not None else ref.n_grid if ref.n_grid is not None else DEFAULT_N_GRID[ref.dim])
    pi, ri, times = align_frames(pred.dt_frame, pred.num_frames, ref.dt_frame, ref.num_frames)
    check_evaluate_size(len(pi), pred.positions.shape[1], ref.positions.shape[1], ref.dim)
    pm, rm = pred.fluid_mask(), ref.fluid_mask()
    for name, mask in (("pred", pm), ("ref", rm)):
        if not mask.any():
            raise InvalidInputError(f"{name}.particle_type: no fluid particles (all are kinematic, type {GNS_KINEMATIC})", f"{name}.particle_type")
    pp = pred.positions[pi][:, pm]
    rp = ref.positions[ri][:, rm]
    n_pred, n_ref = int(pm.sum()), int(rm.sum())
    gme = grid_mass_error(pp, rp, n)

    result: dict[str, Any] = {
        "n_grid": n,
        "dim": ref.dim,
        "frames_compared": len(pi),
        "times": [float(t) for t in times],
        "pred": {"frames": pred.num_frames, "dt_frame": pred.dt_frame, "particles": n_pred, "kinematic_particles": int((~pm).sum())},
        "ref": {"frames": ref.num_frames, "dt_frame": ref.dt_frame, "particles": n_ref, "kinematic_particles": int((~rm).sum())},
        "grid_mass_error": rollout_summary(gme),
        "grid_mass_error_mass_weighted": None,
    }
    if pred.masses is not None and ref.masses is not None and np.all(pred.masses[pm] > 0) and np.all(ref.masses[rm] > 0):
        # the same error with each particle splatting its own mass: differs from the
        # 1/N definition when particles carry unequal masses (k-means clusters, r_p < 1)
        result["grid_mass_error_mass_weighted"] = rollout_summary(grid_mass_error(pp, rp, n, pred_weights=pred.masses[pm], ref_weights=ref.masses[rm]))

    mismatch = f"fluid particle counts differ (pred {n_pred}, ref {n_ref}): no particle correspondence, use grid_mass_error"
    if n_pred == n_ref:
        result["position_mse_rollout"] = rollout_summary(position_mse(pp, rp))
        result["position_mse_rollout_reason"] = None
    else:
        result["position_mse_rollout"] = None
        result["position_mse_rollout_reason"] = mismatch

    one_step = pred.extras.get("one_step_positions")
    result["position_mse_one_step"] = None
    if one_step is None:
        result["position_mse_one_step_reason"] = "pred has no one_step_positions array"
    else:
        field = "extras.one_step_positions"
        arr = np.asarray(one_step)
        if arr.dtype.kind != "f" or arr.shape != pred.positions.shape:
            raise InvalidInputError(
                f"{field}: expected a float array shaped like pred.positions {list(pred.positions.shape)}, got {arr.dtype} {list(arr.shape)}", field
            )
        if n_pred != n_ref:
            result["position_mse_one_step_reason"] = mismatch
        else:
            os_ = arr[pi][:, pm]
            keep = np.isfinite(os_).all(axis=(1, 2))
            if not keep.any():
                result["position_mse_one_step_reason"] = "one_step_positions has no finite frame at the compared times"
            else:
                summary = rollout_summary(position_mse(os_[keep], rp[keep]))
                summary["times"] = [float(t) for t in times[keep]]
                result["position_mse_one_step"] = summary
                result["position_mse_one_step_reason"] = None

    weights = None, None
    if pred.masses is not None and ref.masses is not None and np.all(pred.masses[pm] > 0) and np.all(ref.masses[rm] > 0):
        weights = pred.masses[pm], ref.masses[rm]
    m = rollout_metrics(pp, rp, times, n, errors=gme, pred_weights=weights[0], ref_weights=weights[1], dam_break=dam_break)
    s = m["series"]
    result["kinetic_energy"] = {"units": "J/kg", "times": s["ke_times"], "pred": s["ke_pred"], "ref": s["ke_ref"]}
    result["short_horizon_error"] = {"mean": _finite(m["short_error"]), "frames": SHORT_HORIZON_FRAMES}
    result["sinkhorn_divergence"] = {
        "mean": _finite(m["sinkhorn"]), "units": "m²", "times": s["sinkhorn_times"], "per_frame": s["sinkhorn"],
        "blur": SINKHORN_BLUR, "max_points": SINKHORN_MAX_POINTS, "mass_weighted": weights[0] is not None,
    }  # fmt: skip
    result["kinetic_energy_error"] = {"mean": _finite(m["ke_error"]), "floor": KE_FLOOR}
    result["dam_break_front"] = None
    if dam_break is not None:
        result["dam_break_front"] = {"rms": _finite(m["front_rms"]), "front": s["front"], "reason": s["front_reason"], "geometry": dict(dam_break)}
    result["metrics"] = json_scores(m)
    result["metric_seconds"] = m["seconds"]
    return result
