"""The ``hybridmpm`` command line.

``hybridmpm simulate [SCENE] [--solver hybrid|mpm|neural] --frames N --out DIR
[--r-c 0.8] [--reference] [--export ply|vtu]`` runs a scene (default: the
dam break, hybrid) and writes ``trajectory.npz``, ``summary.json`` and
``render.gif`` (hybrid: also ``timeline.png``).

``hybridmpm bench SCENE [--seeds K] [--frames T] [--out DIR]``
runs every method from the same held-out initial conditions and writes
error-against-latency charts and tables (:func:`hybridmpm.bench.bench`);
``hybridmpm tune SCENE --error-budget E`` writes the fastest configuration
within the budget, which ``simulate SCENE --solver auto`` then uses.

``hybridmpm stress SCENE`` runs neural-only, MPM-only and hybrid through the
failure cases of :mod:`hybridmpm.bench.stress` and writes a table.

``hybridmpm generate SCENE --trajectories M --out DIR`` writes a GNS-layout
dataset of MPM rollouts (:func:`hybridmpm.train.datasets.generate_dataset`);
``hybridmpm inspect DIR`` checks and summarises a GNS dataset (ours or
another tool's).

``hybridmpm evaluate PRED.npz REF.npz [--n-grid N] [--out metrics.json]``
compares two trajectories (:func:`hybridmpm.metrics.evaluate`: grid-mass
error, position MSE, kinetic energy) and writes the metrics as JSON.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from hybridmpm.control.diffusion import SAMPLE_STEPS
from hybridmpm.conventions import AUDIT_EVERY, AUDIT_MAX, AUDIT_TOL, R_C, RESIDUAL_TOL, SAFEGUARD, SAFEGUARDS, T_CTR
from hybridmpm.errors import HybridMpmError, InvalidInputError
from hybridmpm.jsonutil import json_safe
from hybridmpm.trajectory import Trajectory


def _seed(text: str) -> int:
    """argparse type of a seed: an integer in [0, 2^63)."""
    try:
        v = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"must be an integer, got {text!r}") from None
    if not 0 <= v < 2**63:
        raise argparse.ArgumentTypeError(f"must be in [0, 2^63), got {v}")
    return v


def _out_dir(path: str | Path, field: str = "out") -> Path:
    """Create output directory ``path`` (parents too) and check that it can be
    written, before any work: raises :class:`InvalidInputError` naming
    ``field`` otherwise."""
    out = Path(path)
    if out.exists() and not out.is_dir():
        raise InvalidInputError(f"{field}: {out} exists and is not a directory", field)
    try:
        out.mkdir(parents=True, exist_ok=True)
        probe = out / f".hybridmpm-write-test-{os.getpid()}"
        probe.write_bytes(b"")
        probe.unlink()
    except OSError as e:
        raise InvalidInputError(f"{field}: cannot write to {out} ({e.strerror or e})", field) from e
    return out


def _write_json(path: Path, obj: Any) -> None:
    """Write strict JSON atomically (a temporary file beside it, then a rename)."""
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(json.dumps(json_safe(obj), indent=2, allow_nan=False))
    tmp.replace(path)


def _ms(seconds: np.ndarray) -> dict[str, float | None]:
    """Per-frame wall time [s] → median/p95/mean in ms (None for no frames)."""
    if len(seconds) == 0:
        return {"median": None, "p95": None, "mean": None}
    ms = np.asarray(seconds) * 1e3
    return {"median": float(np.median(ms)), "p95": float(np.percentile(ms, 95)), "mean": float(ms.mean())}


def _simulate(args: argparse.Namespace) -> int:
    """``hybridmpm simulate``: one simulator (:func:`hybridmpm.sim.make_simulator`),
    one :func:`~hybridmpm.sim.rollout`, then the files."""
    # import time: loaded by this command only
    import hybridmpm
    from hybridmpm.metrics import grid_mass_error
    from hybridmpm.render import export_points, plot_timeline, render_gif
    from hybridmpm.scenes import make_scene
    from hybridmpm.sim import NEURAL, make_simulator, reference, rollout, warmup_frames

    scene = make_scene(args.scene, seed=args.seed)
    frames = args.frames if args.frames is not None else scene.frames
    if args.solver == "auto":
        _apply_tuned(args, scene.name)
    if frames < 1:
        raise InvalidInputError(f"frames: must be >= 1, got {frames}", "frames")
    out = _out_dir(args.out)
    sim = make_simulator(
        scene, args.solver, model=args.model, r_c=args.r_c, r_p=args.r_p, dwell=args.dwell, audit_every=args.audit_every, audit_tol=args.audit_tol,
        safeguard=args.safeguard, residual_tol=args.residual_tol, audit_max=args.audit_max, seed=args.seed, threads=args.threads,
        nn_threads=max(1, args.threads) if args.solver == "neural" else 1, n_grid=args.n_grid, particles_per_cell=args.particles_per_cell,
        **({"cheap": args.cheap, "cheap_grid": args.cheap_grid} if args.solver == "hybrid" else {}),
    )  # fmt: skip
    label = f"{scene.name} [{args.solver}" + (f" r_c={args.r_c:g}]" if args.solver == "hybrid" else "]")
    ro = rollout(sim, frames, progress=None if args.quiet else label)
    low = sim.scene
    per_frame = ro.frame_seconds()
    steps = ro.stats["steps"]
    total = max(1, sum(steps.values()))
    summary: dict = {
        "scene": scene.name, "solver": args.solver, "seed": args.seed, "frames": ro.frames_done, "frames_asked": frames,
        "particles": low.num_particles, "particles_full_resolution": scene.num_particles, "boundary_particles": low.num_boundary,
        "dim": low.dim, "n_grid": low.params.resolved_n_grid(), "dt_frame": low.dt_frame, "r_p": float(low.info.get("r_p", 1.0)), "r_t": sim.r_t,
        "wall_ms_per_frame": _ms(per_frame), "share_of_frames": {k: v / total for k, v in steps.items()}, **ro.stats,
        "failure": ro.failure, "events": [{"step": k, "frame": k * sim.r_t, "event": e} for k, e in ro.events],
        "threads": args.threads, "version": hybridmpm.__version__, "python": platform.python_version(), "machine": platform.machine(),
    }  # fmt: skip
    if ro.failure:
        summary["failure_detail"] = ro.failure_detail
    if args.solver == "mpm":
        subs = ro.substeps[1:]
        summary["substeps_total"] = int(subs.sum())
        summary["substeps_per_frame"] = {"min": int(subs.min()), "median": float(np.median(subs)), "max": int(subs.max())} if len(subs) else None
        summary["realtime_factor"] = float(low.dt_frame / np.median(per_frame)) if len(per_frame) else None
    else:
        model = sim.model  # type: ignore[attr-defined]
        summary["model"] = str(model.path)
        summary["warmup_mpm_frames"] = warmup_frames(model)
        summary["neural_steps"] = steps.get(NEURAL, 0)
    if args.solver == "hybrid":
        summary.update(
            {"safeguard": sim.safeguard, "r_c": sim.r_c, "delta": sim.delta, "dwell": sim.dwell, "audit_every": sim.audit_every,  # type: ignore[attr-defined]
             "audit_tol": sim.audit_tol, "residual_tol": sim.residual_tol, "audit_max": sim.audit_max,  # type: ignore[attr-defined]
             "cheap": sim.cheap, "cheap_kind": sim.cheap_kind}  # type: ignore[attr-defined]
        )  # fmt: skip
        if sim.cheap_kind != NEURAL:  # type: ignore[attr-defined]
            summary["cheap_grid"] = sim.neural.n_grid  # type: ignore[attr-defined]
    err = None
    if args.reference:
        t0 = time.perf_counter()
        ref = reference(scene, ro.frames_done, stride=sim.r_t, threads=args.threads).fluid_positions
        ref_ms = (time.perf_counter() - t0) / max(1, ro.frames_done) * 1e3
        err = grid_mass_error(ro.fluid_positions, ref[: len(ro.positions)], scene.params.resolved_n_grid())  # the reference's grid
        summary["reference"] = {
            "solver": "mpm", "r_p": 1.0, "particles": scene.num_particles, "wall_ms_per_frame_mean": ref_ms,
            "grid_mass_error": {"mean": float(err.mean()), "last": float(err[-1])},
        }  # fmt: skip
    ro.save(out / "trajectory.npz")
    _write_json(out / "summary.json", summary)
    title = f"{scene.name} ({args.solver}" + (f", r_c = {args.r_c:g})" if args.solver == "hybrid" else ")")
    if args.solver == "hybrid":
        plot_timeline(out / "timeline.png", ro.dt_frame, ro.solver, ro.score, args.r_c, err, title=title)
    if not args.no_render:
        render_gif(
            ro.positions, ro.particle_type, out / "render.gif", dt_frame=ro.dt_frame, title=title, frame_solver=ro.solver if args.solver == "hybrid" else None
        )
    if args.export:
        export_points(ro.positions, ro.particle_type, out / "export", fmt=args.export, dt=ro.dt_frame, solver=ro.extras["solver"])
    if not args.quiet:
        ms = summary["wall_ms_per_frame"]
        line = f"{scene.name}: {ro.frames_done} frames, {low.num_particles} particles"
        line += f" (r_p {summary['r_p']:g})" if summary["r_p"] < 1 else ""
        line += f" on a {summary['n_grid']}^{low.dim} grid" if summary["n_grid"] != scene.params.resolved_n_grid() else ""
        line += f", {args.solver} median {ms['median']:.2f} ms/frame (p95 {ms['p95']:.2f})" if ms["median"] is not None else ""
        if args.solver == "hybrid":
            cheap = sim.cheap_kind  # type: ignore[attr-defined]
            line += f", {cheap} {100 * ro.share(cheap):.0f}% of steps, {ro.stats['switches']} switches"
        if err is not None:
            line += f"; grid-mass error vs full-res MPM mean {err.mean():.3f}, last {err[-1]:.3f}"
        if ro.failure:
            line += f"; broke off: {ro.failure} ({ro.failure_detail})"
        print(line + f" -> {out}/")
    return 0


def _apply_tuned(args: argparse.Namespace, scene: str) -> None:
    """``--solver auto``: take solver, model, r_p and r_c from the configuration
    ``hybridmpm tune`` wrote (``--tuned``, default tuned/SCENE.json)."""
    # import time: loaded by this command only
    from hybridmpm.sim import load_tuned, tuned_settings

    if args.model is not None or args.r_p != 1.0 or args.n_grid is not None or args.particles_per_cell is not None:
        raise HybridMpmError(
            "solver: --solver auto takes the model, r_p, grid and r_c from the tuned configuration; drop --model/--r-p/--n-grid/--particles-per-cell"
        )
    doc = load_tuned(scene, args.tuned)
    for key, value in tuned_settings(doc).items():
        setattr(args, key, value)
    cfg = doc["config"]
    if not args.quiet:
        m = doc["measured"]
        print(
            f"auto: {cfg['label']} (tuned for error <= {doc['error_budget']:g}: measured {m['error_mean']:.3f}, "
            f"{m['ms_mean']:.2f} ms/frame on validation seeds)"
        )


def _bench_kwargs(args: argparse.Namespace) -> dict:
    # import time: loaded by this command only
    from hybridmpm.bench import ERROR_TOL_SWEEP, R_C_SWEEP

    def numbers(field: str, text: str) -> tuple[float, ...]:
        try:
            return tuple(float(x) for x in text.split(",") if x.strip())
        except ValueError:
            raise HybridMpmError(f"{field}: expected comma-separated numbers, got {text!r}") from None

    r_cs = R_C_SWEEP if args.r_c is None else numbers("r_c", args.r_c)
    tols = ERROR_TOL_SWEEP if args.error_tols is None else numbers("error_tols", args.error_tols)
    return {
        "frames": args.frames, "r_cs": r_cs, "error_tols": tols, "model": args.model, "variants": not args.no_variants,
        "extra_models": tuple(args.extra_model or ()), "warmup": args.warmup, "mpm_threads": args.threads, "nn_threads": args.nn_threads,
        "nn_alone_threads": args.nn_alone_threads,
    }  # fmt: skip


def _bench(args: argparse.Namespace) -> int:
    # import time: loaded by this command only
    from hybridmpm.bench import TEST_SEED0, bench

    if args.seeds < 1:
        raise HybridMpmError("seeds: must be >= 1")
    seeds = [args.first_seed + i for i in range(args.seeds)] if args.first_seed is not None else [TEST_SEED0 + i for i in range(args.seeds)]
    cmd = "hybridmpm " + " ".join(sys.argv[1:]) if sys.argv[1:2] == ["bench"] else f"hybridmpm bench {args.scene}"
    res = bench(args.scene, seeds=seeds, out=args.out, command=cmd, progress=not args.quiet, **_bench_kwargs(args))
    if not args.quiet:
        for r in res["rows"]:
            print(f"{r['label']:<48} error {r['error_mean']:.3f}  {r['ms_mean']:7.2f} ms/frame{'  (Pareto)' if r['pareto'] else ''}")
        print(f"Pareto front: {'; '.join(res['pareto'])}\n-> {res['out']}/report.md")
    return 0


def _tune(args: argparse.Namespace) -> int:
    # import time: loaded by this command only
    from hybridmpm.bench import VALID_SEED0, tune

    if args.seeds < 1:
        raise HybridMpmError("seeds: must be >= 1")
    seeds = [VALID_SEED0 + i for i in range(args.seeds)]
    doc = tune(args.scene, args.error_budget, seeds=seeds, metric=args.metric, out=args.out, work=args.work, progress=not args.quiet, **_bench_kwargs(args))
    if not args.quiet:
        c, m = doc["config"], doc["measured"]
        print(
            f"{args.scene}: {c['label']} — error {m['error_mean']:.3f} (mean) / {m['error_last']:.3f} (last) <= budget "
            f"{args.error_budget:g} ({args.metric}), {m['ms_mean']:.2f} ms/frame -> {doc['path']}\n"
            f"use it: hybridmpm simulate {args.scene} --solver auto" + (f" --tuned {doc['path']}" if args.out else "")
        )
    return 0


def _evaluate(args: argparse.Namespace) -> int:
    # import time: loaded by this command only
    from hybridmpm.metrics import evaluate

    pred = Trajectory.load(args.pred)
    ref = Trajectory.load(args.ref)
    result = evaluate(pred, ref, n_grid=args.n_grid)
    result["pred"]["path"] = str(Path(args.pred))
    result["ref"]["path"] = str(Path(args.ref))
    out = Path(args.out) if args.out is not None else Path(args.pred).parent / "metrics.json"
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.with_name(out.name + ".tmp")
    tmp.write_text(json.dumps(result, indent=2))
    tmp.replace(out)
    if not args.quiet:
        gme = result["grid_mass_error"]
        lines = [
            f"{result['frames_compared']} frames compared (pred every {pred.dt_frame * 1e3:g} ms, ref every {ref.dt_frame * 1e3:g} ms; "
            f"{result['pred']['particles']} vs {result['ref']['particles']} fluid particles)",
            f"grid-mass error (n_grid {result['n_grid']}): mean {gme['mean']:.4g}, last {gme['last']:.4g}",
        ]
        for key, label in (("position_mse_rollout", "rollout"), ("position_mse_one_step", "one-step")):
            m = result[key]
            lines.append(f"{label} position MSE: " + (f"mean {m['mean']:.4g} m², last {m['last']:.4g} m²" if m else f"n/a ({result[key + '_reason']})"))
        lines.append(f"-> {out}")
        print("\n".join(lines))
    return 0


def _control(args: argparse.Namespace) -> int:
    """``hybridmpm control``: a sketch applied to a scene's fluid (:func:`hybridmpm.control.control_episode`)."""
    from PIL import Image

    # import time: loaded by this command only
    from hybridmpm.control import Controller, Sketch, control_episode, render_sketch, sketch_from_png
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
    controller = Controller.for_scene(Path(args.scene).stem, args.method, frames=args.frames, **kw)
    if args.from_frame < 0:
        raise InvalidInputError(f"from_frame: must be >= 0, got {args.from_frame}", "from_frame")
    out = _out_dir(args.out)
    scene = make_scene(args.scene, seed=args.seed)
    sim = make_simulator(scene, args.solver, seed=args.seed, threads=args.threads)
    rollout(sim, args.from_frame, progress=None if args.quiet else f"{scene.name} [{args.solver}] to frame {args.from_frame}")
    ep = control_episode(sim, sketch, controller, progress=None if args.quiet else f"{scene.name} [control: {args.method}]")
    ro = ep.rollout
    ro.save(out / "trajectory.npz")
    summary = {
        "scene": scene.name, "seed": args.seed, "solver": args.solver, "method": args.method, "from_frame": args.from_frame,
        "frames": ro.frames_done, "particles": sim.particles.num_fluid, "sketch": sketch.to_json(), **ep.metrics,
    }  # fmt: skip
    _write_json(out / "summary.json", summary)
    Image.fromarray(render_sketch(sketch, size=256)).save(out / "sketch.png")
    if not args.no_render:
        line = np.concatenate([sketch.points, sketch.points[:1]]) if sketch.kind == "oval" else sketch.points
        render_gif(ro.positions, ro.particle_type, out / "render.gif", dt_frame=ro.dt_frame, title=f"{scene.name} ({args.method})", overlay=[line])
    if not args.quiet:
        m = ep.metrics
        adherence = (
            f"cosine {m['cosine']:.2f}, length ratio {m['length_ratio']:.2f}" if sketch.kind == "arrow" else f"inside {m['inside']:.0%}, IoU {m['iou']:.2f}"
        )
        print(
            f"{scene.name}: {args.method} control over {ro.frames_done} frames from frame {args.from_frame}: {adherence}; "
            f"effort mean {m['effort_mean_g']:.1f} g; plan {m['plan_ms']:.1f} ms, episode {m['episode_ms']:.0f} ms -> {out}/"
        )
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


