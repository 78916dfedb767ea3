"""Training and export of the Fluid ControlNet (``hybridmpm train-control``;
the ``train`` extra: torch, onnx).

Data: the cases of :mod:`hybridmpm.train.control.cases`. Each case gives two
training pairs: (state, sketch) → the reverse-simulation path ``X_T … X_1``
(paper Sec. 3.2), and (state, blank sketch) → the uncontrolled path from the
same state (so that "no sketch" means "let it flow" and classifier-free
guidance has a meaning); the blank pair is drawn with probability
:data:`P_BLANK` (the paper's condition dropout). Every case is also used
mirrored in x (the sketch with it). The sample is the path's displacement
from the start, on the temporal basis (:func:`~hybridmpm.control.diffusion.project`),
normalised per (basis, dimension).

Diffusion: cosine schedule, T = 100, x0 prediction, MSE on the normalised
coefficients (a few noise levels per state encoding); AdamW with exponential
learning-rate decay; an EMA of the weights is what gets exported.
The loop, checkpoints and curve are the training scaffold's
(:mod:`hybridmpm.train.scaffold`): checkpoints every ``checkpoint_every``
steps (``ckpt.pt``: model, EMA, optimiser, step, random streams) make a run
resumable: re-running the same command continues it as if it had not
stopped. ``log.jsonl`` (every call's rows) and ``curve.json`` (the run's)
hold the training and validation losses.
"""

from __future__ import annotations

import copy
import json
import math
import os
import time
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Any, ClassVar

import numpy as np

from hybridmpm.control.diffusion import (
    DIFFUSION_STEPS,
    GRAPHS,
    META_FILE,
    cosine_alpha_bar,
    mirror_x,
    path_basis,
    prior_coefficients,
    project,
)
from hybridmpm.control.prior import PRIOR_FREE_SKETCH, PRIOR_SKETCH_RAMP, free_motion, material_of, prior_path
from hybridmpm.control.sketch import Sketch, render_sketch
from hybridmpm.control.targets import GEOMETRY_SCALE, sketch_geometry
from hybridmpm.conventions import CONNECTIVITY_RADIUS
from hybridmpm.errors import InvalidInputError
from hybridmpm.graph import radius_graph
from hybridmpm.scenes import make_scene
from hybridmpm.sim import MpmSimulator
from hybridmpm.train.control.cases import iter_cases, load_case
from hybridmpm.train.control.model import GEOMETRY, LOCAL_CHANNELS, SKETCH_EMBED, ControlNetConfig, FluidControlNet
from hybridmpm.train.distributed import LossOf, Ranks, launch
from hybridmpm.train.scaffold import (
    Parts,
    RunConfig,
    TrainingLoop,
    ValidationCurve,
    export_metadata,
    integer,
    number,
    one_of,
    optional,
    processes,
    setting,
    start_run,
)

#: Probability of a blank-sketch (uncontrolled) training pair.
P_BLANK = 0.15
#: Temporal basis size (``docs/control.md``: the smallest whose path replay lands within 1.1× of the unprojected path's).
K_BASIS = 8
#: Noise levels per state encoding in one step.
NOISE_DRAWS = 2
#: Version of the control model format.
CONTROL_FORMAT = 1


@dataclass
class _Pair:
    positions: np.ndarray
    velocities: np.ndarray
    particle_type: np.ndarray
    senders: np.ndarray
    receivers: np.ndarray
    image: np.ndarray  # [1, 3, 64, 64] float32
    geometry: np.ndarray  # [11]
    offset: np.ndarray  # [N, D]
    coef: np.ndarray  # [N, K·D] raw (not normalised), minus the sketch prior
    free: np.ndarray  # [N, K·D] raw, the blank-sketch target


def _mirror_sketch(sk: Sketch, lo: float, hi: float) -> Sketch:
    pts = np.array(sk.points, copy=True)
    pts[:, 0] = lo + hi - pts[:, 0]
    return Sketch(sk.kind, pts, sk.t, sk.width)


