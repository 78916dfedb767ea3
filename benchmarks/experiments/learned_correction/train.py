"""Training of the learned correction of coarse MPM (needs torch), DAgger-style
and without gradients through the solver (List et al. 2024, arXiv 2402.12971;
Ross et al. 2011).

Round 0 rolls out plain MPM on the coarse grid (2 particles per cell per
axis) from the training seeds' initial states; every ``every``-th frame it
saves the particles' features and target
(:class:`~experiments.learned_correction.forcing.LabelledForcing`: the teacher's
velocity after one frame on the scene's grid minus one plain coarse frame's,
in cells per frame). A per-particle MLP is fitted to the aggregate; each later
round rolls out the *corrected* coarse MPM, labels the states it visits the
same way, adds them and fits again. Every round's model is scored on the
validation seeds' rollouts (mean grid-mass error against full-resolution
MPM, at each of ``scales``); the best is kept (``model.npz``).

    from experiments.learned_correction.train import CorrectionTrainConfig, train_correction
    train_correction(CorrectionTrainConfig("sand2d"), Path("runs/correction_sand2d"))
"""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass
from multiprocessing import get_context
from pathlib import Path
from typing import Any

import numpy as np
import torch
from tqdm import tqdm

from experiments.learned_correction.features import num_features
from experiments.learned_correction.forcing import CorrectionForcing, LabelledForcing, coarse_simulator
from experiments.learned_correction.model import Correction
from hybridmpm.bench.harness import write_json
from hybridmpm.metrics import grid_mass_error
from hybridmpm.scenes import PAPER_R_P, make_scene
from hybridmpm.sim import MpmSimulator, rollout
from hybridmpm.train.datasets import trajectory_seed
from hybridmpm.train.scaffold import RunConfig, flag, integer, number, optional, setting

#: Dataset seeds of the correction's training and validation trajectories (streams of :func:`trajectory_seed`).
TRAIN_STREAM, VAL_STREAM = 5601, 5602


@dataclass
class CorrectionTrainConfig(RunConfig):
    """Settings of :func:`train_correction`: the scene, the coarse grid
    (default half the scene's), seeds, frames per trajectory, labelling every
    ``every`` frames, DAgger ``rounds``, the MLP (``hidden`` × ``layers``),
    Adam ``steps`` of ``batch`` rows per round at ``lr`` (cosine decay),
    worker processes, targets averaged per coarse cell (``smooth``), and the
    factors the correction is scored at on validation. :meth:`validate`
    refuses a bad value naming its field (the training scaffold's
    :class:`~hybridmpm.train.scaffold.RunConfig`)."""

    scene: str = "water2d"
    n_grid: int | None = setting(None, optional(integer(1)))
    train_seeds: int = setting(8, integer(1))
    val_seeds: int = setting(4, integer(1))
    frames: int = setting(400, integer(1))
    every: int = setting(4, integer(1))
    rounds: int = setting(2, integer(1))
    hidden: int = setting(64, integer(1))
    layers: int = setting(2, integer(1))
    steps: int = setting(3000, integer(1))
    batch: int = setting(4096, integer(1))
    lr: float = setting(2e-3, number(0, low_open=True))
    workers: int = setting(2, integer(1))
    seed: int = 0
    smooth: bool = setting(True, flag)
    scales: tuple[float, ...] = (0.5, 1.0)


def coarse_grid(scene_name: str, n_grid: int | None) -> int:
    """The coarse grid: ``n_grid``, or half the scene's."""
    n0 = make_scene(scene_name, seed=0).params.resolved_n_grid()
    return n0 // 2 if n_grid is None else int(n_grid)


def corrected_rollout(scene_name: str, seed: int, n_grid: int, frames: int, model: Correction | None, scale: float = 1.0) -> np.ndarray:
    """Fluid positions float32 [frames + 1, N, D] of the coarse MPM corrected by ``model`` (plain without)."""
    sim = coarse_simulator(make_scene(scene_name, seed=seed), n_grid)
    if model is not None:
        sim.forcing = CorrectionForcing(sim, model, scale=scale)
    return rollout(sim, frames).fluid_positions


