"""Training of the grid model (:mod:`hybridmpm.train.grid.model`; needs torch).

Data: GNS-layout datasets stored every frame (``hybridmpm generate SCENE
--r-p R_P``), read with :class:`hybridmpm.data.gns.GnsDataset`. A training
window is a history of ``t_in`` positions one model step (``r_t`` frames)
apart and the next ``unroll · r_t`` frames; the input history gets GNS's
random-walk noise (Sanchez-Gonzalez et al. 2020, arXiv 2002.09405; ``noise``
metres per step), the targets stay clean.

Loss: mean squared position error over every frame of ``unroll`` chained
calls, each call reading the positions the previous one predicted (full
backpropagation through the chain, as NeuralMPM trains with 4 calls), in
units of the grid spacing. The number of chained calls grows from 1 to
``unroll`` over the first half of the run. Adam with a linear warm-up and a
cosine decay to ``lr_final``, gradients clipped to ``clip_grad``.

Selection: every ``val_every`` steps, rollouts of ``val_steps`` model steps
from the start of the validation trajectories, scored with the grid-mass
error against the data (MPM at the same ``r_p``); the best snapshot is kept
(``best.pt``) and exported to ``model.onnx`` at the end
(:func:`~hybridmpm.train.grid.export.export_grid`). The loop, checkpoints and
curve are the training scaffold's (:mod:`hybridmpm.train.scaffold`): the run
is resumable, ``checkpoint.pt`` (model, optimiser, step, random streams,
validation curve) is written every ``val_every`` steps, and a run started
again with the same ``out`` and settings goes on from it as if it had not
stopped. ``curve.json`` holds the validation curve against core-seconds.

Several processes (``nproc``, or torchrun; :mod:`hybridmpm.train.distributed`):
DistributedDataParallel over gloo, ``batch`` windows per rank; every rank
draws the global batch of ``nproc · batch`` windows (noise included) from the
one random stream a single process of that batch draws, keeps its slice, and
divides its squared errors by the global batch's fluid particles, so the
averaged gradient is that process's. Rank 0 validates and writes; the
core-seconds are summed over the ranks, and the curve records ``ranks``.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from hybridmpm.conventions import CONNECTIVITY_RADIUS, GNS_KINEMATIC
from hybridmpm.data.gns import GnsDataset
from hybridmpm.errors import InvalidInputError
from hybridmpm.metrics import grid_mass_error
from hybridmpm.scenes import make_scene
from hybridmpm.train.distributed import LossOf, Ranks, launch
from hybridmpm.train.grid.export import export_grid, load_snapshot
from hybridmpm.train.grid.model import GridConfig, GridModel, p2g, rest_count, stencil
from hybridmpm.train.scaffold import (
    CHECKPOINT,
    Parts,
    RunConfig,
    TrainingLoop,
    export_metadata,
    flag,
    integer,
    load_checkpoint,
    number,
    processes,
    save_torch,
    setting,
    start_run,
)


@dataclass
class GridTrainConfig(RunConfig):
    """Settings of :func:`train_grid` (module doc). ``data`` a dataset
    directory stored every frame; ``scene`` the scene family written to the
    model; ``grid``, ``width``, ``levels``, ``r_t``, ``t_in`` the
    architecture (:class:`~hybridmpm.train.grid.model.GridConfig`); ``steps``
    optimiser steps of ``batch`` windows per rank; ``threads`` torch threads
    per rank; ``nproc`` local ranks (module doc). :meth:`validate` refuses a
    bad value naming its field."""

    scene: str
    data: str
    out: str
    grid: int = setting(64, integer(1))
    width: int = setting(16, integer(1))
    levels: int = setting(3, integer(1))
    r_t: int = setting(4, integer(1))
    t_in: int = setting(6, integer(1))
    steps: int = setting(20000, integer(1))
    batch: int = setting(8, integer(1))
    lr: float = setting(1e-3, number(0, low_open=True))
    lr_final: float = setting(1e-5, number(0, low_open=True))
    warmup: int = setting(200, integer(0))
    noise: float = setting(3e-4, number(0, unit="[m per step]"))
    unroll: int = setting(3, integer(1))
    density_weight: float = setting(0.0, number(0))
    pressure: bool = setting(False, flag)
    flip_init: float = setting(0.5, number(0, 1, low_open=True, high_open=True))
    clip_grad: float = setting(1.0, number(0, low_open=True))
    val_every: int = setting(500, integer(1))
    val_steps: int = setting(100, integer(1))
    val_trajectories: int = setting(3, integer(1))
    seed: int = 0
    threads: int = setting(1, integer(1))
    nproc: int = setting(1, processes)

    def lr_at(self, step: int) -> float:
        """The learning rate of step ``step``: a linear warm-up over ``warmup`` steps, then a cosine decay to ``lr_final``."""
        if step < self.warmup:
            return self.lr * (step + 1) / self.warmup
        f = (step - self.warmup) / max(1, self.steps - self.warmup)
        return self.lr_final + 0.5 * (self.lr - self.lr_final) * (1 + math.cos(math.pi * min(1.0, f)))

    def unroll_at(self, step: int) -> int:
        """Chained calls in the loss of step ``step``: from 1 up to ``unroll`` over the first half of the run."""
        return max(1, min(self.unroll, 1 + int((self.unroll - 1) * step / max(1, self.steps // 2))))


def _stack(split: dict[str, Any]) -> list[tuple[np.ndarray, np.ndarray]]:
    return [(np.asarray(t.positions, np.float32), np.asarray(t.particle_type, np.int64)) for t in split.values()]


def velocity_scale(meta: dict[str, Any]) -> float:
    """Velocity normalisation [m/s]: the dataset's per-frame velocity std over its frame time."""
    return float(np.sqrt(np.mean(np.square(meta["vel_std"])))) / float(meta["dt_frame"] if "dt_frame" in meta else meta["dt"])


