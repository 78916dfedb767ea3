"""The GNS's grid branch in PyTorch: global context for a graph network (needs torch).

Two message-passing steps of radius R see a few particle diameters; a
column's hydrostatic pressure or a wall twenty cells away is outside that
reach. The grid branch gives every particle a view of the whole fluid, as
CoRGI (a grid CNN beside a GNS) does:

1. **p2g** with the quadratic B-spline of MLS-MPM (the engine's kernel, the
   grid model's :func:`~hybridmpm.train.grid.model.stencil`) of the last position's
   particles onto ``G^D`` nodes over the model's bounds (one node of margin
   beyond each wall). Channels per node (:func:`branch_channels`): the
   particle count of each fluid type and of the obstacles over the count of a
   node inside resting fluid (``rest_count``), the fluid's mass-weighted mean
   of each of the ``t_in − 1`` normalised input velocities (the GNS node
   features' ``(v − vel_mean)/vel_std_eff``), and a mask of the nodes beyond
   the walls;
2. a **U-Net** (:class:`~hybridmpm.train.grid.model.UNet`) to ``latent`` channels,
   its last convolution zero at the start (a new branch leaves the GNS as it
   was);
3. **g2p** of those channels at each particle, **added to the node latent**
   after the encoder, before the processor.

At run time the ONNX graph of the GNS takes the gathered context as one more
input (``grid_context`` float32 [N, latent]); the U-Net is a second ONNX
graph stored in the model's metadata, and p2g and g2p run in Rust
(:mod:`hybridmpm.neural.grid_branch`; the tests hold both equal to this
module).
"""

from __future__ import annotations

import torch
from torch import nn

from hybridmpm.conventions import GNS_KINEMATIC
from hybridmpm.neural.grid_branch import branch_channels
from hybridmpm.neural.grid_nodes import MASS_FLOOR
from hybridmpm.train.grid.model import UNet, g2p, grid_geometry, p2g, stencil


class GridBranch(nn.Module):
    """The grid branch (module doc) of a GNS with ``latent`` channels.

    ``dim`` 2 or 3; ``bounds`` ``[[lo, hi]] * dim`` [m]; ``grid`` nodes per
    dimension G (``(hi − lo)/(G − 3)`` apart, G divisible by
    ``2^(levels − 1)``); ``width``, ``levels`` of the U-Net; ``types`` the
    fluid particle types counted per channel (GNS codes); ``rest_count``
    the p2g count of a node inside resting fluid; ``t_in`` positions per
    input (``t_in − 1`` velocities).
    """

    origin: torch.Tensor
    spacing: torch.Tensor
    lo: torch.Tensor
    hi: torch.Tensor
    wall_mask: torch.Tensor

    def __init__(
        self, dim: int, bounds: list[list[float]], latent: int, grid: int, width: int, levels: int, types: list[int], rest_count: float, t_in: int
    ) -> None:
        super().__init__()
        self.dim, self.grid, self.types, self.rest_count, self.t_in = dim, grid, list(types), float(rest_count), t_in
        self.net = UNet(dim, branch_channels(dim, len(types), t_in), latent, width, levels)
        b = torch.tensor(bounds, dtype=torch.float32)
        origin, spacing = grid_geometry(b, grid)
        self.register_buffer("origin", origin, persistent=False)
        self.register_buffer("spacing", spacing, persistent=False)
        self.register_buffer("lo", b[:, 0].clone(), persistent=False)
        self.register_buffer("hi", b[:, 1].clone(), persistent=False)
        axes = [origin[k] + spacing[k] * torch.arange(grid, dtype=torch.float32) for k in range(dim)]
        mesh = torch.stack(torch.meshgrid(*axes, indexing="ij"), dim=0)
        outside = ((mesh < b[:, 0].reshape(dim, *[1] * dim)) | (mesh > b[:, 1].reshape(dim, *[1] * dim))).any(dim=0)
        self.register_buffer("wall_mask", outside.to(torch.float32)[None], persistent=False)  # [1, G^D]

    def grid_input(
        self, last: torch.Tensor, particle_type: torch.Tensor, velocities: torch.Tensor, batch: torch.Tensor | None, windows: int
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """``(grid_in [windows, C, G^D...], weights [N, 3^D], node [N, 3^D])``
        for positions ``last`` float32 [N, D] (clipped to the bounds for the
        stencil), types int64 [N], normalised velocities float32
        [N, (t_in − 1)·D] and the window of each particle ``batch`` int64 [N]."""
        d, g = self.dim, self.grid
        x = torch.minimum(torch.maximum(last, self.lo), self.hi)
        weights, node = stencil(x, self.origin, self.spacing, g, batch)
        fluid = (particle_type != GNS_KINEMATIC).to(last.dtype)[:, None]
        cols = [(particle_type == t).to(last.dtype)[:, None] for t in self.types] + [1.0 - fluid, fluid, velocities * fluid]
        splat = p2g(torch.cat(cols, dim=1), weights, node, windows * g**d)
        m = len(self.types) + 1
        mass = splat[:, m : m + 1]
        feats = torch.cat([splat[:, :m] / self.rest_count, splat[:, m + 1 :] / mass.clamp(min=MASS_FLOOR)], dim=1)  # [nodes, C - 1]
        grid_in = feats.reshape(windows, *[g] * d, feats.shape[1]).permute(0, d + 1, *range(1, d + 1))
        grid_in = torch.cat([grid_in, self.wall_mask.expand(windows, *self.wall_mask.shape)], dim=1)
        return grid_in, weights, node

    def forward(
        self, last: torch.Tensor, particle_type: torch.Tensor, velocities: torch.Tensor, batch: torch.Tensor | None = None, windows: int = 1
    ) -> torch.Tensor:
        """The context float32 [N, latent] each particle adds to its node latent
        (inputs as :meth:`grid_input`)."""
        d = self.dim
        grid_in, weights, node = self.grid_input(last, particle_type, velocities, batch, windows)
        out = self.net(grid_in)  # [windows, latent, G...]
        latent = out.shape[1]
        flat = out.permute(0, *range(2, d + 2), 1).reshape(-1, latent)
        return g2p(flat, weights, node)


__all__ = ["GridBranch"]
