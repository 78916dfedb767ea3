"""Validation against published experiments.

* Water: the dam break of Martin & Moyce (1952), Phil. Trans. R. Soc. Lond. A
  244, 312–324, doi:10.1098/rsta.1952.0006, Table 2 (shipped as
  ``hybridmpm/data/martin_moyce_1952.csv`` with its tolerances).
* Sand: the collapse of a two-dimensional granular column, Lube, Huppert,
  Sparks & Freundt (2005), Phys. Rev. E 72, 041301: runout
  ``(L∞ − L0)/L0 ≈ 1.2·a`` for aspect ratio ``a = H0/L0 ≲ 1.8–2.3`` and final
  height ``H∞ = H0`` for ``a ≲ 1.15``.
"""

from __future__ import annotations

import csv
from dataclasses import dataclass
from importlib import resources

import numpy as np

from hybridmpm.conventions import G


@dataclass
class Experiment:
    """Martin & Moyce (1952) data: surge front ``Z(T)`` with ``T = t·sqrt(2g/a)``
    and column height ``H(T)`` with ``T = t·sqrt(g/a)``."""

    front_T: np.ndarray
    front_Z: np.ndarray
    height_T: np.ndarray
    height_H: np.ndarray


def load_martin_moyce() -> Experiment:
    """Read the shipped Martin & Moyce (1952) table."""
    text = resources.files("hybridmpm.data").joinpath("martin_moyce_1952.csv").read_text()
    rows = [r for r in csv.reader(line for line in text.splitlines() if line and not line.startswith("#"))]
    rows = rows[1:]  # header
    f = [(float(t), float(v)) for k, t, v in rows if k == "front"]
    h = [(float(t), float(v)) for k, t, v in rows if k == "height"]
    return Experiment(np.array([t for t, _ in f]), np.array([v for _, v in f]), np.array([t for t, _ in h]), np.array([v for _, v in h]))


def dam_break_front_height(positions: np.ndarray, a: float, x_wall: float, y_floor: float, spacing: float) -> tuple[np.ndarray, np.ndarray]:
    """Surge front ``Z = x_front/a`` and back-wall height ``H = h/(2a)`` per frame.

    ``positions`` [T, N, 2]. The front is the largest particle x (plus half a
    particle spacing, the extent of a particle's volume) measured from the
    wall's inner face; the height is the largest y among particles within
    two particle spacings of that face, from the floor's inner face.
    """
    x = positions[..., 0]
    y = positions[..., 1]
    front = (x.max(axis=1) + 0.5 * spacing - x_wall) / a
    near = x < x_wall + 2.0 * spacing
    h = np.where(near, y, -np.inf).max(axis=1) + 0.5 * spacing - y_floor
    return front, h / (2.0 * a)


@dataclass
class DamBreakScore:
    best_shift: float
    rms_front_shifted: float
    ratio_min: float
    ratio_max: float
    shallow_water_ok: bool
    height_ratio_min: float
    height_ratio_max: float

    def passes(self) -> bool:
        """The tolerances stated in the data file's header."""
        return (
            self.rms_front_shifted <= 0.12
            and 0.90 <= self.ratio_min
            and self.ratio_max <= 1.32
            and self.shallow_water_ok
            and 0.85 <= self.height_ratio_min
            and self.height_ratio_max <= 1.25
        )


def score_dam_break(times: np.ndarray, front_Z: np.ndarray, height_H: np.ndarray, a: float, exp: Experiment | None = None) -> DamBreakScore:
    """Compare a simulated dam break with Martin & Moyce (1952).

    ``times`` [T] seconds; ``front_Z``, ``height_H`` from
    :func:`dam_break_front_height`. Criteria (from the data file):
    (1) min over a time shift dT ∈ [0, 0.5] of RMS(Z_sim(T − dT) − Z_exp(T)) on
    1.19 ≤ T ≤ 3.33; (2) unshifted 0.90 ≤ Z_sim/Z_exp ≤ 1.32 at every point and
    Z_sim < 1 + 2T (shallow-water bound); (3) 0.85 ≤ H_sim/H_exp ≤ 1.25 on
    0.5 ≤ T ≤ 2.2.
    """
    exp = exp or load_martin_moyce()
    t_front = times * np.sqrt(2 * G / a)
    t_height = times * np.sqrt(G / a)
    sel = (exp.front_T >= 1.19) & (exp.front_T <= 3.33)
    best = (np.inf, 0.0)
    for shift in np.linspace(0.0, 0.5, 51):
        z = np.interp(exp.front_T[sel] - shift, t_front, front_Z)
        rms = float(np.sqrt(np.mean((z - exp.front_Z[sel]) ** 2)))
        if rms < best[0]:
            best = (rms, float(shift))
    z0 = np.interp(exp.front_T, t_front, front_Z)
    ratio = z0 / exp.front_Z
    shallow_ok = bool(np.all(front_Z[t_front > 0] < 1.0 + 2.0 * t_front[t_front > 0]))
    hs = (exp.height_T >= 0.5) & (exp.height_T <= 2.2)
    hr = np.interp(exp.height_T[hs], t_height, height_H) / exp.height_H[hs]
    return DamBreakScore(best[1], best[0], float(ratio.min()), float(ratio.max()), shallow_ok, float(hr.min()), float(hr.max()))


def granular_column_profile(positions: np.ndarray, x_wall: float, y_floor: float, spacing: float) -> tuple[float, float]:
    """Runout length and maximum height of a deposit [m], measured from the wall
    and floor inner faces (``positions`` [N, 2])."""
    length = float(positions[:, 0].max() + 0.5 * spacing - x_wall)
    height = float(positions[:, 1].max() + 0.5 * spacing - y_floor)
    return length, height


__all__ = [
    "DamBreakScore",
    "Experiment",
    "dam_break_front_height",
    "granular_column_profile",
    "load_martin_moyce",
    "score_dam_break",
]


def surface_slope_deg(positions: np.ndarray, y_floor: float, spacing: float, lo: float = 0.2, hi: float = 0.8) -> float:
    """Mean slope angle [°] of a deposit's free surface (``positions`` [N, 2]).

    The surface height ``h(x)`` is the top particle of each column of width
    one particle spacing; the slope is a least-squares line through the
    columns whose height lies between ``lo`` and ``hi`` of the maximum height
    (the flank of the pile, away from its flat top and thin toe).
    """
    x = positions[:, 0]
    y = positions[:, 1] + 0.5 * spacing - y_floor
    bins = np.floor((x - x.min()) / spacing).astype(int)
    h = np.full(bins.max() + 1, -np.inf)
    np.maximum.at(h, bins, y)
    xc = x.min() + (np.arange(len(h)) + 0.5) * spacing
    ok = np.isfinite(h) & (h > lo * h.max()) & (h < hi * h.max())
    if ok.sum() < 3:
        return 0.0
    slope = np.polyfit(xc[ok], h[ok], 1)[0]
    return float(np.degrees(np.arctan(abs(slope))))
