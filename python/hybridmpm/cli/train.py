"""The ``hybridmpm`` command line: training: the GNS (``train``) and the grid model (``train-grid``); both need the ``train`` extra."""

from __future__ import annotations

import argparse
import json
from typing import Any

from hybridmpm.cli.common import parse_seed
from hybridmpm.errors import HybridMpmError


def _train(args: argparse.Namespace) -> int:
    try:
        # import time: loaded by this command only
        from hybridmpm.train.distributed import is_main_process
        from hybridmpm.train.gns.train import TrainConfig, train
    except ImportError as e:
        raise HybridMpmError(f"training needs PyTorch and onnx: pip install 'hybridmpm[train]' ({e})") from e
    cfg = TrainConfig(
        scene=args.scene, data=args.data, out=args.out, latent=args.latent, layers=args.layers, r_t=args.r_t, steps=args.steps,
        batch=args.batch, lr=args.lr, noise_std=args.noise_std, val_every=args.val_every, max_neighbors=args.max_neighbors, radius=args.radius,
        seed=args.seed, threads=args.threads, pushforward=args.pushforward, pushforward_after=args.pushforward_after, ema=args.ema,
        snapshots=not args.no_snapshots, unroll=args.unroll, unroll_after=args.unroll_after, clip_grad=args.clip_grad,
        wall_reach=args.wall_reach, nproc=args.nproc, grid=args.grid, grid_width=args.grid_width, grid_levels=args.grid_levels,
        rollout_steps=args.rollout_steps,
    )  # fmt: skip
    summary = train(cfg, progress=not args.quiet)
    if not args.quiet and is_main_process():
        print(json.dumps(summary, indent=2))
    return 0


def _train_grid(args: argparse.Namespace) -> int:
    try:
        # import time: loaded by this command only
        from hybridmpm.train.distributed import is_main_process
        from hybridmpm.train.grid import GridTrainConfig, train_grid
    except ImportError as e:
        raise HybridMpmError(f"training needs PyTorch and onnx: pip install 'hybridmpm[train]' ({e})") from e
    cfg = GridTrainConfig(
        scene=args.scene, data=args.data, out=args.out, grid=args.grid, width=args.width, levels=args.levels, r_t=args.r_t, steps=args.steps,
        batch=args.batch, lr=args.lr, noise=args.noise, unroll=args.unroll, density_weight=args.density_weight, pressure=args.pressure, flip_init=args.flip_init, val_every=args.val_every,
        val_steps=args.val_steps, seed=args.seed, threads=args.threads, nproc=args.nproc,
    )  # fmt: skip
    summary = train_grid(cfg, progress=not args.quiet)
    if not args.quiet and is_main_process():
        print(json.dumps({k: v for k, v in summary.items() if k != "curve"}, indent=2))
    return 0


