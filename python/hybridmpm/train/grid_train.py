"""Training of the grid model (:mod:`hybridmpm.train.grid`; needs torch).

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
(``best.pt``) and exported to ``model.onnx`` at the end. The run is resumable: ``checkpoint.pt`` (model,
optimiser, step, random state, validation curve) is written every
``val_every`` steps, and a run started again with the same ``out`` goes on
from it. ``curve.json`` holds the validation curve against core-seconds.

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
import os
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from hybridmpm.conventions import CONNECTIVITY_RADIUS, GNS_KINEMATIC
from hybridmpm.data.gns import GnsDataset
from hybridmpm.errors import InvalidInputError
from hybridmpm.metrics import grid_mass_error
from hybridmpm.neural.constants import METADATA_KEY
from hybridmpm.neural.grid import GRID_INPUT, GRID_KIND, GRID_OUTPUT
from hybridmpm.scenes import make_scene
from hybridmpm.train.distributed import LossOf, Ranks, check_nproc, launch
from hybridmpm.train.grid import GridConfig, GridModel, grid_geometry, p2g, stencil


@dataclass
class GridTrainConfig:
    """Settings of :func:`train_grid` (module doc). ``data`` a dataset
    directory stored every frame; ``scene`` the scene family written to the
    model; ``grid``, ``width``, ``levels``, ``r_t``, ``t_in`` the
    architecture (:class:`~hybridmpm.train.grid.GridConfig`); ``steps``
    optimiser steps of ``batch`` windows per rank; ``threads`` torch threads
    per rank; ``nproc`` local ranks (module doc)."""

    scene: str
    data: str
    out: str
    grid: int = 64
    width: int = 16
    levels: int = 3
    r_t: int = 4
    t_in: int = 6
    steps: int = 20000
    batch: int = 8
    lr: float = 1e-3
    lr_final: float = 1e-5
    warmup: int = 200
    noise: float = 3e-4
    unroll: int = 3
    density_weight: float = 0.0
    pressure: bool = False
    flip_init: float = 0.5
    clip_grad: float = 1.0
    val_every: int = 500
    val_steps: int = 100
    val_trajectories: int = 3
    seed: int = 0
    threads: int = 1
    nproc: int = 1

    def validate(self) -> GridTrainConfig:
        for name in ("grid", "width", "levels", "r_t", "t_in", "steps", "batch", "unroll", "val_every", "val_steps", "val_trajectories", "threads"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int) or v < 1:
                raise InvalidInputError(f"{name}: must be an integer >= 1, got {v!r}", name)
        for name in ("lr", "lr_final", "clip_grad"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
                raise InvalidInputError(f"{name}: must be a number > 0, got {v!r}", name)
        if not (isinstance(self.density_weight, (int, float)) and math.isfinite(self.density_weight) and self.density_weight >= 0):
            raise InvalidInputError(f"density_weight: must be a number >= 0, got {self.density_weight!r}", "density_weight")
        if not (isinstance(self.noise, (int, float)) and math.isfinite(self.noise) and self.noise >= 0):
            raise InvalidInputError(f"noise: must be a number >= 0 [m per step], got {self.noise!r}", "noise")
        if isinstance(self.flip_init, bool) or not (isinstance(self.flip_init, (int, float)) and 0.0 < self.flip_init < 1.0):
            raise InvalidInputError(f"flip_init: must be a number in (0, 1), got {self.flip_init!r}", "flip_init")
        check_nproc(self.nproc)
        return self


def _stack(split: dict[str, Any]) -> list[tuple[np.ndarray, np.ndarray]]:
    return [(np.asarray(t.positions, np.float32), np.asarray(t.particle_type, np.int64)) for t in split.values()]


def rest_count(trajectories: list[tuple[np.ndarray, np.ndarray]], bounds: list[list[float]], grid: int) -> float:
    """Particles per grid node inside resting fluid: the 90th percentile of the
    first frames' fluid counts over the nodes that hold any (a normalisation of the count channels)."""
    b = torch.tensor(bounds, dtype=torch.float32)
    origin, spacing = grid_geometry(b, grid)
    counts = []
    for pos, pt in trajectories[:8]:
        x = torch.from_numpy(pos[0][pt != GNS_KINEMATIC])
        w, node = stencil(x, origin, spacing, grid)
        c = p2g(torch.ones(len(x), 1), w, node, grid ** x.shape[1])[:, 0]
        counts.append(c[c > 0.05].numpy())
    return float(np.percentile(np.concatenate(counts), 90))


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


def _lr(step: int, c: GridTrainConfig) -> float:
    if step < c.warmup:
        return c.lr * (step + 1) / c.warmup
    f = (step - c.warmup) / max(1, c.steps - c.warmup)
    return c.lr_final + 0.5 * (c.lr - c.lr_final) * (1 + math.cos(math.pi * min(1.0, f)))


def _atomic_save(obj: Any, path: Path) -> None:
    tmp = path.with_name(path.name + ".tmp")
    torch.save(obj, tmp)
    os.replace(tmp, path)


