"""Control targets by reverse simulation (paper Sec. 3.2, Eq. 3; App. D).

A forward trajectory ``X_1 … X_T`` (``T = T_ctr`` frames of ``dt_frame``) is
replayed backwards: the controlled run starts from ``X_T`` with the forward
velocities negated and should pass through ``y_k = X_{T−k}``, ending on
``X_1``. Indexing, pinned here once:

* controlled frame ``k = 0 … T−2`` moves the fluid from ``y_k`` to ``y_{k+1}``;
  ``a[k]`` is the external acceleration [m/s²] applied during that frame;
* the controlled velocity at ``y_k`` is ``v_0 = −v_forward(X_T)`` (given) and
  ``v_k = (y_k − y_{k−1})/Δt`` after that;
* the paper's formula (Eq. 3, time running backwards) is
  ``a[k] = (y_{k+1} − y_k − v_k·Δt)/Δt² − g``: with the symplectic-Euler
  update ``v ← v + (a + g)Δt``, ``p ← p + vΔt`` it lands on ``y_{k+1}``
  exactly (:func:`reverse_kinematic`; ``tests/test_control.py``).

The formula ignores pressure and friction, so replaying it in MPM misses
``X_1``; :func:`reverse_tracking` solves each frame's acceleration *through*
MPM instead (probe the frame without control, then correct), so that the
replay tracks the targets. Both clip ``‖a‖`` at :data:`A_MAX`.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from hybridmpm.conventions import G
from hybridmpm.errors import InvalidInputError
from hybridmpm.sim import MpmSimulator

#: Largest control acceleration [m/s²] (50 g): bounds the CFL substeps a
#: controlled frame can need (one grid cell per frame is ≈ 127 g at 128²).
A_MAX = 50 * G
#: Smoothing of the targets (paper App. D): λ and β.
SMOOTH_LAMBDA = 0.1
SMOOTH_BETA = 2.0


def clip_norm(a: np.ndarray, a_max: float = A_MAX) -> np.ndarray:
    """``a`` [..., D] with every vector's norm clipped at ``a_max`` (float32)."""
    a = np.asarray(a, np.float64)
    n = np.linalg.norm(a, axis=-1, keepdims=True)
    scale = np.minimum(1.0, a_max / np.maximum(n, 1e-30))
    return (a * scale).astype(np.float32)


def _check_trajectory(x: Any, name: str = "trajectory") -> np.ndarray:
    arr = np.asarray(x, np.float64)
    if arr.ndim != 3 or arr.shape[0] < 2 or arr.shape[2] not in (2, 3) or arr.shape[1] < 1:
        raise InvalidInputError(f"{name}: expected positions [T >= 2, N, D], got {list(arr.shape)}", name)
    if not np.isfinite(arr).all():
        raise InvalidInputError(f"{name}: contains NaN or inf", name)
    return arr


def reverse_kinematic(forward: np.ndarray, v_end: np.ndarray, dt: float, gravity: np.ndarray, a_max: float | None = A_MAX) -> np.ndarray:
    """The paper's reverse-simulation accelerations (Eq. 3).

    ``forward`` float [T, N, D]: fluid positions ``X_1 … X_T`` one frame
    ``dt`` [s] apart; ``v_end`` [N, D] the forward velocity at ``X_T``
    [m/s]; ``gravity`` [D] [m/s²]. Returns float32 [T − 1, N, D]: ``a[k]``
    for controlled frame ``k`` (module doc), clipped at ``a_max`` (None: not
    clipped). Raises :class:`InvalidInputError` naming the argument."""
    x = _check_trajectory(forward, "forward")
    y = x[::-1]  # y_k = X_{T-k}
    v0 = -np.asarray(v_end, np.float64)
    if v0.shape != x.shape[1:]:
        raise InvalidInputError(f"v_end: expected [{x.shape[1]}, {x.shape[2]}], got {list(v0.shape)}", "v_end")
    g = np.asarray(gravity, np.float64)
    v = np.concatenate([v0[None], (y[1:-1] - y[:-2]) / dt])  # v_k, k = 0 … T-2
    a = (y[1:] - y[:-1] - v * dt) / (dt * dt) - g
    return clip_norm(a, a_max) if a_max is not None else a.astype(np.float32)


