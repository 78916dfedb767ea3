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
Checkpoints every ``checkpoint_every`` steps (``ckpt.pt``: model, EMA,
optimiser, step, RNG) make a run resumable: re-running the same command
continues it. ``log.jsonl`` holds the training and validation losses.
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
from typing import Any

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
from hybridmpm.train.distributed import LossOf, Ranks, check_nproc, launch

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
    ``data_root`` into ``out`` (``ckpt.pt``, ``log.jsonl``; module doc) for
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
    naming ``data_root`` when there are fewer than 4 cases, or a bad setting."""
    if isinstance(steps, bool) or not isinstance(steps, int) or not 1 <= steps <= 10_000_000:
        raise InvalidInputError(f"steps: must be an integer in [1, 10⁷], got {steps!r}", "steps")
    if isinstance(batch, bool) or not isinstance(batch, int) or not 1 <= batch <= MAX_BATCH:
        raise InvalidInputError(f"batch: must be an integer in [1, {MAX_BATCH}], got {batch!r}", "batch")
    check_nproc(nproc)
    if not (0 < lr_final <= lr <= 1.0):
        raise InvalidInputError(f"lr: need 0 < lr_final <= lr <= 1, got {lr!r}, {lr_final!r}", "lr")
    paths = list(iter_cases(data_root, scene))[: max_cases or None]
    if len(paths) < 4:
        raise InvalidInputError(
            f"data_root: {len(paths)} control cases of {scene} under {data_root}; run `hybridmpm generate-control {scene}` first", "data_root"
        )
    settings = dict(
        scene=scene, paths=paths, out=Path(out), steps=steps, lr=lr, lr_final=lr_final, k_basis=k_basis, latent_state=latent_state,
        latent_head=latent_head, valid_fraction=valid_fraction, checkpoint_every=checkpoint_every, seed=seed, threads=threads,
        time_limit=time_limit, progress=progress, prior=prior, init_from=init_from, batch=batch,
    )  # fmt: skip
    return launch(_train_control, nproc, settings)


#: Most pairs per step and rank.
MAX_BATCH = 4096


def _train_control(ranks: Ranks, kw: dict[str, Any]) -> dict[str, Any]:
    """:func:`train_control` on one rank of ``ranks`` (``kw``: its settings, the case paths found)."""
    import torch
    from tqdm import tqdm

    scene, paths, out, steps, lr, k_basis, seed = kw["scene"], kw["paths"], kw["out"], kw["steps"], kw["lr"], kw["k_basis"], kw["seed"]
    checkpoint_every, time_limit, batch, prior = kw["checkpoint_every"], kw["time_limit"], kw["batch"], kw["prior"]
    progress = kw["progress"] and ranks.main
    torch.set_num_threads(max(1, int(kw["threads"])))
    if ranks.main:
        out.mkdir(parents=True, exist_ok=True)
    n_valid = max(1, int(round(kw["valid_fraction"] * len(paths))))
    bounds = scene_bounds(scene)
    ckpt_path = out / "ckpt.pt"
    # rank 0 reads the checkpoint (or the warm start) and sends it to the others, who may not share its directory
    ck, init, error = None, None, None
    if ranks.main:
        if ckpt_path.exists():
            ck = torch.load(ckpt_path, map_location="cpu", weights_only=False)
        elif kw["init_from"] is not None:  # warm start: the weights of another run (same sizes), fresh optimiser
            try:
                init = torch.load(Path(kw["init_from"]), map_location="cpu", weights_only=False)["ema"]
            except (OSError, KeyError, RuntimeError) as e:
                error = InvalidInputError(f"init_from: {kw['init_from']} is not a checkpoint of a control model ({e})", "init_from")
        if ck is not None and int(ck.get("batch", 1)) * int(ck.get("ranks", 1)) != batch * ranks.size:
            old_b, old_r = int(ck.get("batch", 1)), int(ck.get("ranks", 1))
            error = InvalidInputError(
                f"batch: {out} holds a run of {old_b * old_r} pairs per step ({old_b} on each of {old_r} ranks), "
                f"not {batch * ranks.size} ({batch} on each of {ranks.size}); use another --out",
                "batch",
            )
    ck, init, error = ranks.broadcast((ck, init, error))
    if error is not None:
        raise error
    if ck is not None:  # a resumed run keeps the prior it started with
        prior = str(ck["config"].get("extra", {}).get("prior", PRIOR_SKETCH_RAMP))
    train_pairs = load_pairs(paths[n_valid:], k_basis, bounds, prior=prior, progress=progress)
    valid_pairs = load_pairs(paths[:n_valid], k_basis, bounds, mirror=False, prior=prior)
    coef_all = np.concatenate([p.coef for p in train_pairs] + [p.free for p in train_pairs])
    mean, std = coef_all.mean(0), np.maximum(coef_all.std(0), 1e-6)
    vel_scale = float(np.concatenate([p.velocities for p in train_pairs]).std()) or 1.0
    cfg = ControlNetConfig(
        dim=int(train_pairs[0].positions.shape[1]),
        k_basis=k_basis,
        frames=int(load_case(paths[0]).path.shape[0]),
        bounds=bounds,
        radius=CONNECTIVITY_RADIUS,
        vel_scale=vel_scale,
        offset_scale=1.0,
        coef_mean=mean.tolist(),
        coef_std=std.tolist(),
        latent_state=kw["latent_state"],
        latent_head=kw["latent_head"],
        extra={"scene": scene, "cases": len(paths) - n_valid, "valid_cases": n_valid, "prior": prior},
    )
    torch.manual_seed(seed)  # the initial weights are the seed's, whichever process draws them
    model = FluidControlNet(cfg)
    ema = copy.deepcopy(model)
    opt = torch.optim.AdamW(model.parameters(), lr=lr, weight_decay=1e-4)
    step, rng_state, spent, core_seconds = 0, None, 0.0, 0.0
    if init is not None:
        try:
            model.load_state_dict(init)
            ema.load_state_dict(init)
        except RuntimeError as e:
            raise InvalidInputError(f"init_from: {kw['init_from']} is not a checkpoint of a control model of the same sizes ({e})", "init_from") from e
    if ck is not None:
        cfg = ControlNetConfig.from_dict(ck["config"])
        model, ema = FluidControlNet(cfg), FluidControlNet(cfg)
        model.load_state_dict(ck["model"])
        ema.load_state_dict(ck["ema"])
        opt = torch.optim.AdamW(model.parameters(), lr=lr, weight_decay=1e-4)
        opt.load_state_dict(ck["opt"])
        step, rng_state, spent = int(ck["step"]), ck["rng"], float(ck.get("seconds", 0.0))
        core_seconds = float(ck.get("core_seconds", spent))  # a checkpoint from before the count: its wall time
    del ck, init
    mean_t = torch.tensor(cfg.coef_mean, dtype=torch.float32)
    std_t = torch.tensor(cfg.coef_std, dtype=torch.float32)
    alpha_bar = torch.tensor(cosine_alpha_bar(DIFFUSION_STEPS), dtype=torch.float32)
    rng = np.random.default_rng(seed)
    if rng_state is not None:
        rng.bit_generator.state = rng_state
    torch.manual_seed(seed + step)
    gamma = (kw["lr_final"] / lr) ** (1.0 / max(steps, 1))
    log = (out / "log.jsonl").open("a") if ranks.main else None
    blank_img = torch.zeros(1, 3, 64, 64)

    def tensors(p: _Pair, blank: bool) -> tuple[Any, ...]:
        x = torch.from_numpy(p.positions)
        target = (torch.from_numpy(p.free if blank else p.coef) - mean_t) / std_t
        img = blank_img if blank else torch.from_numpy(p.image)
        geo = torch.zeros(1, 11) if blank else torch.from_numpy(p.geometry)[None]
        off = torch.zeros_like(x) if blank else torch.from_numpy(p.offset)
        return (
            x,
            torch.from_numpy(p.velocities),
            torch.from_numpy(p.particle_type),
            torch.from_numpy(p.senders),
            torch.from_numpy(p.receivers),
            img,
            geo,
            off,
            target,
        )

    def loss_of(net: FluidControlNet, p: _Pair, blank: bool, ts: list[int], gen: torch.Generator | None = None, noises: list[Any] | None = None) -> Any:
        """The pair's loss at noise levels ``ts``, with the noise ``noises`` (default: drawn from ``gen``)."""
        x, v, pt, s, r, img, geo, off, target = tensors(p, blank)
        h, edges, local, glob = net.encode(x, v, pt, s, r, img)
        cond = torch.cat([glob, geo], dim=1)
        total = torch.zeros(())
        for k, t in enumerate(ts):
            noise = torch.randn(target.shape, generator=gen) if noises is None else noises[k]
            ab = alpha_bar[t]
            xt = ab.sqrt() * target + (1 - ab).sqrt() * noise
            pred = net.head(xt, h, local, off, edges, s, r, torch.tensor([t / DIFFUSION_STEPS]), cond)
            total = total + torch.mean((pred - target) ** 2)
        return total / len(ts)

    def batch_loss(net: FluidControlNet, draws: list[tuple[_Pair, bool, list[int], list[Any]]]) -> Any:
        """The mean loss of this rank's pairs (equal weights: the ranks' mean is the global batch's)."""
        return sum(loss_of(net, p, blank, ts, noises=noises) for p, blank, ts, noises in draws) / len(draws)

    def validate(net: FluidControlNet | None = None, pairs: list[_Pair] | None = None) -> float:
        """The loss at fixed noise levels and draws (no sampling noise between calls): ``net`` (default the EMA) on ``pairs`` (default validation)."""
        gen = torch.Generator().manual_seed(1234)
        with torch.no_grad():
            vals = [float(loss_of(net or ema, p, False, [10, 40, 70, 95], gen)) for p in (valid_pairs if pairs is None else pairs)]
        return float(np.mean(vals))

    fit_pairs = train_pairs[:: max(1, len(train_pairs) // 8)][:8]
    fit_first = validate(model, fit_pairs) if ranks.main else math.nan

    cpu0 = time.process_time()

    def save() -> None:
        """Rank 0 validates, logs and writes the checkpoint (every rank calls it: the CPU seconds are summed)."""
        nonlocal core_seconds, cpu0
        # the global batch's loss is the ranks' mean; the CPU time, their sum
        loss_sum, cpu = ranks.sum(float(np.mean(recent[-checkpoint_every:])) if recent else 0.0, time.process_time() - cpu0)
        core_seconds += cpu
        cpu0 = time.process_time()
        if not ranks.main:
            return
        assert log is not None
        val = validate()
        spent_now = spent + time.perf_counter() - t_start
        entry = {"step": step, "loss": loss_sum / ranks.size if recent else None, "valid": val, "seconds": spent_now}
        log.write(json.dumps({**entry, "ranks": ranks.size, "core_seconds": core_seconds}) + "\n")
        log.flush()
        ck = {"config": cfg.to_dict(), "model": model.state_dict(), "ema": ema.state_dict(), "opt": opt.state_dict(), "step": step}
        ck.update({"rng": rng.bit_generator.state, "seconds": spent_now, "core_seconds": core_seconds, "batch": batch, "ranks": ranks.size})
        tmp = ckpt_path.with_suffix(".tmp")
        torch.save(ck, tmp)
        os.replace(tmp, ckpt_path)

    # the loss of a step, in DistributedDataParallel when there are several ranks (its backward averages the gradients);
    # the state encoder's decoder takes no part in it (its latents are what the head reads)
    step_loss = ranks.wrap(LossOf(model, batch_loss), unused=True)
    saved_at = step
    bar = tqdm(total=steps, initial=min(step, steps), desc=f"train-control {scene}", unit="step", disable=not progress)
    t_start = time.perf_counter()
    cpu0 = time.process_time()
    recent: list[float] = []
    mine = ranks.part(batch)
    model.train()
    while step < steps:
        if time_limit is not None and ranks.any(time.perf_counter() - t_start > time_limit):  # every rank stops at the same step
            break
        # every rank draws the whole global batch (the random stream of one process of ranks x batch pairs) and keeps its slice
        draws = []
        for i in range(ranks.size * batch):
            p = train_pairs[int(rng.integers(len(train_pairs)))]
            blank = bool(rng.random() < P_BLANK)
            ts = [int(t) for t in rng.integers(0, DIFFUSION_STEPS, NOISE_DRAWS)]
            noises = [torch.randn(p.coef.shape) for _ in ts]  # the sample's shape: p.free's too
            if i in mine:
                draws.append((p, blank, ts, noises))
        loss = step_loss(draws)
        opt.zero_grad()
        loss.backward()
        torch.nn.utils.clip_grad_norm_(model.parameters(), 1.0)
        for grp in opt.param_groups:
            grp["lr"] = lr * gamma**step
        opt.step()
        decay = min(0.999, (1 + step) / (10 + step))
        with torch.no_grad():
            for pe, pm in zip(ema.parameters(), model.parameters()):
                pe.mul_(decay).add_(pm.detach(), alpha=1 - decay)
        step += 1
        lv = float(loss.detach())
        recent.append(lv)
        bar.update(1)
        if step % 50 == 0:
            bar.set_postfix(loss=f"{np.mean(recent[-50:]):.4f}")
        if step % checkpoint_every == 0 or step == steps:
            save()
            saved_at = step
    if saved_at != step:  # stopped by the time limit
        save()
    bar.close()
    # this call's first and last 10 steps, the ranks' mean (every rank made as many steps)
    first: float | None = None
    last: float | None = None
    if recent:
        first, last = (v / ranks.size for v in ranks.sum(float(np.mean(recent[:10])), float(np.mean(recent[-10:]))))
    summary = None
    if ranks.main:
        assert log is not None
        log.close()
        seconds = spent + time.perf_counter() - t_start
        export_control(ema, out / "model", {"scene": scene, "steps": step, "train_seconds": seconds, "cases": cfg.extra.get("cases")})
        # the loss on up to 8 training pairs at fixed noise: the model this call started from, then the EMA it exports
        fit_last = validate(ema, fit_pairs)
        summary = {"steps": step, "seconds": seconds, "first_loss": first, "last_loss": last, "fit_first": fit_first, "fit_last": fit_last}
        summary.update({"ranks": ranks.size, "core_seconds": core_seconds})
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
