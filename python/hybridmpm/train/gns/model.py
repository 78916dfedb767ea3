"""The GNS in PyTorch: a reusable encoder–processor–decoder and the simulator
that wraps it (paper App. A; Sanchez-Gonzalez et al. 2020, "Learning to
Simulate Complex Physics with Graph Networks").

* :class:`EncodeProcessDecode` — the graph network alone, on arbitrary node
  and edge inputs: encoder MLPs to ``latent``; a processor of ``L`` blocks,
  each with its own (non-shared) edge and node MLP and residuals on both; a
  decoder MLP. The simulator below uses it on GNS features; the diffusion
  controller reuses it (other input/output sizes, latents returned, an
  optionally zero-initialised output).
* :class:`GnsModel` — the simulator step ``(positions history, types, graph)
  → (acceleration, next position)``: :class:`~hybridmpm.train.gns.features.GnsFeatures`
  (velocity history, wall distances, type embedding, edge displacements,
  normalisation), then :class:`EncodeProcessDecode`, then denormalisation and
  semi-implicit Euler. All of it runs in ``forward`` so that the exported
  ONNX graph holds the feature construction too (docs/design.md).

Processor details: the edge MLP's first layer is factored into per-node
projections gathered per edge (``W·[e; h_r; h_s] = W_e e + (W_r h)[r] +
(W_s h)[s]``, the same function, cheaper); aggregation is a sum over
receivers written as ``index_add`` (exported as ONNX ``ScatterND`` with
``reduction="add"``). MLPs have 2 hidden layers of width ``latent`` with
ReLU, and LayerNorm on the output except the decoder's, as in GNS.

State-dict layout: :class:`GnsModel` holds ``features`` (buffers
``vel_mean``, ``vel_std``, ``acc_mean``, ``acc_std``, ``lower``, ``upper``
and ``embed``) and ``gnn`` (``node_encoder``, ``edge_encoder``,
``edge_blocks``, ``node_blocks``, ``decoder``). Checkpoints written before the
split (FEATURE_VERSION 1, flat keys such as ``embed.weight`` or
``node_encoder.0.weight``) load unchanged: :func:`remap_legacy_state_dict`
is applied by ``load_state_dict``. Parameter order is unchanged, so saved
optimiser states (indexed by position) resume too.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import asdict, dataclass, field
from typing import Any, Literal, overload

import torch
from torch import nn

from hybridmpm.conventions import T_IN
from hybridmpm.errors import InvalidInputError
from hybridmpm.neural.constants import FEATURE_VERSION, NUM_TYPES
from hybridmpm.train.gns.features import GnsFeatures
from hybridmpm.train.gns.grid_branch import GridBranch


@dataclass
class GnsConfig:
    """Architecture and the data facts baked into a model.

    ``dim`` 2 or 3; ``latent`` width; ``layers`` L message-passing blocks;
    ``radius`` R [m]; ``bounds`` ``[[lo, hi]] * dim`` [m]; ``vel_mean``,
    ``vel_std``, ``acc_mean``, ``acc_std`` per dimension in per-step units
    (metadata.json of the training data); ``noise_std`` the training noise on
    the last input velocity (its variance is added to the normalisation
    variances, as GNS does); ``t_in`` input positions (6); ``wall_reach``
    the distance, in units of R, at which the wall-distance features saturate
    (1: GNS's clip at the connectivity radius; larger lets a particle that
    moves more than R per step see a wall before it reaches it, see
    :func:`~hybridmpm.train.gns.features.wall_features`); ``grid`` nodes per
    dimension of the grid branch (:mod:`hybridmpm.train.gns.grid_branch`; 0:
    none, the plain GNS), ``grid_width`` and ``grid_levels`` its U-Net,
    ``grid_types`` the fluid types it counts, ``grid_rest_count`` the p2g
    count of a node inside resting fluid.
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
    t_in: int = T_IN
    embedding: int = 16
    noise_std: float = 3e-4
    wall_reach: float = 1.0
    extra: dict[str, Any] = field(default_factory=dict)
    grid: int = 0
    grid_width: int = 8
    grid_levels: int = 3
    grid_types: list[int] = field(default_factory=list)
    grid_rest_count: float = 1.0

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> GnsConfig:
        return cls(**d)


#: LayerNorm epsilon of every MLP (torch's default; the compiled inference graph reads it here).
LN_EPS = 1e-5