def add_parsers(sub: Any) -> None:
    """Register this group's commands on the subparsers ``sub``."""
    tr = sub.add_parser("train", help="train a GNS on a GNS-layout dataset and export model.onnx (needs the 'train' extra)")
    tr.add_argument("scene", help="scene family the model is for (stored in the model)")
    tr.add_argument("--data", required=True, nargs="+", help="dataset directory (hybridmpm generate, or any GNS dataset); several are pooled split by split")
    tr.add_argument("--out", required=True, help="model directory: checkpoint.pt, log.csv, model.onnx (resumes if present)")
    tr.add_argument("--latent", type=int, default=32, help="latent width (default 32; paper 128)")
    tr.add_argument("--layers", type=int, default=3, help="message-passing layers L (default 3; paper 10)")
    tr.add_argument("--r-t", type=int, default=2, help="frames per model step (default 2, the paper's)")
    tr.add_argument("--steps", type=int, default=20000, help="optimiser steps (default 20000)")
    tr.add_argument("--batch", type=int, default=2, help="windows per step and process (default 2)")
    tr.add_argument("--lr", type=float, default=1e-3, help="initial learning rate (decays x0.1 over the run)")
    tr.add_argument("--noise-std", type=float, default=3e-4, help="random-walk noise on the last input velocity [m/step]")
    tr.add_argument("--val-every", type=int, default=500, help="validate and checkpoint every N steps")
    tr.add_argument(
        "--pushforward",
        type=float,
        default=0.0,
        help="probability that a window's last input is the model's own prediction (pushforward training; default 0: off)",
    )
    tr.add_argument("--pushforward-after", type=float, default=0.2, help="fraction of the steps before pushforward starts (default 0.2)")
    tr.add_argument(
        "--unroll",
        type=int,
        default=1,
        help="model steps each window is rolled out by the network, the loss backpropagated through all of them (default 1: one-step training)",
    )
    tr.add_argument("--unroll-after", type=float, default=0.0, help="fraction of the steps trained one-step before unrolling starts (default 0)")
    tr.add_argument("--clip-grad", type=float, default=1.0, help="gradient-norm clip in unrolled steps (default 1)")
    tr.add_argument(
        "--wall-reach",
        type=float,
        default=1.0,
        help="distance, in units of R, at which the wall-distance features saturate (default 1: GNS's clip at R; "
        "more lets particles that move more than R per step see a wall coming)",
    )
    tr.add_argument(
        "--grid",
        type=int,
        default=0,
        help="nodes per dimension of a grid branch that gives every particle the whole fluid's context (p2g, a U-Net, g2p; default 0: none; docs/neural.md)",
    )
    tr.add_argument("--grid-width", type=int, default=8, help="channels of the grid branch's first U-Net level (default 8)")
    tr.add_argument("--grid-levels", type=int, default=3, help="resolutions of the grid branch's U-Net (default 3)")
    tr.add_argument("--rollout-steps", type=int, default=20, help="model steps of the validation rollout that chooses model.onnx (default 20)")
    tr.add_argument(
        "--ema",
        type=float,
        default=0.0,
        help="validate, snapshot and export the exponential moving average of the weights with this decay (e.g. 0.999; default 0: off)",
    )
    tr.add_argument("--no-snapshots", action="store_true", help="do not export each validated step's model under OUT/snapshots/")
    tr.add_argument("--max-neighbors", type=int, default=None, help="cap on neighbours per particle")
    tr.add_argument("--radius", type=float, default=None, help="connectivity radius R [m] (default: the dataset's)")
    tr.add_argument("--seed", type=parse_seed, default=0)
    tr.add_argument("--threads", type=int, default=0, help="torch threads per process (0 = default: the cores over the local processes)")
    tr.add_argument("--nproc", type=int, default=1, help="local processes of data-parallel training, --batch each (default 1; docs/neural.md)")
    tr.add_argument("--quiet", action="store_true")
    tr.set_defaults(func=_train)

    tg = sub.add_parser("train-grid", help="train a grid model (p2g, U-Net, g2p; NeuralMPM-style) and export OUT/model.onnx (needs the 'train' extra)")
    tg.add_argument("scene", help="scene family the model is for (stored in the model)")
    tg.add_argument("--data", required=True, help="dataset directory stored every frame (hybridmpm generate SCENE --r-p R_P)")
    tg.add_argument("--out", required=True, help="model directory: checkpoint.pt, best.pt, curve.json, model.onnx (resumes if present)")
    tg.add_argument("--grid", type=int, default=64, help="grid nodes per dimension (default 64)")
    tg.add_argument("--width", type=int, default=16, help="channels of the U-Net's first level, doubled per level (default 16)")
    tg.add_argument("--levels", type=int, default=3, help="U-Net levels (default 3)")
    tg.add_argument("--r-t", type=int, default=4, help="frames per call (default 4)")
    tg.add_argument("--steps", type=int, default=20000, help="optimiser steps (default 20000)")
    tg.add_argument("--batch", type=int, default=8, help="windows per step and process (default 8)")
    tg.add_argument("--lr", type=float, default=1e-3, help="peak learning rate (cosine decay)")
    tg.add_argument("--noise", type=float, default=3e-4, help="random-walk noise on the input history [m per step]")
    tg.add_argument("--unroll", type=int, default=3, help="chained calls in the loss, reached by mid-run (default 3)")
    tg.add_argument("--density-weight", type=float, default=0.0, help="weight of the grid-count loss (default 0)")
    tg.add_argument(
        "--pressure", action="store_true",
        help="learn a density correction per frame (particles moved down the gradient of the fluid's excess p2g count; docs/grid_model.md)",
    )  # fmt: skip
    tg.add_argument(
        "--flip-init", type=float, default=0.5,
        help="initial share of a particle's own deviation from the grid velocity it keeps per call (FLIP beta, learned; default 0.5)",
    )  # fmt: skip
    tg.add_argument("--val-every", type=int, default=500, help="validate and checkpoint every N steps")
    tg.add_argument("--val-steps", type=int, default=100, help="model steps per validation rollout (default 100)")
    tg.add_argument("--seed", type=parse_seed, default=0)
    tg.add_argument("--threads", type=int, default=1, help="torch threads per process (default 1)")
    tg.add_argument("--nproc", type=int, default=1, help="local processes of data-parallel training, --batch each (default 1; docs/neural.md)")
    tg.add_argument("--quiet", action="store_true")
    tg.set_defaults(func=_train_grid)
