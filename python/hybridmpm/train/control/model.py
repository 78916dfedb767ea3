"""The Fluid ControlNet in torch (training and export; the ``train`` extra).

Paper Sec. 3.2 and App. B, in the whole-horizon form of design D
(``docs/control.md`` says why):

* **state encoder** — the GNS graph network (:class:`~hybridmpm.train.gns.model.EncodeProcessDecode`)
  on the radius graph of the fluid at the sketch's frame, with the GNS edge
  and wall features (:mod:`hybridmpm.train.gns.features`) plus the particle's
  velocity and place; run once per sketch;
* **sketch encoder** — ControlNet's hint block (App. B: 8 convolutions, 3
  stride-2 downsamplings) on the 64×64 sketch image plus 2 CoordConv
  channels; a global embedding (44, from the 4×4-pooled last map) and a
  per-particle local feature map (8 channels at 32×32, sampled bilinearly at
  each particle); both output projections zero-initialised (ControlNet's
  zero convolutions), so an untrained controller ignores the sketch;
* **denoising head** — one interaction-network layer on the same graph
  (:class:`EncodeProcessDecode` with ``layers = 1`` and a zero-initialised
  decoder) reading ``[x_t ‖ h ‖ local sketch ‖ sketch target offset]`` and
  modulated by adaLN-Zero from ``cond = t-emb(32) ‖ sketch(44) ‖ geometry``
  (DiT, Peebles & Xie 2023); it predicts the clean sample ``x̂0``.

The sample is per particle ``K_b·D`` normalised coefficients of the
controlled motion on the temporal basis (:mod:`hybridmpm.control.diffusion`).
Shapes: N particles, E edges, D = 2 or 3; float32 throughout, int64 indices.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field
from typing import Any

import torch
from torch import nn
from torch.nn import functional as F

from hybridmpm.train.gns.features import edge_features, wall_features
from hybridmpm.train.gns.model import EncodeProcessDecode

#: Width of the sketch's global embedding (paper App. B: 44).
SKETCH_EMBED = 44
#: Channels of the per-particle local sketch feature.
LOCAL_CHANNELS = 8
#: Width of the sketch geometry vector (:func:`hybridmpm.control.targets.sketch_geometry`).
GEOMETRY = 11
#: Width of the diffusion-timestep embedding.
TIME_EMBED = 32
#: Width of the particle-type embedding of the state encoder.
TYPE_EMBED = 8


@dataclass
class ControlNetConfig:
    """Architecture and data facts of one scene's model (saved in checkpoints
    and in the exported metadata). ``bounds`` [[lo, hi]] × D [m]; ``radius``
    the connectivity radius [m]; ``vel_scale`` [m/s] divides velocities;
    ``offset_scale`` [m] divides the sketch target offsets; ``coef_mean`` and
    ``coef_std`` [K_b·D] normalise the sample."""

    dim: int
    k_basis: int
    frames: int
    bounds: list[list[float]]
    radius: float
    vel_scale: float
    offset_scale: float
    coef_mean: list[float]
    coef_std: list[float]
    latent_state: int = 32
    layers_state: int = 2
    latent_head: int = 32
    num_types: int = 9
    extra: dict[str, Any] = field(default_factory=dict)

    @property
    def sample_size(self) -> int:
        return self.k_basis * self.dim

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> ControlNetConfig:
        return cls(**d)


def timestep_embedding(t: torch.Tensor, width: int = TIME_EMBED) -> torch.Tensor:
    """Sinusoidal embedding of continuous ``t`` [B] in [0, 1] → [B, width] (DiT's, on t/T)."""
    half = width // 2
    freqs = torch.exp(-math.log(1000.0) * torch.arange(half, dtype=torch.float32) / half)
    args = t[:, None] * 1000.0 * freqs[None]
    return torch.cat([torch.cos(args), torch.sin(args)], dim=1)


class SketchEncoder(nn.Module):
    """Hint block (ControlNet's ``input_hint_block``; paper App. B): image
    float32 [1, 3, 64, 64] in [0, 1] → ``(global [1, 44], local map [1, 8, 32, 32])``."""

    def __init__(self) -> None:
        super().__init__()
        chans = [(5, 16, 1), (16, 16, 1), (16, 32, 2), (32, 32, 1), (32, 64, 2), (64, 64, 1), (64, 96, 2), (96, 96, 1)]
        self.convs = nn.ModuleList([nn.Conv2d(a, b, 3, stride=s, padding=1) for a, b, s in chans])
        self.local = nn.Conv2d(32, LOCAL_CHANNELS, 1)
        self.glob = nn.Linear(96 * 16, SKETCH_EMBED)
        for w in (self.local.weight, self.local.bias, self.glob.weight, self.glob.bias):
            if w is not None:
                nn.init.zeros_(w)

    def forward(self, image: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        b, _, h, w = image.shape
        ys = torch.linspace(-1.0, 1.0, h).view(1, 1, h, 1).expand(b, 1, h, w)
        xs = torch.linspace(-1.0, 1.0, w).view(1, 1, 1, w).expand(b, 1, h, w)
        x = torch.cat([image, xs, ys], dim=1)
        local = None
        for i, conv in enumerate(self.convs):
            x = F.silu(conv(x))
            if i == 3:
                local = self.local(x)
        assert local is not None
        pooled = F.adaptive_avg_pool2d(x, 4).flatten(1)
        return self.glob(pooled), local


class StateEncoder(nn.Module):
    """The GNS on the fluid state: positions [N, D] m, velocities [N, D] m/s,
    particle_type int64 [N], senders/receivers int64 [E] → ``(h [N,
    latent_state], edges [E, D + 1])``."""

    lower: torch.Tensor
    upper: torch.Tensor

    def __init__(self, cfg: ControlNetConfig) -> None:
        super().__init__()
        d = cfg.dim
        b = torch.tensor(cfg.bounds, dtype=torch.float32)
        self.register_buffer("lower", b[:, 0])
        self.register_buffer("upper", b[:, 1])
        self.inv_radius = 1.0 / cfg.radius
        self.inv_vel = 1.0 / cfg.vel_scale
        self.embed = nn.Embedding(cfg.num_types, TYPE_EMBED)
        self.gnn = EncodeProcessDecode(4 * d + TYPE_EMBED, d + 1, 1, latent=cfg.latent_state, layers=cfg.layers_state)

    def forward(
        self, positions: torch.Tensor, velocities: torch.Tensor, particle_type: torch.Tensor, senders: torch.Tensor, receivers: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        place = 2.0 * (positions - self.lower) / (self.upper - self.lower) - 1.0
        walls = wall_features(positions, self.lower, self.upper, self.inv_radius)
        nodes = torch.cat([velocities * self.inv_vel, place, walls, self.embed(particle_type)], dim=1)
        edges = edge_features(positions, senders, receivers, self.inv_radius)
        h, e = self.gnn.encode(nodes, edges)
        h, _ = self.gnn.process(h, e, senders, receivers)
        return h, edges


class DenoiserHead(nn.Module):
    """``(x_t [N, S], h [N, Ls], local [N, 8], offset [N, D], edges [E, D+1],
    senders, receivers, t [1] in [0, 1], cond [1, 44 + 11]) → x̂0 [N, S]``
    (module doc)."""

    def __init__(self, cfg: ControlNetConfig) -> None:
        super().__init__()
        s, d, lh = cfg.sample_size, cfg.dim, cfg.latent_head
        self.net = EncodeProcessDecode(s + cfg.latent_state + LOCAL_CHANNELS + d, d + 1, s, latent=lh, layers=1, zero_init_output=True)
        self.time = nn.Sequential(nn.Linear(TIME_EMBED, 64), nn.SiLU(), nn.Linear(64, TIME_EMBED))
        ada = nn.Linear(TIME_EMBED + SKETCH_EMBED + GEOMETRY, 2 * lh)
        nn.init.zeros_(ada.weight)
        nn.init.zeros_(ada.bias)
        self.ada = nn.Sequential(nn.SiLU(), ada)

    def forward(
        self,
        x_t: torch.Tensor,
        h: torch.Tensor,
        local: torch.Tensor,
        offset: torch.Tensor,
        edges: torch.Tensor,
        senders: torch.Tensor,
        receivers: torch.Tensor,
        t: torch.Tensor,
        cond: torch.Tensor,
    ) -> torch.Tensor:
        c = torch.cat([self.time(timestep_embedding(t)), cond], dim=1)
        scale, shift = self.ada(c).chunk(2, dim=1)
        hn, e = self.net.encode(torch.cat([x_t, h, local, offset], dim=1), edges)
        hn = hn * (1.0 + scale) + shift
        hn, _ = self.net.process(hn, e, senders, receivers)
        return self.net.decode(hn)


def sample_local(local_map: torch.Tensor, xy: torch.Tensor) -> torch.Tensor:
    """Bilinear sample of ``local_map`` [1, C, H, W] at domain points ``xy``
    [N, 2] (y up) → [N, C]; the torch twin of
    :func:`hybridmpm.control.diffusion.bilinear_sample` (training only)."""
    grid = torch.stack([2.0 * xy[:, 0] - 1.0, 1.0 - 2.0 * xy[:, 1]], dim=1).view(1, 1, -1, 2)
    out = F.grid_sample(local_map, grid, mode="bilinear", padding_mode="zeros", align_corners=False)
    return out.view(local_map.shape[1], -1).t()


class FluidControlNet(nn.Module):
    """The three parts together (module doc); :meth:`denoise` is one
    ``x̂0`` prediction from raw inputs (what training calls)."""

    def __init__(self, cfg: ControlNetConfig) -> None:
        super().__init__()
        self.config = cfg
        self.state = StateEncoder(cfg)
        self.sketch = SketchEncoder()
        self.head = DenoiserHead(cfg)

    def encode(
        self,
        positions: torch.Tensor,
        velocities: torch.Tensor,
        particle_type: torch.Tensor,
        senders: torch.Tensor,
        receivers: torch.Tensor,
        image: torch.Tensor,
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        """``(h, edges, local [N, 8], sketch global [1, 44])``: everything the head needs that does not change across denoising steps."""
        h, edges = self.state(positions, velocities, particle_type, senders, receivers)
        glob, local_map = self.sketch(image)
        return h, edges, sample_local(local_map, positions[:, :2]), glob


__all__ = [
    "GEOMETRY",
    "LOCAL_CHANNELS",
    "SKETCH_EMBED",
    "ControlNetConfig",
    "DenoiserHead",
    "FluidControlNet",
    "SketchEncoder",
    "StateEncoder",
    "sample_local",
    "timestep_embedding",
]