def mlp(inp: int, width: int, out: int, layer_norm: bool = True) -> nn.Sequential:
    """Two hidden layers of ``width`` with ReLU, then ``out``; LayerNorm on the output if asked.

    Maps float32 [..., inp] to [..., out]; indices 0, 2, 4 are the Linear
    layers, 5 the LayerNorm (present only with ``layer_norm``)."""
    mods: list[nn.Module] = [nn.Linear(inp, width), nn.ReLU(), nn.Linear(width, width), nn.ReLU(), nn.Linear(width, out)]
    if layer_norm:
        mods.append(nn.LayerNorm(out, eps=LN_EPS))
    return nn.Sequential(*mods)


class _EdgeBlock(nn.Module):
    """Edge MLP of one processor block with the first layer factored per node."""

    def __init__(self, latent: int) -> None:
        super().__init__()
        self.w_e = nn.Linear(latent, latent)
        self.w_r = nn.Linear(latent, latent, bias=False)
        self.w_s = nn.Linear(latent, latent, bias=False)
        self.rest = nn.Sequential(nn.ReLU(), nn.Linear(latent, latent), nn.ReLU(), nn.Linear(latent, latent), nn.LayerNorm(latent, eps=LN_EPS))

    def forward(self, e: torch.Tensor, h: torch.Tensor, senders: torch.Tensor, receivers: torch.Tensor) -> torch.Tensor:
        first = self.w_e(e) + self.w_r(h)[receivers] + self.w_s(h)[senders]
        return self.rest(first)


def _positive_int(name: str, v: int, minimum: int = 1) -> None:
    if not isinstance(v, int) or isinstance(v, bool) or v < minimum:
        raise InvalidInputError(f"{name}: must be an integer >= {minimum}, got {v!r}", name)


