"""State conversion between the neural simulator and MPM (paper Sec. 3.1.2).

neural → MPM (:func:`neural_to_mpm`): positions are the last positions of the
history; velocities the last finite difference (exactly the velocity the
network's semi-implicit Euler step produced; the mean velocity over the last
step, which lags the motion by ``a·Δt/2``), or with ``velocity="second"`` the
second-order backward difference ``(3p_t − 4p_{t−1} + p_{t−2})/(2Δt)``, the
velocity *at* ``t`` for constant acceleration (measured against each other in
docs/hybrid.md: no difference that survives the seed noise); the APIC affine matrix ``C`` is
zero or a least-squares fit of the neighbours' velocities (``affine="fit"``);
water's volume ratio ``J`` is estimated from the local density so that the
pressure matches the particles' spacing (:func:`estimate_volume_ratio`,
clipped at :func:`hydrostatic_j_min`); sand's
elastic deformation gradient is reset to ``F = I``.

MPM → neural (:func:`mpm_history`): the neural simulator needs ``T_in``
positions ``r_t`` frames apart: the hybrid keeps the last coarse positions of
its trajectory, whichever solver made them, and the newest entry is the MPM
solver's current positions (bit-exact).

Particles keep their order and count both ways (none lost or duplicated).

Between two particle sets of MPM (:func:`merge_state`, :func:`split_state`): the
classical twin may carry the coarse grid's own particle set, fewer particles
than the hybrid's; each of its particles is a group of the hybrid's (the
``r_p`` clustering's labels), merged at a handover to the coarse grid (mass,
centre of mass and momentum conserved; the velocities the group's affine field
does not carry are the merge's measured error) and split back at a handover
to the scene's grid (each particle at its group's position plus its offset,
with the group's affine velocity).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from hybridmpm.conventions import MATERIAL_WATER
from hybridmpm.errors import InvalidInputError
from hybridmpm.graph import radius_graph
from hybridmpm.mpm import MpmSolver, grid_mass


def bspline_weights(x: np.ndarray, n_grid: int) -> tuple[np.ndarray, np.ndarray]:
    """Quadratic B-spline stencil of each particle (MLS-MPM's kernel, Hu et al.
    2018; the Python twin of the Rust ``kernel``): ``x`` [N, D] in the unit
    domain → base node int64 [N, D] and weights float64 [N, D, 3]."""
    fx = x * n_grid
    base = np.floor(fx - 0.5).astype(np.int64)
    f = fx - base
    w = np.stack([0.5 * (1.5 - f) ** 2, 0.75 - (f - 1.0) ** 2, 0.5 * (f - 0.5) ** 2], axis=-1)
    return base, w


def particle_density(positions: np.ndarray, masses: np.ndarray, n_grid: int) -> np.ndarray:
    """Density at each particle [kg/m^D], float64 [N]: particle mass splatted to
    the grid with quadratic B-splines (p2g), divided by the cell volume, and
    gathered back with the same weights (g2p). ``positions`` [N, D] in the unit
    domain, ``masses`` [N] kg."""
    x = np.asarray(positions, np.float64)
    m = np.asarray(masses, np.float64)
    n, dim = x.shape
    total = float(m.sum())
    node_mass = np.asarray(grid_mass(x.astype(np.float32), n_grid, m.astype(np.float32)), np.float64) * total
    rho_grid = node_mass * float(n_grid) ** dim  # / dx^D
    base, w = bspline_weights(x, n_grid)
    rho = np.zeros(n)
    offsets = np.stack(np.meshgrid(*([np.arange(3)] * dim), indexing="ij"), -1).reshape(-1, dim)
    for off in offsets:
        idx = np.clip(base + off, 0, n_grid - 1)
        weight = np.prod(w[np.arange(n)[:, None], np.arange(dim)[None, :], off[None, :]], axis=1)
        rho += weight * rho_grid[tuple(idx.T)]
    return rho


def estimate_volume_ratio(positions: np.ndarray, masses: np.ndarray, volumes: np.ndarray, n_grid: int, j_min: float = 0.5) -> np.ndarray:
    """Water's volume ratio from local density: ``J = ρ_rest / ρ`` with
    ``ρ_rest = m/V₀`` per particle and ``ρ`` from :func:`particle_density`,
    clipped to ``[j_min, 1]`` (no tension: free-surface particles, whose density
    the kernel underestimates, get J = 1, zero pressure). float32 [N]."""
    rho = particle_density(positions, masses, n_grid)
    rest = np.asarray(masses, np.float64) / np.asarray(volumes, np.float64)
    j = np.where(rho > 0, rest / np.maximum(rho, 1e-30), 1.0)
    return np.clip(j, j_min, 1.0).astype(np.float32)


def hydrostatic_j_min(solver: MpmSolver, factor: float = 2.0) -> float:
    """Smallest J a converted water particle may get: ``1 − factor·ρ|g|L/K``
    with L = 1 m the domain height, i.e. ``factor`` × the compression at the
    bottom of a full-depth column. Tighter than any plausible flow, it keeps a
    clump of network particles (e.g. pressed onto a wall by the position
    clipping) from turning into an explosive pressure after the switch."""
    p = solver.params
    g = float(np.linalg.norm(p.resolved_gravity()))
    return float(max(0.5, 1.0 - factor * p.water.density * g * 1.0 / p.water.bulk_modulus))


def fit_affine(positions: np.ndarray, velocities: np.ndarray, radius: float, reg: float = 1e-3) -> np.ndarray:
    """Least-squares velocity gradient per particle from its neighbours within
    ``radius`` [m]: ``C_i = (Σ_j Δv Δxᵀ)(Σ_j Δx Δxᵀ + reg·R²·I)⁻¹`` (the APIC
    affine matrix of a locally linear velocity field). float32 [N, D, D], 1/s."""
    x = np.asarray(positions, np.float32)
    v = np.asarray(velocities, np.float64)
    n, dim = x.shape
    s, r, _, _ = radius_graph(x, float(radius), self_edges=False)
    dx = (x[s] - x[r]).astype(np.float64)
    dv = v[s] - v[r]
    b = np.zeros((n, dim, dim))
    a = np.zeros((n, dim, dim))
    np.add.at(b, r, dv[:, :, None] * dx[:, None, :])
    np.add.at(a, r, dx[:, :, None] * dx[:, None, :])
    a += reg * radius * radius * np.eye(dim)
    return np.einsum("nij,njk->nik", b, np.linalg.inv(a)).astype(np.float32)


#: Velocity estimates of :func:`velocities_from_history`.
VELOCITY_ESTIMATES = ("last", "second")


def velocities_from_history(history: np.ndarray, dt_step: float, velocity: str = "last") -> np.ndarray:
    """Velocity at the last position of ``history`` [T ≥ 2, N, D] (one
    ``dt_step`` [s] apart), [m/s] float32 [N, D]: ``"last"`` the last finite
    difference ``(p_t − p_{t−1})/Δt`` (the mean velocity over the last step),
    ``"second"`` the second-order backward difference
    ``(3p_t − 4p_{t−1} + p_{t−2})/(2Δt)`` (exact for constant acceleration;
    needs T ≥ 3, else falls back to the last difference)."""
    h = np.asarray(history)
    last = h[-1].astype(np.float64)
    if velocity == "second" and h.shape[0] >= 3:
        v = (3.0 * last - 4.0 * h[-2].astype(np.float64) + h[-3].astype(np.float64)) / (2.0 * dt_step)
    else:
        v = (last - h[-2].astype(np.float64)) / dt_step
    return v.astype(np.float32)


@dataclass(frozen=True)
class Conversion:
    """How a network's state is converted for MPM (:func:`neural_to_mpm`; docs/hybrid.md "State
    conversion"): ``affine`` APIC ``C`` "fit" (least squares of the neighbours' velocities) or "zero";
    ``volume_ratio`` water's ``J`` "density" (from the local density) or "one"; ``velocity`` "last"
    (the last finite difference) or "second" (:func:`velocities_from_history`). Raises
    :class:`InvalidInputError` naming the field."""

    affine: str = "fit"
    volume_ratio: str = "density"
    velocity: str = "last"

    def __post_init__(self) -> None:
        if self.affine not in ("fit", "zero"):
            raise InvalidInputError(f"affine: must be 'fit' or 'zero', got {self.affine!r}", "affine")
        if self.volume_ratio not in ("density", "one"):
            raise InvalidInputError(f"volume_ratio: must be 'density' or 'one', got {self.volume_ratio!r}", "volume_ratio")
        if self.velocity not in VELOCITY_ESTIMATES:
            raise InvalidInputError(f"velocity: must be one of {', '.join(map(repr, VELOCITY_ESTIMATES))}, got {self.velocity!r}", "velocity")

    def settings(self) -> dict[str, str]:
        """The keyword arguments of :func:`neural_to_mpm` it stands for."""
        return {"affine": self.affine, "volume_ratio": self.volume_ratio, "velocity": self.velocity}


def neural_to_mpm(
    solver: MpmSolver,
    history: np.ndarray,
    dt_step: float,
    *,
    affine: str = "fit",
    affine_radius: float | None = None,
    volume_ratio: str = "density",
    velocity: str = "last",
) -> dict[str, Any]:
    """Write the neural state into ``solver`` (same particles, same order).

    ``history`` float32 [T ≥ 2, N, D] fluid positions (no boundary particles),
    one coarse step ``dt_step`` [s] apart; ``affine`` "fit" or "zero";
    ``volume_ratio`` "density" (:func:`estimate_volume_ratio`) or "one";
    ``velocity`` "last" or "second" (:func:`velocities_from_history`; the
    last two, resp. three, positions are read).
    Returns what was set (``positions``, ``velocities``, ``affine``,
    ``volume_ratio``). Raises :class:`InvalidInputError` for a history whose
    particle count is not the solver's or that is not finite.
    """
    h = np.asarray(history, np.float32)
    if h.ndim != 3 or h.shape[0] < 2 or h.shape[1] != solver.num_particles or h.shape[2] != solver.dim:
        raise InvalidInputError(f"history: expected [T >= 2, {solver.num_particles}, {solver.dim}] fluid positions, got {list(h.shape)}", "history")
    if velocity not in VELOCITY_ESTIMATES:
        raise InvalidInputError(f"velocity: must be one of {', '.join(map(repr, VELOCITY_ESTIMATES))}, got {velocity!r}", "velocity")
    used = 3 if velocity == "second" and h.shape[0] >= 3 else 2
    if not np.isfinite(h[-used:]).all():
        raise InvalidInputError(f"history: the last {min(used, h.shape[0])} positions must be finite", "history")
    if affine not in ("fit", "zero"):
        raise InvalidInputError(f"affine: must be 'fit' or 'zero', got {affine!r}", "affine")
    if volume_ratio not in ("density", "one"):
        raise InvalidInputError(f"volume_ratio: must be 'density' or 'one', got {volume_ratio!r}", "volume_ratio")
    x = h[-1].copy()
    v = velocities_from_history(h, dt_step, velocity)
    dim = solver.dim
    n = x.shape[0]
    if affine == "fit" and n > 1:
        c = fit_affine(x, v, affine_radius if affine_radius is not None else 2.0 * solver.dx)
    else:
        c = np.zeros((n, dim, dim), np.float32)
    material = solver.material
    if volume_ratio == "density":
        j = estimate_volume_ratio(x, solver.masses, solver.volumes, solver.n_grid, j_min=hydrostatic_j_min(solver))
        j = np.where(material == MATERIAL_WATER, j, 1.0).astype(np.float32)
    else:
        j = np.ones(n, np.float32)
    solver.positions = x
    solver.velocities = v
    solver.affine = c
    solver.deformation_gradient = np.broadcast_to(np.eye(dim, dtype=np.float32), (n, dim, dim)).copy()
    solver.volume_ratio = j
    return {"positions": x, "velocities": v, "affine": c, "volume_ratio": j}


#: The per-particle fields of MPM's state that a merge averages and a split copies (``volume_correction``: sand's log-volume correction).
_FIELDS = ("affine", "deformation_gradient", "volume_ratio", "volume_correction")


def merge_state(fine: MpmSolver, coarse: MpmSolver, labels: np.ndarray) -> tuple[np.ndarray, float]:
    """Merge the particles of ``fine`` into those of ``coarse`` (MPM on another grid): particle ``i``
    of ``fine`` belongs to particle ``labels[i]`` of ``coarse`` (int64 [N_f], values ``0 .. N_c − 1``,
    every group one material; ``coarse``'s masses and rest volumes are the groups' sums). The group's
    position and velocity are the mass-weighted means (mass, centre of mass and momentum conserved,
    as the ``r_p`` clustering does, paper Sec. 3.1.1), its APIC ``C``, elastic ``F`` and sand's
    log-volume correction the mass-weighted means, water's ``J`` the rest-volume-weighted mean.
    Returns each fine particle's offset from its group's centre float64 [N_f, D] (what
    :func:`split_state` puts back) and the merge's error: the mass-weighted RMS [m/s] of the fine
    velocities the group's affine field ``v + C·offset`` does not carry."""
    lab = np.asarray(labels, np.int64)
    k = coarse.num_particles
    m = np.asarray(fine.masses, np.float64)
    msum = np.bincount(lab, m, minlength=k)

    def mean(a: np.ndarray, w: np.ndarray, wsum: np.ndarray) -> np.ndarray:
        flat = np.asarray(a, np.float64).reshape(len(lab), -1) * w[:, None]
        out = np.zeros((k, flat.shape[1]))
        np.add.at(out, lab, flat)
        return (out / wsum[:, None]).reshape((k,) + np.shape(a)[1:])

    x, v = np.asarray(fine.positions, np.float64), np.asarray(fine.velocities, np.float64)
    xc, vc = mean(x, m, msum), mean(v, m, msum)
    vol = np.asarray(fine.volumes, np.float64)
    merged = {f: mean(fine.field(f), vol if f == "volume_ratio" else m, np.bincount(lab, vol if f == "volume_ratio" else m, minlength=k)) for f in _FIELDS}
    offsets = x - xc[lab]
    lo, hi = coarse.domain_bounds
    coarse.positions = np.clip(xc, lo, hi).astype(np.float32)
    coarse.velocities = vc.astype(np.float32)
    for f, a in merged.items():
        coarse.set_field(f, a.astype(np.float32))
    carried = vc[lab] + np.einsum("nij,nj->ni", merged["affine"][lab], offsets)
    residual = float(np.sqrt((m * ((v - carried) ** 2).sum(1)).sum() / max(m.sum(), 1e-300)))
    return offsets, residual


