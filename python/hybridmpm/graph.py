"""The neural simulator's neighbour search (paper App. A; GNS, Sanchez-Gonzalez et al. 2020)."""

from __future__ import annotations

import numpy as np

from hybridmpm import _core
from hybridmpm.conventions import CONNECTIVITY_RADIUS
from hybridmpm.errors import InvalidInputError, as_f32
from hybridmpm.limits import memory_budget


def bytes_per_edge(dim: int) -> int:
    """Bytes of one edge in the returned arrays: int64 sender and receiver,
    float32 displacement [D] and distance (28 in 2D, 32 in 3D)."""
    return 8 + 8 + 4 * dim + 4


def default_max_edges(dim: int) -> int:
    """The edge budget :func:`radius_graph` uses by default: the memory
    budget (:func:`hybridmpm.limits.memory_budget`) over :func:`bytes_per_edge`."""
    return memory_budget() // bytes_per_edge(dim)


def _edge_budget(max_edges: int | None, pos: np.ndarray) -> int:
    """``max_edges`` checked, or :func:`default_max_edges` for None."""
    if max_edges is None:
        return default_max_edges(pos.shape[1] if pos.ndim == 2 else 2)
    if isinstance(max_edges, bool) or not isinstance(max_edges, (int, np.integer)) or max_edges < 0:
        raise InvalidInputError(f"max_edges: must be an integer >= 0 or None, got {max_edges!r}", "max_edges")
    return int(max_edges)


