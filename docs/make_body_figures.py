#!/usr/bin/env python3
"""Figures of docs/bodies.md "Scenes": ``crates2d`` and ``crates3d`` (seed 0)
run by MPM on one thread through :func:`hybridmpm.sim.rollout`, three
snapshots each with every body drawn at its pose (2D: its outline filled, as
render.gif draws it; 3D: its mesh's triangles seen from the front, the x–y
projection the particles use, particles shaded by depth).

    python docs/make_body_figures.py [FRAMES]     # -> docs/img/bodies_scenes.png, docs/img/bodies_crates3d.png
                                                  #    (default: each scene's own frames, 400 and 240)
"""

from __future__ import annotations

import sys
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from matplotlib.collections import PolyCollection  # noqa: E402

from hybridmpm.render.bodies import local_mesh, local_outline, place  # noqa: E402
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


def crates3d(frames: int | None = None) -> Path:
    scene = make_scene("crates3d")
    frames = frames or scene.frames
    ro = rollout(MpmSimulator(scene, threads=1), frames)
    bodies = scene.params.bodies
    fig, axes = plt.subplots(1, 3, figsize=(11, 3.6), dpi=110)
    for ax, t in zip(axes, (0, frames // 4, frames)):
        p = ro.positions[t]
        ax.scatter(p[:, 0], p[:, 1], s=1.5, c=p[:, 2], cmap="Blues", vmin=-0.6, vmax=1.0, linewidths=0)
        for k, body in enumerate(bodies):
            verts, faces = local_mesh(body)
            world = place(verts, ro.body_center[t, k], ro.body_rotation[t, k])
            ax.add_collection(PolyCollection(world[faces][:, :, :2], facecolors=BODY_FILL, edgecolors=BODY_EDGE, linewidths=0.15, zorder=3))
        ax.set_xlim(0, 1)
        ax.set_ylim(0, 0.75)
        ax.set_aspect("equal")
        ax.set_xticks([])
        ax.set_yticks([])
        ax.set_title(f"t = {t * ro.dt_frame:.2f} s", fontsize=9)
    y = ro.body_center[-1, :, 1]
    what = ", ".join(f"{b.shape} {b.density:g} kg/m³ ends at y = {v:.3f} m" for b, v in zip(bodies, y))
    fig.suptitle(f"crates3d (32³, MPM, seen from the front): {what}", fontsize=9)
    fig.tight_layout()
    path = OUT / "bodies_crates3d.png"
    fig.savefig(path)
    plt.close(fig)
    print(f"{path}: centres at the end {np.round(ro.body_center[-1], 3).tolist()}")
    return path


if __name__ == "__main__":
    n = int(sys.argv[1]) if len(sys.argv) > 1 else None
    main(n)
    crates3d(n)
