"""The ``hybridmpm`` command line: sketch control: apply a sketch (``control``), make reverse-simulation cases (``generate-control``) and train the diffusion controller (``train-control``)."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

import numpy as np

from hybridmpm.cli.common import check_frames_made, out_dir, parse_seed, write_json
from hybridmpm.control.diffusion import SAMPLE_STEPS
from hybridmpm.conventions import T_CTR
from hybridmpm.errors import HybridMpmError, InvalidInputError


def _control(args: argparse.Namespace) -> int:
    """``hybridmpm control``: a sketch applied to a scene's fluid (:func:`hybridmpm.control.control_episode`).
    Fewer frames made than asked (:func:`~hybridmpm.cli.common.check_frames_made`, exit status 2): before
    the sketch, nothing is written; during the controlled frames, the files hold the frames made."""
    from PIL import Image

    # import time: loaded by this command only
    from hybridmpm.control import Controller, MpcSettings, Sketch, control_episode, default_method, render_sketch, sketch_from_png
    from hybridmpm.control.sketch import MAX_SKETCH_FILE_BYTES
    from hybridmpm.files import check_nesting, read_regular_file
    from hybridmpm.render import render_gif
    from hybridmpm.scenes import make_scene
    from hybridmpm.sim import make_simulator, rollout

    raw = read_regular_file(args.sketch, MAX_SKETCH_FILE_BYTES, "sketch", "sketch file")
    if raw.startswith(b"\x89PNG"):
        sketch = sketch_from_png(raw)
    else:
        try:
            text = raw.decode("utf-8")
        except UnicodeDecodeError as e:
            raise InvalidInputError(f"sketch: {args.sketch} is neither a PNG nor a JSON text file", "sketch") from e
        check_nesting(text, "sketch")
        sketch = Sketch.from_json(text)
    kw: dict[str, Any] = {"steps": args.steps, "guidance": args.guidance, "seed": args.seed}
    if args.model:
        kw["model"] = args.model
    method = args.method or default_method(Path(args.scene).stem)
    if method == "mpc":
        kw["mpc"] = MpcSettings(rollouts=args.rollouts, rounds=args.rounds, effort_weight=args.effort_weight, seed=args.seed % 2**32)
    args.method = method
    controller = Controller.for_scene(Path(args.scene).stem, method, frames=args.frames, **kw)
    if args.from_frame < 0:
        raise InvalidInputError(f"from_frame: must be >= 0, got {args.from_frame}", "from_frame")
    out = out_dir(args.out)
    scene = make_scene(args.scene, seed=args.seed)
    sim = make_simulator(scene, args.solver, seed=args.seed, threads=args.threads)
    pre = rollout(sim, args.from_frame, progress=None if args.quiet else f"{scene.name} [{args.solver}] to frame {args.from_frame}")
    # the sketch applies at --from-frame or not at all: a run that broke off before it writes nothing
    check_frames_made("control: before the sketch", pre.frames_done, args.from_frame, pre.failure, pre.failure_detail)
    ep = control_episode(sim, sketch, controller, progress=None if args.quiet else f"{scene.name} [control: {args.method}]")
    ro = ep.rollout
    ro.save(out / "trajectory.npz")
    summary = {
        "scene": scene.name, "seed": args.seed, "solver": args.solver, "method": args.method, "from_frame": args.from_frame,
        "frames": ro.frames_done, "particles": sim.particles.num_fluid, "sketch": sketch.to_json(), **ep.metrics,
    }  # fmt: skip
    write_json(out / "summary.json", summary)
    Image.fromarray(render_sketch(sketch, size=256)).save(out / "sketch.png")
    if not args.no_render:
        line = np.concatenate([sketch.points, sketch.points[:1]]) if sketch.kind == "oval" else sketch.points
        render_gif(
            ro.positions, ro.particle_type, out / "render.gif", dt_frame=ro.dt_frame, title=f"{scene.name} ({args.method})", overlay=[line],
            bodies=ro.bodies,
        )  # fmt: skip
    if not args.quiet:
        m = ep.metrics
        adherence = (
            f"cosine {m['cosine']:.2f}, length ratio {m['length_ratio']:.2f}" if sketch.kind == "arrow" else f"inside {m['inside']:.0%}, IoU {m['iou']:.2f}"
        )
        print(
            f"{scene.name}: {args.method} control over {ro.frames_done} frames from frame {args.from_frame}: {adherence}; "
            f"effort mean {m['effort_mean_g']:.1f} g; plan {m['plan_ms']:.1f} ms, episode {m['episode_ms']:.0f} ms -> {out}/"
        )
    # fewer controlled frames than asked (the rollout broke off): what was made is written above, and the command fails
    check_frames_made("control", ro.frames_done, args.frames, ro.failure, ro.failure_detail, kept=f"{out}/")
    return 0


def _generate_control(args: argparse.Namespace) -> int:
    """``hybridmpm generate-control``: reverse-simulation control cases (:func:`hybridmpm.train.control.cases.generate_control`)."""
    # import time: loaded by this command only
    from hybridmpm.train.control.cases import generate_control

    try:
        paths = generate_control(args.scene, args.out, args.cases, args.first_seed, tracking=args.tracking, progress=not args.quiet)
    except KeyboardInterrupt:
        print(f"hybridmpm: interrupted; finished cases are kept in {args.out}/{args.scene}, rerun the same command to resume", file=sys.stderr)
        return 130
    if not args.quiet:
        size = sum(p.stat().st_size for p in paths)
        print(f"{args.scene}: {len(paths)} control cases, {size / 1e6:.0f} MB -> {args.out}/{args.scene}/")
    return 0


def _train_control(args: argparse.Namespace) -> int:
    """``hybridmpm train-control``: train (or resume) and export a scene's diffusion controller."""
    try:
        # import time: loaded by this command only
        from hybridmpm.train.control.train import train_control
        from hybridmpm.train.distributed import is_main_process
    except ImportError as e:
        raise HybridMpmError(f"training needs PyTorch and onnx: pip install 'hybridmpm[train]' ({e})") from e
    out = args.out or f"runs/control-{args.scene}"
    summary = train_control(
        args.scene, args.data, out, steps=args.steps, lr=args.lr, k_basis=args.k_basis, max_cases=args.max_cases,
        checkpoint_every=args.checkpoint_every, seed=args.seed, threads=args.threads, time_limit=args.time_limit, progress=not args.quiet,
        prior=args.prior, init_from=args.init_from, batch=args.batch, nproc=args.nproc,
    )  # fmt: skip
    if not args.quiet and is_main_process():
        print(json.dumps(summary, indent=2) + f"\n-> {out}/model")
    return 0


