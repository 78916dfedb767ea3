"""Control metrics (docs/design.md "Control metrics"; paper Table 4).

* final-shape error: grid-mass error of the controlled fluid at ``T_ctr``
  against the target positions (docs/design.md definition), and the paper's grid
  RMSE of the normalised mass;
* arrow adherence: cosine and length ratio of the centroid displacement
  against the arrow (x–y);
* oval adherence: fraction of particles inside the drawn ellipse, and the
  IoU of the occupied cells with the ellipse;
* effort: mean and max ``‖a‖/g`` of the applied control;
* smoothness: mean per-particle cosine of consecutive control accelerations;
* a user's sketch (``benchmarks/bench_control_user.py``): the centroid's
  lateral deviation from an arrow's line over the whole path
  (:func:`lateral_deviation`), the share of the fluid's mass an arrow carries
  (:func:`mass_carried`), and how far fluid away from the sketch is pushed
  off its free motion (:func:`off_sketch_disturbance`).
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


def lateral_deviation(centroids: np.ndarray, sketch: Sketch) -> dict[str, float]:
    """How far the fluid's centroid strays sideways from an arrow on its way:
    ``centroids`` float [F, ≥2] the (mass-weighted) centroid at every frame
    (row 0 where the arrow starts from: an arrow is a displacement, so its line
    is ``centroids[0] + s·vector``); the perpendicular distance [m] (x–y) of
    each row from that line, its max and mean over the frames, and the max over
    the arrow's length (``lateral_max_rel``). Raises :class:`ValueError` for an
    oval or a zero-length arrow."""
    if sketch.kind != "arrow":
        raise ValueError("lateral_deviation: needs an arrow")
    v = np.asarray(sketch.vector, np.float64)
    nv = float(np.linalg.norm(v))
    if nv == 0.0:
        raise ValueError("lateral_deviation: zero-length arrow")
    c = np.asarray(centroids, np.float64)[:, :2]
    rel = c - c[0]
    perp = np.abs(rel[:, 0] * v[1] - rel[:, 1] * v[0]) / nv
    return {"lateral_max_m": float(perp.max()), "lateral_mean_m": float(perp.mean()), "lateral_max_rel": float(perp.max() / nv)}


def mass_carried(start: np.ndarray, end: np.ndarray, masses: np.ndarray, sketch: Sketch, share: float = 0.5) -> float:
    """Share of the fluid's mass an arrow carries: the mass of the particles
    (``start``/``end`` float [N, D] m, ``masses`` [N] kg) whose own x–y
    displacement along the arrow is at least ``share`` of its length, over
    the total mass. Raises :class:`ValueError` for an oval."""
    if sketch.kind != "arrow":
        raise ValueError("mass_carried: needs an arrow")
    v = np.asarray(sketch.vector, np.float64)
    nv2 = float(v @ v)
    along = (np.asarray(end, np.float64)[:, :2] - np.asarray(start, np.float64)[:, :2]) @ v / max(nv2, 1e-300)
    m = np.asarray(masses, np.float64)
    return float(m[along >= share].sum() / m.sum()) if m.sum() > 0 else 0.0


def sketch_distance(points: np.ndarray, sketch: Sketch) -> np.ndarray:
    """Distance [m] (x–y) of each of ``points`` float [N, ≥2] to what a sketch
    covers: an arrow's segment (from its first to its last point), or an oval's
    filled ellipse (0 inside; outside, the distance to the nearest of 256
    points on its outline). float64 [N]."""
    xy = np.asarray(points, np.float64)[:, :2]
    if sketch.kind == "arrow":
        a, b = sketch.points[0], sketch.points[-1]
        ab = b - a
        s = np.clip((xy - a) @ ab / max(float(ab @ ab), 1e-300), 0.0, 1.0)
        return np.linalg.norm(xy - (a + s[:, None] * ab), axis=-1)
    c, r, angle = sketch.ellipse()
    rot = np.array([[math.cos(angle), -math.sin(angle)], [math.sin(angle), math.cos(angle)]])
    q = (xy - c) @ rot / np.maximum(r, 1e-9)
    inside = (q**2).sum(-1) <= 1.0
    t = np.linspace(0.0, 2 * math.pi, 256, endpoint=False)
    outline = c + (np.stack([r[0] * np.cos(t), r[1] * np.sin(t)], -1)) @ rot.T
    d = np.sqrt(((xy[:, None, :] - outline[None]) ** 2).sum(-1)).min(1)
    return np.where(inside, 0.0, d)


def off_sketch_disturbance(start: np.ndarray, end: np.ndarray, free_end: np.ndarray, sketch: Sketch, radius: float = 0.1) -> dict[str, float]:
    """How far the control pushes fluid away from the sketch off its free
    motion: for the particles whose start position (``start`` float [N, D] m)
    lies farther than ``radius`` m from the sketch (:func:`sketch_distance`),
    the mean and max distance [m] between their end position under control
    (``end``) and without it (``free_end``, the same start run with no
    control). ``off_sketch_share`` the share of particles counted; the means
    are nan when there are none."""
    far = sketch_distance(start, sketch) > radius
    if not far.any():
        return {"off_sketch_share": 0.0, "off_sketch_mean_m": math.nan, "off_sketch_max_m": math.nan}
    gap = np.linalg.norm(np.asarray(end, np.float64)[far] - np.asarray(free_end, np.float64)[far], axis=-1)
    return {"off_sketch_share": float(far.mean()), "off_sketch_mean_m": float(gap.mean()), "off_sketch_max_m": float(gap.max())}


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


__all__ = [
    "AppliedStats",
    "arrow_adherence",
    "control_metrics",
    "effort",
    "lateral_deviation",
    "mass_carried",
    "off_sketch_disturbance",
    "oval_adherence",
    "shape_errors",
    "sketch_distance",
    "smoothness",
]