def _stress(args: argparse.Namespace) -> int:
    # import time: loaded by this command only
    from hybridmpm.bench.stress import CASES, METHODS, markdown_table, stress

    cases = tuple(args.cases.split(",")) if args.cases else CASES
    methods = tuple(args.methods.split(",")) if args.methods else METHODS
    for c in cases:
        if c not in CASES:
            raise HybridMpmError(f"cases: unknown case {c!r} (choose from {', '.join(CASES)})")
    for m in methods:
        if m not in METHODS:
            raise HybridMpmError(f"methods: unknown method {m!r} (choose from {', '.join(METHODS)})")
    if args.frames < 1:
        raise HybridMpmError("frames: must be >= 1")
    out = _out_dir(args.out)
    res = stress(args.scene, cases=cases, methods=methods, frames=args.frames, seed=args.seed, model=args.model, threads=args.threads, progress=not args.quiet)
    table = markdown_table(res)
    cmd = "hybridmpm stress " + " ".join(sys.argv[2:]) if sys.argv[1:2] == ["stress"] else f"hybridmpm stress {args.scene}"
    (out / f"stress_{args.scene}.md").write_text(f"Command: `{cmd}`\n\n" + table)
    (out / f"stress_{args.scene}.json").write_text(json.dumps([r.row() for r in res], indent=2))
    if not args.quiet:
        print(table + f"-> {out}/stress_{args.scene}.md")
    return 0


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
        from hybridmpm.train.grid_train import GridTrainConfig, train_grid
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


