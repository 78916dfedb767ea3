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
#: Every per-particle field a solver holds (:meth:`~hybridmpm.mpm.MpmSolver.field`'s names, ``stress`` derived).
PARTICLE_FIELDS = ("positions", "velocities", "masses", "volumes", "material", "material_set", *_FIELDS, "external_acceleration")
#: The fields a particle's group shares as it is split: its material and parameter set, and each member's own mass and rest volume.
STATIC_FIELDS = ("masses", "volumes", "material", "material_set")


def group_mean(a: np.ndarray, labels: np.ndarray, w: np.ndarray, k: int) -> np.ndarray:
    """The ``w``-weighted mean of ``a`` [N, ...] over the groups ``labels`` (int64 [N], ``0 .. k − 1``, each
    non-empty), float64 [k, ...]: per group ``Σ w·a / Σ w``, summed in particle order."""
    flat = np.asarray(a, np.float64).reshape(len(labels), -1) * w[:, None]
    out = np.stack([np.bincount(labels, flat[:, j], minlength=k) for j in range(flat.shape[1])], axis=1)
    return (out / np.bincount(labels, w, minlength=k)[:, None]).reshape((k,) + np.shape(a)[1:])


def group_firsts(labels: np.ndarray, k: int) -> np.ndarray:
    """The index of each group's first particle, int64 [k] (``labels`` int [N], ``0 .. k − 1``)."""
    first = np.full(k, len(labels), np.int64)
    np.minimum.at(first, np.asarray(labels, np.int64), np.arange(len(labels)))
    return first


def merge_arrays(fields: dict[str, np.ndarray], labels: np.ndarray, k: int) -> tuple[dict[str, np.ndarray], np.ndarray]:
    """Merge particles into groups: ``fields`` every :data:`PARTICLE_FIELDS` array of N particles (as
    :meth:`~hybridmpm.mpm.MpmSolver.field` reads them; any other float array [N, ...] given, such as a
    simulator's forcing, is merged as the velocities are), particle ``i`` in group ``labels[i]`` (int [N], values
    ``0 .. k − 1``, each group non-empty and of one parameter set). The group is one particle (paper Sec. 3.1.1's
    ``r_p`` clustering): its mass and rest volume the sums (float32 of the float64 sum), its position, velocity,
    APIC ``C``, ``F``, sand's log-volume correction and external acceleration the mass-weighted means (mass,
    centre of mass, momentum and the applied force conserved), water's ``J`` the rest-volume-weighted mean, its
    material and set its members'. Returns the k merged particles' arrays (float32; int32 codes) and each
    particle's offset from its group's centre, float64 [N, D] (what :func:`split_arrays` puts back)."""
    lab = np.asarray(labels, np.int64)
    m = np.asarray(fields["masses"], np.float64)
    vol = np.asarray(fields["volumes"], np.float64)
    means = [f for f in fields if f not in (*STATIC_FIELDS, "positions")]
    out: dict[str, np.ndarray] = {f: group_mean(fields[f], lab, vol if f == "volume_ratio" else m, k).astype(np.float32) for f in means}
    x = np.asarray(fields["positions"], np.float64)
    xc = group_mean(x, lab, m, k)
    out["positions"] = xc.astype(np.float32)
    out["masses"] = np.bincount(lab, m, minlength=k).astype(np.float32)
    out["volumes"] = np.bincount(lab, vol, minlength=k).astype(np.float32)
    first = group_firsts(lab, k)
    for f in ("material", "material_set"):
        out[f] = np.asarray(fields[f], np.int32)[first]
    return out, x - xc[lab]


def split_arrays(
    merged: dict[str, np.ndarray], labels: np.ndarray, offsets: np.ndarray, members: dict[str, np.ndarray], bounds: tuple[float, float]
) -> dict[str, np.ndarray]:
    """The inverse of :func:`merge_arrays`: each particle ``i`` at its group's position plus ``offsets[i]``
    (clipped to ``bounds`` [m]), with the group's affine velocity ``v + C·offset`` and its ``C``, ``F``, ``J``,
    log-volume correction, external acceleration (and any other merged array); ``members`` the particles' own
    ``masses``, ``volumes``, ``material`` and ``material_set`` [N]. Mass is the members' again, and momentum the
    group's (the offsets are about the group's centre of mass). Returns the N particles' arrays."""
    lab = np.asarray(labels, np.int64)
    off = np.asarray(offsets, np.float64)
    aff = np.asarray(merged["affine"], np.float64)[lab]
    lo, hi = bounds
    out = {f: np.asarray(a)[lab] for f, a in merged.items() if f not in (*STATIC_FIELDS, "positions", "velocities")}
    out["positions"] = np.clip(np.asarray(merged["positions"], np.float64)[lab] + off, lo, hi).astype(np.float32)
    out["velocities"] = (np.asarray(merged["velocities"], np.float64)[lab] + np.einsum("nij,nj->ni", aff, off)).astype(np.float32)
    out.update({f: np.asarray(members[f]) for f in STATIC_FIELDS})
    return out