def _collect(args: tuple[str, int, int, int, int, Correction | None, bool, float]) -> tuple[np.ndarray, np.ndarray]:
    scene_name, seed, n, frames, every, model, smooth, scale = args
    base = make_scene(scene_name, seed=seed)
    sim = coarse_simulator(base, n)
    lab = LabelledForcing(sim, model, base.params, every=every, smooth=smooth, scale=scale)
    sim.forcing = lab
    rollout(sim, frames)
    return np.concatenate(lab.xs), np.concatenate(lab.ys)


def _baselines(args: tuple[str, int, int, int]) -> tuple[np.ndarray, float, float]:
    """A validation seed: the full-resolution reference, the plain coarse grid's error and MPM at r_p's."""
    scene_name, sd, n, frames = args
    base = make_scene(scene_name, seed=sd)
    ref = rollout(MpmSimulator(base, threads=1), frames).fluid_positions
    n0 = base.params.resolved_n_grid()
    plain = grid_mass_error(corrected_rollout(scene_name, sd, n, frames, None), ref, n0).mean()
    rp = rollout(MpmSimulator(base, r_p=PAPER_R_P, seed=sd, threads=1), frames).fluid_positions
    return ref, float(plain), float(grid_mass_error(rp, ref, n0).mean())


def _val_one(args: tuple[str, int, int, int, Correction, np.ndarray, float]) -> float:
    scene_name, sd, n, frames, model, ref, scale = args
    pos = corrected_rollout(scene_name, sd, n, frames, model, scale)
    if len(pos) != len(ref):
        return float("inf")  # the run failed
    return float(grid_mass_error(pos, ref, make_scene(scene_name, seed=0).params.resolved_n_grid()).mean())


class _Mlp(torch.nn.Module):
    def __init__(self, f: int, d: int, hidden: int, layers: int) -> None:
        super().__init__()
        dims = [f] + [hidden] * layers + [d]
        self.lin = torch.nn.ModuleList(torch.nn.Linear(a, b) for a, b in zip(dims, dims[1:]))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        for i, lin in enumerate(self.lin):
            x = lin(x)
            if i < len(self.lin) - 1:
                x = torch.nn.functional.silu(x)
        return x


def fit(x: np.ndarray, y: np.ndarray, cfg: CorrectionTrainConfig, meta: dict, *, log: list | None = None) -> Correction:
    """Fit the MLP to standardised features [M, F] and targets [M, D]; a
    tenth of the rows is held out for the one-step loss, logged beside the
    loss of no correction (both in units of the targets' variance)."""
    rng = np.random.default_rng(cfg.seed)
    x_mean, x_std = x.mean(0), x.std(0) + 1e-6
    y_std = y.std(0) + 1e-9
    perm = rng.permutation(len(x))
    n_val = max(1, len(x) // 10)
    vi, ti = perm[:n_val], perm[n_val:]
    xt = torch.from_numpy(((x - x_mean) / x_std).astype(np.float32))
    yt = torch.from_numpy((y / y_std).astype(np.float32))
    torch.manual_seed(cfg.seed)
    net = _Mlp(x.shape[1], y.shape[1], cfg.hidden, cfg.layers)
    opt = torch.optim.Adam(net.parameters(), lr=cfg.lr)
    sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, cfg.steps)
    g = torch.Generator().manual_seed(cfg.seed)
    tidx = torch.from_numpy(ti)
    for _ in tqdm(range(cfg.steps), desc="fit", leave=False):
        b = tidx[torch.randint(len(tidx), (cfg.batch,), generator=g)]
        loss = torch.nn.functional.mse_loss(net(xt[b]), yt[b])
        opt.zero_grad()
        loss.backward()
        opt.step()
        sched.step()
    with torch.no_grad():
        v = torch.from_numpy(vi)
        val = float(torch.nn.functional.mse_loss(net(xt[v]), yt[v]))
        zero = float((yt[v] ** 2).mean())
    if log is not None:
        log.append({"one_step_val": val, "no_correction": zero, "rows": int(len(x))})
    lins: list[torch.nn.Linear] = list(net.lin)  # type: ignore[arg-type]
    ws = [lin.weight.detach().numpy().T.copy() for lin in lins]
    bs = [lin.bias.detach().numpy().copy() for lin in lins]
    return Correction(ws, bs, x_mean.astype(np.float32), x_std.astype(np.float32), y_std.astype(np.float32), dict(meta))