def smooth(a: np.ndarray, lam: float = SMOOTH_LAMBDA, beta: float = SMOOTH_BETA) -> np.ndarray:
    """Temporal smoothing of control accelerations (paper App. D, Eq. 10):
    ``a_t − λ·exp(−β·cos(a_t, a_{t+1}))·(a_t − a_{t+1})``, one Jacobi pass
    (every frame from the unsmoothed field), the last frame unchanged; the
    cosine is per particle, 1 where either vector is zero. ``λ = 0`` is the
    identity. ``a`` float [T, N, D] → float32 [T, N, D]."""
    a = np.asarray(a, np.float64)
    if a.ndim != 3:
        raise InvalidInputError(f"a: expected [T, N, D], got {list(a.shape)}", "a")
    if lam == 0 or len(a) < 2:
        return a.astype(np.float32)
    cur, nxt = a[:-1], a[1:]
    nc, nn = np.linalg.norm(cur, axis=-1), np.linalg.norm(nxt, axis=-1)
    ok = (nc > 0) & (nn > 0)
    cos = np.where(ok, (cur * nxt).sum(-1) / np.where(ok, nc * nn, 1.0), 1.0)
    out = a.copy()
    out[:-1] = cur - lam * np.exp(-beta * cos)[..., None] * (cur - nxt)
    return out.astype(np.float32)


def reverse_tracking(
    sim: MpmSimulator, forward: np.ndarray, a_max: float = A_MAX, iterations: int = 2, lam: float = 0.0, beta: float = SMOOTH_BETA
) -> np.ndarray:
    """Control accelerations solved through MPM, frame by frame.

    ``sim`` an :class:`~hybridmpm.sim.MpmSimulator` (``r_t = 1``) holding the
    start state (``X_T`` with the forward velocities negated); ``forward``
    [T, N, D] as in :func:`reverse_kinematic`. For each controlled frame the
    solver's state is checkpointed, the frame is run with the current guess
    (first: no control), and the guess is corrected by the miss
    ``(y_{k+1} − p̂)/(c·Δt²)`` with ``c = (n + 1)/(2n)`` for ``n`` substeps
    (the displacement a constant acceleration causes under symplectic Euler),
    ``iterations`` times; then the frame is run for real. With ``lam`` > 0 the
    solved acceleration is pulled towards the previous frame's as App. D
    smooths (``a − λ·exp(−β cos(a, a_prev))·(a − a_prev)``) *before* it is
    applied, so that the following frames correct what smoothing costs (the
    field is smooth and its replay still lands; smoothing a tracking field
    afterwards does not land). The simulator ends at the controlled state
    after ``T − 1`` frames. Returns float32 [T − 1, N, D] clipped at ``a_max``."""
    x = _check_trajectory(forward, "forward")
    y = x[::-1]
    n, d = sim.particles.num_fluid, sim.particles.dim
    if x.shape[1:] != (n, d) or sim.r_t != 1:
        raise InvalidInputError(f"sim: expected an MpmSimulator with r_t = 1 and {n} particles matching forward {list(x.shape)}", "sim")
    dt = sim.dt_frame
    out = np.zeros((len(y) - 1, n, d), np.float32)
    for k in range(len(y) - 1):
        guess = np.zeros((n, d), np.float32)
        for _ in range(max(1, iterations)):
            saved = sim.state()
            sim.forcing = guess
            fr = sim.advance()
            landed = sim.particles.fluid(fr.positions).astype(np.float64)
            sim.restore(saved)
            c = (fr.substeps + 1) / (2.0 * max(fr.substeps, 1))
            guess = clip_norm(guess + (y[k + 1] - landed) / (c * dt * dt), a_max)
        if lam > 0 and k > 0:
            guess = smooth(np.stack([guess, out[k - 1]]), lam, beta)[0]
        sim.forcing = guess
        sim.advance()
        out[k] = guess
    sim.forcing = None
    return out


__all__ = ["A_MAX", "SMOOTH_BETA", "SMOOTH_LAMBDA", "clip_norm", "reverse_kinematic", "reverse_tracking", "smooth"]