def scene_bounds(scene: str) -> list[list[float]]:
    """The walls of registered ``scene`` as [[lo, hi]] × D [m]."""

    sim = MpmSimulator(make_scene(scene, seed=0))
    lo, hi = sim.solver.domain_bounds
    return [[float(lo), float(hi)] for _ in range(sim.particles.dim)]


def load_pairs(
    paths: list[Path],
    k_basis: int,
    bounds: list[list[float]],
    mirror: bool = True,
    radius: float = CONNECTIVITY_RADIUS,
    prior: str = PRIOR_FREE_SKETCH,
    progress: bool = False,
) -> list[_Pair]:
    """Training pairs from case files (module doc), with their radius graphs;
    the targets are taken relative to ``prior`` (:mod:`hybridmpm.control.prior`:
    the coarse free rollout of each case is computed here, the same function
    the sampler calls)."""
    from tqdm import tqdm

    if prior not in (PRIOR_SKETCH_RAMP, PRIOR_FREE_SKETCH):
        raise InvalidInputError(f"prior: must be {PRIOR_SKETCH_RAMP!r} or {PRIOR_FREE_SKETCH!r}, got {prior!r}", "prior")
    lo, hi = bounds[0]
    pairs = []
    for p in tqdm(paths, desc="control pairs", unit="case", disable=not progress):
        rec = load_case(p)
        basis = path_basis(len(rec.path), k_basis)
        coarse = None
        if prior == PRIOR_FREE_SKETCH:
            params = make_scene(str(rec.info["scene"]), seed=int(rec.info["seed"])).params
            frames = len(rec.path) - 1
            coarse = free_motion(rec.positions, rec.velocities, material_of(rec.particle_type), params, frames, dt_frame=float(rec.info["dt_frame"]))
        variants = [False, True] if mirror else [False]
        for flip in variants:
            x, v, path, free, sk, cfree = rec.positions, rec.velocities, rec.path, rec.free_path, rec.sketch, coarse
            if flip:
                x, path, free, sk = mirror_x(x, lo, hi), mirror_x(path, lo, hi), mirror_x(free, lo, hi), _mirror_sketch(sk, lo, hi)
                cfree = None if coarse is None else mirror_x(coarse, lo, hi)
                v = np.array(v, copy=True)
                v[:, 0] = -v[:, 0]
            s, r, _, _ = radius_graph(x, radius)
            geo, off = sketch_geometry(sk, x)
            x64 = np.asarray(x, np.float64)
            if cfree is None:
                prior_sk = prior_coefficients(off * GEOMETRY_SCALE, basis)
                prior_blank: Any = 0.0
            else:
                prior_sk = project(prior_path(cfree, x64, sk) - x64[None], basis).reshape(len(x), -1)
                prior_blank = project(cfree - x64[None], basis).reshape(len(x), -1)
            coef = (project(path - path[0], basis).reshape(len(x), -1) - prior_sk).astype(np.float32)
            fcoef = project(free - free[0], basis).reshape(len(x), -1) - prior_blank
            img = render_sketch(sk).astype(np.float32).transpose(2, 0, 1)[None] / 255.0
            pairs.append(_Pair(x.astype(np.float32), v.astype(np.float32), rec.particle_type, s, r, img, geo, off, coef, fcoef))
    return pairs


#: Most pairs per step and rank.
MAX_BATCH = 4096
#: The checkpoint's file name.
CKPT = "ckpt.pt"