class EncodeProcessDecode(nn.Module):
    """The GNS graph network on arbitrary inputs (Sanchez-Gonzalez et al. 2020,
    Sec. 2; paper App. A: encoder, processor of ``L`` blocks, decoder).

    ``node_in``, ``edge_in``: widths of the node and edge inputs; ``node_out``
    width of the per-node output; ``latent`` width of every latent and hidden
    layer (paper: 128; GNS: 128); ``layers`` L message-passing blocks (paper:
    10; 0 gives an encoder–decoder that ignores the edges).
    ``zero_init_output``: zero the decoder's last layer so the output is
    exactly 0 at initialisation whatever the input (ControlNet-style heads
    that start as a no-op); gradients still reach every parameter after the
    first update of that layer.

    Stages (each callable on its own):

    * :meth:`encode` ``(nodes [N, node_in], edges [E, edge_in]) → (h [N,
      latent], e [E, latent])``;
    * :meth:`process` ``(h, e, senders, receivers) → (h, e)`` on *any*
      latents of width ``latent`` (``L`` blocks: ``e += φ_e(e, h_r, h_s)``,
      ``h += φ_v(h, Σ_{edges into i} e)``);
    * :meth:`decode` ``h → [N, node_out]`` (MLP without LayerNorm).

    ``forward(nodes, edges, senders, receivers, return_latents=False)`` runs
    the three; with ``return_latents=True`` it returns ``(out, h, e)`` (the
    processed latents). Dtype float32 throughout; ``senders``/``receivers``
    int64 [E] index rows of the node tensors (an edge sends from its sender to
    its receiver; receivers without edges aggregate 0).

    Raises :class:`~hybridmpm.errors.InvalidInputError` for sizes < 1 or
    ``layers`` < 0; inputs of the wrong width raise torch's ``RuntimeError``.
    """

    def __init__(self, node_in: int, edge_in: int, node_out: int, latent: int = 128, layers: int = 10, zero_init_output: bool = False) -> None:
        super().__init__()
        for name, v in (("node_in", node_in), ("edge_in", edge_in), ("node_out", node_out), ("latent", latent)):
            _positive_int(name, v)
        _positive_int("layers", layers, minimum=0)
        self.node_in, self.edge_in, self.node_out, self.latent, self.layers = node_in, edge_in, node_out, latent, layers
        self.node_encoder = mlp(node_in, latent, latent)
        self.edge_encoder = mlp(edge_in, latent, latent)
        self.edge_blocks = nn.ModuleList([_EdgeBlock(latent) for _ in range(layers)])
        self.node_blocks = nn.ModuleList([mlp(2 * latent, latent, latent) for _ in range(layers)])
        self.decoder = mlp(latent, latent, node_out, layer_norm=False)
        if zero_init_output:
            last = self.decoder[-1]
            assert isinstance(last, nn.Linear)
            nn.init.zeros_(last.weight)
            nn.init.zeros_(last.bias)

    def encode(self, nodes: torch.Tensor, edges: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Node latents [N, latent] and edge latents [E, latent] from inputs [N, node_in], [E, edge_in]."""
        return self.node_encoder(nodes), self.edge_encoder(edges)

    def process(self, h: torch.Tensor, e: torch.Tensor, senders: torch.Tensor, receivers: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """``L`` message-passing blocks with residuals on latents ``h`` [N, latent], ``e`` [E, latent]; returns the updated ``(h, e)``."""
        for edge_block, node_block in zip(self.edge_blocks, self.node_blocks):
            e = e + edge_block(e, h, senders, receivers)
            agg = torch.zeros_like(h).index_add(0, receivers, e)
            h = h + node_block(torch.cat([h, agg], dim=1))
        return h, e

    def decode(self, h: torch.Tensor) -> torch.Tensor:
        """Per-node output [N, node_out] from latents [N, latent]."""
        out: torch.Tensor = self.decoder(h)
        return out

    @overload
    def forward(
        self, nodes: torch.Tensor, edges: torch.Tensor, senders: torch.Tensor, receivers: torch.Tensor, return_latents: Literal[False] = ...
    ) -> torch.Tensor: ...

    @overload
    def forward(
        self, nodes: torch.Tensor, edges: torch.Tensor, senders: torch.Tensor, receivers: torch.Tensor, return_latents: Literal[True]
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]: ...

    def forward(
        self, nodes: torch.Tensor, edges: torch.Tensor, senders: torch.Tensor, receivers: torch.Tensor, return_latents: bool = False
    ) -> torch.Tensor | tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """``decode(process(encode(nodes, edges), senders, receivers))``: [N, node_out];
        with ``return_latents`` also the processed latents ``h`` [N, latent], ``e`` [E, latent]."""
        h, e = self.encode(nodes, edges)
        h, e = self.process(h, e, senders, receivers)
        out = self.decode(h)
        return (out, h, e) if return_latents else out


#: Pre-split (flat) state-dict names → their place in the composed :class:`GnsModel`.
LEGACY_PREFIXES: dict[str, str] = {
    **{name: f"features.{name}" for name in ("vel_mean", "vel_std", "acc_mean", "acc_std", "lower", "upper", "embed")},
    **{name: f"gnn.{name}" for name in ("node_encoder", "edge_encoder", "edge_blocks", "node_blocks", "decoder")},
}


def remap_legacy_state_dict(state_dict: Mapping[str, Any], prefix: str = "") -> dict[str, Any]:
    """A copy of ``state_dict`` with pre-split :class:`GnsModel` keys renamed
    (``embed.weight`` → ``features.embed.weight``, ``vel_std`` →
    ``features.vel_std``, ``node_encoder.0.weight`` →
    ``gnn.node_encoder.0.weight``, ... see :data:`LEGACY_PREFIXES`); keys
    already in the new layout, and keys outside ``prefix``, are kept as they
    are. Values are not copied. Order is kept."""
    out: dict[str, Any] = {}
    for key, value in state_dict.items():
        new = key
        if key.startswith(prefix):
            local = key[len(prefix) :]
            head, _, _ = local.partition(".")
            if head in LEGACY_PREFIXES:
                new = prefix + LEGACY_PREFIXES[head] + local[len(head) :]
        out[new] = value
    return out


def _legacy_pre_hook(module: nn.Module, state_dict: dict[str, Any], prefix: str, *args: Any) -> None:
    remapped = remap_legacy_state_dict(state_dict, prefix)
    if list(remapped) != list(state_dict):
        state_dict.clear()
        state_dict.update(remapped)


class GnsModel(nn.Module):
    """GNS simulator step: ``forward(positions, particle_type, senders, receivers)``
    (paper App. A; Sanchez-Gonzalez et al. 2020).

    Inputs: ``positions`` float32 [T_in, N, D] (oldest first, one model step
    apart, metres), ``particle_type`` int64 [N] (GNS codes 0–8), ``senders``,
    ``receivers`` int64 [E] (the radius graph on ``positions[-1]``, self-edges
    included). Returns ``(acceleration [N, D] in m/step², next_position
    [N, D] in m)``, kinematic (type 3) particles kept in place. Use
    :meth:`normalised_acceleration` for the training loss.

    Composition: ``features`` (:class:`~hybridmpm.train.gns.features.GnsFeatures`)
    → ``gnn`` (:class:`EncodeProcessDecode`, ``node_in = features.node_size``,
    ``edge_in = D + 1``, ``node_out = D``) → ``features.integrate``.
    Old flat checkpoints load through :func:`remap_legacy_state_dict`.

    Raises :class:`~hybridmpm.errors.InvalidInputError` for an inconsistent
    ``config`` (see :class:`~hybridmpm.train.gns.features.GnsFeatures` and
    :class:`EncodeProcessDecode`) and, in ``forward``, for ``positions`` not
    [t_in, N, dim].
    """

    def __init__(self, config: GnsConfig) -> None:
        super().__init__()
        self.config = config
        # registration order (features first: embed, then the network) keeps the
        # pre-split parameter order, so saved optimiser states still line up
        self.features = GnsFeatures(
            dim=config.dim, radius=config.radius, bounds=config.bounds, vel_mean=config.vel_mean, vel_std=config.vel_std,
            acc_mean=config.acc_mean, acc_std=config.acc_std, noise_std=config.noise_std, t_in=config.t_in,
            embedding=config.embedding, num_types=NUM_TYPES, wall_reach=config.wall_reach,
        )  # fmt: skip
        self.gnn = EncodeProcessDecode(self.features.node_size, self.features.edge_size, config.dim, latent=config.latent, layers=config.layers)
        self.branch: GridBranch | None = None
        if config.grid:
            self.branch = GridBranch(
                config.dim, config.bounds, config.latent, config.grid, config.grid_width, config.grid_levels, config.grid_types,
                config.grid_rest_count, config.t_in,
            )  # fmt: skip
        self.register_load_state_dict_pre_hook(_legacy_pre_hook)

    def input_features(
        self, positions: torch.Tensor, particle_type: torch.Tensor, senders: torch.Tensor, receivers: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """The encoder inputs: node features [N, 5·D + 2·D + 16] (normalised
        velocities oldest first, each ``(v − vel_mean)/vel_std_eff``; the lower
        then upper wall distances ``/R`` clipped to [−1, 1]; the type
        embedding) and edge features [E, D + 1] (``(p_s − p_r)/R`` and its norm).
        Same as ``self.features(...)``."""
        nodes, edges = self.features(positions, particle_type, senders, receivers)
        return nodes, edges

    def normalised_acceleration(
        self, positions: torch.Tensor, particle_type: torch.Tensor, senders: torch.Tensor, receivers: torch.Tensor, batch: torch.Tensor | None = None,
        windows: int = 1,
    ) -> torch.Tensor:  # fmt: skip
        """The network's output: normalised acceleration float32 [N, D]
        (``(a − acc_mean)/acc_std_eff``; compare with
        ``features.normalise_acceleration(target)``). ``batch`` int64 [N]
        (the window of each particle of a batch of ``windows`` disjoint
        graphs; default one window) keeps the windows apart on the grid
        branch's grid; without a branch it is not read."""
        nodes, edges = self.features(positions, particle_type, senders, receivers)
        if self.branch is None:
            out: torch.Tensor = self.gnn(nodes, edges, senders, receivers)
            return out
        h, e = self.gnn.encode(nodes, edges)
        nv = (self.config.t_in - 1) * self.config.dim  # the node features start with the normalised velocities
        h = h + self.branch(positions[-1], particle_type, nodes[:, :nv], batch, windows)
        h, e = self.gnn.process(h, e, senders, receivers)
        return self.gnn.decode(h)

    def forward(
        self, positions: torch.Tensor, particle_type: torch.Tensor, senders: torch.Tensor, receivers: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        return self.features.integrate(positions, particle_type, self.normalised_acceleration(positions, particle_type, senders, receivers))


__all__ = [
    "FEATURE_VERSION", "LEGACY_PREFIXES", "LN_EPS", "NUM_TYPES", "EncodeProcessDecode", "GnsConfig", "GnsModel", "mlp",
    "remap_legacy_state_dict",
]  # fmt: skip
