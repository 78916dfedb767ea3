"""Training the GNS (paper App. B "Training"; GNS, Sanchez-Gonzalez et al. 2020).

``hybridmpm train SCENE --data DIR --out MODEL_DIR`` runs :func:`train`:

* data: a GNS-layout dataset (``hybridmpm generate``, or any GNS dataset),
  or several (``--data A B``: their trajectories pooled split by split, e.g.
  ``water2d`` with ``water_columns2d``; they must agree on dimension, box,
  frame time, ``r_p`` and ``r_t``, and the first one's connectivity radius is
  the default);
  ``r_t`` (default: the paper's 2, counted in *frames*) sets the model step:
  a dataset stored every ``r_t_data`` frames is subsampled by ``r_t / r_t_data``;
  the model's spatial resolution is the data's (``r_p`` from its metadata);
* samples: windows of ``T_in = 6`` positions and the next one from random
  trajectories and times of the training split, a batch being several windows
  joined into one disjoint graph (radius graph from the Rust crate);
* noise: a random walk on the input velocities (std ``noise_std`` on the last
  velocity), the target acceleration corrected so the model learns to undo it;
* walls: ``wall_reach`` (default 1, GNS's clip) sets the distance, in units
  of R, at which the wall-distance features saturate
  (:func:`~hybridmpm.train.gns.features.wall_features`); it is part of the
  model (stored in its metadata; resuming a run with another raises, as for
  every setting);
* pushforward (Brandstetter et al. 2022, "Message passing neural PDE
  solvers", Sec. 2.3; off by default): after the first ``pushforward_after``
  of the steps (of this command's ``steps``: resuming with another ``steps``
  moves the start), each window is with probability ``pushforward`` one whose
  last input position is the model's own prediction (one step without
  gradient from the window before), and whose target acceleration takes that
  predicted state to the true next position — the model learns to correct
  the drift of its own rollouts, not only input noise;
* unrolled training (``unroll`` = K > 1, off by default; backpropagation
  through time as in Ummenhofer et al. 2020 and Prantl et al. 2022, and
  NeuralMPM's multi-call position loss): after the first ``unroll_after`` of
  the steps, each window is rolled out K model steps by the network itself
  (the radius graph rebuilt from each predicted state, without gradient; the
  predicted positions clipped to the domain bounds as the simulator clips
  them) and the loss is the mean over the K steps of the normalised
  acceleration error *to the true next position* — with the history made of
  the model's own predictions this is a position error, and its gradient
  flows back through every earlier prediction, so the model is trained on
  what a rollout accumulates, not only on one step from true inputs. The
  gradient norm is clipped to ``clip_grad`` in these steps. K forward and
  backward passes per window: a step costs about K times a one-step one;
* ema (off by default): with ``ema`` = β > 0 the weights that are validated,
  snapshotted and exported are the exponential moving average of the trained
  ones (``w̄ ← β·w̄ + (1 − β)·w`` after every step; torch's ``AveragedModel``),
  which smooths the step-to-step scatter of a small-batch run's rollouts;
* loss: **MSE of the normalised acceleration** over non-kinematic particles
  (the GNS choice: it weighs both axes alike whatever their scales; it is
  the paper's per-particle acceleration RMSE squared, up to the per-axis
  normalisation constants);
* Adam with exponential learning-rate decay ``lr = lr_final + (lr − lr_final)·0.1^(step/steps)``;
* validation every ``val_every`` steps: one-step loss on fixed validation
  windows (no noise) and a ``rollout_steps`` rollout on the first validation
  trajectory of each dataset (position MSE and grid-mass error of the last
  step; with pooled datasets, their means, so that every pooled domain counts
  in the choice of ``model.onnx``);
* ``checkpoint.pt`` at every validation (model, optimiser, step, RNG states):
  rerunning the same command resumes; ``log.csv`` holds the losses;
  ``model.onnx`` (the best validation rollout) is exported at the end;
* with ``snapshots`` (default) every validation also exports the model of
  that step as ``snapshots/step_NNNNNNN/model.onnx`` (a few tens of kB; its
  metadata's ``val_rollout_mse`` is that step's own score), so a
  checkpoint can be chosen afterwards on the benchmark's own rollout error
  (``benchmarks/bench_neural.py --split valid --models OUT/snapshots/*``,
  then ``benchmarks/ship_model.py``) rather than on the one 20-step
  validation rollout the run itself scores;
* several processes (``nproc`` = N, or torchrun; :mod:`hybridmpm.train.distributed`):
  data-parallel training with DistributedDataParallel over gloo. ``batch``
  stays the windows per rank: every rank draws the windows of the global
  batch of N·``batch`` (noise included) from the one random stream a single
  process of batch N·``batch`` would draw, keeps its slice, and weighs its
  loss by the non-kinematic particles of the whole batch, so the averaged
  gradient is that process's and the weights agree to float rounding
  (``tests/test_ddp.py``). Rank 0 validates, logs, checkpoints and exports.
  A run may resume with another split of the same global batch (N = 2 of
  batch 2 as N = 1 of batch 4). ``train_config.json`` records ``ranks``;
  ``log.csv`` and ``summary.json`` add ``ranks`` and ``core_seconds`` (the
  CPU seconds of every rank's process, summed).

``checkpoint.pt`` is a ``torch.save`` dict: ``model`` (the
:class:`~hybridmpm.train.gns.model.GnsModel` state_dict), ``optimizer`` (Adam's,
indexed by parameter order), ``step``, ``best`` (best rollout MSE),
``elapsed`` [s], ``core_seconds``, ``ranks``, ``rng`` (numpy bit-generator state), ``torch_rng``,
``gns_config`` (:meth:`GnsConfig.to_dict`) and, with ``ema``, ``ema`` (the
``AveragedModel``'s state_dict); ``best.pt`` is the best validated model's
state_dict (the EMA's with ``ema``). Checkpoints written before the features / encoder–processor–decoder
split (flat keys such as ``embed.weight``) resume unchanged: ``load_state_dict``
remaps them (:func:`~hybridmpm.train.gns.model.remap_legacy_state_dict`) and the
parameter order, hence the optimiser state, is the same.
"""