def add_parsers(sub: Any) -> None:
    """Register this group's commands on the subparsers ``sub``."""
    co = sub.add_parser("control", help="apply a sketch (arrow or oval, JSON) to a scene's fluid; writes trajectory.npz, summary.json, render.gif, sketch.png")
    co.add_argument("scene", nargs="?", default="water2d", help="a scene or scene file (default water2d)")
    co.add_argument(
        "--sketch", required=True, help='sketch: JSON {"kind": "arrow"|"oval", "points": [[x, y], ...]} in domain coordinates (y up), or a PNG of the drawing'
    )
    co.add_argument(
        "--method", default=None, choices=["none", "constant", "pd", "mpc", "diffusion"],
        help="controller (default: the scene's, control.default_method; docs/control.md 'Defaults')",
    )  # fmt: skip
    co.add_argument("--rollouts", type=int, default=16, help="mpc: rollouts of the coarse model per plan (default 16)")
    co.add_argument("--rounds", type=int, default=4, help="mpc: cross-entropy rounds (default 4; at most --rollouts)")
    co.add_argument("--effort-weight", type=float, default=0.02, help="mpc: score lost per g of mean effort (default 0.02)")
    co.add_argument("--model", default=None, help="diffusion controller directory (default: the scene's shipped one)")
    co.add_argument(
        "--steps", type=int, default=None, help=f"DDIM steps of the diffusion controller (default: the model's control.json sample_steps, else {SAMPLE_STEPS})"
    )
    co.add_argument("--guidance", type=float, default=1.0, help="classifier-free guidance scale (default 1: no blank pass)")
    co.add_argument(
        "--solver", default="default", choices=["default", "hybrid", "mpm"],
        help="simulator before and after the control (it always runs on MPM; default: the scene's default configuration, chosen by the chart; hybrid: the paper's)",
    )  # fmt: skip
    co.add_argument("--from-frame", type=int, default=40, help="frames simulated before the sketch applies (default 40)")
    co.add_argument("--frames", type=int, default=T_CTR, help=f"control horizon T_ctr in frames (default {T_CTR})")
    co.add_argument("--seed", type=parse_seed, default=0, help="seed of the scene's initial condition and of the diffusion noise")
    co.add_argument("--threads", type=int, default=0, help="MPM threads (0 = all cores)")
    co.add_argument("--out", default="runs/control", help="output directory (default runs/control)")
    co.add_argument("--no-render", action="store_true", help="skip render.gif")
    co.add_argument("--quiet", action="store_true")
    co.set_defaults(func=_control)
    gc = sub.add_parser("generate-control", help="make reverse-simulation control cases (resumable: rerun to continue)")
    gc.add_argument("scene", help="registered scene")
    gc.add_argument("--cases", type=int, default=800, help="cases (default 800; seeds first-seed …; even seeds arrows, odd ovals)")
    gc.add_argument("--first-seed", type=int, default=0, help="first seed (default 0; seeds 5000+ are the benchmark's held-out cases)")
    gc.add_argument("--tracking", action="store_true", help="also solve and store the tracking field (3x the cost)")
    gc.add_argument("--out", default="data/control", help="root directory (default data/control)")
    gc.add_argument("--quiet", action="store_true")
    gc.set_defaults(func=_generate_control)
    tc = sub.add_parser("train-control", help="train (or resume) a scene's diffusion controller and export it (needs the 'train' extra)")
    tc.add_argument("scene", help="registered scene")
    tc.add_argument("--data", default="data/control", help="root of generate-control's cases (default data/control)")
    tc.add_argument("--out", default=None, help="run directory (default runs/control-SCENE)")
    tc.add_argument("--steps", type=int, default=20000, help="optimiser steps (default 20000)")
    tc.add_argument("--lr", type=float, default=1e-3, help="initial learning rate (decays exponentially to 1e-4)")
    tc.add_argument("--k-basis", type=int, default=8, help="temporal basis size K_b (default 8)")
    tc.add_argument("--max-cases", type=int, default=None, help="use at most this many cases")
    tc.add_argument("--checkpoint-every", type=int, default=500, help="steps between checkpoints and validation (default 500)")
    tc.add_argument("--time-limit", type=float, default=None, help="stop (and export) after this many seconds; rerun to resume")
    tc.add_argument("--seed", type=parse_seed, default=0, help="seed of the initial weights and of the data order, in [0, 2^63)")
    tc.add_argument("--init-from", default=None, help="warm start from another run's ckpt.pt (same sizes; a new run only)")
    tc.add_argument("--prior", default="free_sketch", choices=["free_sketch", "sketch_ramp"], help="what plans are relative to (default free_sketch)")
    tc.add_argument("--batch", type=int, default=1, help="training pairs per step and process (default 1)")
    tc.add_argument("--threads", type=int, default=1, help="torch threads per process (default 1)")
    tc.add_argument("--nproc", type=int, default=1, help="local processes of data-parallel training, --batch each (default 1; docs/neural.md)")
    tc.add_argument("--quiet", action="store_true")
    tc.set_defaults(func=_train_control)