def _generate(args: argparse.Namespace) -> int:
    # import time: loaded by this command only
    from hybridmpm.train.datasets import GenerateConfig, generate_dataset

    try:
        split = tuple(float(v) for v in args.split.split(","))
    except ValueError:
        raise InvalidInputError(f"split: three comma-separated fractions, e.g. 0.8,0.1,0.1; got {args.split!r}", "split") from None
    config = GenerateConfig(
        scene=args.scene, trajectories=args.trajectories, frames=args.frames, seed=args.seed,
        r_p=args.r_p, r_t=args.r_t, lowres=args.lowres, split=split,  # type: ignore[arg-type]
    )  # fmt: skip
    try:
        report = generate_dataset(
            config, args.out, workers=args.workers, executor=args.executor, keep_parts=args.keep_parts, compress=args.compress, progress=not args.quiet
        )
    except KeyboardInterrupt:
        print(f"hybridmpm: interrupted; finished trajectories are kept in {args.out}/parts, rerun the same command to resume", file=sys.stderr)
        return 130
    if not args.quiet:
        size = sum(report.sizes.values())
        print(
            f"{args.scene}: {args.trajectories} trajectories ({report.simulated} simulated now, {report.resumed} already done) "
            f"in {report.wall_s:.1f} s with {args.workers} worker(s) (assembly {report.assemble_s:.1f} s); {size / 1e6:.1f} MB on disk -> {args.out}/"
        )
    return 0


