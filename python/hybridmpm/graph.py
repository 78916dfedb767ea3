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
    if max_edges is None:
        max_edges = default_max_edges(pos.shape[1] if pos.ndim == 2 else 2)
    elif isinstance(max_edges, bool) or not isinstance(max_edges, (int, np.integer)) or max_edges < 0:
        raise InvalidInputError(f"max_edges: must be an integer >= 0 or None, got {max_edges!r}", "max_edges")
    return _core.radius_graph(pos, float(radius), self_edges=self_edges, max_neighbors=max_neighbors, max_edges=int(max_edges))


__all__ = ["bytes_per_edge", "default_max_edges", "radius_graph"]
