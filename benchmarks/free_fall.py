"""Does the network know gravity? One-step predictions of a block in free fall.

A thrown block in flight is the simplest flow a scene has: every particle
accelerates at exactly ``g`` (the analytic result; MPM reproduces it to
rounding). This script runs MPM at a model's ``r_p`` and ``r_t`` from a
scene's initial condition, finds the model steps where the whole fluid is in
free fall over the network's input window and the step after it (every
particle's second difference within ``--tol`` of ``g``, in g), and asks the
network for that next step from MPM's true history (density relaxation off,
failure checks off, so the network alone is measured). Per step it records
the fluid's mean predicted acceleration along gravity as a fraction of
``g`` (1 is right), the mean across gravity [g], and the RMS per-particle
error [g].

    python benchmarks/free_fall.py --scenes water2d sand2d --seeds 1000 1001 1002 \
        --models water2d=python/hybridmpm/models/water2d.onnx sand2d=runs/s2k4/model.onnx \
        --out benchmarks/results/free_fall

Without ``--models`` each scene's shipped model is measured. A scene whose
seeds give no free-fall step (the dam break: its column stands on the floor)
is reported with 0 steps.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from hybridmpm.bench.harness import script_argv, write_results
from hybridmpm.conventions import G
from hybridmpm.models import shipped_model
from hybridmpm.scenes import make_scene
from hybridmpm.sim import MpmSimulator, NeuralSimulator


def free_fall_samples(scene_name: str, model: str, seed: int, steps: int, tol: float) -> list[dict[str, float]]:
    """One dict per free-fall model step ``step`` of one seed: ``ratio`` (mean
    predicted acceleration along gravity / g), ``across_g`` (norm of the mean
    predicted acceleration across gravity, in g), ``rms_g`` (RMS over fluid
    particles of the acceleration error, in g), ``speed_r`` (the fluid's mean
    displacement in the last input step, in R) and ``wall_gap_r`` (the
    smallest distance of a particle to a wall, in R)."""
    scene = make_scene(scene_name, seed=seed)
    net = NeuralSimulator(scene, model, seed=seed, relax=0, detect_failures=False, warmup=False, mpm_threads=1)
    mpm = MpmSimulator(scene, r_p=net.model.r_p, r_t=net.r_t, seed=seed, threads=1)
    n, t_in, dt = net.particles.num_fluid, net.t_in, net.dt_step
    g = scene.params.resolved_gravity()
    g_hat = g / np.linalg.norm(g)
    lo, hi = np.asarray(net.model.meta["bounds"], np.float64).T
    pos = [mpm.particles.fluid(mpm.frame.positions).astype(np.float64)]
    for _ in range(steps):
        pos.append(mpm.particles.fluid(mpm.advance().positions).astype(np.float64))
    x = np.stack(pos)
    acc = (x[2:] - 2 * x[1:-1] + x[:-2]) / dt**2  # acc[k]: the second difference centred on step k + 1
    free = (np.linalg.norm(acc - g, axis=2) <= tol * G).all(axis=1)
    out = []
    for t in range(t_in - 1, steps):
        # the window's accelerations are centred on steps t - t_in + 2 .. t, the target's on t
        if not free[t - t_in + 1 : t].all():
            continue
        net.set_history(x[t - t_in + 1 : t + 1].astype(np.float32))
        p = net.propose()
        pred = (p.predicted[:n].astype(np.float64) - 2 * x[t] + x[t - 1]) / dt**2
        mean = pred.mean(axis=0)
        along = float(mean @ g_hat)
        speed = float(np.linalg.norm(x[t] - x[t - 1], axis=1).mean()) / net.model.radius
        gap = float(min((x[t] - lo).min(), (hi - x[t]).min())) / net.model.radius
        out.append(
            {
                "step": t,
                "speed_r": speed,
                "wall_gap_r": gap,
                "ratio": along / float(np.linalg.norm(g)),
                "across_g": float(np.linalg.norm(mean - along * g_hat)) / G,
                "rms_g": float(np.sqrt(np.mean(np.sum((pred - g) ** 2, axis=1)))) / G,
            }
        )
    return out


def plot(rows: list[dict]):
    """Per free-fall step, the predicted acceleration along gravity / g
    against the fluid's speed in R per model step, one panel per scene (the figure)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    scenes = list(dict.fromkeys(str(r["scene"]) for r in rows))
    fig, axes = plt.subplots(1, len(scenes), figsize=(3.2 * len(scenes), 3.0), sharey=True, squeeze=False)
    for ax, scene in zip(axes[0], scenes, strict=True):
        for r in rows:
            if r["scene"] == scene and r["samples"]:
                ss = r["samples"]
                ax.plot([s["speed_r"] for s in ss], [s["ratio"] for s in ss], ".", ms=4, label=str(r["model"]))
        ax.axhline(1.0, color="k", lw=0.8)
        ax.set_title(scene, fontsize=9)
        ax.set_xlabel("speed [R / model step]")
        ax.legend(fontsize=7)
    axes[0][0].set_ylabel("predicted / true acceleration")
    fig.tight_layout()
    return fig


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scenes", nargs="+", default=["water2d", "sand2d", "water_ramps2d", "sand_ramps2d", "water_sand2d", "water3d", "sand3d"])
    ap.add_argument("--models", nargs="*", default=[], help="SCENE=PATH or SCENE:LABEL=PATH (default: the shipped model)")
    ap.add_argument("--seeds", nargs="+", type=int, default=[1000, 1001, 1002])
    ap.add_argument("--steps", type=int, default=40, help="model steps of MPM per seed")
    ap.add_argument("--tol", type=float, default=0.02, help="free fall: every particle's acceleration within tol*g of g")
    ap.add_argument("--out", required=True, help="output stem (.md and .json)")
    args = ap.parse_args(argv)
    runs: list[tuple[str, str, str]] = []  # scene, label, path
    given: dict[str, list[tuple[str, str]]] = {}
    for spec in args.models:
        key, _, path = spec.partition("=")
        scene, _, label = key.partition(":")
        given.setdefault(scene, []).append((label or Path(path).parent.name or path, path))
    for scene in args.scenes:
        for label, path in given.get(scene, [("shipped", str(shipped_model(scene)))]):
            runs.append((scene, label, path))
    rows = []
    for scene, label, path in runs:
        samples = [s for seed in args.seeds for s in free_fall_samples(scene, path, seed, args.steps, args.tol)]
        row: dict[str, object] = {"scene": scene, "model": label, "path": path, "steps": len(samples), "samples": samples}
        if samples:
            for key in ("ratio", "across_g", "rms_g"):
                row[key] = float(np.mean([s[key] for s in samples]))
            row["ratio_min"] = float(np.min([s["ratio"] for s in samples]))
        rows.append(row)
        print(json.dumps({k: v for k, v in row.items() if k != "samples"}), file=sys.stderr)
    lines = [
        f"One network step from MPM's true history while the whole fluid is in free fall (every particle within {args.tol:g} g of g "
        f"over the input window and the next step); seeds {args.seeds}, the first {args.steps} model steps of each. "
        "Predicted mean acceleration along gravity / g (1 is right; its minimum over the steps), its component across gravity, "
        "and the RMS per-particle error, in g; means over the free-fall steps.",
        "",
        "| scene | model | free-fall steps | along g / g | min | across [g] | RMS error [g] |",
        "|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        if r["steps"]:
            lines.append(f"| {r['scene']} | {r['model']} | {r['steps']} | {r['ratio']:.3f} | {r['ratio_min']:.3f} | {r['across_g']:.3f} | {r['rms_g']:.3f} |")
        else:
            lines.append(f"| {r['scene']} | {r['model']} | 0 | – | – | – | – |")
    out = Path(args.out)
    lines += ["", f"![along g / g against speed](./{out.name}.png)"]
    md = "\n".join(lines)
    write_results(out.parent, out.name, doc={"rows": rows}, markdown=md, figures={f"{out.name}.png": plot(rows)}, dpi=110, argv=script_argv(__file__, argv))
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    sys.exit(main())