def _inspect(args: argparse.Namespace) -> int:
    """``hybridmpm inspect DIR``: the dataset's summary as JSON; exit status 1
    if it does not match its own metadata (:func:`hybridmpm.data.gns.check_dataset`)."""
    # import time: loaded by this command only
    from hybridmpm.data import GnsDataset
    from hybridmpm.data.gns import check_dataset

    info = check_dataset(GnsDataset(args.directory))
    print(json.dumps(json_safe(info), indent=2))
    for p in info["problems"]:
        print(f"hybridmpm: problem: {p}", file=sys.stderr)
    return 1 if info["problems"] else 0


def _serve(args: argparse.Namespace) -> int:
    """``hybridmpm serve``: the HTTP service and its page (one process: sessions live in memory, and in ``--store`` when given)."""
    try:
        # import time: loaded by this command only
        from hybridmpm.service import ServiceConfig, create_app
        from hybridmpm.service.server import run
    except ImportError as e:
        raise InvalidInputError(f"serve: needs the service extra (pip install 'hybridmpm[service]'): {e}", "serve") from None
    hosts = None if args.allowed_hosts is None else tuple(h.strip() for h in args.allowed_hosts.split(",") if h.strip())
    cfg = ServiceConfig.from_env(
        max_sessions=args.max_sessions,
        idle_ttl_s=args.ttl,
        allowed_hosts=hosts,
        max_sessions_per_client=args.max_sessions_per_client,
        memory_budget=args.memory_budget,
        store=args.store,
        save_every_s=args.save_every,
        backend=args.backend,
        ray_address=args.ray_address,
        ray_namespace=args.ray_namespace,
        ray_num_cpus=args.ray_num_cpus,
    )
    app = create_app(cfg)  # opens the store, joins the Ray cluster of --backend ray (a clear error if it cannot)
    print(
        f"hybridmpm: serving on http://{args.host}:{args.port}/ (max {cfg.max_sessions} sessions, {cfg.max_sessions_per_client} per client, "
        f"idle TTL {cfg.idle_ttl_s:g} s, hosts {', '.join(cfg.allowed_hosts) or 'loopback names on loopback addresses'}"
        f"{f', store {cfg.store}, saved every {cfg.save_every_s:g} s' if cfg.store else ''}"
        f"{f', sessions in the Ray cluster at {cfg.ray_address}' if cfg.backend == 'ray' else ('' if cfg.store else ', sessions in memory only')})",
        file=sys.stderr,
        flush=True,
    )
    run(app, args.host, args.port, cfg, log_level=args.log_level)
    return 0


