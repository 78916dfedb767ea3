"""The ``hybridmpm`` command line.

``hybridmpm simulate [SCENE] --solver mpm --frames N --out DIR`` runs a scene
and writes ``trajectory.npz``, ``summary.json`` and ``render.gif``.

``hybridmpm evaluate PRED.npz REF.npz [--n-grid N] [--out metrics.json]``
compares two trajectories (:func:`hybridmpm.metrics.evaluate`: grid-mass
error, position MSE, kinetic energy) and writes the metrics as JSON.
"""

from __future__ import annotations

import argparse
import json
import platform
import sys
import time
from pathlib import Path
from typing import Sequence

import numpy as np

from hybridmpm.errors import HybridMpmError
from hybridmpm.trajectory import Trajectory


def _simulate(args: argparse.Namespace) -> int:
    from tqdm import tqdm

    import hybridmpm
    from hybridmpm.scenes import make_scene

    scene = make_scene(args.scene, seed=args.seed)
    frames = args.frames if args.frames is not None else scene.frames
    if frames < 1:
        raise HybridMpmError("frames: must be >= 1")
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    sim = scene.make_solver(num_threads=args.threads)
    positions = np.empty((frames + 1, scene.num_particles, scene.dim), dtype=np.float32)
    positions[0] = sim.positions
    wall = np.empty(frames)
    substeps = np.empty(frames, dtype=np.int64)
    for f in tqdm(range(frames), desc=f"{scene.name} [{args.solver}]", unit="frame", disable=args.quiet):
        t0 = time.perf_counter()
        stats = sim.step_frame(scene.dt_frame)
        wall[f] = time.perf_counter() - t0
        substeps[f] = stats["substeps"]
        positions[f + 1] = sim.positions
    ptype = scene.particle_type()
    Trajectory(
        positions=positions,
        particle_type=ptype,
        dt_frame=scene.dt_frame,
        n_grid=sim.n_grid,
        masses=sim.masses,
        material=scene.material,
    ).save(out / "trajectory.npz")
    summary = {
        "scene": scene.name,
        "solver": args.solver,
        "seed": args.seed,
        "frames": frames,
        "particles": scene.num_particles,
        "dim": scene.dim,
        "n_grid": sim.n_grid,
        "dt_frame": scene.dt_frame,
        "substeps_total": int(substeps.sum()),
        "substeps_per_frame": {"min": int(substeps.min()), "median": float(np.median(substeps)), "max": int(substeps.max())},
        "wall_ms_per_frame": {
            "median": float(np.median(wall) * 1e3),
            "p95": float(np.percentile(wall, 95) * 1e3),
            "mean": float(wall.mean() * 1e3),
        },
        "realtime_factor": float(scene.dt_frame / np.median(wall)),
        "threads": args.threads,
        "version": hybridmpm.__version__,
        "python": platform.python_version(),
        "machine": platform.machine(),
    }
    (out / "summary.json").write_text(json.dumps(summary, indent=2))
    if not args.no_render:
        from hybridmpm.render import render_gif

        render_gif(positions, ptype, out / "render.gif", dt_frame=scene.dt_frame, title=f"{scene.name} ({args.solver})")
    if not args.quiet:
        print(
            f"{scene.name}: {frames} frames, {scene.num_particles} particles, "
            f"median {summary['wall_ms_per_frame']['median']:.2f} ms/frame "
            f"(p95 {summary['wall_ms_per_frame']['p95']:.2f}), "
            f"{summary['substeps_per_frame']['median']:.0f} substeps/frame -> {out}/"
        )
    return 0


def _evaluate(args: argparse.Namespace) -> int:
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


def build_parser() -> argparse.ArgumentParser:
    from hybridmpm.scenes import SCENES

    parser = argparse.ArgumentParser(prog="hybridmpm", description="Real-time hybrid neural / MLS-MPM fluid simulation.")
    sub = parser.add_subparsers(dest="command", required=True)
    sim = sub.add_parser("simulate", help="run a scene and write trajectory.npz, summary.json and render.gif")
    sim.add_argument("scene", nargs="?", default="dam_break2d", choices=sorted(SCENES), help="scene (default: dam_break2d)")
    sim.add_argument("--solver", default="mpm", choices=["mpm"], help="solver (the neural and hybrid solvers arrive with their issues)")
    sim.add_argument("--frames", type=int, default=None, help="frames of 2.5 ms (default: the scene's)")
    sim.add_argument("--out", default="runs/out", help="output directory (default: runs/out)")
    sim.add_argument("--seed", type=int, default=0, help="seed of the scene's random initial condition")
    sim.add_argument("--threads", type=int, default=0, help="solver threads (0 = all cores)")
    sim.add_argument("--no-render", action="store_true", help="skip render.gif")
    sim.add_argument("--quiet", action="store_true", help="no progress bar or summary line")
    sim.set_defaults(func=_simulate)
    ev = sub.add_parser("evaluate", help="compare a predicted trajectory.npz with a reference one and write metrics.json")
    ev.add_argument("pred", help="predicted trajectory (.npz, as written by simulate)")
    ev.add_argument("ref", help="reference trajectory (.npz), e.g. full-resolution MPM from the same initial condition")
    ev.add_argument("--n-grid", type=int, default=None, help="grid of the grid-mass error (default: the reference's, else 128 in 2D / 64 in 3D)")
    ev.add_argument("--out", default=None, help="metrics JSON to write (default: metrics.json next to PRED)")
    ev.add_argument("--quiet", action="store_true", help="no summary")
    ev.set_defaults(func=_evaluate)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        return int(args.func(args))
    except HybridMpmError as e:
        print(f"hybridmpm: error: {e}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