def _windows(
    data: list[tuple[np.ndarray, np.ndarray]], cfg: GridConfig, unroll: int, batch: int, noise: float, rng: np.random.Generator
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """A batch: ``(history [t_in, P, D], targets [unroll·r_t, P, D], particle_type [P], batch [P])``."""
    r_t, t_in = cfg.r_t, cfg.t_in
    hs, ts, pts, bs = [], [], [], []
    lo = np.asarray(cfg.bounds, np.float32)[:, 0]
    hi = np.asarray(cfg.bounds, np.float32)[:, 1]
    for b in range(batch):
        pos, pt = data[int(rng.integers(len(data)))]
        first = (t_in - 1) * r_t
        t = int(rng.integers(first, pos.shape[0] - unroll * r_t))
        h = pos[t - first : t + 1 : r_t].copy()
        if noise > 0:
            fluid = pt != GNS_KINEMATIC
            steps = rng.normal(0.0, noise / math.sqrt(t_in - 1), size=(t_in - 1, int(fluid.sum()), h.shape[2])).astype(np.float32)
            walk = np.concatenate([np.zeros_like(steps[:1]), np.cumsum(steps, axis=0)])
            h[:, fluid] = np.clip(h[:, fluid] + walk, lo, hi)
        hs.append(h)
        ts.append(pos[t + 1 : t + 1 + unroll * r_t])
        pts.append(pt)
        bs.append(np.full(len(pt), b, np.int64))
    return (
        torch.from_numpy(np.concatenate(hs, axis=1)),
        torch.from_numpy(np.concatenate(ts, axis=1)),
        torch.from_numpy(np.concatenate(pts)),
        torch.from_numpy(np.concatenate(bs)),
    )


def rollout(model: GridModel, positions: np.ndarray, particle_type: np.ndarray, steps: int) -> np.ndarray:
    """``steps`` model steps from the first ``t_in`` stored steps of a
    trajectory stored every frame (``positions`` float32 [T, N, D]): float32
    [steps, N, D], the positions after each step (torch, no gradient)."""
    cfg = model.config
    first = (cfg.t_in - 1) * cfg.r_t
    hist = torch.from_numpy(positions[0 : first + 1 : cfg.r_t].copy())
    pt = torch.from_numpy(particle_type)
    out = []
    with torch.no_grad():
        for _ in range(steps):
            nxt = model.frames(hist, pt)[-1]
            out.append(nxt.numpy().copy())
            hist = torch.cat([hist[1:], nxt[None]])
    return np.stack(out)


def validation_error(model: GridModel, data: list[tuple[np.ndarray, np.ndarray]], steps: int, n_grid: int = 128) -> float:
    """Mean grid-mass error of :func:`rollout` against the data over ``steps``
    model steps, averaged over the trajectories (module doc)."""
    cfg = model.config
    first = (cfg.t_in - 1) * cfg.r_t
    errs = []
    for pos, pt in data:
        n = min(steps, (pos.shape[0] - 1 - first) // cfg.r_t)
        pred = rollout(model, pos, pt, n)
        ref = pos[first + cfg.r_t : first + cfg.r_t * n + 1 : cfg.r_t]
        fluid = pt != GNS_KINEMATIC
        errs.append(float(grid_mass_error(pred[:, fluid], ref[:, fluid], n_grid).mean()))
    return float(np.mean(errs))


def _density_loss(
    model: GridModel, pred: torch.Tensor, target: torch.Tensor, fluid: torch.Tensor, batch: torch.Tensor, windows: int, count: Any = None
) -> torch.Tensor:
    """Mean squared difference of the fluid's p2g counts (over ``rest_count``)
    of predicted and target frames [K, P, D] on the model's grid: the grid-mass
    error's own quantity, which penalises clumping that positions alone barely see.
    Per fluid particle: of the batch, or ``count`` of them (a rank's share of a global batch)."""
    cfg = model.config
    nodes = windows * cfg.grid**cfg.dim
    total = torch.zeros(())
    for x, y in zip(pred, target):
        wp, np_ = stencil(x, model.origin, model.spacing, cfg.grid, batch)
        wt, nt = stencil(y, model.origin, model.spacing, cfg.grid, batch)
        diff = p2g(fluid, wp, np_, nodes) - p2g(fluid, wt, nt, nodes)
        total = total + diff.square().sum() / (cfg.rest_count**2 * (fluid.sum() if count is None else count))
    return total / len(pred)


def _slice(
    windows: tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor], part: range
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """The windows ``part`` of a global batch of :func:`_windows` (their window index renumbered from 0)."""
    hist, target, pt, batch = windows
    sel = (batch >= part.start) & (batch < part.stop)
    return hist[:, sel], target[:, sel], pt[sel], batch[sel] - part.start


def _grid_loss(
    model: GridModel, hist: torch.Tensor, target: torch.Tensor, pt: torch.Tensor, batch: torch.Tensor, c: GridTrainConfig, unroll: int, count: Any
) -> torch.Tensor:
    """The loss of one step (module doc): ``unroll`` chained calls; squared
    errors per fluid particle of the batch, or per ``count`` of them."""
    cfg = model.config
    fluid = (pt != GNS_KINEMATIC)[None, :, None].to(torch.float32)
    per = fluid.sum() if count is None else count
    loss = torch.zeros(())
    h = hist
    for k in range(unroll):
        frames = model.frames(h, pt, batch, c.batch)
        err = (frames - target[k * cfg.r_t : (k + 1) * cfg.r_t]) / model.spacing
        loss = loss + (err.square() * fluid).sum() / (per * cfg.r_t * cfg.dim)
        if c.density_weight > 0:
            loss = loss + c.density_weight * _density_loss(model, frames, target[k * cfg.r_t : (k + 1) * cfg.r_t], fluid[0], batch, c.batch, count)
        h = torch.cat([h[1:], frames[-1:]])
    return loss / unroll


def train_grid(c: GridTrainConfig, progress: bool = True) -> dict[str, Any]:
    """Train (or resume) a grid model (module doc); returns the summary written
    to ``out/summary.json`` (rank 0's, with several processes). Raises :class:`InvalidInputError` for bad settings,
    a dataset that is not stored every frame, or an ``out`` directory holding a run of other settings."""
    c.validate()
    return launch(_train_grid, c.nproc, c, progress)


def _upgrade(ck: dict[str, Any]) -> dict[str, Any]:
    """A checkpoint written before the training scaffold (``seconds``: core-seconds; ``best``: [error, step]) in the scaffold's keys."""
    if isinstance(ck.get("best"), (list, tuple)):
        ck = {**ck, "best": float(ck["best"][0]), "best_step": int(ck["best"][1]), "core_seconds": float(ck.get("seconds", 0.0))}
    return ck


class _Run:
    """One rank's grid-model run: the data, the model and what the training
    loop (:class:`~hybridmpm.train.scaffold.TrainingLoop`) calls of it."""

    def __init__(self, c: GridTrainConfig, ranks: Ranks) -> None:
        self.c, self.ranks, self.out = c, ranks, Path(c.out)
        ds = GnsDataset(c.data)
        self.meta = meta = ds.metadata
        if int(meta.get("r_t", 1)) != 1:
            raise InvalidInputError(f"data: the grid model trains on datasets stored every frame (r_t = 1), {c.data} has r_t = {meta.get('r_t')}", "data")
        self.train = _stack(ds["train"])
        self.valid = _stack(ds["valid"])[: c.val_trajectories]
        gravity = [float(v) for v in make_scene(c.scene, seed=0).params.resolved_gravity()]
        types = sorted({int(t) for _, pt in self.train for t in np.unique(pt)} - {GNS_KINEMATIC})
        bounds = [[float(a), float(b)] for a, b in meta["bounds"]]
        self.cfg = GridConfig(
            dim=int(meta["dim"]), bounds=bounds, dt_frame=float(meta.get("dt_frame", meta["dt"])), gravity=gravity, grid=c.grid, width=c.width,
            levels=c.levels, t_in=c.t_in, r_t=c.r_t, velocity_scale=velocity_scale(meta), rest_count=rest_count(self.train, bounds, c.grid),
            types=types, pressure=c.pressure, flip_init=float(c.flip_init),
        )  # fmt: skip
        torch.manual_seed(c.seed)  # the initial weights are the seed's, whichever process draws them
        self.model = GridModel(self.cfg)
        self.opt = torch.optim.Adam(self.model.parameters(), lr=c.lr)
        self.rng = np.random.default_rng(c.seed)
        self.parts = Parts(self.model, self.opt, self.rng, lr=c.lr_at)
        self.mine = ranks.part(c.batch)
        self.step_loss: Any = None
        self.loop: TrainingLoop | None = None

    def wrap(self) -> None:
        """The loss of a step, in DistributedDataParallel when there are several ranks (its backward averages the gradients)."""
        self.step_loss = self.ranks.wrap(LossOf(self.model, _grid_loss))

    def train_step(self, step: int) -> float:
        """One optimiser step (the loop has set its learning rate); its loss on this rank."""
        c, ranks = self.c, self.ranks
        unroll = c.unroll_at(step)
        # every rank draws the whole global batch (the random stream of one process of batch ranks x batch) and keeps its slice
        windows = _windows(self.train, self.cfg, unroll, ranks.size * c.batch, c.noise, self.rng)
        count = None
        if ranks.size > 1:
            count = float((windows[2] != GNS_KINEMATIC).sum()) / ranks.size  # the global batch's fluid particles per rank
            windows = _slice(windows, self.mine)
        loss = self.step_loss(*windows, c, unroll, count)
        self.opt.zero_grad()
        loss.backward()
        torch.nn.utils.clip_grad_norm_(self.model.parameters(), c.clip_grad)
        self.opt.step()
        return float(loss.item())

    def evaluate(self, step: int, train_loss: float | None) -> dict[str, Any]:
        """Rank 0's validation: the row of ``curve.json``."""
        assert self.loop is not None
        self.model.eval()
        verr = validation_error(self.model, self.valid, self.c.val_steps)
        self.model.train()
        return {
            "step": step, "core_seconds": self.loop.core_seconds, "train_loss": train_loss, "valid_error": verr,
            "unroll": self.c.unroll_at(step - 1), "ranks": self.ranks.size,
        }  # fmt: skip

    def save_best(self, step: int) -> None:
        assert self.loop is not None
        save_torch({"model": self.model.state_dict(), "config": self.cfg.to_dict(), "step": step, "valid_error": self.loop.best}, self.out / "best.pt")

    def summary(self) -> dict[str, Any]:
        """Rank 0's summary, after exporting ``best.pt`` to ``model.onnx``."""
        c, loop, meta = self.c, self.loop, self.meta
        assert loop is not None
        summary = {
            "config": self.cfg.to_dict(), "train_config": c.to_dict(), "ranks": self.ranks.size, "best_valid_error": loop.best,
            "best_step": loop.best_step, "core_seconds": loop.core_seconds, "curve": loop.curve.rows,
        }  # fmt: skip
        if (self.out / "best.pt").exists():
            best = load_snapshot(self.out / "best.pt")
            facts = export_metadata(
                best, scene=c.scene, steps=loop.best_step, data=meta, radius=float(meta.get("default_connectivity_radius", CONNECTIVITY_RADIUS)),
                core_seconds=loop.core_seconds, valid_error=loop.best,
            )  # fmt: skip
            export_grid(best, self.out / "model.onnx", facts)
            summary["model"] = str(self.out / "model.onnx")
        return summary


def _train_grid(ranks: Ranks, c: GridTrainConfig, progress: bool) -> dict[str, Any]:
    """:func:`train_grid` on one rank of ``ranks``."""
    torch.set_num_threads(c.threads)
    out = Path(c.out)
    start_run(c, ranks, out)
    run = _Run(c, ranks)
    run.loop = loop = TrainingLoop(
        out, ranks, run.parts, steps=c.steps, every=c.val_every, desc=f"train grid {c.scene}", progress=progress, score="valid_error",
        postfix=lambda row: {"valid": f"{row['valid_error']:.3f}", "best": f"{loop.best:.3f}@{loop.best_step}"},
        state=lambda: {"config": run.cfg.to_dict()},
    )  # fmt: skip
    # rank 0 reads the checkpoint and sends it to the others (who may not share its directory)
    state = load_checkpoint(out / CHECKPOINT, ranks)
    if state is not None:
        loop.restore(_upgrade(state))
    del state
    run.wrap()
    loop.run(run.train_step, run.evaluate, on_best=run.save_best)
    summary = None
    if ranks.main:
        summary = run.summary()
        (out / "summary.json").write_text(json.dumps(summary, indent=1))
    # the others wait for rank 0's export and return its summary
    result = ranks.broadcast(summary)
    assert result is not None
    return result


__all__ = ["GridTrainConfig", "export_grid", "load_snapshot", "rollout", "train_grid", "validation_error", "velocity_scale"]
