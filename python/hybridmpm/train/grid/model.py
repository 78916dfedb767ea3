"""The grid model: a learned simulator that sees the whole fluid through a grid (needs torch).

A NeuralMPM-style model (Rochman Sharabi, Lewin, Louppe, arXiv 2408.15753)
on this engine's own transfer kernel. One call covers one model step of
``r_t`` frames:

1. **p2g** (the quadratic B-spline of MLS-MPM, as :func:`hybridmpm.mpm.grid_mass`
   splats mass) of the fluid and obstacle particles onto a grid of ``G^D``
   nodes spanning the model's bounds (one node of margin beyond each wall):
   per node the particle count of each material and of the obstacles (over
   ``rest_count``, the count of a node inside resting fluid), the fluid's
   mass-weighted mean velocity of each of the ``t_in − 1`` last steps (over
   ``velocity_scale``), and a mask of the nodes beyond the walls;
2. a **U-Net** (:class:`UNet`) maps these channels to ``r_t`` grid velocity
   corrections ``Δv_k`` (one per frame), added to the last step's grid
   velocity;
3. **g2p** and advection, frame by frame: each fluid particle moves with
   the grid velocity at its position plus gravity (applied analytically, as
   Neural SPH subtracts it from the target), plus ``β`` times its own
   deviation from the grid's mean velocity at the start (a learned FLIP-like
   share ``β = sigmoid(flip_logit)``), and is clipped to the bounds, as the
   engine's walls keep it in. Obstacle particles do not move.
4. optionally (``pressure``) a density correction after each frame
   (:func:`pressure_shift`, learned strength).

Training runs the whole call in torch; the exported ``.onnx`` file holds the
U-Net alone (standard operators), and the run time
(:class:`hybridmpm.neural.grid.GridRuntime`) does p2g, g2p and the
advection in Rust with the same arithmetic (the tests hold the two equal).
Batched training concatenates the windows' particles and gives
each its window index (``batch``), which offsets its grid nodes.

Shapes: positions float32 ``[T, P, D]``; particle_type int64 ``[P]``; batch
int64 ``[P]``. Units: metres, seconds (the frame is ``dt_frame``).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np
import torch
from torch import nn

from hybridmpm.conventions import GNS_KINEMATIC, GNS_SAND, GNS_WATER
from hybridmpm.errors import InvalidInputError
from hybridmpm.neural.grid import GRID_KIND, MASS_FLOOR


@dataclass
class GridConfig:
    """Architecture and physical constants of a :class:`GridModel`.

    ``dim`` 2 or 3; ``bounds`` ``[[lo, hi]] * dim`` [m], the walls particles
    are clipped to; ``grid`` nodes per dimension G (even, ≥ 8; the node
    spacing is ``(hi − lo) / (G − 3)``); ``width`` channels of the U-Net's
    first level (doubled per level); ``levels`` resolutions of the U-Net
    (G must be divisible by ``2^(levels − 1)``); ``t_in`` positions read
    (``t_in − 1`` velocities); ``r_t`` frames per call; ``dt_frame`` [s];
    ``gravity`` [m/s²] (D values); ``velocity_scale`` [m/s] and
    ``rest_count`` (particles per node in resting fluid) normalise the
    inputs; ``types`` the GNS particle types the model simulates;
    ``pressure`` adds, after each frame's advection, a displacement down the
    gradient of the fluid's excess density on the grid (:func:`pressure_shift`)
    with a learned strength; ``flip_init`` the initial FLIP share ``β`` in
    (0, 1) (default 0.5; learned from there).
    """

    dim: int
    bounds: list[list[float]]
    dt_frame: float
    gravity: list[float]
    grid: int = 64
    width: int = 16
    levels: int = 3
    t_in: int = 6
    r_t: int = 4
    velocity_scale: float = 1.0
    rest_count: float = 1.0
    types: list[int] = field(default_factory=lambda: [GNS_WATER])
    pressure: bool = False
    flip_init: float = 0.5

    def validate(self) -> GridConfig:
        if self.dim not in (2, 3):
            raise InvalidInputError(f"dim: must be 2 or 3, got {self.dim!r}", "dim")
        if len(self.bounds) != self.dim or not all(len(b) == 2 and float(b[0]) < float(b[1]) for b in self.bounds):
            raise InvalidInputError(f"bounds: must be {self.dim} pairs [lo, hi] with lo < hi, got {self.bounds!r}", "bounds")
        if len(self.gravity) != self.dim:
            raise InvalidInputError(f"gravity: must have {self.dim} components, got {self.gravity!r}", "gravity")
        if not isinstance(self.levels, int) or not 1 <= self.levels <= 5:
            raise InvalidInputError(f"levels: must be an integer in [1, 5], got {self.levels!r}", "levels")
        step = 2 ** (self.levels - 1)
        if not isinstance(self.grid, int) or self.grid < 8 or self.grid % max(2, step) or self.grid > 256:
            raise InvalidInputError(f"grid: must be an even integer in [8, 256] divisible by 2^(levels-1) = {step}, got {self.grid!r}", "grid")
        for name in ("width", "t_in", "r_t"):
            v = getattr(self, name)
            if not isinstance(v, int) or v < (2 if name == "t_in" else 1):
                raise InvalidInputError(f"{name}: must be an integer >= {2 if name == 't_in' else 1}, got {v!r}", name)
        if isinstance(self.flip_init, bool) or not (isinstance(self.flip_init, (int, float)) and 0.0 < self.flip_init < 1.0):
            raise InvalidInputError(f"flip_init: must be a number in (0, 1), got {self.flip_init!r}", "flip_init")
        for name in ("dt_frame", "velocity_scale", "rest_count"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and v > 0):
                raise InvalidInputError(f"{name}: must be a number > 0, got {v!r}", name)
        return self

    @property
    def materials(self) -> list[int]:
        """The fluid particle types, in channel order (water, then sand)."""
        return [t for t in (GNS_WATER, GNS_SAND) if t in self.types]

    @property
    def in_channels(self) -> int:
        """Count channels (one per material + obstacles), velocity channels, the wall mask."""
        return len(self.materials) + 1 + (self.t_in - 1) * self.dim + 1

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


def grid_geometry(bounds: torch.Tensor, grid: int) -> tuple[torch.Tensor, torch.Tensor]:
    """``(origin [D], spacing [D])`` of the grid: node ``i`` sits at
    ``origin + i·spacing`` with ``spacing = (hi − lo)/(G − 3)`` and
    ``origin = lo − spacing``, so that the 3-node stencil of a particle
    anywhere in ``[lo, hi]`` stays inside the ``G`` nodes."""
    spacing = (bounds[:, 1] - bounds[:, 0]) / (grid - 3)
    return bounds[:, 0] - spacing, spacing


def stencil(x: torch.Tensor, origin: torch.Tensor, spacing: torch.Tensor, grid: int, batch: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """Quadratic B-spline stencil of MLS-MPM for positions ``x`` float [P, D]:
    ``(weights [P, 3^D], node [P, 3^D] int64)``, the flat node index (row-major
    over the D axes, plus ``batch · G^D`` when ``batch`` [P] is given). The
    weights of a particle sum to 1 and are differentiable in ``x``. Positions
    must lie within the grid's bounds (callers clip them)."""
    d = x.shape[-1]
    u = (x - origin) / spacing
    base = torch.floor(u - 0.5)
    fx = u - base
    w = torch.stack([0.5 * (1.5 - fx) ** 2, 0.75 - (fx - 1.0) ** 2, 0.5 * (fx - 0.5) ** 2], dim=-1)  # [P, D, 3]
    b = base.to(torch.int64).clamp(0, grid - 3)
    offs = torch.arange(3, dtype=torch.int64, device=x.device)
    if d == 2:
        weights = (w[:, 0, :, None] * w[:, 1, None, :]).reshape(-1, 9)
        node = ((b[:, 0, None, None] + offs[:, None]) * grid + (b[:, 1, None, None] + offs[None, :])).reshape(-1, 9)
    else:
        weights = (w[:, 0, :, None, None] * w[:, 1, None, :, None] * w[:, 2, None, None, :]).reshape(-1, 27)
        node = (
            ((b[:, 0, None, None, None] + offs[:, None, None]) * grid + (b[:, 1, None, None, None] + offs[None, :, None])) * grid
            + (b[:, 2, None, None, None] + offs[None, None, :])
        ).reshape(-1, 27)
    if batch is not None:
        node = node + batch[:, None] * grid**d
    return weights, node


