"""The fluid-complexity safeguard ``s(t)`` (docs/design.md "Safeguard"; paper Sec. 3.1.2).

With ``a_i(t) = p_i(t) − 2 p_i(t−1) + p_i(t−2)`` the per-particle acceleration
of the trajectory at coarse step ``t`` (one step = ``r_t`` frames), ``u_i`` the
concatenation of ``a_i`` over steps ``(t−2δ, t−δ]`` and ``v_i`` over
``(t−δ, t]``, the score is ``s(t) = mean_i cos(u_i, v_i)``. The hybrid falls
back to MPM while ``s(t) < r_c``.

Two points the definition leaves open, settled here:

* a particle at rest has an acceleration of pure round-off / solver noise,
  whose direction is random: its cosine would read ~0 ("complex") for the
  calmest particles of all. A particle whose RMS acceleration over either
  window is below ``accel_floor`` [m/s²] counts as cos = 1;
* early in a rollout fewer than ``2δ + 2`` positions exist: the score then
  uses the longest window the history allows (``δ' = ⌊(T − 2)/2⌋ ≥ 1``), so
  it is defined from 4 positions on.
"""

from __future__ import annotations

import numpy as np

from hybridmpm.conventions import DELTA, R_C
from hybridmpm.errors import InvalidInputError

#: Default acceleration floor [m/s²] below which a particle counts as calm
#: (a tenth of gravity; see docs/hybrid.md for the measurement).
ACCEL_FLOOR = 1.0


def window_for(history_len: int, delta: int = DELTA) -> int:
    """The window the score uses with ``history_len`` positions: ``min(δ, ⌊(T − 2)/2⌋)`` (0 = undefined)."""
    return max(0, min(int(delta), (int(history_len) - 2) // 2))


def complexity_score(positions: np.ndarray, dt_step: float, delta: int = DELTA, accel_floor: float = ACCEL_FLOOR) -> float:
    """``s(t)`` of a position history.

    ``positions`` float [T, N, D] (oldest first, one coarse step of
    ``dt_step`` seconds apart; fluid particles only), ``delta`` the window δ,
    ``accel_floor`` [m/s²]. Uses the last ``2δ' + 2`` positions with
    ``δ' = window_for(T, delta)``. Returns a float in [−1, 1], or ``nan`` if
    ``T < 4`` (no window fits) or ``N = 0``. Raises :class:`InvalidInputError`.
    """
    p = np.asarray(positions)
    if p.ndim != 3:
        raise InvalidInputError(f"positions: expected shape [T, N, D], got {list(p.shape)}", "positions")
    if not (np.isfinite(dt_step) and dt_step > 0):
        raise InvalidInputError(f"dt_step: must be > 0 [s], got {dt_step!r}", "dt_step")
    if int(delta) < 1:
        raise InvalidInputError(f"delta: must be >= 1, got {delta!r}", "delta")
    d = window_for(p.shape[0], delta)
    n = p.shape[1]
    if d == 0 or n == 0:
        return float("nan")
    p = p[-(2 * d + 2) :].astype(np.float64)
    a = p[2:] - 2.0 * p[1:-1] + p[:-2]  # [2δ, N, D], metres per step²
    u = a[:d].transpose(1, 0, 2).reshape(n, -1)
    v = a[d:].transpose(1, 0, 2).reshape(n, -1)
    nu = np.linalg.norm(u, axis=1)
    nv = np.linalg.norm(v, axis=1)
    floor = float(accel_floor) * dt_step * dt_step * np.sqrt(d)  # RMS floor over the window, in m/step²
    calm = (nu <= floor) | (nv <= floor)
    denom = np.where(calm, 1.0, nu * nv)
    cos = np.where(calm, 1.0, np.einsum("ij,ij->i", u, v) / denom)
    return float(np.clip(cos, -1.0, 1.0).mean())


__all__ = ["ACCEL_FLOOR", "DELTA", "R_C", "complexity_score", "window_for"]