from __future__ import annotations

import csv
import json
import math
import os
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch.optim import swa_utils

from hybridmpm.conventions import DEFAULT_N_GRID, GNS_KINEMATIC, T_IN
from hybridmpm.data import GnsDataset, compute_statistics, read_metadata
from hybridmpm.errors import InvalidInputError
from hybridmpm.graph import radius_graph
from hybridmpm.metrics import grid_mass_error
from hybridmpm.neural.constants import WALL_REACH_MAX
from hybridmpm.train.distributed import LossOf, Ranks, check_nproc, launch
from hybridmpm.train.gns.export import export_onnx
from hybridmpm.train.gns.model import GnsConfig, GnsModel
from hybridmpm.train.grid_train import rest_count


@dataclass
class TrainConfig:
    """Settings of :func:`train` (see the module docstring). ``scene`` names the
    scene family stored in the model; ``steps`` optimiser steps; ``batch``
    windows per step and rank; ``max_neighbors`` caps the radius graph per receiver;
    ``radius`` the connectivity radius R [m] (default: the dataset's);
    ``nproc`` local processes (ranks) of data-parallel training (1: this
    process; under torchrun, torchrun's ranks); ``grid`` nodes per dimension
    of the grid branch (0: none; :mod:`hybridmpm.train.gns.grid_branch`),
    ``grid_width`` and ``grid_levels`` its U-Net."""

    scene: str
    data: str | list[str]
    out: str
    latent: int = 32
    layers: int = 3
    r_t: int = 2
    steps: int = 20000
    batch: int = 2
    lr: float = 1e-3
    lr_final: float = 1e-5
    noise_std: float = 3e-4
    val_every: int = 500
    val_windows: int = 16
    rollout_steps: int = 20
    max_neighbors: int | None = None
    radius: float | None = None
    seed: int = 0
    threads: int = 0
    pushforward: float = 0.0
    pushforward_after: float = 0.2
    snapshots: bool = True
    ema: float = 0.0
    unroll: int = 1
    unroll_after: float = 0.0
    clip_grad: float = 1.0
    wall_reach: float = 1.0
    nproc: int = 1
    grid: int = 0
    grid_width: int = 8
    grid_levels: int = 3

    def data_dirs(self) -> list[Path]:
        """The dataset directories (``data`` is one path or a list of them)."""
        return [Path(d) for d in ([self.data] if isinstance(self.data, (str, os.PathLike)) else self.data)]

    def validate(self) -> TrainConfig:
        if not isinstance(self.data, (str, os.PathLike)):
            if not (isinstance(self.data, (list, tuple)) and self.data and all(isinstance(d, (str, os.PathLike)) for d in self.data)):
                raise InvalidInputError(f"data: must be a dataset directory or a non-empty list of them, got {self.data!r}", "data")
            self.data = str(self.data[0]) if len(self.data) == 1 else [str(d) for d in self.data]  # one directory is stored as before
        for name in ("latent", "layers", "r_t", "steps", "batch", "val_every", "val_windows", "rollout_steps", "unroll"):
            v = getattr(self, name)
            if not isinstance(v, int) or v < 1:
                raise InvalidInputError(f"{name}: must be an integer >= 1, got {v!r}", name)
        for name in ("lr", "lr_final"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
                raise InvalidInputError(f"{name}: must be a number > 0, got {v!r}", name)
        if self.radius is not None and not (isinstance(self.radius, (int, float)) and math.isfinite(self.radius) and 0 < self.radius < 0.5):
            raise InvalidInputError(f"radius: must be in (0, 0.5) m, got {self.radius!r}", "radius")
        if not (isinstance(self.noise_std, (int, float)) and math.isfinite(self.noise_std) and self.noise_std >= 0):
            raise InvalidInputError(f"noise_std: must be a number >= 0, got {self.noise_std!r}", "noise_std")
        if not isinstance(self.snapshots, bool):
            raise InvalidInputError(f"snapshots: must be true or false, got {self.snapshots!r}", "snapshots")
        if not (isinstance(self.ema, (int, float)) and math.isfinite(self.ema) and 0 <= self.ema < 1):
            raise InvalidInputError(f"ema: must be a number in [0, 1), got {self.ema!r}", "ema")
        if self.unroll > 1 and self.pushforward > 0:
            raise InvalidInputError("unroll: unrolled training and pushforward are alternatives; set one of them", "unroll")
        if not (isinstance(self.clip_grad, (int, float)) and math.isfinite(self.clip_grad) and self.clip_grad > 0):
            raise InvalidInputError(f"clip_grad: must be a number > 0, got {self.clip_grad!r}", "clip_grad")
        if not (isinstance(self.wall_reach, (int, float)) and math.isfinite(self.wall_reach) and 1 <= self.wall_reach <= WALL_REACH_MAX):
            raise InvalidInputError(f"wall_reach: must be a number in [1, {WALL_REACH_MAX:g}] (units of R), got {self.wall_reach!r}", "wall_reach")
        for name in ("pushforward", "pushforward_after", "unroll_after"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and 0 <= v <= 1):
                raise InvalidInputError(f"{name}: must be a number in [0, 1], got {v!r}", name)
        for name in ("grid", "grid_width", "grid_levels"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int) or v < (0 if name == "grid" else 1):
                raise InvalidInputError(f"{name}: must be an integer >= {0 if name == 'grid' else 1}, got {v!r}", name)
        if self.grid and (self.grid < 8 or self.grid > 128 or self.grid % 2 ** (self.grid_levels - 1)):
            raise InvalidInputError(
                f"grid: must be 0 (no grid branch) or in [8, 128] and divisible by 2^(grid_levels - 1) = {2 ** (self.grid_levels - 1)}, got {self.grid}", "grid"
            )
        check_nproc(self.nproc)
        return self


#: Metadata entries that pooled datasets must share.
_POOLED_KEYS = ("dim", "bounds", "dt", "r_p", "r_t")


def _pooled_metadata(dirs: list[Path]) -> list[dict[str, Any]]:
    """The datasets' metadata, after checking that every one agrees with the first
    on :data:`_POOLED_KEYS` (raises :class:`InvalidInputError` naming ``data``)."""

    metas = [read_metadata(d / "metadata.json") for d in dirs]
    for d, m in zip(dirs[1:], metas[1:]):
        for key in _POOLED_KEYS:
            a, b = metas[0].get(key), m.get(key)
            if a != b and not (isinstance(a, (int, float)) and isinstance(b, (int, float)) and math.isclose(a, b, rel_tol=1e-9)):
                raise InvalidInputError(f"data: {d} has {key} = {b!r}, {dirs[0]} has {a!r}; pooled datasets must agree on {', '.join(_POOLED_KEYS)}", "data")
    return metas


class _Data:
    """Trajectories of one split at the model step, pooled over the datasets in
    order, in memory (float32)."""

    def __init__(self, directories: list[Path], split: str, stride: int) -> None:
        self.trajs: list[tuple[np.ndarray, np.ndarray]] = []
        #: index in ``trajs`` of each dataset's first trajectory
        self.first: list[int] = []
        for directory in directories:
            ds = GnsDataset(directory)
            trajs = [(t.positions[::stride].astype(np.float32), t.particle_type.astype(np.int64)) for _, t in sorted(ds.split(split).items())]
            if not trajs:
                raise InvalidInputError(f"data: split {split!r} of {directory} is empty", "data")
            self.first.append(len(self.trajs))
            self.trajs += trajs
        self.t_max = min(len(p) for p, _ in self.trajs)


def _noised_history(traj: tuple[np.ndarray, np.ndarray], t: int, t_in: int, noise_std: float, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Input history float64 [T_in, N, D] ending at step ``t``, with the random-walk
    velocity noise (none on kinematic particles), and the noise of its last
    position [N, D] (the shift the targets carry, so the model learns to undo
    velocity noise, not position noise)."""
    pos, ptype = traj
    hist = pos[t - t_in + 1 : t + 1].astype(np.float64)
    n, d = hist.shape[1], hist.shape[2]
    if noise_std <= 0:
        return hist, np.zeros((n, d))
    steps = t_in - 1
    vel_noise = np.cumsum(rng.normal(0.0, noise_std / math.sqrt(steps), (steps, n, d)), axis=0)
    pos_noise = np.concatenate([np.zeros((1, n, d)), np.cumsum(vel_noise, axis=0)])
    pos_noise[:, ptype == GNS_KINEMATIC] = 0.0
    return hist + pos_noise, pos_noise[-1]


def _window(traj: tuple[np.ndarray, np.ndarray], t: int, t_in: int, noise_std: float, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Input history [T_in, N, D], types [N], target acceleration [N, D] (noise-corrected)."""
    pos, ptype = traj
    hist, offset = _noised_history(traj, t, t_in, noise_std, rng)
    nxt = pos[t + 1].astype(np.float64) + offset
    acc = nxt - 2 * hist[-1] + hist[-2]
    return hist.astype(np.float32), ptype, acc.astype(np.float32)


def _pushforward_window(
    model: torch.nn.Module,
    traj: tuple[np.ndarray, np.ndarray],
    t: int,
    t_in: int,
    noise_std: float,
    rng: np.random.Generator,
    radius: float,
    max_neighbors: int | None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A pushforward window at step ``t`` (``t >= t_in``): the inputs end at
    ``t − 1`` (noised as :func:`_window`'s), the model predicts position
    ``t`` from them without gradient, and that prediction replaces the true
    position ``t`` as the last input. The target is the acceleration from the
    predicted state to the true position ``t + 1`` (shifted by the last input
    position's noise, as in :func:`_window`). Kinematic particles keep their
    true positions. Same shapes as :func:`_window`."""
    pos, ptype = traj
    hist0, _, _ = _window(traj, t - 1, t_in, noise_std, rng)
    s, r, _, _ = radius_graph(hist0[-1], radius, max_neighbors=max_neighbors)
    with torch.no_grad():
        _, pred_t = model(torch.from_numpy(hist0), torch.from_numpy(ptype), torch.from_numpy(s), torch.from_numpy(r))
    pred = pred_t.numpy().astype(np.float64)
    kin = ptype == GNS_KINEMATIC
    pred[kin] = pos[t][kin]
    hist = np.concatenate([hist0[1:].astype(np.float64), pred[None]])
    offset = hist[-2] - pos[t - 1]  # the last true input position's noise
    acc = (pos[t + 1] + offset) - 2 * hist[-1] + hist[-2]
    return hist.astype(np.float32), ptype, acc.astype(np.float32)


def _batch(windows: list[tuple[np.ndarray, np.ndarray, np.ndarray]], radius: float, max_neighbors: int | None) -> tuple[torch.Tensor, ...]:
    """The windows as one disjoint graph: ``(history, types, senders, receivers, target acceleration, window of each particle)``."""
    hs, ts, accs, ss, rs, ws = [], [], [], [], [], []
    offset = 0
    for k, (hist, ptype, acc) in enumerate(windows):
        s, r, _, _ = radius_graph(hist[-1], radius, max_neighbors=max_neighbors)
        hs.append(hist)
        ts.append(ptype)
        accs.append(acc)
        ss.append(s + offset)
        rs.append(r + offset)
        ws.append(np.full(hist.shape[1], k, np.int64))
        offset += hist.shape[1]
    return (
        torch.from_numpy(np.concatenate(hs, axis=1)),
        torch.from_numpy(np.concatenate(ts)),
        torch.from_numpy(np.concatenate(ss)),
        torch.from_numpy(np.concatenate(rs)),
        torch.from_numpy(np.concatenate(accs)),
        torch.from_numpy(np.concatenate(ws)),
    )


def _loss(model: GnsModel, batch: tuple[torch.Tensor, ...], count: float | None = None) -> torch.Tensor:
    """MSE of the normalised acceleration over the batch's non-kinematic
    particles; with ``count``, the sum of their squared errors over ``count``
    particles instead (a rank's share of a global batch's mean: ``count`` is
    the global batch's particles over the ranks)."""
    hist, ptype, s, r, acc, window = batch
    pred = model.normalised_acceleration(hist, ptype, s, r, window, int(window[-1]) + 1 if len(window) else 1)
    target = model.features.normalise_acceleration(acc)
    mask = ptype != GNS_KINEMATIC
    sq = (pred - target)[mask] ** 2
    return sq.mean() if count is None else sq.sum() / (count * sq.shape[-1])


def _unrolled_window(
    traj: tuple[np.ndarray, np.ndarray], t: int, t_in: int, unroll: int, noise_std: float, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """A window for unrolled training at step ``t`` (``t + unroll`` within the
    trajectory): the noised input history float32 [T_in, N, D], the types [N],
    the targets float32 [unroll, N, D] (the true positions ``t + 1 … t + unroll``
    shifted by the last input position's noise, as :func:`_window`'s target) and
    the true positions float32 [unroll, N, D] (for kinematic particles)."""
    pos, ptype = traj
    hist, offset = _noised_history(traj, t, t_in, noise_std, rng)
    truth = pos[t + 1 : t + 1 + unroll].astype(np.float64)
    return hist.astype(np.float32), ptype, (truth + offset).astype(np.float32), truth.astype(np.float32)


def _unrolled_loss(
    model: GnsModel,
    windows: list[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]],
    radius: float,
    max_neighbors: int | None,
    count: float | None = None,
) -> torch.Tensor:
    """The loss of unrolled training (module docstring): the windows of
    :func:`_unrolled_window` joined into one disjoint graph, rolled out by
    ``model`` for as many steps as they have targets; at each step the radius
    graph is rebuilt from the detached predicted positions, the normalised
    acceleration is compared with the one that reaches the target position
    from the (predicted) history, and the prediction, clipped to the domain
    bounds, becomes the next input (kinematic particles take their true
    positions). Returns the mean over steps of the mean squared error over
    non-kinematic particles (with ``count``, as :func:`_loss`); with one step
    it equals :func:`_loss` of the same window."""
    sizes = [w[0].shape[1] for w in windows]
    starts = np.cumsum([0, *sizes[:-1]])
    hist = torch.from_numpy(np.concatenate([w[0] for w in windows], axis=1))
    ptype = torch.from_numpy(np.concatenate([w[1] for w in windows]))
    targets = torch.from_numpy(np.concatenate([w[2] for w in windows], axis=1))
    truth = torch.from_numpy(np.concatenate([w[3] for w in windows], axis=1))
    kin = (ptype == GNS_KINEMATIC).unsqueeze(1)
    mask = ptype != GNS_KINEMATIC
    window = torch.from_numpy(np.repeat(np.arange(len(sizes), dtype=np.int64), sizes))
    bounds = torch.tensor(model.config.bounds, dtype=hist.dtype)
    losses = []
    for k in range(targets.shape[0]):
        last = hist[-1].detach().numpy()
        ss, rs = [], []
        for start, n in zip(starts, sizes):
            s, r, _, _ = radius_graph(np.ascontiguousarray(last[start : start + n]), radius, max_neighbors=max_neighbors)
            ss.append(s + start)
            rs.append(r + start)
        senders, receivers = torch.from_numpy(np.concatenate(ss)), torch.from_numpy(np.concatenate(rs))
        pred = model.normalised_acceleration(hist, ptype, senders, receivers, window, len(sizes))
        target = model.features.normalise_acceleration(targets[k] - 2 * hist[-1] + hist[-2])
        sq = (pred - target)[mask] ** 2
        losses.append(sq.mean() if count is None else sq.sum() / (count * sq.shape[-1]))
        if k + 1 < targets.shape[0]:
            _, nxt = model.features.integrate(hist, ptype, pred)
            nxt = torch.where(kin, truth[k], torch.clamp(nxt, bounds[:, 0], bounds[:, 1]))
            hist = torch.cat([hist[1:], nxt[None]])
    return torch.stack(losses).mean()


def _rollout(model: GnsModel, traj: tuple[np.ndarray, np.ndarray], steps: int, radius: float, max_neighbors: int | None) -> np.ndarray:
    pos, ptype = traj
    t_in = model.config.t_in
    hist = torch.from_numpy(pos[:t_in].copy())
    pt = torch.from_numpy(ptype)
    out = []
    with torch.no_grad():
        for _ in range(steps):
            s, r, _, _ = radius_graph(hist[-1].numpy(), radius, max_neighbors=max_neighbors)
            _, nxt = model(hist, pt, torch.from_numpy(s), torch.from_numpy(r))
            hist = torch.cat([hist[1:], nxt[None]])
            out.append(nxt.numpy())
    return np.stack(out)


def _step_loss(model: GnsModel, windows: list[Any], unrolling: bool, radius: float, max_neighbors: int | None, count: float | None) -> torch.Tensor:
    """The loss of one step's ``windows`` (one-step or unrolled; ``count`` as :func:`_loss`)."""
    if unrolling:
        return _unrolled_loss(model, windows, radius, max_neighbors, count)
    return _loss(model, _batch(windows, radius, max_neighbors), count)


#: Settings a run may resume with changed (``batch`` and ``nproc`` are compared as the global batch).
_RESUMABLE = ("steps", "threads", "out", "snapshots", "nproc", "ranks", "batch")


def _saved_config_error(saved: Path, config: TrainConfig, ranks: int) -> InvalidInputError | None:
    """Why the run in ``saved``'s directory cannot be resumed by ``config`` on ``ranks`` ranks, or None."""
    old = json.loads(saved.read_text())
    defaults = asdict(TrainConfig(scene="", data="", out=""))
    for key, v in asdict(config).items():
        # a moved run directory still resumes; a setting added since the run was made has its default
        if key not in _RESUMABLE and old.get(key, defaults[key]) != v:
            return InvalidInputError(f"{key}: {saved.parent} holds a run with {key} = {old.get(key, defaults[key])!r}, not {v!r}; use another --out", key)
    old_batch, old_ranks = old.get("batch", defaults["batch"]), old.get("ranks", 1)
    if old_batch * old_ranks != config.batch * ranks:
        return InvalidInputError(
            f"batch: {saved.parent} holds a run of {old_batch * old_ranks} windows per step ({old_batch} on each of {old_ranks} ranks), "
            f"not {config.batch * ranks} ({config.batch} on each of {ranks}); use another --out",
            "batch",
        )
    return None


def train(config: TrainConfig, progress: bool = True) -> dict[str, Any]:
    """Train (or resume) a GNS; returns a summary dict (also ``out/summary.json``).

    With ``nproc`` > 1, or under torchrun, trains on several processes
    (module docstring); the summary is rank 0's.

    Raises :class:`InvalidInputError` for bad settings, a dataset that does not
    fit (``r_t`` not a multiple of the data's), or an ``out`` directory holding
    a run with different settings.
    """
    config.validate()
    return launch(_train, config.nproc, config, progress)


def _train(ranks: Ranks, config: TrainConfig, progress: bool) -> dict[str, Any]:
    """:func:`train` on one rank of ``ranks``."""
    from tqdm import tqdm

    out = Path(config.out)
    saved = out / "train_config.json"
    error = None
    if ranks.main:
        out.mkdir(parents=True, exist_ok=True)
        error = _saved_config_error(saved, config, ranks.size) if saved.exists() else None
        if error is None:
            saved.write_text(json.dumps({**asdict(config), "ranks": ranks.size}, indent=2))
    error = ranks.broadcast(error)
    if error is not None:
        raise error
    if config.threads:
        torch.set_num_threads(config.threads)
    dirs = config.data_dirs()
    metas = _pooled_metadata(dirs)
    meta = metas[0]
    r_t_data = int(meta.get("r_t", 1))
    if config.r_t % r_t_data:
        raise InvalidInputError(f"r_t: {config.r_t} frames is not a multiple of the data's step ({r_t_data} frames)", "r_t")
    stride = config.r_t // r_t_data
    train_data = _Data(dirs, "train", stride)
    valid_data = _Data(dirs, "valid", stride)
    t_in = T_IN
    if train_data.t_max < t_in + 1:
        raise InvalidInputError(f"data: trajectories have {train_data.t_max} steps at r_t = {config.r_t}; need >= {t_in + 1}", "data")
    if config.unroll > 1 and train_data.t_max < t_in + config.unroll:
        raise InvalidInputError(
            f"unroll: trajectories have {train_data.t_max} steps at r_t = {config.r_t}; an unrolled window needs >= {t_in + config.unroll}", "unroll"
        )
    if config.pushforward > 0 and train_data.t_max < t_in + 2:
        raise InvalidInputError(
            f"pushforward: trajectories have {train_data.t_max} steps at r_t = {config.r_t}; a pushforward window needs >= {t_in + 2}", "pushforward"
        )

    stats = compute_statistics(train_data.trajs, exclude_types=(GNS_KINEMATIC,))  # at the model step (strided data)
    radius = float(config.radius if config.radius is not None else meta["default_connectivity_radius"])
    types = sorted({int(v) for _, t in train_data.trajs for v in np.unique(t)} - {GNS_KINEMATIC})
    gcfg = GnsConfig(
        dim=int(meta["dim"]), radius=radius, bounds=[list(map(float, b)) for b in meta["bounds"]],
        vel_mean=stats["vel_mean"], vel_std=stats["vel_std"], acc_mean=stats["acc_mean"], acc_std=stats["acc_std"],
        latent=config.latent, layers=config.layers, t_in=t_in, noise_std=config.noise_std, wall_reach=float(config.wall_reach),
        grid=config.grid, grid_width=config.grid_width, grid_levels=config.grid_levels, grid_types=types,
        grid_rest_count=rest_count(train_data.trajs, [list(map(float, b)) for b in meta["bounds"]], config.grid) if config.grid else 1.0,
    )  # fmt: skip
    torch.manual_seed(config.seed)
    model = GnsModel(gcfg)
    opt = torch.optim.Adam(model.parameters(), lr=config.lr)
    # the weights that are validated, snapshotted and exported: the EMA of the
    # trained ones when ``ema`` > 0 (torch's AveragedModel), else the trained ones
    ema = swa_utils.AveragedModel(model, multi_avg_fn=swa_utils.get_ema_multi_avg_fn(config.ema)) if config.ema > 0 else None
    net: GnsModel = ema.module if ema is not None else model  # type: ignore[assignment]
    rng = np.random.default_rng(config.seed)
    step, best, elapsed, core_seconds = 0, math.inf, 0.0, 0.0
    ckpt = out / "checkpoint.pt"
    # rank 0 reads the checkpoint and sends it to the others (who may not share its directory)
    state = ranks.broadcast(torch.load(ckpt, weights_only=False) if ranks.main and ckpt.exists() else None)
    if state is not None:
        model.load_state_dict(state["model"])
        opt.load_state_dict(state["optimizer"])
        if ema is not None:
            ema.load_state_dict(state["ema"])
        step, best, elapsed = state["step"], state["best"], state["elapsed"]
        core_seconds = float(state.get("core_seconds", elapsed))  # a checkpoint from before the count: its wall time
        rng.bit_generator.state = state["rng"]
        torch.set_rng_state(state["torch_rng"])
    del state
    # the loss of a step, in DistributedDataParallel when there are several ranks (its backward averages the gradients)
    step_loss = ranks.wrap(LossOf(model, _step_loss))
    val_windows = []
    val_trajs: list[tuple[np.ndarray, np.ndarray]] = []
    rollout_steps = 0
    if ranks.main:  # only rank 0 validates
        vrng = np.random.default_rng(12345)
        for _ in range(config.val_windows):
            k = int(vrng.integers(len(valid_data.trajs)))
            traj = valid_data.trajs[k]
            t = int(vrng.integers(t_in - 1, len(traj[0]) - 1))
            val_windows.append(_window(traj, t, t_in, 0.0, vrng))
        val_trajs = [valid_data.trajs[i] for i in valid_data.first]  # one per pooled dataset
        rollout_steps = min(config.rollout_steps, min(len(v[0]) for v in val_trajs) - t_in)
    n_grid = int(meta.get("n_grid", DEFAULT_N_GRID[gcfg.dim]))
    log = None
    counted = False  # whether the log has the columns ranks and core_seconds
    if ranks.main:
        log_path = out / "log.csv"
        new_log = not log_path.exists()
        log = open(log_path, "a", newline="")
        writer = csv.writer(log)
        if new_log:
            counted = True
            writer.writerow(["step", "lr", "train_loss", "val_one_step", "val_rollout_mse", "val_rollout_grid_mass", "elapsed_s", "ranks", "core_seconds"])
        else:  # a log begun before the ranks were counted keeps its columns
            with open(log_path, newline="") as f:
                counted = "core_seconds" in next(csv.reader(f), [])
    running: list[float] = []

    def validate(lr: float, train_loss: float) -> float:
        net.eval()
        with torch.no_grad():
            v1 = float(np.mean([_loss(net, _batch([w], radius, config.max_neighbors)).item() for w in val_windows]))
        mses, gms = [], []
        for val_traj in val_trajs:
            roll = _rollout(net, val_traj, rollout_steps, radius, config.max_neighbors)
            truth = val_traj[0][t_in : t_in + rollout_steps]
            fluid = val_traj[1] != GNS_KINEMATIC
            m = float(np.mean((roll[:, fluid] - truth[:, fluid]) ** 2)) if np.all(np.isfinite(roll)) else math.inf
            mses.append(m)
            gms.append(float(grid_mass_error(roll[-1:, fluid], truth[-1:, fluid], n_grid)[0]) if math.isfinite(m) else math.inf)
        mse, gm = float(np.mean(mses)), float(np.mean(gms))
        row = [step, f"{lr:.3e}", f"{train_loss:.5f}", f"{v1:.5f}", f"{mse:.4e}", f"{gm:.4f}", f"{time.perf_counter() - t0:.1f}"]
        writer.writerow(row + ([ranks.size, f"{core_seconds:.1f}"] if counted else []))
        assert log is not None
        log.flush()
        bar.set_postfix(val=f"{v1:.3f}", roll=f"{mse:.2e}")
        return mse

    # the scene families the model may serve: the one named, then those of the pooled datasets
    scenes = list(dict.fromkeys([config.scene, *(str(m["scene"]) for m in metas if m.get("scene"))]))
    shas = [m["sha256"].get("train") if isinstance(m.get("sha256"), dict) else None for m in metas]
    sha = shas[0] if len(shas) == 1 else shas  # a list for pooled datasets, in order

    def export_to(path: Path, seconds: float, extra: dict[str, Any] | None = None) -> dict[str, Any]:
        """Export the model's current weights to ``path`` with the run's metadata (and ``extra``); returns the summary part."""
        summary = {
            "scene": config.scene, "latent": config.latent, "layers": config.layers, "r_t": config.r_t,
            "r_p": float(meta.get("r_p", 1.0)), "steps": step, "train_seconds": round(seconds, 1),
            "best_val_rollout_mse": best, "parameters": int(sum(p.numel() for p in net.parameters())),
        }  # fmt: skip
        path.parent.mkdir(parents=True, exist_ok=True)
        export_onnx(
            net,
            path,
            {
                **summary,
                "particle_types": types,
                "scenes": scenes,
                "data_sha256": sha,
                "dt_frame": float(meta.get("dt_frame", 2.5e-3)),
                "n_grid": n_grid,
                "noise_std": config.noise_std,
                "pushforward": config.pushforward,
                "unroll": config.unroll,
                "rollout_steps": rollout_steps,
                **(extra or {}),
            },  # fmt: skip
        )
        return summary

    bar = tqdm(
        total=config.steps, initial=step, desc=f"train {config.scene} L{config.layers}x{config.latent}", unit="step", disable=not (progress and ranks.main)
    )
    t0 = time.perf_counter() - elapsed
    cpu0 = time.process_time()
    mine = ranks.part(config.batch)
    try:
        if step == 0 and ranks.main:
            validate(config.lr, math.nan)  # the untrained baseline
        while step < config.steps:
            lr = config.lr_final + (config.lr - config.lr_final) * 0.1 ** (step / config.steps)
            for g in opt.param_groups:
                g["lr"] = lr
            windows: list[Any] = []
            pushing = config.pushforward > 0 and step >= config.pushforward_after * config.steps
            unrolling = config.unroll > 1 and step >= config.unroll_after * config.steps
            particles = 0  # non-kinematic, in the global batch
            # every rank draws the whole global batch (the random stream of one process of batch ranks x batch) and keeps its slice
            for i in range(ranks.size * config.batch):
                w: Any
                traj = train_data.trajs[int(rng.integers(len(train_data.trajs)))]
                particles += int(np.count_nonzero(traj[1] != GNS_KINEMATIC))
                if unrolling:
                    t = int(rng.integers(t_in - 1, len(traj[0]) - config.unroll))
                    w = _unrolled_window(traj, t, t_in, config.unroll, config.noise_std, rng)
                elif pushing and rng.random() < config.pushforward:
                    model.eval()
                    t = int(rng.integers(t_in, len(traj[0]) - 1))
                    if i in mine:
                        w = _pushforward_window(model, traj, t, t_in, config.noise_std, rng, radius, config.max_neighbors)
                    else:  # another rank's: the same draws (its one plain window), without the model step
                        w = _window(traj, t - 1, t_in, config.noise_std, rng)
                else:
                    t = int(rng.integers(t_in - 1, len(traj[0]) - 1))
                    w = _window(traj, t, t_in, config.noise_std, rng)
                if i in mine:
                    windows.append(w)
            model.train()
            # one rank: the batch's own mean; several: this slice's share of the global batch's mean
            loss = step_loss(windows, unrolling, radius, config.max_neighbors, particles / ranks.size if ranks.size > 1 else None)
            opt.zero_grad()
            loss.backward()
            if unrolling:
                torch.nn.utils.clip_grad_norm_(model.parameters(), config.clip_grad)
            opt.step()
            if ema is not None:
                ema.update_parameters(model)
            step += 1
            running.append(loss.item())
            bar.update(1)
            if step % config.val_every == 0 or step == config.steps:
                # the global batch's loss is the ranks' mean; the CPU time, their sum
                loss_sum, cpu = ranks.sum(float(np.mean(running)), time.process_time() - cpu0)
                core_seconds += cpu
                cpu0 = time.process_time()
                running = []
                elapsed = time.perf_counter() - t0
                if not ranks.main:
                    continue
                mse = validate(lr, loss_sum / ranks.size)
                elapsed = time.perf_counter() - t0
                if mse < best:
                    best = mse
                    torch.save(net.state_dict(), out / "best.pt")
                ck = {
                    "model": model.state_dict(), "optimizer": opt.state_dict(), "step": step, "best": best, "elapsed": elapsed,
                    "core_seconds": core_seconds, "ranks": ranks.size,
                    "rng": rng.bit_generator.state, "torch_rng": torch.get_rng_state(), "gns_config": gcfg.to_dict(),
                }  # fmt: skip
                if ema is not None:
                    ck["ema"] = ema.state_dict()
                if config.snapshots:  # before the checkpoint, so a resumed run never lacks a validated step's snapshot
                    export_to(out / "snapshots" / f"step_{step:07d}" / "model.onnx", elapsed, {"val_rollout_mse": mse})
                tmp = out / "checkpoint.pt.tmp"
                torch.save(ck, tmp)
                os.replace(tmp, ckpt)
    finally:
        bar.close()
        if log is not None:
            log.close()
    summary: dict[str, Any] | None = None
    if ranks.main:
        if (out / "best.pt").exists():
            net.load_state_dict(torch.load(out / "best.pt", weights_only=True))
        summary = {**export_to(out / "model.onnx", elapsed), "ranks": ranks.size, "core_seconds": round(core_seconds, 1)}
        (out / "summary.json").write_text(json.dumps(summary, indent=2))
    # the others wait for rank 0's export and return its summary
    result = ranks.broadcast(summary)
    assert result is not None
    return result


__all__ = ["TrainConfig", "train"]
