"""The GNS encoder–processor–decoder in PyTorch (paper App. A; Sanchez-Gonzalez et al. 2020).

Everything between raw positions and the next positions lives in
:class:`GnsModel.forward`, so that the exported ONNX graph holds the feature
construction and the (de)normalisation too (DESIGN.md):

* node input: the last ``T_in − 1 = 5`` velocities (finite differences of
  ``T_in = 6`` positions, one step apart), normalised with the dataset
  statistics; the distances to the domain walls (``bounds``) divided by ``R``
  and clipped to [−1, 1]; a 16-d embedding of the particle type (9 types);
* edge input over the radius graph (senders → receivers, self-edges
  included): ``(p_s − p_r)/R`` and its norm;
* encoder: node and edge MLPs to ``latent``; processor: ``L`` blocks, each with
  its own edge and node MLP and residuals; the edge MLP's first layer is
  factored into per-node projections gathered per edge
  (``W·[e; h_r; h_s] = W_e e + (W_r h)[r] + (W_s h)[s]``, the same function,
  cheaper); aggregation is a sum over receivers written as ``index_add``
  (exported as ONNX ``ScatterND`` with ``reduction="add"``);
* decoder: MLP without LayerNorm to the normalised acceleration;
  semi-implicit Euler with ``dt = 1`` step: ``v' = v + a``, ``p' = p + v'``;
  kinematic (type 3) particles stay where they are.

MLPs have 2 hidden layers of width ``latent`` with ReLU, and LayerNorm on the
output (except the decoder), as in GNS.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field
from typing import Any

import torch
from torch import nn

from hybridmpm.neural.constants import FEATURE_VERSION, KINEMATIC, NUM_TYPES


@dataclass
class GnsConfig:
    """Architecture and the data facts baked into a model.

    ``dim`` 2 or 3; ``latent`` width; ``layers`` L message-passing blocks;
    ``radius`` R [m]; ``bounds`` ``[[lo, hi]] * dim`` [m]; ``vel_mean``,
    ``vel_std``, ``acc_mean``, ``acc_std`` per dimension in per-step units
    (metadata.json of the training data); ``noise_std`` the training noise on
    the last input velocity (its variance is added to the normalisation
    variances, as GNS does); ``t_in`` input positions (6).
    """

    dim: int
    radius: float
    bounds: list[list[float]]
    vel_mean: list[float]
    vel_std: list[float]
    acc_mean: list[float]
    acc_std: list[float]
    latent: int = 32
    layers: int = 3
    t_in: int = 6
    embedding: int = 16
    noise_std: float = 3e-4
    extra: dict[str, Any] = field(default_factory=dict)

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> GnsConfig:
        return cls(**d)


def mlp(inp: int, width: int, out: int, layer_norm: bool = True) -> nn.Sequential:
    """Two hidden layers of ``width`` with ReLU, then ``out``; LayerNorm on the output if asked."""
    mods: list[nn.Module] = [nn.Linear(inp, width), nn.ReLU(), nn.Linear(width, width), nn.ReLU(), nn.Linear(width, out)]
    if layer_norm:
        mods.append(nn.LayerNorm(out))
    return nn.Sequential(*mods)


class _EdgeBlock(nn.Module):
    """Edge MLP of one processor block with the first layer factored per node."""

    def __init__(self, latent: int) -> None:
        super().__init__()
        self.w_e = nn.Linear(latent, latent)
        self.w_r = nn.Linear(latent, latent, bias=False)
        self.w_s = nn.Linear(latent, latent, bias=False)
        self.rest = nn.Sequential(nn.ReLU(), nn.Linear(latent, latent), nn.ReLU(), nn.Linear(latent, latent), nn.LayerNorm(latent))

    def forward(self, e: torch.Tensor, h: torch.Tensor, senders: torch.Tensor, receivers: torch.Tensor) -> torch.Tensor:
        first = self.w_e(e) + self.w_r(h)[receivers] + self.w_s(h)[senders]
        return self.rest(first)


class GnsModel(nn.Module):
    """GNS simulator: ``forward(positions, particle_type, senders, receivers)``.

    Inputs: ``positions`` float32 [T_in, N, D] (oldest first, one model step
    apart, metres), ``particle_type`` int64 [N] (GNS codes 0–8), ``senders``,
    ``receivers`` int64 [E] (the radius graph on ``positions[-1]``, self-edges
    included). Returns ``(acceleration [N, D] in m/step², next_position
    [N, D])``. Use :meth:`normalised_acceleration` for the training loss.
    """

    vel_mean: torch.Tensor
    vel_std: torch.Tensor
    acc_mean: torch.Tensor
    acc_std: torch.Tensor
    lower: torch.Tensor
    upper: torch.Tensor

    def __init__(self, config: GnsConfig) -> None:
        super().__init__()
        self.config = config
        d, lat = config.dim, config.latent
        self.register_buffer("vel_mean", torch.tensor(config.vel_mean, dtype=torch.float32))
        self.register_buffer("vel_std", torch.tensor([math.sqrt(s * s + config.noise_std**2) for s in config.vel_std], dtype=torch.float32))
        self.register_buffer("acc_mean", torch.tensor(config.acc_mean, dtype=torch.float32))
        self.register_buffer("acc_std", torch.tensor([math.sqrt(s * s + config.noise_std**2) for s in config.acc_std], dtype=torch.float32))
        b = torch.tensor(config.bounds, dtype=torch.float32)
        self.register_buffer("lower", b[:, 0])
        self.register_buffer("upper", b[:, 1])
        self.inv_radius = 1.0 / config.radius
        self.embed = nn.Embedding(NUM_TYPES, config.embedding)
        node_in = (config.t_in - 1) * d + 2 * d + config.embedding
        self.node_encoder = mlp(node_in, lat, lat)
        self.edge_encoder = mlp(d + 1, lat, lat)
        self.edge_blocks = nn.ModuleList([_EdgeBlock(lat) for _ in range(config.layers)])
        self.node_blocks = nn.ModuleList([mlp(2 * lat, lat, lat) for _ in range(config.layers)])
        self.decoder = mlp(lat, lat, d, layer_norm=False)

    def input_features(
        self, positions: torch.Tensor, particle_type: torch.Tensor, senders: torch.Tensor, receivers: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """The encoder inputs: node features [N, 5·D + 2·D + 16] (normalised
        velocities oldest first, each ``(v − vel_mean)/vel_std_eff``; the lower
        then upper wall distances ``/R`` clipped to [−1, 1]; the type
        embedding) and edge features [E, D + 1] (``(p_s − p_r)/R`` and its norm)."""
        last = positions[-1]
        vel = (positions[1:] - positions[:-1] - self.vel_mean) / self.vel_std  # [T_in-1, N, D]
        n = last.shape[0]
        vel_feat = vel.permute(1, 0, 2).reshape(n, -1)
        walls = torch.cat([(last - self.lower) * self.inv_radius, (self.upper - last) * self.inv_radius], dim=1).clamp(-1.0, 1.0)
        nodes = torch.cat([vel_feat, walls, self.embed(particle_type)], dim=1)
        disp = (last[senders] - last[receivers]) * self.inv_radius
        edges = torch.cat([disp, torch.linalg.vector_norm(disp, dim=1, keepdim=True)], dim=1)
        return nodes, edges

    def normalised_acceleration(
        self, positions: torch.Tensor, particle_type: torch.Tensor, senders: torch.Tensor, receivers: torch.Tensor
    ) -> torch.Tensor:
        """The network's output: normalised acceleration [N, D]."""
        nodes, edges = self.input_features(positions, particle_type, senders, receivers)
        h = self.node_encoder(nodes)
        e = self.edge_encoder(edges)
        for edge_block, node_block in zip(self.edge_blocks, self.node_blocks):
            e = e + edge_block(e, h, senders, receivers)
            agg = torch.zeros_like(h).index_add(0, receivers, e)
            h = h + node_block(torch.cat([h, agg], dim=1))
        out: torch.Tensor = self.decoder(h)
        return out

    def forward(
        self, positions: torch.Tensor, particle_type: torch.Tensor, senders: torch.Tensor, receivers: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        acc = self.normalised_acceleration(positions, particle_type, senders, receivers) * self.acc_std + self.acc_mean
        last = positions[-1]
        nxt = last + (last - positions[-2]) + acc
        kin = (particle_type == KINEMATIC).unsqueeze(1)
        return acc, torch.where(kin, last, nxt)


__all__ = ["FEATURE_VERSION", "KINEMATIC", "NUM_TYPES", "GnsConfig", "GnsModel", "mlp"]