def train_grid(c: GridTrainConfig, progress: bool = True) -> dict[str, Any]:
    """Train (or resume) a grid model (module doc); returns the summary written
    to ``out/summary.json`` (rank 0's, with several processes). Raises :class:`InvalidInputError` for bad settings
    or a dataset that is not stored every frame."""
    c.validate()
    return launch(_train_grid, c.nproc, c, progress)


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


def _train_grid(ranks: Ranks, c: GridTrainConfig, progress: bool) -> dict[str, Any]:
    """:func:`train_grid` on one rank of ``ranks``."""
    from tqdm import tqdm

    torch.set_num_threads(c.threads)
    out = Path(c.out)
    if ranks.main:
        out.mkdir(parents=True, exist_ok=True)
    ds = GnsDataset(c.data)
    meta = ds.metadata
    if int(meta.get("r_t", 1)) != 1:
        raise InvalidInputError(f"data: the grid model trains on datasets stored every frame (r_t = 1), {c.data} has r_t = {meta.get('r_t')}", "data")
    train = _stack(ds["train"])
    valid = _stack(ds["valid"])[: c.val_trajectories]

    gravity = [float(v) for v in make_scene(c.scene, seed=0).params.resolved_gravity()]
    types = sorted({int(t) for _, pt in train for t in np.unique(pt)} - {GNS_KINEMATIC})
    bounds = [[float(a), float(b)] for a, b in meta["bounds"]]
    cfg = GridConfig(
        dim=int(meta["dim"]),
        bounds=bounds,
        dt_frame=float(meta.get("dt_frame", meta["dt"])),
        gravity=gravity,
        grid=c.grid,
        width=c.width,
        levels=c.levels,
        t_in=c.t_in,
        r_t=c.r_t,
        velocity_scale=velocity_scale(meta),
        rest_count=rest_count(train, bounds, c.grid),
        types=types,
        pressure=c.pressure,
        flip_init=float(c.flip_init),
    )
    torch.manual_seed(c.seed)  # the initial weights are the seed's, whichever process draws them
    model = GridModel(cfg)
    opt = torch.optim.Adam(model.parameters(), lr=c.lr)
    rng = np.random.default_rng(c.seed)
    step, seconds = 0, 0.0
    curve: list[dict[str, Any]] = []
    best: tuple[float, int] = (math.inf, -1)
    ckpt = out / "checkpoint.pt"
    # rank 0 reads the checkpoint and sends it to the others (who may not share its directory)
    state, error = None, None
    if ranks.main and ckpt.exists():
        state = torch.load(ckpt, weights_only=False)
        old, new = {**asdict(GridTrainConfig("", "", "")), **state["train_config"]}, asdict(c)  # settings added since: their defaults
        old_global, new_global = old.get("batch", 0) * int(state.get("ranks", 1)), c.batch * ranks.size
        if {k: v for k, v in old.items() if k not in _RESUMABLE} != {k: v for k, v in new.items() if k not in _RESUMABLE}:
            error = InvalidInputError(f"out: {out} holds a run of other settings; choose another directory", "out")
        elif old_global != new_global:
            error = InvalidInputError(
                f"batch: {out} holds a run of {old_global} windows per step, not {new_global} ({c.batch} on each of {ranks.size} ranks)", "batch"
            )
    state, error = ranks.broadcast((state, error))
    if error is not None:
        raise error
    if state is not None:
        model.load_state_dict(state["model"])
        opt.load_state_dict(state["optimizer"])
        step, seconds, curve, best = state["step"], state["seconds"], state["curve"], (float(state["best"][0]), int(state["best"][1]))
        rng.bit_generator.state = state["rng"]
        torch.set_rng_state(state["torch_rng"])
    del state
    # the loss of a step, in DistributedDataParallel when there are several ranks (its backward averages the gradients)
    step_loss = ranks.wrap(LossOf(model, _grid_loss))
    bar = tqdm(total=c.steps, initial=step, desc=f"train grid {c.scene}", disable=not (progress and ranks.main), unit="step")
    losses: list[float] = []
    t_last = time.process_time()
    mine = ranks.part(c.batch)
    while step < c.steps:
        unroll = max(1, min(c.unroll, 1 + int((c.unroll - 1) * step / max(1, c.steps // 2))))
        # every rank draws the whole global batch (the random stream of one process of batch ranks x batch) and keeps its slice
        windows = _windows(train, cfg, unroll, ranks.size * c.batch, c.noise, rng)
        count = None
        if ranks.size > 1:
            count = float((windows[2] != GNS_KINEMATIC).sum()) / ranks.size  # the global batch's fluid particles per rank
            windows = _slice(windows, mine)
        for group in opt.param_groups:
            group["lr"] = _lr(step, c)
        loss = step_loss(*windows, c, unroll, count)
        opt.zero_grad()
        loss.backward()
        torch.nn.utils.clip_grad_norm_(model.parameters(), c.clip_grad)
        opt.step()
        losses.append(loss.item())
        step += 1
        bar.update(1)
        if step % c.val_every == 0 or step == c.steps:
            now = time.process_time()
            # the global batch's loss is the ranks' mean; the CPU time, their sum
            loss_sum, cpu = ranks.sum(float(np.mean(losses)), now - t_last)
            seconds += cpu
            t_last = now
            losses = []
            if not ranks.main:
                continue
            model.eval()
            verr = validation_error(model, valid, c.val_steps)
            model.train()
            curve.append(
                {"step": step, "core_seconds": seconds, "train_loss": loss_sum / ranks.size, "valid_error": verr, "unroll": unroll, "ranks": ranks.size}
            )
            if verr < best[0]:
                best = (verr, step)
                _atomic_save({"model": model.state_dict(), "config": cfg.to_dict(), "step": step, "valid_error": verr}, out / "best.pt")
            _atomic_save(
                {
                    "model": model.state_dict(),
                    "optimizer": opt.state_dict(),
                    "step": step,
                    "seconds": seconds,
                    "curve": curve,
                    "best": list(best),
                    "rng": rng.bit_generator.state,
                    "torch_rng": torch.get_rng_state(),
                    "train_config": asdict(c),
                    "ranks": ranks.size,
                    "config": cfg.to_dict(),
                },
                ckpt,
            )
            (out / "curve.json").write_text(json.dumps(curve, indent=1))
            bar.set_postfix(loss=f"{curve[-1]['train_loss']:.3g}", valid=f"{verr:.3f}", best=f"{best[0]:.3f}@{best[1]}")
    bar.close()
    summary: dict[str, Any] | None = None
    if ranks.main:
        summary = {
            "config": cfg.to_dict(), "train_config": asdict(c), "ranks": ranks.size, "best_valid_error": best[0], "best_step": best[1],
            "core_seconds": seconds, "curve": curve,
        }  # fmt: skip
        if (out / "best.pt").exists():
            export_grid(
                load_snapshot(out / "best.pt"),
                out / "model.onnx",
                {
                    "scene": c.scene,
                    "r_p": float(meta.get("r_p", 1.0)),
                    "radius": float(meta.get("default_connectivity_radius", CONNECTIVITY_RADIUS)),
                    "data_sha256": meta.get("sha256", {}).get("train") if isinstance(meta.get("sha256"), dict) else None,
                    "steps": best[1],
                    "core_seconds": seconds,
                    "valid_error": best[0],
                },
            )
            summary["model"] = str(out / "model.onnx")
        (out / "summary.json").write_text(json.dumps(summary, indent=1))
    # the others wait for rank 0's export and return its summary
    result = ranks.broadcast(summary)
    assert result is not None
    return result


#: Settings a run may resume with changed (``batch`` and ``nproc`` are compared as the global batch).
_RESUMABLE = ("steps", "nproc", "batch")


def export_grid(model: GridModel, path: str | Path, metadata: dict[str, Any]) -> Path:
    """Write ``model``'s U-Net to ``path`` (atomically) as the file
    :class:`hybridmpm.neural.grid.GridRuntime` runs: input ``grid`` float32
    [1, C, G^D], output ``dv`` float32 [1, r_t·D, G^D], standard ONNX
    operators (opset 18); the metadata property ``hybridmpm`` holds
    ``metadata`` merged over ``kind``, ``grid_config``, ``beta``, ``dim``,
    ``r_t``, ``t_in``, ``bounds``, ``parameters``. Needs torch and onnx."""
    import warnings

    import onnx

    cfg = model.config
    meta = {
        "kind": GRID_KIND,
        "grid_config": cfg.to_dict(),
        "beta": float(torch.sigmoid(model.flip_logit.detach())),
        "pressure_strength": float(torch.nn.functional.softplus(model.pressure_logit.detach())) if cfg.pressure else None,
        "dim": cfg.dim,
        "r_t": cfg.r_t,
        "t_in": cfg.t_in,
        "bounds": cfg.bounds,
        "particle_types": cfg.types,
        "parameters": int(sum(p.numel() for p in model.parameters())),
        **metadata,
    }
    meta["kind"] = GRID_KIND
    path = Path(path)
    tmp = path.with_name(path.name + ".tmp")
    example = torch.zeros(1, cfg.in_channels, *[cfg.grid] * cfg.dim)
    net = model.net.eval()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        torch.onnx.export(net, (example,), str(tmp), input_names=[GRID_INPUT], output_names=[GRID_OUTPUT], opset_version=18, dynamo=False)
    proto = onnx.load(str(tmp))
    entry = proto.metadata_props.add()
    entry.key, entry.value = METADATA_KEY, json.dumps(meta, sort_keys=True)
    onnx.save(proto, str(tmp))
    os.replace(tmp, path)
    return path


def load_snapshot(path: str | Path) -> GridModel:
    """A :class:`GridModel` from a ``best.pt`` / ``checkpoint.pt`` of :func:`train_grid`."""
    state = torch.load(path, weights_only=False)
    model = GridModel(GridConfig(**state["config"]))
    model.load_state_dict(state["model"])
    return model.eval()


__all__ = ["GridTrainConfig", "export_grid", "load_snapshot", "rest_count", "rollout", "train_grid", "validation_error", "velocity_scale"]
