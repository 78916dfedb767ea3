"""The neural simulator's neighbour search (paper App. A; GNS, Sanchez-Gonzalez et al. 2020)."""

from __future__ import annotations

import numpy as np

from hybridmpm import _core
from hybridmpm.conventions import CONNECTIVITY_RADIUS
from hybridmpm.errors import as_f32


def radius_graph(
    positions: np.ndarray, radius: float = CONNECTIVITY_RADIUS, *, self_edges: bool = True, max_neighbors: int | None = None
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """All particle pairs within the connectivity radius ``R`` (cell list, Rust).

    ``positions`` float [N, D], D ∈ {2, 3} (converted to float32). Returns
    ``(senders, receivers, displacement, distance)``: int64 [E], int64 [E],
    float32 [E, D] = ``positions[senders] − positions[receivers]`` and float32 [E],
    sorted by receiver then sender. A pair is an edge iff its float32 distance is
    ≤ ``radius``; self-edges are included unless ``self_edges=False``;
    ``max_neighbors`` keeps each receiver's nearest senders (ties to the lower
    index). Raises :class:`~hybridmpm.errors.InvalidInputError` naming the field.
    """
    return _core.radius_graph(as_f32("positions", positions), float(radius), self_edges=self_edges, max_neighbors=max_neighbors)


__all__ = ["radius_graph"]