def split_state(coarse: MpmSolver, fine: MpmSolver, labels: np.ndarray, offsets: np.ndarray) -> None:
    """The inverse of :func:`merge_state`: each fine particle ``i`` at its group's position plus
    ``offsets[i]`` (clipped to ``fine``'s domain), with the group's affine velocity ``v + C·offset``
    and its ``C``, ``F``, ``J`` and log-volume correction."""
    lab = np.asarray(labels, np.int64)
    aff = np.asarray(coarse.affine, np.float64)[lab]
    lo, hi = fine.domain_bounds
    fine.positions = np.clip(np.asarray(coarse.positions, np.float64)[lab] + offsets, lo, hi).astype(np.float32)
    fine.velocities = (np.asarray(coarse.velocities, np.float64)[lab] + np.einsum("nij,nj->ni", aff, offsets)).astype(np.float32)
    for f in _FIELDS:
        fine.set_field(f, np.asarray(coarse.field(f))[lab])


def mpm_history(current: np.ndarray, kept: np.ndarray, t_in: int) -> np.ndarray:
    """The neural simulator's input after MPM: the last ``t_in − 1`` kept coarse
    positions followed by the MPM solver's ``current`` positions float [N, D],
    float32 [t_in, N, D] (fluid particles only). ``kept`` float [K ≥ t_in − 1, N, D].
    Raises :class:`InvalidInputError` (field ``kept``) for other shapes."""
    cur = np.asarray(current, np.float32)
    k = np.asarray(kept, np.float32)
    if k.ndim != 3 or k.shape[0] < t_in - 1 or k.shape[1:] != cur.shape:
        raise InvalidInputError(f"kept: expected [>= {t_in - 1}, {cur.shape[0]}, {cur.shape[-1]}] positions, got {list(k.shape)}", "kept")
    return np.concatenate([k[len(k) - (t_in - 1) :], cur[None]])


__all__ = [
    "VELOCITY_ESTIMATES",
    "Conversion",
    "bspline_weights",
    "estimate_volume_ratio",
    "fit_affine",
    "hydrostatic_j_min",
    "merge_state",
    "mpm_history",
    "neural_to_mpm",
    "particle_density",
    "split_state",
    "velocities_from_history",
]
