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
* the loop, checkpoints and curve are the training scaffold's
  (:mod:`hybridmpm.train.scaffold`): ``checkpoint.pt`` at every validation
  (model, optimiser, step, RNG states): rerunning the same command resumes,
  as if it had not stopped; ``log.csv`` (every call's rows) and
  ``curve.json`` (the run's) hold the losses; ``model.onnx`` (the best
  validation rollout) is exported at the end;
* with ``snapshots`` (default) every validation also exports the model of
  that step as ``snapshots/step_NNNNNNN/model.onnx`` (a few tens of kB; its
  metadata's ``val_rollout_mse`` is that step's own score), so a
  checkpoint can be chosen afterwards on the benchmark's own rollout error
  (``benchmarks/bench_neural.py --split valid --models OUT/snapshots/*``,
  then ``benchmarks/release/ship_model.py``) rather than on the one 20-step
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

``checkpoint.pt`` is the scaffold's (:class:`~hybridmpm.train.scaffold.TrainingLoop`):
``model`` (the :class:`~hybridmpm.train.gns.model.GnsModel` state_dict),
``optimizer`` (Adam's, indexed by parameter order), ``step``, ``best`` (best
rollout MSE) and ``best_step``, ``curve``, ``elapsed`` [s], ``core_seconds``,
``ranks``, ``rng`` (numpy bit-generator state), ``torch_rng``, ``gns_config``
(:meth:`GnsConfig.to_dict`) and, with ``ema``, ``ema`` (the
``AveragedModel``'s state_dict); ``best.pt`` is the best validated model's
state_dict (the EMA's with ``ema``). Checkpoints written before the features / encoder–processor–decoder
split (flat keys such as ``embed.weight``) resume unchanged: ``load_state_dict``
remaps them (:func:`~hybridmpm.train.gns.model.remap_legacy_state_dict`) and the
parameter order, hence the optimiser state, is the same.
"""

from __future__ import annotations

import json
import math
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any, ClassVar

import numpy as np
import torch
from torch.optim import swa_utils

from hybridmpm.conventions import DEFAULT_N_GRID, GNS_KINEMATIC, T_IN
from hybridmpm.data import GnsDataset, compute_statistics, read_metadata
from hybridmpm.errors import InvalidInputError
from hybridmpm.graph import radius_graph
from hybridmpm.metrics import grid_mass_error
from hybridmpm.neural.constants import WALL_REACH_MAX
from hybridmpm.train.distributed import LossOf, Ranks, launch
from hybridmpm.train.gns.export import export_onnx
from hybridmpm.train.gns.model import GnsConfig, GnsModel
from hybridmpm.train.grid.model import rest_count
from hybridmpm.train.scaffold import (
    CHECKPOINT,
    Parts,
    RunConfig,
    TrainingLoop,
    ValidationCurve,
    export_metadata,
    flag,
    integer,
    load_checkpoint,
    number,
    optional,
    processes,
    save_torch,
    setting,
    start_run,
)


@dataclass
class TrainConfig(RunConfig):
    """Settings of :func:`train` (see the module docstring). ``scene`` names the
    scene family stored in the model; ``steps`` optimiser steps; ``batch``
    windows per step and rank; ``max_neighbors`` caps the radius graph per receiver;
    ``radius`` the connectivity radius R [m] (default: the dataset's);
    ``nproc`` local processes (ranks) of data-parallel training (1: this
    process; under torchrun, torchrun's ranks); ``grid`` nodes per dimension
    of the grid branch (0: none; :mod:`hybridmpm.train.gns.grid_branch`),
    ``grid_width`` and ``grid_levels`` its U-Net. :meth:`validate` refuses a
    bad value naming its field."""

    RESUMABLE: ClassVar[tuple[str, ...]] = (*RunConfig.RESUMABLE, "snapshots")

    scene: str
    data: str | list[str]
    out: str
    latent: int = setting(32, integer(1))
    layers: int = setting(3, integer(1))
    r_t: int = setting(2, integer(1))
    steps: int = setting(20000, integer(1))
    batch: int = setting(2, integer(1))
    lr: float = setting(1e-3, number(0, low_open=True))
    lr_final: float = setting(1e-5, number(0, low_open=True))
    noise_std: float = setting(3e-4, number(0))
    val_every: int = setting(500, integer(1))
    val_windows: int = setting(16, integer(1))
    rollout_steps: int = setting(20, integer(1))
    max_neighbors: int | None = setting(None, optional(integer(1)))
    radius: float | None = setting(None, optional(number(0, 0.5, low_open=True, high_open=True, unit="m")))
    seed: int = 0
    threads: int = setting(0, integer(0))
    pushforward: float = setting(0.0, number(0, 1))
    pushforward_after: float = setting(0.2, number(0, 1))
    snapshots: bool = setting(True, flag)
    ema: float = setting(0.0, number(0, 1, high_open=True))
    unroll: int = setting(1, integer(1))
    unroll_after: float = setting(0.0, number(0, 1))
    clip_grad: float = setting(1.0, number(0, low_open=True))
    wall_reach: float = setting(1.0, number(1, WALL_REACH_MAX, unit="(units of R)"))
    nproc: int = setting(1, processes)
    grid: int = setting(0, integer(0))
    grid_width: int = setting(8, integer(1))
    grid_levels: int = setting(3, integer(1))

    def data_dirs(self) -> list[Path]:
        """The dataset directories (``data`` is one path or a list of them)."""
        return [Path(d) for d in ([self.data] if isinstance(self.data, (str, os.PathLike)) else self.data)]

    def validate(self) -> TrainConfig:
        """``data`` as stored (one directory a string, several a list), then every field's check and :meth:`check`."""
        if not isinstance(self.data, (str, os.PathLike)):
            if not (isinstance(self.data, (list, tuple)) and self.data and all(isinstance(d, (str, os.PathLike)) for d in self.data)):
                raise InvalidInputError(f"data: must be a dataset directory or a non-empty list of them, got {self.data!r}", "data")
            self.data = str(self.data[0]) if len(self.data) == 1 else [str(d) for d in self.data]  # one directory is stored as before
        return super().validate()  # type: ignore[no-any-return]

    def check(self) -> None:
        if self.unroll > 1 and self.pushforward > 0:
            raise InvalidInputError("unroll: unrolled training and pushforward are alternatives; set one of them", "unroll")
        if self.grid and (self.grid < 8 or self.grid > 128 or self.grid % 2 ** (self.grid_levels - 1)):
            raise InvalidInputError(
                f"grid: must be 0 (no grid branch) or in [8, 128] and divisible by 2^(grid_levels - 1) = {2 ** (self.grid_levels - 1)}, got {self.grid}", "grid"
            )

    def lr_at(self, step: int) -> float:
        """The learning rate of step ``step``: ``lr_final + (lr − lr_final)·0.1^(step/steps)``."""
        return self.lr_final + (self.lr - self.lr_final) * 0.1 ** (step / self.steps)


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


#: How ``log.csv`` writes its numbers.
_LOG_FORMATS = {
    "lr": ".3e", "train_loss": ".5f", "val_one_step": ".5f", "val_rollout_mse": ".4e", "val_rollout_grid_mass": ".4f", "elapsed_s": ".1f",
    "core_seconds": ".1f",
}  # fmt: skip
#: What :func:`train` returns of a model's export metadata (then ``ranks`` and ``core_seconds``).
_SUMMARY_KEYS = ("scene", "latent", "layers", "r_t", "r_p", "steps", "train_seconds", "best_val_rollout_mse", "parameters")


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


class _Run:
    """One rank's GNS run: the data, the model and what the training loop
    (:class:`~hybridmpm.train.scaffold.TrainingLoop`) calls of it."""

    def __init__(self, config: TrainConfig, ranks: Ranks) -> None:
        self.config, self.ranks, self.out = config, ranks, Path(config.out)
        dirs = config.data_dirs()
        self.metas = _pooled_metadata(dirs)
        self.meta = meta = self.metas[0]
        r_t_data = int(meta.get("r_t", 1))
        if config.r_t % r_t_data:
            raise InvalidInputError(f"r_t: {config.r_t} frames is not a multiple of the data's step ({r_t_data} frames)", "r_t")
        stride = config.r_t // r_t_data
        self.train_data = _Data(dirs, "train", stride)
        self.valid_data = _Data(dirs, "valid", stride)
        self.t_in = T_IN
        _check_lengths(config, self.train_data.t_max, self.t_in)
        self.radius = float(config.radius if config.radius is not None else meta["default_connectivity_radius"])
        self.types = sorted({int(v) for _, t in self.train_data.trajs for v in np.unique(t)} - {GNS_KINEMATIC})
        self.gcfg = _model_config(config, meta, self.train_data, self.radius, self.types, self.t_in)
        torch.manual_seed(config.seed)
        self.model = GnsModel(self.gcfg)
        self.opt = torch.optim.Adam(self.model.parameters(), lr=config.lr)
        # the weights that are validated, snapshotted and exported: the EMA of the
        # trained ones when ``ema`` > 0 (torch's AveragedModel), else the trained ones
        self.ema = swa_utils.AveragedModel(self.model, multi_avg_fn=swa_utils.get_ema_multi_avg_fn(config.ema)) if config.ema > 0 else None
        self.net: GnsModel = self.ema.module if self.ema is not None else self.model  # type: ignore[assignment]
        self.rng = np.random.default_rng(config.seed)
        self.parts = Parts(self.model, self.opt, self.rng, lr=config.lr_at, extra={"ema": self.ema} if self.ema is not None else {})
        self.n_grid = int(meta.get("n_grid", DEFAULT_N_GRID[self.gcfg.dim]))
        self.mine = ranks.part(config.batch)
        self.step_loss: Any = None  # set by wrap(), after the checkpoint is restored
        self.loop: TrainingLoop | None = None
        self.val_windows: list[Any] = []
        self.val_trajs: list[tuple[np.ndarray, np.ndarray]] = []
        self.rollout_steps = 0
        if ranks.main:  # only rank 0 validates
            vrng = np.random.default_rng(12345)
            for _ in range(config.val_windows):
                traj = self.valid_data.trajs[int(vrng.integers(len(self.valid_data.trajs)))]
                t = int(vrng.integers(self.t_in - 1, len(traj[0]) - 1))
                self.val_windows.append(_window(traj, t, self.t_in, 0.0, vrng))
            self.val_trajs = [self.valid_data.trajs[i] for i in self.valid_data.first]  # one per pooled dataset
            self.rollout_steps = min(config.rollout_steps, min(len(v[0]) for v in self.val_trajs) - self.t_in)

    def wrap(self) -> None:
        """The loss of a step, in DistributedDataParallel when there are several ranks (its backward averages the gradients)."""
        self.step_loss = self.ranks.wrap(LossOf(self.model, _step_loss))

    def draw(self, step: int) -> tuple[list[Any], bool, int]:
        """This rank's windows of step ``step``, whether they are unrolled, and
        the non-kinematic particles of the global batch: every rank draws the
        whole global batch (the random stream of one process of batch ranks x
        batch) and keeps its slice."""
        c, rng, t_in = self.config, self.rng, self.t_in
        pushing = c.pushforward > 0 and step >= c.pushforward_after * c.steps
        unrolling = c.unroll > 1 and step >= c.unroll_after * c.steps
        windows: list[Any] = []
        particles = 0
        for i in range(self.ranks.size * c.batch):
            w: Any
            traj = self.train_data.trajs[int(rng.integers(len(self.train_data.trajs)))]
            particles += int(np.count_nonzero(traj[1] != GNS_KINEMATIC))
            if unrolling:
                t = int(rng.integers(t_in - 1, len(traj[0]) - c.unroll))
                w = _unrolled_window(traj, t, t_in, c.unroll, c.noise_std, rng)
            elif pushing and rng.random() < c.pushforward:
                self.model.eval()
                t = int(rng.integers(t_in, len(traj[0]) - 1))
                if i in self.mine:
                    w = _pushforward_window(self.model, traj, t, t_in, c.noise_std, rng, self.radius, c.max_neighbors)
                else:  # another rank's: the same draws (its one plain window), without the model step
                    w = _window(traj, t - 1, t_in, c.noise_std, rng)
            else:
                t = int(rng.integers(t_in - 1, len(traj[0]) - 1))
                w = _window(traj, t, t_in, c.noise_std, rng)
            if i in self.mine:
                windows.append(w)
        return windows, unrolling, particles

    def train_step(self, step: int) -> float:
        """One optimiser step (the loop has set its learning rate); its loss on this rank."""
        c, size = self.config, self.ranks.size
        windows, unrolling, particles = self.draw(step)
        self.model.train()
        # one rank: the batch's own mean; several: this slice's share of the global batch's mean
        loss = self.step_loss(windows, unrolling, self.radius, c.max_neighbors, particles / size if size > 1 else None)
        self.opt.zero_grad()
        loss.backward()
        if unrolling:
            torch.nn.utils.clip_grad_norm_(self.model.parameters(), c.clip_grad)
        self.opt.step()
        if self.ema is not None:
            self.ema.update_parameters(self.model)
        return float(loss.item())

    def evaluate(self, step: int, train_loss: float | None) -> dict[str, Any]:
        """Rank 0's validation (module doc): the row of ``log.csv``."""
        assert self.loop is not None
        net, c = self.net, self.config
        net.eval()
        with torch.no_grad():
            v1 = float(np.mean([_loss(net, _batch([w], self.radius, c.max_neighbors)).item() for w in self.val_windows]))
        mses, gms = [], []
        for val_traj in self.val_trajs:
            roll = _rollout(net, val_traj, self.rollout_steps, self.radius, c.max_neighbors)
            truth = val_traj[0][self.t_in : self.t_in + self.rollout_steps]
            fluid = val_traj[1] != GNS_KINEMATIC
            m = float(np.mean((roll[:, fluid] - truth[:, fluid]) ** 2)) if np.all(np.isfinite(roll)) else math.inf
            mses.append(m)
            gms.append(float(grid_mass_error(roll[-1:, fluid], truth[-1:, fluid], self.n_grid)[0]) if math.isfinite(m) else math.inf)
        return {
            "step": step, "lr": c.lr if step == 0 else c.lr_at(step - 1), "train_loss": math.nan if train_loss is None else train_loss,
            "val_one_step": v1, "val_rollout_mse": float(np.mean(mses)), "val_rollout_grid_mass": float(np.mean(gms)),
            "elapsed_s": self.loop.wall(), "ranks": self.ranks.size, "core_seconds": self.loop.core_seconds,
        }  # fmt: skip

    def save_best(self, step: int) -> None:
        save_torch(self.net.state_dict(), self.out / "best.pt")

    def snapshot(self, step: int, row: dict[str, Any]) -> None:
        """Before the checkpoint, so a resumed run never lacks a validated step's snapshot."""
        if self.config.snapshots:
            assert self.loop is not None
            self.export(self.out / "snapshots" / f"step_{step:07d}" / "model.onnx", {"val_rollout_mse": row["val_rollout_mse"]})

    def export(self, path: Path, extra: dict[str, Any] | None = None) -> dict[str, Any]:
        """Export the model's current weights to ``path`` with the run's metadata (and ``extra``); returns the summary part."""
        c, loop = self.config, self.loop
        assert loop is not None
        # the scene families the model may serve: the one named, then those of the pooled datasets
        scenes = list(dict.fromkeys([c.scene, *(str(m["scene"]) for m in self.metas if m.get("scene"))]))
        meta = export_metadata(
            self.net, scene=c.scene, steps=loop.step, data=self.metas[0] if len(self.metas) == 1 else self.metas, latent=c.latent,
            layers=c.layers, r_t=c.r_t, train_seconds=round(loop.elapsed, 1), best_val_rollout_mse=loop.best, particle_types=self.types,
            scenes=scenes, dt_frame=float(self.meta.get("dt_frame", 2.5e-3)), n_grid=self.n_grid, noise_std=c.noise_std,
            pushforward=c.pushforward, unroll=c.unroll, rollout_steps=self.rollout_steps, **(extra or {}),
        )  # fmt: skip
        path.parent.mkdir(parents=True, exist_ok=True)
        export_onnx(self.net, path, meta)
        return {k: meta[k] for k in _SUMMARY_KEYS}


def _check_lengths(config: TrainConfig, t_max: int, t_in: int) -> None:
    """Refuse trajectories of ``t_max`` steps (at the model step) too short for the windows ``config`` draws."""
    if t_max < t_in + 1:
        raise InvalidInputError(f"data: trajectories have {t_max} steps at r_t = {config.r_t}; need >= {t_in + 1}", "data")
    if config.unroll > 1 and t_max < t_in + config.unroll:
        raise InvalidInputError(f"unroll: trajectories have {t_max} steps at r_t = {config.r_t}; an unrolled window needs >= {t_in + config.unroll}", "unroll")
    if config.pushforward > 0 and t_max < t_in + 2:
        raise InvalidInputError(f"pushforward: trajectories have {t_max} steps at r_t = {config.r_t}; a pushforward window needs >= {t_in + 2}", "pushforward")


def _model_config(config: TrainConfig, meta: dict[str, Any], train_data: _Data, radius: float, types: list[int], t_in: int) -> GnsConfig:
    """The model's architecture and normalisation from the settings and the (strided) training data."""
    stats = compute_statistics(train_data.trajs, exclude_types=(GNS_KINEMATIC,))  # at the model step (strided data)
    bounds = [list(map(float, b)) for b in meta["bounds"]]
    return GnsConfig(
        dim=int(meta["dim"]), radius=radius, bounds=bounds,
        vel_mean=stats["vel_mean"], vel_std=stats["vel_std"], acc_mean=stats["acc_mean"], acc_std=stats["acc_std"],
        latent=config.latent, layers=config.layers, t_in=t_in, noise_std=config.noise_std, wall_reach=float(config.wall_reach),
        grid=config.grid, grid_width=config.grid_width, grid_levels=config.grid_levels, grid_types=types,
        grid_rest_count=rest_count(train_data.trajs, bounds, config.grid) if config.grid else 1.0,
    )  # fmt: skip


def _train(ranks: Ranks, config: TrainConfig, progress: bool) -> dict[str, Any]:
    """:func:`train` on one rank of ``ranks``."""
    out = Path(config.out)
    start_run(config, ranks, out)
    if config.threads:
        torch.set_num_threads(config.threads)
    run = _Run(config, ranks)
    run.loop = loop = TrainingLoop(
        out, ranks, run.parts, steps=config.steps, every=config.val_every, desc=f"train {config.scene} L{config.layers}x{config.latent}",
        progress=progress, curve=ValidationCurve(out, "log.csv", _LOG_FORMATS), score="val_rollout_mse",
        postfix=lambda row: {"val": f"{row['val_one_step']:.3f}", "roll": f"{row['val_rollout_mse']:.2e}"},
        state=lambda: {"gns_config": run.gcfg.to_dict()},
    )  # fmt: skip
    # rank 0 reads the checkpoint and sends it to the others (who may not share its directory)
    state = load_checkpoint(out / CHECKPOINT, ranks)
    if state is not None:
        loop.restore(state)
    del state
    run.wrap()
    loop.run(run.train_step, run.evaluate, on_best=run.save_best, before_save=run.snapshot, evaluate_first=True)
    summary: dict[str, Any] | None = None
    if ranks.main:
        if (out / "best.pt").exists():
            run.net.load_state_dict(torch.load(out / "best.pt", weights_only=True))
        summary = {**run.export(out / "model.onnx"), "ranks": ranks.size, "core_seconds": round(loop.core_seconds, 1)}
        (out / "summary.json").write_text(json.dumps(summary, indent=2))
    # the others wait for rank 0's export and return its summary
    result = ranks.broadcast(summary)
    assert result is not None
    return result


__all__ = ["TrainConfig", "train"]
