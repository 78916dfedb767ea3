"""Does a network generalise to the dam break? (target 2)

The dam break (Martin & Moyce 1952; ``dam_break2d``) is a column at rest that
no training domain contains (``water_columns2d`` redraws columns near it). For
each model given, the network runs **alone** after its MPM warm-up (no
safeguard, no audit; the bench's break-off rule at a collapsed graph), and
MPM at the model's ``r_p`` runs on the same initial condition as the floor.
Each is scored by

* the grid-mass error (docs/design.md) against full-resolution MPM, mean over the
  first 100 frames and at frame 100 (the model cards' figure);
* the same for the particles held still after the warm-up (the trivial
  model: a network must beat it to have learnt anything);
* the surge front ``Z(T)`` and column height ``H(T)`` against the published
  table with its tolerances (:func:`hybridmpm.validation.score_dam_break`:
  shifted RMS ≤ 0.12, unshifted ratio 0.90–1.32, height ratio 0.85–1.25);
  the front is measured at the run's own particle spacing (``spacing /
  sqrt(r_p)`` in 2D).

Writes ``OUT.md`` (table), ``OUT.json`` and ``OUT.png`` (front and height
against the experiment).

    python benchmarks/dam_break_generalisation.py --models python/hybridmpm/models/dam_break2d.onnx \\
        runs/mix/snapshots/step_0040000/model.onnx --out benchmarks/results/dam_break_generalisation
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from hybridmpm.bench.harness import write_results
from hybridmpm.bench.run import collapsed, held_still
from hybridmpm.metrics import grid_mass_error
from hybridmpm.neural import GnsRuntime
from hybridmpm.scenes import make_scene
from hybridmpm.sim.mpm import MpmSimulator
from hybridmpm.sim.neural import NeuralSimulator, warmup_frames
from hybridmpm.sim.rollout import Rollout, reference, rollout
from hybridmpm.validation import dam_break_front_height, load_martin_moyce, score_dam_break

#: Frames of every run: the table's last front point (T = 3.33) is about frame 130 at a = 24 cells.
FRAMES = 140
#: Frames over which the grid-mass error is averaged (as in the model cards).
ERROR_FRAMES = 100


def score(ro: Rollout, scene, ref: np.ndarray, r_p: float) -> dict:
    """Grid-mass error and the Martin & Moyce score of a rollout of the dam break."""
    return score_positions(ro.fluid_positions, ro.frame_index, ro.failure, scene, ref, r_p)


def score_positions(positions: np.ndarray, frame_index: np.ndarray, failure: str | None, scene, ref: np.ndarray, r_p: float) -> dict:
    """:func:`score` of fluid positions [F, N, D] at frames ``frame_index``."""
    info = scene.spec.info
    keep = frame_index <= FRAMES
    pos, frames = positions[keep], frame_index[keep]
    err = grid_mass_error(pos, ref[frames], scene.params.resolved_n_grid())
    first = frames <= ERROR_FRAMES
    spacing = info["spacing"] / np.sqrt(r_p)
    z, h = dam_break_front_height(pos, info["a"], info["x_wall"], info["y_floor"], spacing)
    s = score_dam_break(frames * scene.spec.dt_frame, z, h, info["a"])
    return {
        "frames_done": int(frames[-1]), "failure": failure,
        "error_mean": float(err[first].mean()), "error_last": float(err[first][-1]),
        "mm_passes": bool(s.passes()), "front_rms_shifted": s.rms_front_shifted, "front_ratio": [s.ratio_min, s.ratio_max],
        "height_ratio": [s.height_ratio_min, s.height_ratio_max],
        "series": {"t": (frames * scene.spec.dt_frame).tolist(), "Z": z.tolist(), "H": h.tolist()},
    }  # fmt: skip


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--models", nargs="+", required=True, type=Path, help="model.onnx files (any 2D water model)")
    ap.add_argument("--names", nargs="*", default=None, help="a label per model (default: the path)")
    ap.add_argument("--threads", type=int, default=1, help="MPM threads")
    ap.add_argument("--out", required=True, type=Path)
    a = ap.parse_args()
    names = a.names or [str(p) for p in a.models]
    if len(names) != len(a.models):
        raise SystemExit("--names: give one per model")
    scene = make_scene("dam_break2d")
    ref = reference(scene, FRAMES, threads=a.threads, progress="full-resolution MPM").fluid_positions
    result: dict = {"frames": FRAMES, "error_frames": ERROR_FRAMES, "runs": {}}
    models = [GnsRuntime(p) for p in a.models]
    for name, model in zip(names, models):
        # a model trained on other domains is run on the dam break on purpose: that is the test
        model.meta["scenes"] = sorted({*model.meta.get("scenes", [model.meta.get("scene")]), "dam_break2d"})
        sim = NeuralSimulator(scene, model, detect_failures=False, mpm_threads=a.threads, nn_threads=1)
        result["runs"][name] = {
            "kind": "neural",
            "r_p": float(model.meta["r_p"]),
            **score(rollout(sim, FRAMES, stop=collapsed, progress=name), scene, ref, float(model.meta["r_p"])),
        }
    for r_p in sorted({float(m.meta["r_p"]) for m in models}):
        ro = rollout(MpmSimulator(scene, r_p=r_p, threads=a.threads), FRAMES, progress=f"MPM r_p {r_p:.4f}")
        result["runs"][f"MPM at r_p = {r_p:.4f}"] = {"kind": "mpm", "r_p": r_p, **score(ro, scene, ref, r_p)}
        # the trivial model: the particles held still after the networks' MPM warm-up
        warm = max(warmup_frames(m) for m in models if float(m.meta["r_p"]) == r_p)
        still = held_still(ro.fluid_positions, ro.frame_index, warm)
        result["runs"][f"held still after frame {warm} (r_p = {r_p:.4f})"] = {
            "kind": "still", "r_p": r_p, **score_positions(still, ro.frame_index, None, scene, ref, r_p),
        }  # fmt: skip
    lines = [
        "# Dam break: the network alone against Martin & Moyce (1952)",
        "",
        f"Network alone after its MPM warm-up, {FRAMES} frames; grid-mass error against full-resolution MPM over the first {ERROR_FRAMES} frames.",
        "",
        "| run | error mean | error at 100 | front RMS (shifted; ≤ 0.12) | front ratio (0.90–1.32) | height ratio (0.85–1.25) | passes | frames |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for name, r in result["runs"].items():
        lines.append(
            f"| {name} | {r['error_mean']:.3f} | {r['error_last']:.3f} | {r['front_rms_shifted']:.3f} | {r['front_ratio'][0]:.2f}–{r['front_ratio'][1]:.2f} "
            f"| {r['height_ratio'][0]:.2f}–{r['height_ratio'][1]:.2f} | {'yes' if r['mm_passes'] else 'no'} | {r['frames_done']}{' (' + r['failure'] + ')' if r['failure'] else ''} |"
        )
    fig = plot(result, scene)
    write_results(a.out.parent, a.out.name, doc=result, markdown="\n".join(lines), figures={f"{a.out.name}.png": fig}, dpi=110)
    print("\n".join(lines))


def plot(result: dict, scene):  # type: ignore[no-untyped-def]
    """Surge front and column height of every run against Martin & Moyce's (the figure)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from hybridmpm.conventions import G

    exp = load_martin_moyce()
    aa = scene.spec.info["a"]
    fig, ax = plt.subplots(1, 2, figsize=(11, 4))
    ax[0].plot(exp.front_T, exp.front_Z, "ko", label="Martin & Moyce (1952)")
    ax[1].plot(exp.height_T, exp.height_H, "ko", label="Martin & Moyce (1952)")
    for name, r in result["runs"].items():
        t = np.asarray(r["series"]["t"])
        style = {"mpm": "--", "still": ":"}.get(r["kind"], "-")
        ax[0].plot(t * np.sqrt(2 * G / aa), r["series"]["Z"], style, label=name)
        ax[1].plot(t * np.sqrt(G / aa), r["series"]["H"], style, label=name)
    ax[0].set(xlabel="T = t·sqrt(2g/a)", ylabel="surge front Z = x/a", xlim=(0, 3.5))
    ax[1].set(xlabel="T = t·sqrt(g/a)", ylabel="column height H = h/2a", xlim=(0, 2.5), ylim=(0, 1.1))
    ax[0].legend(fontsize=7)
    fig.tight_layout()
    return fig


if __name__ == "__main__":
    main()