def p2g(values: torch.Tensor, weights: torch.Tensor, node: torch.Tensor, nodes: int) -> torch.Tensor:
    """Splat per-particle ``values`` [P, C] onto ``nodes`` grid nodes with a
    :func:`stencil`: returns [nodes, C], ``Σ_p w_pi · values_p`` per node."""
    c = values.shape[1]
    src = (weights[:, :, None] * values[:, None, :]).reshape(-1, c)
    idx = node.reshape(-1, 1).expand(-1, c)
    return torch.zeros(nodes, c, dtype=values.dtype, device=values.device).scatter_add(0, idx, src)


def g2p(grid_values: torch.Tensor, weights: torch.Tensor, node: torch.Tensor) -> torch.Tensor:
    """Interpolate node values [nodes, C] at particles with a :func:`stencil`:
    returns [P, C], ``Σ_i w_pi · grid_i``."""
    return (grid_values[node] * weights[:, :, None]).sum(dim=1)


def rest_count(trajectories: list[tuple[np.ndarray, np.ndarray]], bounds: list[list[float]], grid: int) -> float:
    """Particles per grid node inside resting fluid: the 90th percentile of the
    first frames' fluid counts over the nodes that hold any, on a grid of
    ``grid`` nodes per dimension over ``bounds`` [m] (trajectories: positions
    float32 [T, N, D] and GNS particle types int64 [N]; the first 8 are
    read). A normalisation of the count channels (:attr:`GridConfig.rest_count`)."""
    b = torch.tensor(bounds, dtype=torch.float32)
    origin, spacing = grid_geometry(b, grid)
    counts = []
    for pos, pt in trajectories[:8]:
        x = torch.from_numpy(pos[0][pt != GNS_KINEMATIC])
        w, node = stencil(x, origin, spacing, grid)
        c = p2g(torch.ones(len(x), 1), w, node, grid ** x.shape[1])[:, 0]
        counts.append(c[c > 0.05].numpy())
    return float(np.percentile(np.concatenate(counts), 90))