def build_parser() -> argparse.ArgumentParser:
    # import time: loaded by this command only
    from hybridmpm.scenes import DOMAINS

    parser = argparse.ArgumentParser(prog="hybridmpm", description="Real-time hybrid neural / MLS-MPM fluid simulation.")
    sub = parser.add_subparsers(dest="command", required=True)
    sim = sub.add_parser("simulate", help="run a scene and write trajectory.npz, summary.json and render.gif")
    sim.add_argument(
        "scene", nargs="?", default="dam_break2d", help=f"a scene ({', '.join(sorted(DOMAINS))}) or a scene file (.toml/.json); default dam_break2d"
    )
    sim.add_argument(
        "--solver", default="hybrid", choices=["hybrid", "mpm", "neural", "auto"],
        help="solver (default hybrid: neural, MPM while s(t) < r_c; auto: the configuration hybridmpm tune chose)",
    )  # fmt: skip
    sim.add_argument("--tuned", default=None, help="--solver auto: tuned configuration (default tuned/SCENE.json)")
    sim.add_argument("--model", default=None, help="ONNX model for --solver neural|hybrid (default: the shipped model for the scene)")
    sim.add_argument(
        "--cheap",
        default="neural",
        choices=["neural", "mpm-coarse"],
        help="hybrid: its cheap half, the network (default) or MPM on a coarser grid with the same particles (the classical twin)",
    )
    sim.add_argument("--cheap-grid", type=int, default=None, help="hybrid --cheap mpm-coarse: the coarse grid (default half the scene's)")
    sim.add_argument("--r-c", type=float, default=R_C, help=f"hybrid threshold r_c (default {R_C:g}; 0 = no complexity trigger, > 1 = MPM only)")
    sim.add_argument("--dwell", type=int, default=None, help="hybrid: steps of s(t) >= r_c on MPM before the network takes over again")
    sim.add_argument("--audit-every", type=int, default=None, help=f"hybrid: network steps per MPM audit (default {AUDIT_EVERY}; 0 = no audit; docs/hybrid.md)")
    sim.add_argument("--audit-tol", type=float, default=None, help=f"hybrid: MPM audit tolerance in g (default {AUDIT_TOL:g})")
    sim.add_argument(
        "--safeguard", default=None, choices=list(SAFEGUARDS),
        help=f"hybrid: switching rule (default {SAFEGUARD}: s(t) and the MPM audit; paper: s(t) alone; error: an audit whose interval adapts, no s(t); docs/hybrid.md)",
    )  # fmt: skip
    sim.add_argument(
        "--residual-tol", type=float, default=None, help=f"hybrid, error rule: density residual in g that brings the audit forward (default {RESIDUAL_TOL:g})"
    )
    sim.add_argument("--audit-max", type=int, default=None, help=f"hybrid, error rule: longest interval between audits in network steps (default {AUDIT_MAX})")
    sim.add_argument("--reference", action="store_true", help="also run full-resolution MPM and report the grid-mass error (hybrid)")
    sim.add_argument(
        "--export", default=None, choices=["ply", "vtu"], help="also write a point-cloud sequence to OUT/export/ (PLY for Blender, VTU for ParaView)"
    )
    sim.add_argument("--frames", type=int, default=None, help="frames of 2.5 ms (default: the scene's)")
    sim.add_argument("--out", default="runs/out", help="output directory (default: runs/out)")
    sim.add_argument("--seed", type=_seed, default=0, help="seed of the scene's random initial condition")
    sim.add_argument("--threads", type=int, default=0, help="solver threads (0 = all cores)")
    sim.add_argument("--r-p", type=float, default=1.0, help="spatial downsampling r_p in (0, 1]: cluster the initial particles (default 1)")
    sim.add_argument(
        "--n-grid", type=int, default=None, help="--solver mpm: run on this grid of the same domain (same blocks, obstacles, wall faces; default: the scene's)"
    )
    sim.add_argument(
        "--particles-per-cell",
        type=int,
        default=None,
        help="--solver mpm: particles per cell per axis of the lattice on --n-grid (1-4; default the scene's, 2)",
    )
    sim.add_argument("--no-render", action="store_true", help="skip render.gif")
    sim.add_argument("--quiet", action="store_true", help="no progress bar or summary line")
    sim.set_defaults(func=_simulate)
    co = sub.add_parser("control", help="apply a sketch (arrow or oval, JSON) to a scene's fluid; writes trajectory.npz, summary.json, render.gif, sketch.png")
    co.add_argument("scene", nargs="?", default="water2d", help="a scene or scene file (default water2d)")
    co.add_argument(
        "--sketch", required=True, help='sketch: JSON {"kind": "arrow"|"oval", "points": [[x, y], ...]} in domain coordinates (y up), or a PNG of the drawing'
    )
    co.add_argument("--method", default="diffusion", choices=["none", "constant", "pd", "diffusion"], help="controller (default diffusion: the shipped model)")
    co.add_argument("--model", default=None, help="diffusion controller directory (default: the scene's shipped one)")
    co.add_argument(
        "--steps", type=int, default=None, help=f"DDIM steps of the diffusion controller (default: the model's control.json sample_steps, else {SAMPLE_STEPS})"
    )
    co.add_argument("--guidance", type=float, default=1.0, help="classifier-free guidance scale (default 1: no blank pass)")
    co.add_argument("--solver", default="hybrid", choices=["hybrid", "mpm"], help="simulator (control always runs on its MPM; default hybrid)")
    co.add_argument("--from-frame", type=int, default=40, help="frames simulated before the sketch applies (default 40)")
    co.add_argument("--frames", type=int, default=T_CTR, help=f"control horizon T_ctr in frames (default {T_CTR})")
    co.add_argument("--seed", type=_seed, default=0, help="seed of the scene's initial condition and of the diffusion noise")
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
    tc.add_argument("--seed", type=int, default=0)
    tc.add_argument("--init-from", default=None, help="warm start from another run's ckpt.pt (same sizes; a new run only)")
    tc.add_argument("--prior", default="free_sketch", choices=["free_sketch", "sketch_ramp"], help="what plans are relative to (default free_sketch)")
    tc.add_argument("--batch", type=int, default=1, help="training pairs per step and process (default 1)")
    tc.add_argument("--threads", type=int, default=1, help="torch threads per process (default 1)")
    tc.add_argument("--nproc", type=int, default=1, help="local processes of data-parallel training, --batch each (default 1; docs/neural.md)")
    tc.add_argument("--quiet", action="store_true")
    tc.set_defaults(func=_train_control)
    st = sub.add_parser("stress", help="neural-only, MPM-only and hybrid through failure cases over long rollouts; writes a table")
    st.add_argument("scene", help="registered scene (its shipped model is used unless --model)")
    st.add_argument("--frames", type=int, default=1000, help="frames per rollout (default 1000)")
    st.add_argument("--cases", default=None, help="comma-separated subset of baseline,fast,obstacle,dense (default all)")
    st.add_argument("--methods", default=None, help="comma-separated subset of neural,mpm,hybrid (default all)")
    st.add_argument("--model", default=None, help="ONNX model (default: the shipped model for the scene)")
    st.add_argument("--seed", type=_seed, default=0, help="seed of the scene's initial condition and clustering")
    st.add_argument("--threads", type=int, default=1, help="MPM threads (default 1)")
    st.add_argument("--out", default="runs/stress", help="directory of stress_SCENE.md / .json (default runs/stress)")
    st.add_argument("--quiet", action="store_true")
    st.set_defaults(func=_stress)

    def bench_args(p: argparse.ArgumentParser) -> None:
        p.add_argument("scene", choices=sorted(DOMAINS), help="registered scene")
        p.add_argument("--frames", type=int, default=None, help="frames per rollout (default: the paper's T of the scene)")
        p.add_argument("--r-c", default=None, help="comma-separated hybrid thresholds (default 0,0.1,...,0.9)")
        p.add_argument("--error-tols", default=None, help="comma-separated audit tolerances [g] of the hybrid's error rule (default 0.5,1,2,3,5; '' = none)")
        p.add_argument("--model", default=None, help="the hybrid's ONNX model (default: the shipped model of the scene)")
        p.add_argument("--extra-model", action="append", help="another ONNX model to run alone (repeatable)")
        p.add_argument("--no-variants", action="store_true", help="skip the shipped variant networks (full-resolution, spatial-/temporal-only)")
        p.add_argument("--warmup", type=int, default=24, help="frames at the start not timed (default 24)")
        p.add_argument("--threads", type=int, default=0, help="MPM threads (0 = all cores)")
        p.add_argument("--nn-threads", type=int, default=1, help="onnxruntime threads of the hybrid (default 1)")
        p.add_argument(
            "--nn-alone-threads", type=int, default=0, help="onnxruntime threads of the networks run alone (0 = all cores, the default: MPM is idle then)"
        )
        p.add_argument("--quiet", action="store_true", help="no progress bar or summary")

    be = sub.add_parser("bench", help="error against latency for every method from the same held-out initial conditions; charts and report")
    bench_args(be)
    be.add_argument("--seeds", type=int, default=3, help="number of held-out seeds (default 3: 1000, 1001, 1002)")
    be.add_argument("--first-seed", type=int, default=None, help="first seed (default 1000, the held-out test seeds)")
    be.add_argument("--out", default=None, help="output directory (default runs/bench/SCENE; resumes finished cells)")
    be.set_defaults(func=_bench)

    tu = sub.add_parser("tune", help="the fastest configuration (r_p, r_t, r_c, model) within an error budget, for --solver auto")
    bench_args(tu)
    tu.add_argument("--error-budget", type=float, required=True, help="largest allowed grid-mass error (see --metric)")
    tu.add_argument("--metric", default="error_mean", choices=["error_mean", "error_last"], help="error over the rollout (mean, default) or at its last frame")
    tu.add_argument("--seeds", type=int, default=2, help="number of validation seeds (default 2: 2000, 2001)")
    tu.add_argument("--out", default=None, help="config file to write (default tuned/SCENE.json)")
    tu.add_argument("--work", default=None, help="benchmark directory (default runs/tune/SCENE; resumes finished cells)")
    tu.set_defaults(func=_tune)

    gen = sub.add_parser("generate", help="generate a GNS-layout dataset (train/valid/test.npz, metadata.json) of MPM rollouts")
    gen.add_argument("scene", choices=sorted(DOMAINS), help="domain")
    gen.add_argument("--trajectories", type=int, required=True, help="number of trajectories M (>= 3; split 80/10/10 by default)")
    gen.add_argument("--out", required=True, help="dataset directory (resumes if it holds an unfinished generation)")
    gen.add_argument("--frames", type=int, default=None, help="frames T per trajectory (default: the paper's T for the domain)")
    gen.add_argument("--workers", type=int, default=2, help="parallel worker processes (default 2)")
    gen.add_argument("--seed", type=_seed, default=0, help="dataset seed (default 0)")
    gen.add_argument("--r-p", type=float, default=1.0, help="spatial downsampling r_p in (0, 1] (default 1; the paper's is 0.5714)")
    gen.add_argument("--r-t", type=int, default=1, help="temporal downsampling: store every r_t-th frame (default 1; the paper's is 2)")
    gen.add_argument(
        "--lowres", default="simulate", choices=["simulate", "centroids"], help="how r_p < 1 data is made (default: simulate the clustered initial condition)"
    )
    gen.add_argument("--split", default="0.8,0.1,0.1", help="train,valid,test fractions (default 0.8,0.1,0.1)")
    gen.add_argument("--executor", default="process", choices=["process", "ray"], help="process pool (default) or Ray (RAY_ADDRESS or a local instance)")
    gen.add_argument("--compress", action="store_true", help="deflate the split files (~13%% smaller for float32 positions, slower to write)")
    gen.add_argument("--keep-parts", action="store_true", help="keep the per-trajectory files in DIR/parts after assembling")
    gen.add_argument("--quiet", action="store_true", help="no progress bar or summary line")
    gen.set_defaults(func=_generate)

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
    tr.add_argument("--seed", type=_seed, default=0)
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
    tg.add_argument("--seed", type=_seed, default=0)
    tg.add_argument("--threads", type=int, default=1, help="torch threads per process (default 1)")
    tg.add_argument("--nproc", type=int, default=1, help="local processes of data-parallel training, --batch each (default 1; docs/neural.md)")
    tg.add_argument("--quiet", action="store_true")
    tg.set_defaults(func=_train_grid)

    ins = sub.add_parser("inspect", help="check a GNS-layout dataset directory and print its summary as JSON")
    ins.add_argument("directory", help="dataset directory (metadata.json + train/valid/test.npz)")
    ins.set_defaults(func=_inspect)

    ev = sub.add_parser("evaluate", help="compare a predicted trajectory.npz with a reference one and write metrics.json")
    ev.add_argument("pred", help="predicted trajectory (.npz, as written by simulate)")
    ev.add_argument("ref", help="reference trajectory (.npz), e.g. full-resolution MPM from the same initial condition")
    ev.add_argument("--n-grid", type=int, default=None, help="grid of the grid-mass error (default: the reference's, else 128 in 2D / 64 in 3D)")
    ev.add_argument("--out", default=None, help="metrics JSON to write (default: metrics.json next to PRED)")
    ev.add_argument("--quiet", action="store_true", help="no summary")
    ev.set_defaults(func=_evaluate)

    sv = sub.add_parser("serve", help="the HTTP service and its web page (needs the 'service' extra; one process, sessions in memory)")
    sv.add_argument("--host", default="127.0.0.1", help="address to listen on (default 127.0.0.1)")
    sv.add_argument("--port", type=int, default=8000, help="port (default 8000)")
    sv.add_argument("--max-sessions", type=int, default=None, help="sessions held at once; more get 503 (default 100, env HYBRIDMPM_MAX_SESSIONS)")
    sv.add_argument("--ttl", type=float, default=None, help="idle seconds before a session is removed (default 600, env HYBRIDMPM_IDLE_TTL_S)")
    sv.add_argument(
        "--allowed-hosts", default=None,
        help="comma-separated Host names served (others: 400; '*' any). Default (env HYBRIDMPM_ALLOWED_HOSTS): the loopback names on loopback addresses, any elsewhere",
    )  # fmt: skip
    sv.add_argument("--max-sessions-per-client", type=int, default=None, help="sessions one client address may hold; more get 429 (default 20)")
    sv.add_argument(
        "--memory-budget", default=None,
        help="memory for sessions, kept controls and requests together, e.g. 8G; beyond it 503 (default half the RAM, env HYBRIDMPM_SERVICE_MEMORY_BUDGET)",
    )  # fmt: skip
    sv.add_argument(
        "--store", default=None,
        help="directory or fsspec URL (s3://..., memory://...) keeping every session's checkpoint: a restarted server brings them back (env HYBRIDMPM_STORE)",
    )  # fmt: skip
    sv.add_argument(
        "--save-every", type=float, default=None,
        help="with --store: seconds a stepping session goes at most without a save, what a crash can lose (default 1, env HYBRIDMPM_SAVE_EVERY_S)",
    )  # fmt: skip
    sv.add_argument(
        "--backend", default=None,
        help="where sessions live: 'local' (this process, the default) or 'ray' (an actor each on a Ray cluster; any number of front ends; env HYBRIDMPM_BACKEND)",
    )  # fmt: skip
    sv.add_argument("--ray-address", default=None, help="with --backend ray: 'auto' (the cluster `ray start` made here; default) or HOST:PORT of its head")
    sv.add_argument("--ray-namespace", default=None, help="with --backend ray: the Ray namespace of the sessions' actors (default hybridmpm)")
    sv.add_argument("--ray-num-cpus", type=float, default=None, help="with --backend ray: CPUs Ray reserves for each session's actor (default 0.25)")
    sv.add_argument("--log-level", default="warning", choices=["critical", "error", "warning", "info", "debug"], help="uvicorn log level")
    sv.set_defaults(func=_serve)
    for p in sub.choices.values():
        p.add_argument("--debug", action="store_true", help="show the full traceback of an error")
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Run a command; every :class:`HybridMpmError` (bad input, failed
    simulation) ends as one line on stderr with exit status 2, an OS error
    (missing or unwritable file) with status 1, Ctrl-C with 130. ``--debug``
    shows the traceback instead."""
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        return int(args.func(args))
    except (HybridMpmError, OSError, KeyboardInterrupt) as e:
        if getattr(args, "debug", False):
            raise
        if isinstance(e, KeyboardInterrupt):
            print("hybridmpm: interrupted", file=sys.stderr)
            return 130
        print(f"hybridmpm: error: {e}", file=sys.stderr)
        return 2 if isinstance(e, HybridMpmError) else 1


if __name__ == "__main__":
    sys.exit(main())