@dataclass
class ControlTrainConfig(RunConfig):
    """Settings of :func:`train_control` (its arguments; module doc). A run
    resumes with any of them changed but the global batch (``batch`` times
    the ranks): the sizes and the prior of the model are the checkpoint's."""

    RESUMABLE: ClassVar[tuple[str, ...]] = (
        "scene", "data_root", "out", "steps", "lr", "lr_final", "k_basis", "latent_state", "latent_head", "valid_fraction", "max_cases",
        "checkpoint_every", "seed", "threads", "time_limit", "prior", "init_from", "nproc", "ranks",
    )  # fmt: skip

    scene: str
    data_root: str
    out: str
    steps: int = setting(20000, integer(1, 10_000_000))
    lr: float = setting(1e-3, number(0, 1, low_open=True))
    lr_final: float = setting(1e-4, number(0, 1, low_open=True))
    k_basis: int = setting(K_BASIS, integer(1))
    latent_state: int = setting(32, integer(1))
    latent_head: int = setting(32, integer(1))
    valid_fraction: float = setting(0.05, number(0, 1))
    max_cases: int | None = setting(None, optional(integer(0)))
    checkpoint_every: int = setting(500, integer(1))
    seed: int = 0
    threads: int = 1
    time_limit: float | None = setting(None, optional(number(0)))
    prior: str = setting(PRIOR_FREE_SKETCH, one_of((PRIOR_SKETCH_RAMP, PRIOR_FREE_SKETCH)))
    init_from: str | None = None
    batch: int = setting(1, integer(1, MAX_BATCH))
    nproc: int = setting(1, processes)

    def check(self) -> None:
        if not self.lr_final <= self.lr:
            raise InvalidInputError(f"lr: need 0 < lr_final <= lr <= 1, got {self.lr!r}, {self.lr_final!r}", "lr")

    def lr_at(self, step: int) -> float:
        """The learning rate of step ``step``: from ``lr`` down to ``lr_final`` exponentially over ``steps``."""
        return self.lr * ((self.lr_final / self.lr) ** (1.0 / max(self.steps, 1))) ** step


def train_control(
    scene: str,
    data_root: str | Path,
    out: str | Path,
    *,
    steps: int = 20000,
    lr: float = 1e-3,
    lr_final: float = 1e-4,
    k_basis: int = K_BASIS,
    latent_state: int = 32,
    latent_head: int = 32,
    valid_fraction: float = 0.05,
    max_cases: int | None = None,
    checkpoint_every: int = 500,
    seed: int = 0,
    threads: int = 1,
    time_limit: float | None = None,
    progress: bool = True,
    prior: str = PRIOR_FREE_SKETCH,
    init_from: str | Path | None = None,
    batch: int = 1,
    nproc: int = 1,
) -> dict[str, Any]:
    """Train (or resume) the controller of ``scene`` on the cases under
    ``data_root`` into ``out`` (``ckpt.pt``, ``log.jsonl``, ``curve.json``; module doc) for
    ``steps`` optimiser steps of ``batch`` pairs (or until ``time_limit`` seconds), then export
    it (:func:`export_control`) to ``out/model``. Returns a summary
    (steps, seconds, mean loss of this call's first and last 10 steps, and
    ``fit_first`` / ``fit_last``: the loss on up to 8 training pairs at fixed
    noise levels and draws, before this call and of the exported EMA;
    ``ranks`` and ``core_seconds``, the CPU seconds of every rank's process, summed).

    With ``nproc`` > 1 (or under torchrun) it trains on several processes
    (:mod:`hybridmpm.train.distributed`), ``batch`` pairs each: every rank
    draws the pairs, blank choices, noise levels and noise of the global batch
    from the one random stream a single process of ``nproc · batch`` pairs
    draws and keeps its slice, so the weights are that process's to float
    rounding; rank 0 logs, checkpoints and exports. A run resumes with another
    split of the same global batch. Raises :class:`InvalidInputError`
    naming ``data_root`` when there are fewer than 4 cases, or a bad setting
    (:class:`ControlTrainConfig`)."""
    config = ControlTrainConfig(
        scene=scene, data_root=str(data_root), out=str(out), steps=steps, lr=lr, lr_final=lr_final, k_basis=k_basis, latent_state=latent_state,
        latent_head=latent_head, valid_fraction=valid_fraction, max_cases=max_cases, checkpoint_every=checkpoint_every, seed=seed,
        threads=threads, time_limit=time_limit, prior=prior, init_from=None if init_from is None else str(init_from), batch=batch, nproc=nproc,
    ).validate()  # fmt: skip
    paths = list(iter_cases(data_root, scene))[: max_cases or None]
    if len(paths) < 4:
        raise InvalidInputError(
            f"data_root: {len(paths)} control cases of {scene} under {data_root}; run `hybridmpm generate-control {scene}` first", "data_root"
        )
    return launch(_train_control, nproc, config, paths, progress)


