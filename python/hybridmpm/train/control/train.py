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
) -> dict[str, Any]:
    """Train (or resume) the controller of ``scene`` on the cases under
    ``data_root`` into ``out`` (``ckpt.pt``, ``log.jsonl``; module doc) for
    ``steps`` optimiser steps (or until ``time_limit`` seconds), then export
    it (:func:`export_control`) to ``out/model``. Returns a summary
    (steps, seconds, mean loss of this call's first and last 10 steps, and
    ``fit_first`` / ``fit_last``: the loss on up to 8 training pairs at fixed
    noise levels and draws, before this call and of the exported EMA). Raises :class:`InvalidInputError`
    naming ``data_root`` when there are fewer than 4 cases, or a bad setting."""
    import torch
    from tqdm import tqdm

    if isinstance(steps, bool) or not isinstance(steps, int) or not 1 <= steps <= 10_000_000:
        raise InvalidInputError(f"steps: must be an integer in [1, 10⁷], got {steps!r}", "steps")
    if not (0 < lr_final <= lr <= 1.0):
        raise InvalidInputError(f"lr: need 0 < lr_final <= lr <= 1, got {lr!r}, {lr_final!r}", "lr")
    paths = list(iter_cases(data_root, scene))[: max_cases or None]
    if len(paths) < 4:
        raise InvalidInputError(
            f"data_root: {len(paths)} control cases of {scene} under {data_root}; run `hybridmpm generate-control {scene}` first", "data_root"
        )
    torch.set_num_threads(max(1, int(threads)))
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    n_valid = max(1, int(round(valid_fraction * len(paths))))
    bounds = scene_bounds(scene)
    if (out / "ckpt.pt").exists():  # a resumed run keeps the prior it started with
        import torch as _torch

        prior = str(_torch.load(out / "ckpt.pt", map_location="cpu", weights_only=False)["config"].get("extra", {}).get("prior", PRIOR_SKETCH_RAMP))
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
        latent_state=latent_state,
        latent_head=latent_head,
        extra={"scene": scene, "cases": len(paths) - n_valid, "valid_cases": n_valid, "prior": prior},
    )
    ckpt_path = out / "ckpt.pt"
    model = FluidControlNet(cfg)
    ema = copy.deepcopy(model)
    opt = torch.optim.AdamW(model.parameters(), lr=lr, weight_decay=1e-4)
    step, rng_state, spent = 0, None, 0.0
    if init_from is not None and not ckpt_path.exists():  # warm start: the weights of another run (same sizes), fresh optimiser
        try:
            init = torch.load(Path(init_from), map_location="cpu", weights_only=False)["ema"]
            model.load_state_dict(init)
            ema.load_state_dict(init)
        except (OSError, KeyError, RuntimeError) as e:
            raise InvalidInputError(f"init_from: {init_from} is not a checkpoint of a control model of the same sizes ({e})", "init_from") from e
    if ckpt_path.exists():
        ck = torch.load(ckpt_path, map_location="cpu", weights_only=False)
        cfg = ControlNetConfig.from_dict(ck["config"])
        model, ema = FluidControlNet(cfg), FluidControlNet(cfg)
        model.load_state_dict(ck["model"])
        ema.load_state_dict(ck["ema"])
        opt = torch.optim.AdamW(model.parameters(), lr=lr, weight_decay=1e-4)
        opt.load_state_dict(ck["opt"])
        step, rng_state, spent = int(ck["step"]), ck["rng"], float(ck.get("seconds", 0.0))
    mean_t = torch.tensor(cfg.coef_mean, dtype=torch.float32)
    std_t = torch.tensor(cfg.coef_std, dtype=torch.float32)
    alpha_bar = torch.tensor(cosine_alpha_bar(DIFFUSION_STEPS), dtype=torch.float32)
    rng = np.random.default_rng(seed)
    if rng_state is not None:
        rng.bit_generator.state = rng_state
    torch.manual_seed(seed + step)
    gamma = (lr_final / lr) ** (1.0 / max(steps, 1))
    log = (out / "log.jsonl").open("a")
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

    def loss_of(net: FluidControlNet, p: _Pair, blank: bool, ts: list[int], gen: torch.Generator | None = None) -> Any:
        x, v, pt, s, r, img, geo, off, target = tensors(p, blank)
        h, edges, local, glob = net.encode(x, v, pt, s, r, img)
        cond = torch.cat([glob, geo], dim=1)
        total = torch.zeros(())
        for t in ts:
            noise = torch.randn(target.shape, generator=gen)
            ab = alpha_bar[t]
            xt = ab.sqrt() * target + (1 - ab).sqrt() * noise
            pred = net.head(xt, h, local, off, edges, s, r, torch.tensor([t / DIFFUSION_STEPS]), cond)
            total = total + torch.mean((pred - target) ** 2)
        return total / len(ts)

    def validate(net: FluidControlNet | None = None, pairs: list[_Pair] | None = None) -> float:
        """The loss at fixed noise levels and draws (no sampling noise between calls): ``net`` (default the EMA) on ``pairs`` (default validation)."""
        gen = torch.Generator().manual_seed(1234)
        with torch.no_grad():
            vals = [float(loss_of(net or ema, p, False, [10, 40, 70, 95], gen)) for p in (valid_pairs if pairs is None else pairs)]
        return float(np.mean(vals))

    fit_pairs = train_pairs[:: max(1, len(train_pairs) // 8)][:8]
    fit_first = validate(model, fit_pairs)

    def save() -> None:
        val = validate()
        spent_now = spent + time.perf_counter() - t_start
        log.write(json.dumps({"step": step, "loss": float(np.mean(recent[-checkpoint_every:])) if recent else None, "valid": val, "seconds": spent_now}) + "\n")
        log.flush()
        ck = {"config": cfg.to_dict(), "model": model.state_dict(), "ema": ema.state_dict(), "opt": opt.state_dict(), "step": step}
        ck.update({"rng": rng.bit_generator.state, "seconds": spent_now})
        tmp = ckpt_path.with_suffix(".tmp")
        torch.save(ck, tmp)
        os.replace(tmp, ckpt_path)

    saved_at = step
    bar = tqdm(total=steps, initial=min(step, steps), desc=f"train-control {scene}", unit="step", disable=not progress)
    t_start = time.perf_counter()
    recent: list[float] = []
    model.train()
    while step < steps:
        if time_limit is not None and time.perf_counter() - t_start > time_limit:
            break
        p = train_pairs[int(rng.integers(len(train_pairs)))]
        blank = bool(rng.random() < P_BLANK)
        ts = [int(t) for t in rng.integers(0, DIFFUSION_STEPS, NOISE_DRAWS)]
        loss = loss_of(model, p, blank, ts)
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
    log.close()
    seconds = spent + time.perf_counter() - t_start
    export_control(ema, out / "model", {"scene": scene, "steps": step, "train_seconds": seconds, "cases": cfg.extra.get("cases")})
    first = float(np.mean(recent[:10])) if recent else None  # this call's first and last 10 steps
    last = float(np.mean(recent[-10:])) if recent else None
    # the loss on up to 8 training pairs at fixed noise: the model this call started from, then the EMA it exports
    fit_last = validate(ema, fit_pairs)
    return {"steps": step, "seconds": seconds, "first_loss": first, "last_loss": last, "fit_first": fit_first, "fit_last": fit_last}


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


__all__ = ["K_BASIS", "P_BLANK", "export_control", "load_pairs", "scene_bounds", "train_control"]
