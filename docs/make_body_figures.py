#!/usr/bin/env python3
"""Figure of docs/bodies.md "Scenes": ``crates2d`` (seed 0) run by MPM on one
thread through :func:`hybridmpm.sim.rollout`, three snapshots with each body
drawn at its pose (its outline filled, as render.gif draws it).

    python docs/make_body_figures.py [FRAMES]     # -> docs/img/bodies_scenes.png (default: the scene's 400 frames)
"""

from __future__ import annotations

import sys
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from hybridmpm.render.bodies import local_outline, place  # noqa: E402
from hybridmpm.render.gif import BODY_EDGE, BODY_FILL  # noqa: E402
from hybridmpm.scenes import make_scene  # noqa: E402
from hybridmpm.sim import MpmSimulator, rollout  # noqa: E402

OUT = Path(__file__).with_name("img")


def main(frames: int | None = None) -> Path:
    scene = make_scene("crates2d")
    frames = frames or scene.frames
    sim = MpmSimulator(scene, threads=1)
    ro = rollout(sim, frames)
    bodies = scene.params.bodies
    labels = [f"{b.density:g}" for b in bodies]
    fig, axes = plt.subplots(1, 3, figsize=(11, 2.9), dpi=110)
    for ax, t in zip(axes, (0, frames // 4, frames)):
        p = ro.positions[t]
        ax.scatter(p[:, 0], p[:, 1], s=0.3, c="#1f77b4", linewidths=0)
        for k, body in enumerate(bodies):
            c, r = ro.body_center[t, k], ro.body_rotation[t, k]
            ax.fill(*place(local_outline(body), c, r).T, facecolor=BODY_FILL, edgecolor=BODY_EDGE, lw=0.8, zorder=3)
            ax.text(c[0], c[1], labels[k], ha="center", va="center", fontsize=7, color="white", zorder=4)
        ax.set_xlim(0, 1)
        ax.set_ylim(0, 0.6)
        ax.set_aspect("equal")
        ax.set_xticks([])
        ax.set_yticks([])
        ax.set_title(f"t = {t * ro.dt_frame:.2f} s", fontsize=9)
    y = ro.body_center[-1, :, 1]
    fig.suptitle(f"crates2d (128², MPM): boxes of {' / '.join(labels)} kg/m³; centres at the end {', '.join(f'{v:.3f}' for v in y)} m", fontsize=9)
    fig.tight_layout()
    OUT.mkdir(exist_ok=True)
    path = OUT / "bodies_scenes.png"
    fig.savefig(path)
    plt.close(fig)
    print(f"{path}: centres at the end {np.round(ro.body_center[-1], 3).tolist()}")
    return path


if __name__ == "__main__":
    main(int(sys.argv[1]) if len(sys.argv) > 1 else None)
