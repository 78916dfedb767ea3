"""Arithmetic cost of a network step, to read the error-latency charts: why a
tiny network on a 2-core CPU is not always faster than MPM.

:func:`gnn_flops` counts the floating-point operations of the dense layers of
one GNS step (paper App. A; :class:`hybridmpm.train.gns.model.GnsModel`): every
``Linear`` costs ``2·in·out`` per row (multiply and add), applied to ``N``
node rows or ``E`` edge rows. Gathers, scatter-adds, LayerNorms and
activations are not counted (they are memory traffic, which is what bounds
small latents; see ``docs/neural.md``).
"""

from __future__ import annotations


def gnn_flops(latent: int, layers: int, dim: int, nodes: int, edges: int, t_in: int = 6, embedding: int = 16) -> int:
    """FLOPs of the dense layers of one GNS step on ``nodes`` particles and
    ``edges`` directed edges (self-edges included).

    Encoder: node MLP ``(t_in−1)·D + 2·D + embedding → latent → latent → latent``
    on N rows, edge MLP ``D+1 → latent → latent → latent`` on E rows.
    Each of ``layers`` processor blocks: edge first layer factored (``W_r``,
    ``W_s`` on N rows, ``W_e`` on E rows) then ``latent → latent`` twice on E
    rows; node MLP ``2·latent → latent → latent → latent`` on N rows.
    Decoder ``latent → latent → latent → D`` on N rows."""
    lat = latent
    node_in = (t_in - 1) * dim + 2 * dim + embedding

    def mlp(i: int, o: int) -> int:
        return 2 * (i * lat + lat * lat + lat * o)

    f = nodes * mlp(node_in, lat) + edges * mlp(dim + 1, lat)
    per_block = nodes * 2 * (2 * lat * lat) + edges * 2 * (3 * lat * lat) + nodes * mlp(2 * lat, lat)
    f += layers * per_block
    f += nodes * mlp(lat, dim)
    return int(f)
