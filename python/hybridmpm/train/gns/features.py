"""Feature construction of the GNS, in one place (paper App. A "Input"; GNS,
Sanchez-Gonzalez et al. 2020, Sec. 2 and App. C.1).

Everything between raw particle positions and the network's inputs, and
between its output and the next positions, lives here, as torch operations,
so that :class:`~hybridmpm.train.gns.model.GnsModel` runs it inside its
``forward`` and the exported ONNX graph holds it too (docs/design.md):

* :func:`velocity_features` — the last ``T_in − 1`` velocities, finite
  differences of ``T_in`` positions one model step apart, each normalised
  ``(v − vel_mean) / vel_std_eff`` and flattened oldest first;
* :func:`wall_features` — the distances to the lower then the upper domain
  walls divided by ``wall_reach·R`` and clipped to [−1, 1] (``wall_reach`` 1:
  GNS's clip at ``R``);
* :func:`edge_features` — ``(p_s − p_r) / R`` and its norm for every edge
  ``senders → receivers``;
* :func:`euler_step` — the semi-implicit Euler update with ``dt = 1`` model
  step: ``v' = v + a``, ``p' = p + v'``; kinematic particles (type 3) stay;
* :func:`effective_std` — the normalisation std with the training-noise
  variance added (``sqrt(std² + noise_std²)``, as GNS does);
* :class:`GnsFeatures` — the module holding the dataset statistics (buffers),
  the domain bounds and the particle-type embedding, which composes the above.

Units: positions in metres on the unit domain; velocities in m/step and
accelerations in m/step² (a *step* is the model step, ``r_t`` frames).
Arrays are float32 (positions, features) and int64 (types, edges).
Changing any number produced here changes what a trained model sees: bump
:data:`~hybridmpm.neural.constants.FEATURE_VERSION`.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import torch
from torch import nn

from hybridmpm.conventions import GNS_KINEMATIC, T_IN
from hybridmpm.errors import InvalidInputError
from hybridmpm.neural.constants import NUM_TYPES, WALL_REACH_MAX


def effective_std(std: Sequence[float], noise_std: float) -> list[float]:
    """Per-dimension normalisation std with the training noise folded in:
    ``sqrt(std² + noise_std²)`` (GNS adds the noise variance so that the
    normalised noisy inputs keep unit scale). Same units as ``std``."""
    return [math.sqrt(s * s + noise_std**2) for s in std]


def velocity_features(positions: torch.Tensor, vel_mean: torch.Tensor, vel_std: torch.Tensor) -> torch.Tensor:
    """Normalised velocity history.

    ``positions`` float32 [T, N, D] (oldest first, one model step apart, m);
    ``vel_mean``, ``vel_std`` float32 [D] (m/step; ``vel_std`` already the
    effective std, see :func:`effective_std`). Returns float32
    [N, (T − 1)·D]: per particle the ``T − 1`` velocities
    ``(p_{k+1} − p_k − vel_mean) / vel_std`` oldest first, each ``D`` wide.
    """
    vel = (positions[1:] - positions[:-1] - vel_mean) / vel_std  # [T-1, N, D]
    n = positions.shape[1]
    return vel.permute(1, 0, 2).reshape(n, -1)


def wall_features(last: torch.Tensor, lower: torch.Tensor, upper: torch.Tensor, inv_radius: float) -> torch.Tensor:
    """Distances to the domain walls in units of the distance at which they saturate.

    ``last`` float32 [N, D] current positions (m); ``lower``, ``upper``
    float32 [D] the walls (m); ``inv_radius`` ``1 / (wall_reach·R)`` (1/m;
    GNS, Sanchez-Gonzalez et al. 2020 App. C.1, clips at the connectivity
    radius: ``wall_reach`` 1). Returns float32 [N, 2·D]: ``(p − lower)·inv_radius``
    then ``(upper − p)·inv_radius``, clipped to [−1, 1] (a particle farther
    than ``1/inv_radius`` from a wall sees 1).

    Why the reach may exceed ``R``: at ``r_t = 4`` a thrown block
    moves 2–4 R per model step, so with GNS's clip a floor can be hit within
    one step without ever being seen; a network trained on such data learns
    to hedge on speed alone and slows every fast fall
    (``benchmarks/free_fall.py``).
    """
    return torch.cat([(last - lower) * inv_radius, (upper - last) * inv_radius], dim=1).clamp(-1.0, 1.0)


def edge_features(last: torch.Tensor, senders: torch.Tensor, receivers: torch.Tensor, inv_radius: float) -> torch.Tensor:
    """Relative displacement features of the radius graph.

    ``last`` float32 [N, D] current positions (m); ``senders``,
    ``receivers`` int64 [E] node indices (an edge carries a message from its
    sender to its receiver; self-edges allowed); ``inv_radius`` ``1 / R``.
    Returns float32 [E, D + 1]: ``(p_s − p_r)/R`` and its Euclidean norm.
    Indices out of ``[0, N)`` raise torch's ``IndexError``.
    """
    disp = (last[senders] - last[receivers]) * inv_radius
    return torch.cat([disp, torch.linalg.vector_norm(disp, dim=1, keepdim=True)], dim=1)


def euler_step(positions: torch.Tensor, acceleration: torch.Tensor, particle_type: torch.Tensor) -> torch.Tensor:
    """Semi-implicit Euler with ``dt = 1`` model step (GNS Sec. 2).

    ``positions`` float32 [T ≥ 2, N, D] (m, oldest first); ``acceleration``
    float32 [N, D] (m/step², *not* normalised); ``particle_type`` int64 [N].
    Returns the next positions float32 [N, D]:
    ``p' = p + (p − p_prev) + a``; kinematic particles (type
    :data:`~hybridmpm.neural.constants.GNS_KINEMATIC`) keep their position.
    """
    last = positions[-1]
    nxt = last + (last - positions[-2]) + acceleration
    kin = (particle_type == GNS_KINEMATIC).unsqueeze(1)
    return torch.where(kin, last, nxt)


def _check_vector(name: str, v: Sequence[float], dim: int, positive: bool = False) -> None:
    if len(v) != dim or not all(math.isfinite(float(x)) and (float(x) > 0 or not positive) for x in v):
        want = "positive finite numbers" if positive else "finite numbers"
        raise InvalidInputError(f"{name}: must be {dim} {want} (one per dimension), got {list(v)!r}", name)


class GnsFeatures(nn.Module):
    """GNS input features and output integration (paper App. A "Input";
    GNS, Sanchez-Gonzalez et al. 2020).

    ``dim`` 2 or 3; ``radius`` R [m]; ``bounds`` ``[[lo, hi]] * dim`` [m];
    ``vel_mean``, ``vel_std``, ``acc_mean``, ``acc_std`` per dimension in
    per-step units (metadata.json of the training data, at the model step);
    ``noise_std`` the training-noise std on the last input velocity (its
    variance is added to both stds, :func:`effective_std`); ``t_in`` input
    positions (6); ``embedding`` width of the learned particle-type embedding
    (16) over ``num_types`` codes (9, GNS).

    ``forward(positions, particle_type, senders, receivers)`` returns
    ``(nodes, edges)``: nodes float32 [N, node_size] with
    ``node_size = (t_in − 1)·D + 2·D + embedding`` (normalised velocities,
    wall distances, type embedding, in that order; 30 in 2D, 37 in 3D with
    the defaults, as in the paper), edges float32 [E, edge_size = D + 1].

    The statistics, ``lower``/``upper`` walls and effective stds are buffers
    (they are saved in the state_dict and baked into exported ONNX graphs);
    the type embedding is the only parameter.

    Raises :class:`~hybridmpm.errors.InvalidInputError` (naming the field)
    for a ``dim`` other than 2 or 3, ``radius`` not > 0, bounds or statistics
    of the wrong length, non-positive stds, ``noise_std`` < 0 or ``t_in`` < 2.
    """

    vel_mean: torch.Tensor
    vel_std: torch.Tensor
    acc_mean: torch.Tensor
    acc_std: torch.Tensor
    lower: torch.Tensor
    upper: torch.Tensor

    def __init__(
        self,
        dim: int,
        radius: float,
        bounds: Sequence[Sequence[float]],
        vel_mean: Sequence[float],
        vel_std: Sequence[float],
        acc_mean: Sequence[float],
        acc_std: Sequence[float],
        noise_std: float = 3e-4,
        t_in: int = T_IN,
        embedding: int = 16,
        num_types: int = NUM_TYPES,
        wall_reach: float = 1.0,
    ) -> None:
        super().__init__()
        if dim not in (2, 3):
            raise InvalidInputError(f"dim: must be 2 or 3, got {dim!r}", "dim")
        if not (math.isfinite(radius) and radius > 0):
            raise InvalidInputError(f"radius: must be a number > 0 m, got {radius!r}", "radius")
        if len(bounds) != dim or not all(len(b) == 2 and float(b[0]) < float(b[1]) for b in bounds):
            raise InvalidInputError(f"bounds: must be {dim} pairs [lo, hi] with lo < hi, got {bounds!r}", "bounds")
        _check_vector("vel_mean", vel_mean, dim)
        _check_vector("acc_mean", acc_mean, dim)
        _check_vector("vel_std", vel_std, dim, positive=noise_std == 0)
        _check_vector("acc_std", acc_std, dim, positive=noise_std == 0)
        if not (math.isfinite(noise_std) and noise_std >= 0):
            raise InvalidInputError(f"noise_std: must be a number >= 0, got {noise_std!r}", "noise_std")
        if t_in < 2:
            raise InvalidInputError(f"t_in: must be >= 2 (velocities are differences), got {t_in!r}", "t_in")
        if not (isinstance(wall_reach, (int, float)) and math.isfinite(wall_reach) and 1 <= wall_reach <= WALL_REACH_MAX):
            raise InvalidInputError(f"wall_reach: must be a number in [1, {WALL_REACH_MAX:g}] (units of R), got {wall_reach!r}", "wall_reach")
        self.dim = dim
        self.t_in = t_in
        self.radius = radius
        self.inv_radius = 1.0 / radius
        self.wall_reach = float(wall_reach)
        #: ``1 / (wall_reach·R)``, the wall features' scale (1/m)
        self.inv_wall = 1.0 / (radius * self.wall_reach)
        self.register_buffer("vel_mean", torch.tensor(list(vel_mean), dtype=torch.float32))
        self.register_buffer("vel_std", torch.tensor(effective_std(vel_std, noise_std), dtype=torch.float32))
        self.register_buffer("acc_mean", torch.tensor(list(acc_mean), dtype=torch.float32))
        self.register_buffer("acc_std", torch.tensor(effective_std(acc_std, noise_std), dtype=torch.float32))
        b = torch.tensor([list(map(float, x)) for x in bounds], dtype=torch.float32)
        self.register_buffer("lower", b[:, 0])
        self.register_buffer("upper", b[:, 1])
        self.embed = nn.Embedding(num_types, embedding)
        #: width of the node features (``(t_in − 1)·D + 2·D + embedding``)
        self.node_size = (t_in - 1) * dim + 2 * dim + embedding
        #: width of the edge features (``D + 1``)
        self.edge_size = dim + 1

    def forward(
        self, positions: torch.Tensor, particle_type: torch.Tensor, senders: torch.Tensor, receivers: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Node features [N, node_size] and edge features [E, D + 1] (see the class).

        ``positions`` float32 [t_in, N, D] (oldest first, one model step
        apart, m); ``particle_type`` int64 [N] codes in ``[0, num_types)``;
        ``senders``, ``receivers`` int64 [E] (the radius graph on
        ``positions[-1]``). Raises :class:`~hybridmpm.errors.InvalidInputError`
        when ``positions`` is not [t_in, N, dim]; out-of-range types or
        indices raise torch's ``IndexError``.
        """
        if positions.dim() != 3 or positions.shape[0] != self.t_in or positions.shape[2] != self.dim:
            raise InvalidInputError(f"positions: must be [{self.t_in}, N, {self.dim}], got {list(positions.shape)}", "positions")
        last = positions[-1]
        vel = velocity_features(positions, self.vel_mean, self.vel_std)
        walls = wall_features(last, self.lower, self.upper, self.inv_wall)
        nodes = torch.cat([vel, walls, self.embed(particle_type)], dim=1)
        return nodes, edge_features(last, senders, receivers, self.inv_radius)

    def normalise_acceleration(self, acceleration: torch.Tensor) -> torch.Tensor:
        """``(a − acc_mean) / acc_std_eff`` for ``acceleration`` [..., D] in m/step² (the training target)."""
        return (acceleration - self.acc_mean) / self.acc_std

    def denormalise_acceleration(self, normalised: torch.Tensor) -> torch.Tensor:
        """Inverse of :meth:`normalise_acceleration`: ``a·acc_std_eff + acc_mean`` in m/step², shape kept."""
        return normalised * self.acc_std + self.acc_mean

    def integrate(self, positions: torch.Tensor, particle_type: torch.Tensor, normalised: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """From the network's normalised acceleration [N, D] to ``(acceleration
        [N, D] in m/step², next positions [N, D] in m)`` with :func:`euler_step`."""
        acc = self.denormalise_acceleration(normalised)
        return acc, euler_step(positions, acc, particle_type)


__all__ = ["GnsFeatures", "edge_features", "effective_std", "euler_step", "velocity_features", "wall_features"]