def bin_groups(positions: np.ndarray, sets: np.ndarray, size: float) -> tuple[np.ndarray, int]:
    """Group particles by parameter set and by cube of side ``size`` [m] on a lattice from the origin: the
    labels, int64 [N] (groups numbered in the order of their first particle, so the same particles give the same
    labels), and the number of groups. ``positions`` float [N, D], ``sets`` int [N]."""
    cells = np.floor(np.asarray(positions, np.float64) / size).astype(np.int64)
    keys = np.concatenate([np.asarray(sets, np.int64)[:, None], cells], axis=1)
    _, first, inverse = np.unique(keys, axis=0, return_index=True, return_inverse=True)
    rank = np.empty(len(first), np.int64)
    rank[np.argsort(first, kind="stable")] = np.arange(len(first))
    return rank[inverse.ravel()], len(first)


def merge_state(fine: MpmSolver, coarse: MpmSolver, labels: np.ndarray) -> tuple[np.ndarray, float]:
    """Merge the particles of ``fine`` into those of ``coarse`` (MPM on another grid): particle ``i``
    of ``fine`` belongs to particle ``labels[i]`` of ``coarse`` (int64 [N_f], values ``0 .. N_c − 1``,
    every group one material; ``coarse``'s masses and rest volumes are the groups' sums), as
    :func:`merge_arrays` merges them (its masses and rest volumes are ``coarse``'s own).
    Returns each fine particle's offset from its group's centre float64 [N_f, D] (what
    :func:`split_state` puts back) and the merge's error: the mass-weighted RMS [m/s] of the fine
    velocities the group's affine field ``v + C·offset`` does not carry."""
    lab = np.asarray(labels, np.int64)
    merged, offsets = merge_arrays({f: fine.field(f) for f in PARTICLE_FIELDS}, lab, coarse.num_particles)
    lo, hi = coarse.domain_bounds
    coarse.positions = np.clip(merged["positions"], lo, hi)
    coarse.velocities = merged["velocities"]
    for f in _FIELDS:
        coarse.set_field(f, merged[f])
    m = np.asarray(fine.masses, np.float64)
    carried = np.asarray(merged["velocities"], np.float64)[lab] + np.einsum("nij,nj->ni", np.asarray(merged["affine"], np.float64)[lab], offsets)
    residual = float(np.sqrt((m * ((np.asarray(fine.velocities, np.float64) - carried) ** 2).sum(1)).sum() / max(m.sum(), 1e-300)))
    return offsets, residual


def split_state(coarse: MpmSolver, fine: MpmSolver, labels: np.ndarray, offsets: np.ndarray) -> None:
    """The inverse of :func:`merge_state`: each fine particle ``i`` at its group's position plus
    ``offsets[i]`` (clipped to ``fine``'s domain), with the group's affine velocity ``v + C·offset``
    and its ``C``, ``F``, ``J`` and log-volume correction (:func:`split_arrays`)."""
    members = {f: fine.field(f) for f in STATIC_FIELDS}
    out = split_arrays({f: coarse.field(f) for f in PARTICLE_FIELDS}, labels, offsets, members, fine.domain_bounds)
    fine.positions = out["positions"]
    fine.velocities = out["velocities"]
    for f in _FIELDS:
        fine.set_field(f, out[f])


def replace_particles(solver: MpmSolver, fields: dict[str, np.ndarray]) -> None:
    """Make ``solver`` hold exactly the particles ``fields`` (every :data:`PARTICLE_FIELDS` array, in order),
    in place: its clock, grid, bodies, obstacles and parameter sets are kept. The new particles are appended
    and checked before the old ones go, so a refusal (:class:`InvalidInputError` naming the field) removes the
    ones it appended and leaves the old ones."""
    n_old = solver.num_particles
    solver.add_particles(
        fields["positions"], np.asarray(fields["material"], np.int32), velocities=fields["velocities"], masses=fields["masses"],
        volumes=fields["volumes"], material_set=np.asarray(fields["material_set"], np.int32),
    )  # fmt: skip
    old = np.zeros(solver.num_particles, bool)
    old[:n_old] = True
    try:
        for f in (*_FIELDS, "external_acceleration"):
            solver.set_field(f, np.concatenate([solver.field(f)[:n_old], np.asarray(fields[f], np.float32)]))
    except BaseException:
        solver.remove_particles(~old)
        raise
    solver.remove_particles(old)


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
    "group_firsts",
    "group_mean",
    "hydrostatic_j_min",
    "PARTICLE_FIELDS",
    "STATIC_FIELDS",
    "bin_groups",
    "merge_arrays",
    "merge_state",
    "mpm_history",
    "neural_to_mpm",
    "particle_density",
    "replace_particles",
    "split_arrays",
    "split_state",
    "velocities_from_history",
]
