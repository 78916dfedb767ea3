"""Accuracy metrics of a rollout against a reference rollout.

* :func:`grid_mass_error` — the accuracy metric across resolutions (docs/design.md
  "Definitions: Grid-mass error"; paper Sec. 3.1.1, ``RMSE_m̃``): each frame's
  particle mass is splatted to one grid with quadratic B-spline weights and
  normalised to sum 1 (``m̃``, :func:`hybridmpm.grid_mass`); the error at a
  frame is ``‖m̃_pred − m̃_ref‖₂ / ‖m̃_ref‖₂``. It needs no particle
  correspondence, so a prediction with fewer particles (spatial reduction
  ``r_p``) can be compared with full-resolution MPM.
* :func:`position_mse` — the particle-level metric of GNS (Sanchez-Gonzalez et
  al. 2020, "Learning to simulate complex physics with graph networks"): mean
  squared position error, reported one-step (each prediction made from
  ground-truth history) and over a rollout (:func:`rollout_summary`).
* :func:`kinetic_energy` — a physical sanity series from finite differences.
* :func:`rollout_metrics` — the scores of a whole rollout that stay fair on a
  chaotic flow (:mod:`hybridmpm.metrics.chaotic`; :data:`ROLLOUT_METRICS`):
  the long-horizon grid-mass error, its mean over the first 50 frames
  (:func:`short_horizon_error`), the Sinkhorn divergence between the
  mass-weighted particle sets (:func:`sinkhorn_divergence`, POT, NumPy only:
  :mod:`hybridmpm.metrics.transport`), the kinetic energy's relative error
  (:func:`kinetic_energy_error`) and the dam break's surge front against
  Martin & Moyce (:func:`dam_break_front`).
* :func:`align_frames` — pairs the frames of two rollouts stored at different
  frame intervals (temporal reduction ``r_t``).
* :func:`evaluate` — all of the above for two :class:`~hybridmpm.trajectory.Trajectory`
  objects, as a JSON-serialisable dict (what ``hybridmpm evaluate`` writes).

Kinematic (boundary / obstacle, GNS type 3) particles never count: they are
dropped with :func:`fluid_mask` before any metric. Every function raises
:class:`~hybridmpm.errors.InvalidInputError` naming the bad argument.
"""

from __future__ import annotations

from hybridmpm.conventions import DEFAULT_N_GRID
from hybridmpm.metrics.chaotic import (
    KE_FLOOR,
    ROLLOUT_METRICS,
    SHORT_HORIZON_FRAMES,
    dam_break_front,
    dam_break_geometry,
    json_scores,
    kinetic_energy_error,
    rollout_metrics,
    short_horizon_error,
)
from hybridmpm.metrics.compare import check_evaluate_size, evaluate, evaluate_bytes
from hybridmpm.metrics.core import align_frames, fluid_mask, grid_mass_error, kinetic_energy, position_mse, rollout_summary
from hybridmpm.metrics.transport import (
    SINKHORN_BLUR,
    SINKHORN_FRAMES,
    SINKHORN_MAX_POINTS,
    bin_width,
    binned_set,
    sinkhorn_divergence,
    sinkhorn_frames,
    sinkhorn_series,
)

__all__ = [
    "DEFAULT_N_GRID", "KE_FLOOR", "ROLLOUT_METRICS", "SHORT_HORIZON_FRAMES", "SINKHORN_BLUR", "SINKHORN_FRAMES", "SINKHORN_MAX_POINTS",
    "align_frames", "bin_width", "binned_set", "check_evaluate_size", "dam_break_front", "dam_break_geometry", "evaluate", "evaluate_bytes", "fluid_mask", "grid_mass_error", "json_scores", "kinetic_energy",
    "kinetic_energy_error", "position_mse", "rollout_metrics", "rollout_summary", "short_horizon_error", "sinkhorn_divergence",
    "sinkhorn_frames", "sinkhorn_series",
]  # fmt: skip