def train_correction(cfg: CorrectionTrainConfig, out: Path) -> dict[str, Any]:
    """DAgger rounds (module doc); writes ``roundR.npz``, ``model.npz`` (the
    best round, its scale in ``meta``) and ``log.json`` under ``out``;
    returns the best round, its validation error and the log. Raises
    :class:`~hybridmpm.errors.InvalidInputError` naming a bad setting."""
    cfg.validate()
    out.mkdir(parents=True, exist_ok=True)
    torch.set_num_threads(max(1, cfg.workers))
    n = coarse_grid(cfg.scene, cfg.n_grid)
    train = [trajectory_seed(TRAIN_STREAM, i) for i in range(cfg.train_seeds)]
    val = [trajectory_seed(VAL_STREAM, i) for i in range(cfg.val_seeds)]
    meta = {"scene": cfg.scene, "n_grid": n, "features": num_features(make_scene(cfg.scene, seed=0).dim), "config": asdict(cfg)}
    log: list[dict] = []
    t0 = time.time()
    ctx = get_context("fork")
    with ctx.Pool(cfg.workers) as pool:
        first = pool.map(_baselines, [(cfg.scene, sd, n, cfg.frames) for sd in val])
    refs = {sd: r[0] for sd, r in zip(val, first)}
    plain = {sd: r[1] for sd, r in zip(val, first)}
    rp = {sd: r[2] for sd, r in zip(val, first)}
    xs: list[np.ndarray] = []
    ys: list[np.ndarray] = []
    model: Correction | None = None
    best, best_scale = (float("inf"), -1), 1.0
    for r in range(cfg.rounds):
        jobs = [(cfg.scene, sd, n, cfg.frames, cfg.every, model, cfg.smooth, best_scale) for sd in train]
        with ctx.Pool(cfg.workers) as pool:
            for x, y in tqdm(pool.imap_unordered(_collect, jobs), total=len(jobs), desc=f"round {r} data"):
                xs.append(x)
                ys.append(y)
        model = fit(np.concatenate(xs), np.concatenate(ys), cfg, meta, log=log)
        jobs_v = [(cfg.scene, sd, n, cfg.frames, model, refs[sd], sc) for sc in cfg.scales for sd in val]
        with ctx.Pool(cfg.workers) as pool:
            got = pool.map(_val_one, jobs_v)
        by_scale = {sc: dict(zip(val, got[i * len(val) : (i + 1) * len(val)])) for i, sc in enumerate(cfg.scales)}
        means = {sc: float(np.mean(list(e.values()))) for sc, e in by_scale.items()}
        sc = min(means, key=lambda k: means[k])
        log[-1] |= {
            "round": r,
            "scale": sc,
            "val_error_by_scale": means,
            "val_error": means[sc],
            "val_error_plain": float(np.mean(list(plain.values()))),
            "val_error_rp": float(np.mean(list(rp.values()))),
            "per_seed": {str(k): {"corrected": by_scale[sc][k], "plain": plain[k], "rp": rp[k]} for k in val},
            "wall_s": time.time() - t0,
        }
        model.meta["scale"] = sc
        model.save(out / f"round{r}.npz")
        if means[sc] < best[0]:
            best, best_scale = (means[sc], r), sc
            model.save(out / "model.npz")
        write_json(out / "log.json", log)
    return {"best_round": best[1], "best_val_error": best[0], "log": log}


__all__ = ["TRAIN_STREAM", "VAL_STREAM", "CorrectionTrainConfig", "corrected_rollout", "train_correction"]
