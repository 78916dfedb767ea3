"""Control metrics (docs/design.md "Control metrics"; paper Table 4).

* final-shape error: grid-mass error of the controlled fluid at ``T_ctr``
  against the target positions (docs/design.md definition), and the paper's grid
  RMSE of the normalised mass;
* arrow adherence: cosine and length ratio of the centroid displacement
  against the arrow (x–y);
* oval adherence: fraction of particles inside the drawn ellipse, and the
  IoU of the occupied cells with the ellipse;
* effort: mean and max ``‖a‖/g`` of the applied control;
* smoothness: mean per-particle cosine of consecutive control accelerations.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from hybridmpm.control.sketch import Sketch
from hybridmpm.conventions import G
from hybridmpm.metrics import grid_mass_error
from hybridmpm.mpm import grid_mass


def shape_errors(end: np.ndarray, target: np.ndarray, n_grid: int) -> dict[str, float]:
    """``grid_mass_error`` (relative) and the paper's ``RMSE_m̃`` (root mean
    square over the nodes of the normalised mass difference) of ``end`` [N, D]
    against ``target`` [M, D]."""
    rel = float(grid_mass_error(end[None], target[None], n_grid)[0])
    a = np.asarray(grid_mass(np.asarray(end, np.float32), n_grid), np.float64)
    b = np.asarray(grid_mass(np.asarray(target, np.float32), n_grid), np.float64)
    return {"grid_mass_error": rel, "rmse_m": float(np.sqrt(np.mean((a - b) ** 2)))}


def arrow_adherence(start: np.ndarray, end: np.ndarray, sketch: Sketch) -> dict[str, float]:
    """Cosine and length ratio of the centroid's x–y displacement against the arrow."""
    d = np.asarray(end, np.float64)[:, :2].mean(0) - np.asarray(start, np.float64)[:, :2].mean(0)
    v = sketch.vector
    nd, nv = float(np.linalg.norm(d)), float(np.linalg.norm(v))
    cos = float(d @ v / (nd * nv)) if nd > 0 and nv > 0 else 0.0
    return {"cosine": cos, "length_ratio": nd / nv if nv > 0 else math.nan}


def oval_adherence(end: np.ndarray, sketch: Sketch, n_grid: int = 64) -> dict[str, float]:
    """Fraction of particles (x–y) inside the drawn ellipse, and the IoU of the
    ``n_grid``² cells holding a particle with the cells inside the ellipse."""
    c, r, angle = sketch.ellipse()
    rot = np.array([[math.cos(angle), -math.sin(angle)], [math.sin(angle), math.cos(angle)]])

    def inside(p: np.ndarray) -> np.ndarray:
        q = (p - c) @ rot / np.maximum(r, 1e-9)
        return (q**2).sum(-1) <= 1.0

    xy = np.asarray(end, np.float64)[:, :2]
    frac = float(inside(xy).mean())
    occ = np.zeros((n_grid, n_grid), bool)
    idx = np.clip((xy * n_grid).astype(int), 0, n_grid - 1)
    occ[idx[:, 0], idx[:, 1]] = True
    centres = (np.stack(np.meshgrid(np.arange(n_grid), np.arange(n_grid), indexing="ij"), -1) + 0.5) / n_grid
    ell = inside(centres.reshape(-1, 2)).reshape(n_grid, n_grid)
    union = (occ | ell).sum()
    return {"inside": frac, "iou": float((occ & ell).sum() / union) if union else 0.0}


class AppliedStats:
    """Effort and smoothness of a control, taken one applied field at a time
    (:meth:`add`, float [N, D] m/s²): memory of one field, whatever the number
    of frames (a list of every field, stacked in float64 at the end, was ~30×
    a control's trajectory at its peak)."""

    def __init__(self) -> None:
        self.frames = 0
        self._norm_sum = 0.0
        self._norm_count = 0
        self._norm_max = 0.0
        self._cos_sum = 0.0
        self._cos_count = 0
        self._previous: tuple[np.ndarray, np.ndarray] | None = None

    def add(self, a: np.ndarray) -> None:
        a64 = np.asarray(a, np.float64)
        n = np.linalg.norm(a64, axis=-1)
        self._norm_sum += float(n.sum())
        self._norm_count += int(n.size)
        if n.size:
            self._norm_max = max(self._norm_max, float(n.max()))
        if self._previous is not None:
            u, nu = self._previous
            ok = (nu > 0) & (n > 0)
            if ok.any():
                self._cos_sum += float(((u * a64).sum(-1)[ok] / (nu * n)[ok]).sum())
                self._cos_count += int(ok.sum())
        self._previous = (a64, n)
        self.frames += 1

    def effort(self) -> dict[str, float]:
        """Mean and max ``‖a‖/g`` over particles and frames of the applied control (0 without)."""
        if not self._norm_count:
            return {"effort_mean_g": 0.0, "effort_max_g": 0.0}
        return {"effort_mean_g": self._norm_sum / self._norm_count / G, "effort_max_g": self._norm_max / G}

    def smoothness(self) -> float:
        """Mean per-particle cosine of consecutive control accelerations (1 = steady; nan for < 2 frames)."""
        if self.frames < 2:
            return math.nan
        return self._cos_sum / self._cos_count if self._cos_count else 1.0


def effort(applied: list[np.ndarray]) -> dict[str, float]:
    """Mean and max ``‖a‖/g`` over particles and frames of the applied fields ``applied`` (0 without)."""
    st = AppliedStats()
    for a in applied:
        st.add(a)
    return st.effort()


def smoothness(applied: list[np.ndarray]) -> float:
    """Mean per-particle cosine of consecutive control accelerations (1 = steady; nan for < 2 frames)."""
    st = AppliedStats()
    for a in applied:
        st.add(a)
    return st.smoothness()


def control_metrics(start: np.ndarray, end: np.ndarray, sketch: Sketch | None, applied: AppliedStats, target: np.ndarray | None, n_grid: int) -> dict[str, Any]:
    """Every metric of one controlled episode (``start``/``end`` fluid positions
    at its first and last frame; ``applied`` the statistics of the fields it
    applied; ``target`` the positions it should reach, if known)."""
    out: dict[str, Any] = {**applied.effort(), "smoothness": applied.smoothness()}
    if target is not None:
        out.update(shape_errors(end, target, n_grid))
    if sketch is not None:
        out.update(arrow_adherence(start, end, sketch) if sketch.kind == "arrow" else oval_adherence(end, sketch))
    return out


__all__ = ["AppliedStats", "arrow_adherence", "control_metrics", "effort", "oval_adherence", "shape_errors", "smoothness"]