def pressure_shift(
    x: torch.Tensor, fluid: torch.Tensor, origin: torch.Tensor, spacing: torch.Tensor, grid: int, rest_count: float, batch: torch.Tensor | None, windows: int
) -> torch.Tensor:
    """The direction a compressed fluid pushes its particles [m per unit strength],
    float [P, D]: the fluid's p2g count over ``rest_count`` less 1, clipped at 0
    (the excess density ``e``), its central-difference gradient on the nodes
    (edges replicated), read back at the particles and scaled by the spacing:
    ``g2p(∇e)·spacing``. Subtracted with a learned strength it moves particles
    out of compressed regions, as a one-iteration position-based density
    constraint (Macklin & Müller 2013) on the grid would."""
    d = x.shape[1]
    w, node = stencil(x, origin, spacing, grid, batch)
    e = torch.relu(p2g(fluid, w, node, windows * grid**d) / rest_count - 1.0).reshape(windows, *[grid] * d)
    grads = []
    for axis in range(1, d + 1):
        pad_lo = e.narrow(axis, 0, 1)
        pad_hi = e.narrow(axis, grid - 1, 1)
        padded = torch.cat([pad_lo, e, pad_hi], dim=axis)
        grads.append(0.5 * (padded.narrow(axis, 2, grid) - padded.narrow(axis, 0, grid)))
    grad = torch.stack(grads, dim=-1).reshape(windows * grid**d, d)
    return g2p(grad, w, node) * spacing