def _start(ranks: Ranks, c: ControlTrainConfig) -> tuple[dict[str, Any] | None, dict[str, Any] | None]:
    """The run's checkpoint (rank 0 reads it, or the warm start's weights, and sends them to the
    others, who may not share its directory): ``(checkpoint or None, warm-start state dict or None)``."""
    import torch

    ck, init, error = None, None, None
    if ranks.main:
        path = Path(c.out) / CKPT
        if path.exists():
            ck = torch.load(path, map_location="cpu", weights_only=False)
        elif c.init_from is not None:  # warm start: the weights of another run (same sizes), fresh optimiser
            try:
                init = torch.load(Path(c.init_from), map_location="cpu", weights_only=False)["ema"]
            except (OSError, KeyError, RuntimeError) as e:
                error = InvalidInputError(f"init_from: {c.init_from} is not a checkpoint of a control model ({e})", "init_from")
    ck, init, error = ranks.broadcast((ck, init, error))
    if error is not None:
        raise error
    if ck is not None and "opt" in ck:  # written before the training scaffold: its keys
        ck = {**ck, "optimizer": ck["opt"], "elapsed": float(ck.get("seconds", 0.0))}
    return ck, init


class _Run:
    """One rank's controller run: the pairs, the model and what the training
    loop (:class:`~hybridmpm.train.scaffold.TrainingLoop`) calls of it."""

    def __init__(self, c: ControlTrainConfig, ranks: Ranks, paths: list[Path], ck: dict[str, Any] | None, progress: bool) -> None:
        import torch

        self.c, self.ranks = c, ranks
        n_valid = max(1, int(round(c.valid_fraction * len(paths))))
        bounds = scene_bounds(c.scene)
        prior = c.prior if ck is None else str(ck["config"].get("extra", {}).get("prior", PRIOR_SKETCH_RAMP))  # a resumed run keeps its prior
        self.train_pairs = load_pairs(paths[n_valid:], c.k_basis, bounds, prior=prior, progress=progress and ranks.main)
        self.valid_pairs = load_pairs(paths[:n_valid], c.k_basis, bounds, mirror=False, prior=prior)
        coef_all = np.concatenate([p.coef for p in self.train_pairs] + [p.free for p in self.train_pairs])
        mean, std = coef_all.mean(0), np.maximum(coef_all.std(0), 1e-6)
        vel_scale = float(np.concatenate([p.velocities for p in self.train_pairs]).std()) or 1.0
        cfg = ControlNetConfig(
            dim=int(self.train_pairs[0].positions.shape[1]), k_basis=c.k_basis, frames=int(load_case(paths[0]).path.shape[0]), bounds=bounds,
            radius=CONNECTIVITY_RADIUS, vel_scale=vel_scale, offset_scale=1.0, coef_mean=mean.tolist(), coef_std=std.tolist(),
            latent_state=c.latent_state, latent_head=c.latent_head,
            extra={"scene": c.scene, "cases": len(paths) - n_valid, "valid_cases": n_valid, "prior": prior},
        )  # fmt: skip
        torch.manual_seed(c.seed)  # the initial weights are the seed's, whichever process draws them
        self.model = FluidControlNet(cfg)
        self.ema = copy.deepcopy(self.model)
        if ck is not None:
            cfg = ControlNetConfig.from_dict(ck["config"])
            self.model, self.ema = FluidControlNet(cfg), FluidControlNet(cfg)
        self.cfg = cfg
        self.opt = torch.optim.AdamW(self.model.parameters(), lr=c.lr, weight_decay=1e-4)
        self.parts = Parts(self.model, self.opt, np.random.default_rng(c.seed), lr=c.lr_at, extra={"ema": self.ema})
        self.mean_t = torch.tensor(cfg.coef_mean, dtype=torch.float32)
        self.std_t = torch.tensor(cfg.coef_std, dtype=torch.float32)
        self.alpha_bar = torch.tensor(cosine_alpha_bar(DIFFUSION_STEPS), dtype=torch.float32)
        self.fit_pairs = self.train_pairs[:: max(1, len(self.train_pairs) // 8)][:8]
        self.mine = ranks.part(c.batch)
        self.step_loss: Any = None
        self.loop: TrainingLoop | None = None

    def warm_start(self, init: dict[str, Any]) -> None:
        """Load another run's EMA weights into the model and its EMA (same sizes, or :class:`InvalidInputError`)."""
        try:
            self.model.load_state_dict(init)
            self.ema.load_state_dict(init)
        except RuntimeError as e:
            raise InvalidInputError(f"init_from: {self.c.init_from} is not a checkpoint of a control model of the same sizes ({e})", "init_from") from e

    def wrap(self) -> None:
        """The loss of a step, in DistributedDataParallel when there are several ranks (its backward averages the
        gradients); the state encoder's decoder takes no part in it (its latents are what the head reads)."""
        self.step_loss = self.ranks.wrap(LossOf(self.model, self.batch_loss), unused=True)

    def tensors(self, p: _Pair, blank: bool) -> tuple[Any, ...]:
        """A pair's inputs and normalised target (the blank sketch's: no image, geometry or offset)."""
        import torch

        x = torch.from_numpy(p.positions)
        target = (torch.from_numpy(p.free if blank else p.coef) - self.mean_t) / self.std_t
        img = torch.zeros(1, 3, 64, 64) if blank else torch.from_numpy(p.image)
        geo = torch.zeros(1, 11) if blank else torch.from_numpy(p.geometry)[None]
        off = torch.zeros_like(x) if blank else torch.from_numpy(p.offset)
        v, pt, s, r = (torch.from_numpy(a) for a in (p.velocities, p.particle_type, p.senders, p.receivers))
        return x, v, pt, s, r, img, geo, off, target

    def loss_of(self, net: FluidControlNet, p: _Pair, blank: bool, ts: list[int], gen: Any = None, noises: list[Any] | None = None) -> Any:
        """The pair's loss at noise levels ``ts``, with the noise ``noises`` (default: drawn from ``gen``)."""
        import torch

        x, v, pt, s, r, img, geo, off, target = self.tensors(p, blank)
        h, edges, local, glob = net.encode(x, v, pt, s, r, img)
        cond = torch.cat([glob, geo], dim=1)
        total = torch.zeros(())
        for k, t in enumerate(ts):
            noise = torch.randn(target.shape, generator=gen) if noises is None else noises[k]
            ab = self.alpha_bar[t]
            xt = ab.sqrt() * target + (1 - ab).sqrt() * noise
            pred = net.head(xt, h, local, off, edges, s, r, torch.tensor([t / DIFFUSION_STEPS]), cond)
            total = total + torch.mean((pred - target) ** 2)
        return total / len(ts)

    def batch_loss(self, net: FluidControlNet, draws: list[tuple[_Pair, bool, list[int], list[Any]]]) -> Any:
        """The mean loss of this rank's pairs (equal weights: the ranks' mean is the global batch's)."""
        return sum(self.loss_of(net, p, blank, ts, noises=noises) for p, blank, ts, noises in draws) / len(draws)

    def validate(self, net: FluidControlNet | None = None, pairs: list[_Pair] | None = None) -> float:
        """The loss at fixed noise levels and draws (no sampling noise between calls): ``net`` (default the EMA) on ``pairs`` (default validation)."""
        import torch

        gen = torch.Generator().manual_seed(1234)
        with torch.no_grad():
            vals = [float(self.loss_of(net or self.ema, p, False, [10, 40, 70, 95], gen)) for p in (self.valid_pairs if pairs is None else pairs)]
        return float(np.mean(vals))

    def train_step(self, step: int) -> float:
        """One optimiser step (the loop has set its learning rate), then the EMA; its loss on this rank."""
        import torch

        rng = self.parts.rng
        # every rank draws the whole global batch (the random stream of one process of ranks x batch pairs) and keeps its slice
        draws = []
        for i in range(self.ranks.size * self.c.batch):
            p = self.train_pairs[int(rng.integers(len(self.train_pairs)))]
            blank = bool(rng.random() < P_BLANK)
            ts = [int(t) for t in rng.integers(0, DIFFUSION_STEPS, NOISE_DRAWS)]
            noises = [torch.randn(p.coef.shape) for _ in ts]  # the sample's shape: p.free's too
            if i in self.mine:
                draws.append((p, blank, ts, noises))
        loss = self.step_loss(draws)
        self.opt.zero_grad()
        loss.backward()
        torch.nn.utils.clip_grad_norm_(self.model.parameters(), 1.0)
        self.opt.step()
        decay = min(0.999, (1 + step) / (10 + step))
        with torch.no_grad():
            for pe, pm in zip(self.ema.parameters(), self.model.parameters()):
                pe.mul_(decay).add_(pm.detach(), alpha=1 - decay)
        return float(loss.detach())

    def evaluate(self, step: int, train_loss: float | None) -> dict[str, Any]:
        """Rank 0's validation of the EMA: the row of ``log.jsonl``."""
        assert self.loop is not None
        return {
            "step": step,
            "loss": train_loss,
            "valid": self.validate(),
            "seconds": self.loop.wall(),
            "ranks": self.ranks.size,
            "core_seconds": self.loop.core_seconds,
        }


def _train_control(ranks: Ranks, c: ControlTrainConfig, paths: list[Path], progress: bool) -> dict[str, Any]:
    """:func:`train_control` on one rank of ``ranks`` (``paths``: the case files found)."""
    import torch

    torch.set_num_threads(max(1, int(c.threads)))
    out = Path(c.out)
    start_run(c, ranks, out, CKPT)
    ck, init = _start(ranks, c)
    run = _Run(c, ranks, paths, ck, progress)
    if init is not None:
        run.warm_start(init)
    run.loop = loop = TrainingLoop(
        out, ranks, run.parts, steps=c.steps, every=c.checkpoint_every, desc=f"train-control {c.scene}", progress=progress, checkpoint=CKPT,
        curve=ValidationCurve(out, "log.jsonl"), state=lambda: {"config": run.cfg.to_dict(), "batch": c.batch},
    )  # fmt: skip
    if ck is not None:
        loop.restore(ck)
    if ck is None or "torch_rng" not in ck:  # a checkpoint from before the scaffold saved no torch stream
        torch.manual_seed(c.seed + loop.step)
    del ck, init
    fit_first = run.validate(run.model, run.fit_pairs) if ranks.main else math.nan
    run.wrap()
    run.model.train()
    t_start = time.perf_counter()
    stop = None if c.time_limit is None else (lambda: time.perf_counter() - t_start > float(c.time_limit))  # type: ignore[arg-type]
    loop.run(run.train_step, run.evaluate, stop=stop)
    # this call's first and last 10 steps, the ranks' mean (every rank made as many steps)
    first: float | None = None
    last: float | None = None
    if loop.losses:
        first, last = (v / ranks.size for v in ranks.sum(float(np.mean(loop.losses[:10])), float(np.mean(loop.losses[-10:]))))
    summary = None
    if ranks.main:
        seconds = loop.wall()
        export_control(
            run.ema, out / "model", export_metadata(run.ema, scene=c.scene, steps=loop.step, train_seconds=seconds, cases=run.cfg.extra.get("cases"))
        )
        # the loss on up to 8 training pairs at fixed noise: the model this call started from, then the EMA it exports
        fit_last = run.validate(run.ema, run.fit_pairs)
        summary = {"steps": loop.step, "seconds": seconds, "first_loss": first, "last_loss": last, "fit_first": fit_first, "fit_last": fit_last}
        summary.update({"ranks": ranks.size, "core_seconds": loop.core_seconds})
    # the others wait for rank 0's export and return its summary
    result = ranks.broadcast(summary)
    assert result is not None
    return result


def export_control(model: Any, out: str | Path, info: dict[str, Any]) -> Path:
    """Export ``model`` (a :class:`~hybridmpm.train.control.model.FluidControlNet`)
    to the directory ``out``: the three ONNX graphs of
    :data:`~hybridmpm.control.diffusion.GRAPHS` and ``control.json`` (config,
    schedule, ``info``). Written to a temporary directory and moved into
    place. Needs torch, onnx and onnxscript."""
    import shutil

    import torch

    model = model.eval()
    cfg = model.config
    out = Path(out)
    tmp = out.with_name(out.name + ".tmp")
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.mkdir(parents=True)
    rng = np.random.default_rng(0)
    lo = np.array([b[0] for b in cfg.bounds]) + 2 * cfg.radius
    x = (lo + rng.uniform(0, 4 * cfg.radius, (24, cfg.dim))).astype(np.float32)
    s, r, _, _ = radius_graph(x, cfg.radius)
    xt, vt = torch.from_numpy(x), torch.from_numpy(rng.normal(size=x.shape).astype(np.float32))
    pt, st, rt = torch.full((len(x),), 5, dtype=torch.int64), torch.from_numpy(s), torch.from_numpy(r)
    n, e = torch.export.Dim("N"), torch.export.Dim("E")
    with torch.no_grad():
        h, edges = model.state(xt, vt, pt, st, rt)
    S = cfg.sample_size

    specs = {
        "sketch_encoder": (model.sketch, (torch.zeros(1, 3, 64, 64),), ["image"], ["global", "local_map"], None),
        "state_encoder": (
            model.state,
            (xt, vt, pt, st, rt),
            ["positions", "velocities", "particle_type", "senders", "receivers"],
            ["h", "edges"],
            {"positions": {0: n}, "velocities": {0: n}, "particle_type": {0: n}, "senders": {0: e}, "receivers": {0: e}},
        ),
        "denoiser_head": (
            model.head,
            (
                torch.zeros(len(x), S),
                h,
                torch.zeros(len(x), LOCAL_CHANNELS),
                torch.zeros(len(x), cfg.dim),
                edges,
                st,
                rt,
                torch.tensor([0.5]),
                torch.zeros(1, SKETCH_EMBED + GEOMETRY),
            ),
            ["x_t", "h", "local", "offset", "edges", "senders", "receivers", "t", "cond"],
            ["x0"],
            {"x_t": {0: n}, "h": {0: n}, "local": {0: n}, "offset": {0: n}, "edges": {0: e}, "senders": {0: e}, "receivers": {0: e}, "t": None, "cond": None},
        ),
    }
    for name in GRAPHS:
        mod, args, ins, outs, dyn = specs[name]
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            prog = torch.onnx.export(mod, args, dynamo=True, opset_version=18, input_names=ins, output_names=outs, dynamic_shapes=dyn, verbose=False)
        assert prog is not None
        prog.save(str(tmp / f"{name}.onnx"))
    meta = {
        "format": CONTROL_FORMAT,
        "config": cfg.to_dict(),
        "diffusion_steps": DIFFUSION_STEPS,
        "schedule": "squaredcos_cap_v2",
        "prediction": "sample",
        "prior": str(cfg.extra.get("prior", PRIOR_SKETCH_RAMP)),
        "parameters": int(sum(p.numel() for p in model.parameters())),
        **info,
    }
    (tmp / META_FILE).write_text(json.dumps(meta, indent=1, sort_keys=True))
    if out.exists():
        shutil.rmtree(out)
    os.replace(tmp, out)
    return out


__all__ = ["K_BASIS", "MAX_BATCH", "P_BLANK", "export_control", "load_pairs", "scene_bounds", "train_control"]