def radius_graph(
    positions: np.ndarray,
    radius: float = CONNECTIVITY_RADIUS,
    *,
    self_edges: bool = True,
    max_neighbors: int | None = None,
    max_edges: int | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """All particle pairs within the connectivity radius ``R`` (cell list, Rust).

    ``positions`` float [N, D], D ∈ {2, 3} (converted to float32). Returns
    ``(senders, receivers, displacement, distance)``: int64 [E], int64 [E],
    float32 [E, D] = ``positions[senders] − positions[receivers]`` and float32 [E],
    sorted by receiver then sender. A pair is an edge iff its float32 distance is
    ≤ ``radius``; self-edges are included unless ``self_edges=False``;
    ``max_neighbors`` keeps each receiver's nearest senders (ties to the lower
    index). Raises :class:`~hybridmpm.errors.InvalidInputError` naming the field.

    ``max_edges`` is the edge budget: a graph of more edges (after
    ``max_neighbors``) is refused with :class:`~hybridmpm.errors.InvalidInputError`
    naming ``radius`` (and the count) before any edge array is allocated.
    Default: :func:`default_max_edges`, the memory budget over
    :func:`bytes_per_edge` (e.g. 30 000 points with a radius covering them all,
    9·10⁸ edges and 25 GiB, are refused on a machine with a budget below that).
    """
    pos = as_f32("positions", positions)
    max_edges = _edge_budget(max_edges, pos)
    return _core.radius_graph(pos, float(radius), self_edges=self_edges, max_neighbors=max_neighbors, max_edges=int(max_edges))


def kernel_density(positions: np.ndarray, radius: float = CONNECTIVITY_RADIUS) -> np.ndarray:
    """Kernel density of every particle, float32 [N]: ``ρ_i = Σ_j W(|x_i − x_j|/R)``
    with ``W(q) = (1 − q)²`` for ``q < 1`` (0 beyond), the particle itself
    included (an isolated particle has 1; kernel units, not kg/m³).

    ``positions`` float [N, D], D ∈ {2, 3} (converted to float32); ``radius``
    R > 0 in position units. The density :func:`relax_density` constrains.
    Raises :class:`~hybridmpm.errors.InvalidInputError` naming ``positions``
    or ``radius``."""
    return _core.kernel_density(as_f32("positions", positions), float(radius))


def _relax_inputs(positions: np.ndarray, movable: np.ndarray, rest_density: float, iterations: int, omega: float) -> tuple[np.ndarray, np.ndarray]:
    """The checks of :func:`relax_density`'s arguments Rust does not make:
    positions as float32, ``movable`` bool [N], numbers where numbers are due."""
    pos = as_f32("positions", positions)
    mv = np.asarray(movable)
    if mv.dtype != np.bool_ or mv.shape != (pos.shape[0] if pos.ndim == 2 else -1,):
        raise InvalidInputError(f"movable: must be a bool array of shape ({pos.shape[0] if pos.ndim else '?'},), got {mv.dtype} {list(mv.shape)}", "movable")
    for name, v in (("rest_density", rest_density), ("omega", omega)):
        if isinstance(v, bool) or not isinstance(v, (int, float, np.floating, np.integer)):
            raise InvalidInputError(f"{name}: must be a number, got {v!r}", name)
    if isinstance(iterations, bool) or not isinstance(iterations, (int, np.integer)):
        raise InvalidInputError(f"iterations: must be an integer in [0, 100], got {iterations!r}", "iterations")
    return pos, np.ascontiguousarray(mv)


def relax_density(
    positions: np.ndarray, movable: np.ndarray, radius: float, rest_density: float, iterations: int = 3, omega: float = 1.0
) -> tuple[np.ndarray, int, float]:
    """Push apart particles packed denser than ``rest_density`` (Rust, ``hybridmpm-neighbors``).

    A unilateral Position Based Fluids density constraint (Macklin & Müller
    2013, Eqs. 1–12: ``C_i = max(ρ_i/ρ_0 − 1, 0)`` with :func:`kernel_density`'s
    ``ρ_i``), solved by ``iterations`` Jacobi iterations on the neighbour list
    of the given positions, each move capped at ``R/4`` per iteration and
    coincident particles pushed apart along the first axis (Rust
    ``rust/neighbors/src/relax`` module docs); only compression is corrected, so free surfaces
    and splashes are left alone. Used between network steps against the
    particle clustering a learned simulator accumulates (Toshev et al.
    2024, "Neural SPH", Sec. 4, relaxes its GNS rollouts with SPH the same
    way).

    ``positions`` float [N, D] (m), D ∈ {2, 3}; ``movable`` bool [N] (False:
    obstacles, which count in the density and never move); ``radius`` R > 0
    (the kernel's support, m); ``rest_density`` > 0 in kernel units (e.g. a
    high percentile of the initial condition's :func:`kernel_density`);
    ``iterations`` in [0, 100]; ``omega`` in (0, 2]. Returns ``(positions
    float32 [N, D], compressed, max_compression)``: the relaxed positions,
    how many movable particles were denser than ``rest_density`` before, and
    their largest ``ρ/ρ_0 − 1``. The result is the same for any number of
    threads. Raises :class:`~hybridmpm.errors.InvalidInputError` naming the field.
    """
    pos, mv = _relax_inputs(positions, movable, rest_density, iterations, omega)
    out, compressed, worst = _core.relax_density(pos, mv, float(radius), float(rest_density), int(iterations), float(omega))
    return out, int(compressed), float(worst)


def relax_then_graph(
    positions: np.ndarray,
    movable: np.ndarray,
    radius: float,
    rest_density: float,
    iterations: int = 3,
    omega: float = 1.0,
    *,
    bounds: tuple[np.ndarray, np.ndarray] | None = None,
    graph_radius: float | None = None,
    max_neighbors: int | None = None,
    max_edges: int | None = None,
) -> tuple[np.ndarray, int, float, int, tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]]:
    """Every coordinate clipped to ``bounds``, :func:`relax_density`, the
    coordinates clipped again, then :func:`radius_graph` of the result
    (self-edges included), in one call (Rust): the neural simulator's work
    between two network steps (without ``bounds``, no clipping).

    The result is the four calls' in turn, bit for bit, but the graph is
    built from the relaxation's neighbour lists: particles that the
    relaxation and the clipping left in place keep their lists, those that
    moved are searched again (``hybridmpm-neighbors``, ``relax_then_graph``;
    from scratch when more than a quarter moved, with ``max_neighbors`` or
    another radius). Arguments as :func:`relax_density`; ``bounds`` None or
    ``(lo, hi)``, float [D] each (m), finite with ``lo <= hi``
    (``x < lo`` becomes ``lo``, ``x > hi`` becomes ``hi``, as
    :func:`numpy.clip`); ``graph_radius`` the graph's connectivity radius
    (default ``radius``); ``max_neighbors``, ``max_edges`` as
    :func:`radius_graph` (``max_edges`` default :func:`default_max_edges`).

    Returns ``(positions float32 [N, D], compressed, max_compression,
    clamped, graph)``: the first three as :func:`relax_density` gives them,
    ``clamped`` the particles with a coordinate outside ``bounds`` after the
    relaxation (the first clipping is not counted), ``graph`` as :func:`radius_graph` returns it for
    ``positions``. Raises :class:`~hybridmpm.errors.InvalidInputError`
    naming the field (``bounds`` for bounds of the wrong length, non-finite
    or crossed).
    """
    pos, mv = _relax_inputs(positions, movable, rest_density, iterations, omega)
    b = None
    if bounds is not None:
        try:
            lo, hi = (np.asarray(v, np.float32).reshape(-1) for v in bounds)
        except (TypeError, ValueError) as e:
            raise InvalidInputError(f"bounds: must be (lo, hi), two float arrays of D entries, got {bounds!r}", "bounds") from e
        b = (lo.tolist(), hi.tolist())
    max_edges = _edge_budget(max_edges, pos)
    gr = radius if graph_radius is None else graph_radius
    out, compressed, worst, clamped, _, graph = _core.relax_then_graph(
        pos, mv, float(radius), float(rest_density), int(iterations), float(omega), b, float(gr),
        max_neighbors=max_neighbors, max_edges=int(max_edges),
    )  # fmt: skip
    return out, int(compressed), float(worst), int(clamped), graph


__all__ = ["bytes_per_edge", "default_max_edges", "kernel_density", "radius_graph", "relax_density", "relax_then_graph"]