class _Block(nn.Module):
    def __init__(self, conv: type, c_in: int, c_out: int) -> None:
        super().__init__()
        self.a = conv(c_in, c_out, 3, padding=1)
        self.b = conv(c_out, c_out, 3, padding=1)
        self.act = nn.SiLU()

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.act(self.b(self.act(self.a(x))))


class UNet(nn.Module):
    """A small U-Net (Ronneberger et al. 2015) over a 2D or 3D grid: per
    level two 3^D convolutions with SiLU, stride-2 convolutions down,
    transposed convolutions up, skip connections by concatenation; the
    last 1×1 convolution starts at zero (the model starts as the
    "keep the grid velocity" baseline)."""

    def __init__(self, dim: int, c_in: int, c_out: int, width: int, levels: int) -> None:
        super().__init__()
        conv = nn.Conv2d if dim == 2 else nn.Conv3d
        up = nn.ConvTranspose2d if dim == 2 else nn.ConvTranspose3d
        widths = [width * 2**i for i in range(levels)]
        self.enc = nn.ModuleList()
        self.down = nn.ModuleList()
        self.up = nn.ModuleList()
        self.dec = nn.ModuleList()
        c = c_in
        for i, w in enumerate(widths):
            self.enc.append(_Block(conv, c, w))
            c = w
            if i < levels - 1:
                self.down.append(conv(w, w, 2, stride=2))
        for i in reversed(range(levels - 1)):
            self.up.append(up(widths[i + 1], widths[i], 2, stride=2))
            self.dec.append(_Block(conv, 2 * widths[i], widths[i]))
        self.out = conv(widths[0], c_out, 1)
        nn.init.zeros_(self.out.weight)
        if self.out.bias is not None:
            nn.init.zeros_(self.out.bias)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        skips = []
        for i, block in enumerate(self.enc):
            x = block(x)
            if i < len(self.down):
                skips.append(x)
                x = self.down[i](x)
        for up, block in zip(self.up, self.dec):
            x = block(torch.cat([up(x), skips.pop()], dim=1))
        return self.out(x)


class GridModel(nn.Module):
    """The grid model (module doc). :meth:`forward` takes one call;
    :meth:`frames` returns every frame of it (for training losses)."""

    lo: torch.Tensor
    hi: torch.Tensor
    origin: torch.Tensor
    spacing: torch.Tensor
    gravity: torch.Tensor
    wall_mask: torch.Tensor

    def __init__(self, config: GridConfig) -> None:
        super().__init__()
        self.config = config.validate()
        d = config.dim
        self.net = UNet(d, config.in_channels, config.r_t * d, config.width, config.levels)
        self.flip_logit = nn.Parameter(torch.full((), math.log(config.flip_init / (1.0 - config.flip_init))))
        if config.pressure:
            self.pressure_logit = nn.Parameter(torch.full((), -2.0))
        b = torch.tensor(config.bounds, dtype=torch.float32)
        origin, spacing = grid_geometry(b, config.grid)
        self.register_buffer("lo", b[:, 0].clone(), persistent=False)
        self.register_buffer("hi", b[:, 1].clone(), persistent=False)
        self.register_buffer("origin", origin, persistent=False)
        self.register_buffer("spacing", spacing, persistent=False)
        self.register_buffer("gravity", torch.tensor(config.gravity, dtype=torch.float32), persistent=False)
        g = config.grid
        axes = [origin[k] + spacing[k] * torch.arange(g, dtype=torch.float32) for k in range(d)]
        mesh = torch.stack(torch.meshgrid(*axes, indexing="ij"), dim=0)  # [D, G, ...]
        outside = ((mesh < b[:, 0].reshape(d, *[1] * d)) | (mesh > b[:, 1].reshape(d, *[1] * d))).any(dim=0)
        self.register_buffer("wall_mask", outside.to(torch.float32)[None], persistent=False)  # [1, G, ...]

    @property
    def dt_step(self) -> float:
        return self.config.dt_frame * self.config.r_t

    def frames(self, positions: torch.Tensor, particle_type: torch.Tensor, batch: torch.Tensor | None = None, windows: int = 1) -> torch.Tensor:
        """All ``r_t`` frames of one call: positions float [t_in, P, D] (oldest
        first, one step apart) → float [r_t, P, D]. ``batch`` int64 [P] (window
        of each particle, default all 0) and ``windows`` the number of windows."""
        cfg = self.config
        d, g = cfg.dim, cfg.grid
        nodes = windows * g**d
        x0 = positions[-1]
        fluid = (particle_type != GNS_KINEMATIC).to(x0.dtype)[:, None]
        vel = (positions[1:] - positions[:-1]) / self.dt_step  # [t_in-1, P, D]
        weights, node = stencil(x0, self.origin, self.spacing, g, batch)
        counts = [(particle_type == t).to(x0.dtype)[:, None] for t in cfg.materials] + [(particle_type == GNS_KINEMATIC).to(x0.dtype)[:, None]]
        v_fluid = (vel * fluid[None]).permute(1, 0, 2).reshape(x0.shape[0], -1)  # [P, (t_in-1)·D]
        splat = p2g(torch.cat(counts + [fluid, v_fluid], dim=1), weights, node, nodes)  # [nodes, M+1+1+V]
        m = len(counts)
        count = splat[:, :m]
        mass = splat[:, m : m + 1]
        # [nodes, (t_in-1)·D] m/s; exact for a rigid translation (a node under the floor weighs less in every g2p)
        v_grid = splat[:, m + 1 :] / mass.clamp(min=MASS_FLOOR)
        features = torch.cat([count / cfg.rest_count, v_grid / cfg.velocity_scale], dim=1)  # [nodes, C-1]
        grid_in = features.reshape(windows, *[g] * d, features.shape[1]).permute(0, d + 1, *range(1, d + 1))
        grid_in = torch.cat([grid_in, self.wall_mask.expand(windows, *self.wall_mask.shape)], dim=1)
        dv = self.net(grid_in).permute(0, *range(2, d + 2), 1).reshape(nodes, cfg.r_t, d) * cfg.velocity_scale  # m/s
        v_last = v_grid[:, -d:]  # [nodes, D]
        beta = torch.sigmoid(self.flip_logit)
        own = beta * (vel[-1] - g2p(v_last, weights, node))  # [P, D]
        dt = cfg.dt_frame
        x = x0
        out = []
        for k in range(cfg.r_t):
            if k:
                weights, node = stencil(x, self.origin, self.spacing, g, batch)
            t_k = (cfg.r_t / 2 + k + 0.5) * dt  # time from the middle of the last step to the middle of frame k
            u = g2p(v_last + dv[:, k], weights, node) + own + self.gravity * t_k
            x = torch.minimum(torch.maximum(x + fluid * u * dt, self.lo), self.hi)
            if cfg.pressure:
                shift = pressure_shift(x, fluid, self.origin, self.spacing, g, cfg.rest_count, batch, windows)
                x = torch.minimum(torch.maximum(x - nn.functional.softplus(self.pressure_logit) * fluid * shift, self.lo), self.hi)
            x = fluid * x + (1 - fluid) * x0
            out.append(x)
        return torch.stack(out)

    def forward(self, positions: torch.Tensor, particle_type: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """One call as the runtime runs it: ``positions`` float32 [t_in, N, D],
        ``particle_type`` int64 [N] → ``(acceleration [N, D] in m per step²,
        next_position [N, D])``, the GNS graph's outputs."""
        nxt = self.frames(positions, particle_type)[-1]
        acc = nxt - 2 * positions[-1] + positions[-2]
        return acc, nxt


__all__ = ["GRID_KIND", "MASS_FLOOR", "GridConfig", "GridModel", "UNet", "g2p", "grid_geometry", "p2g", "pressure_shift", "rest_count", "stencil"]
