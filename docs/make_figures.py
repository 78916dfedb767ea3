"""Regenerate the figures of docs/engine.md.

    python docs/make_figures.py

Writes docs/img/dam_break.png (snapshots of the Martin & Moyce dam break) and
docs/img/dam_break_front.png (surge front and column height against the
experiment).
"""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np

from hybridmpm.scenes import dam_break2d
from hybridmpm.sim import MpmSimulator, rollout
from hybridmpm.validation import G, dam_break_front_height, load_martin_moyce, score_dam_break

OUT = Path(__file__).with_name("img")


def main() -> None:
    OUT.mkdir(exist_ok=True)
    scene = dam_break2d()
    frames = 300
    pos = rollout(MpmSimulator(scene), frames).fluid_positions
    times = np.arange(frames + 1) * scene.dt_frame

    snaps = [0, 40, 80, 130, 200, 300]
    fig, axes = plt.subplots(1, len(snaps), figsize=(2.2 * len(snaps), 2.4))
    for ax, f in zip(axes, snaps):
        ax.scatter(pos[f, :, 0], pos[f, :, 1], s=0.3, c="#1f77b4", linewidths=0)
        ax.set_xlim(0, 1)
        ax.set_ylim(0, 1)
        ax.set_aspect("equal")
        ax.set_xticks([])
        ax.set_yticks([])
        ax.set_title(f"t = {times[f]:.3f} s", fontsize=8)
    fig.tight_layout()
    fig.savefig(OUT / "dam_break.png", dpi=110)
    plt.close(fig)

    info = scene.info
    a = info["a"]
    z, h = dam_break_front_height(pos, a, info["x_wall"], info["y_floor"], info["spacing"])
    score = score_dam_break(times, z, h, a)
    exp = load_martin_moyce()
    fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(8, 3.2))
    tf = times * np.sqrt(2 * G / a)
    ax1.plot(tf, z, label="hybridmpm (MPM, 128²)")
    ax1.plot(tf + score.best_shift, z, "--", label=f"shifted by dT = {score.best_shift:.2f}")
    ax1.plot(exp.front_T, exp.front_Z, "ko", ms=4, label="Martin & Moyce (1952)")
    ax1.set_xlim(0, 3.5)
    ax1.set_ylim(1, 4.5)
    ax1.set_xlabel("T = t·sqrt(2g/a)")
    ax1.set_ylabel("Z = front / a")
    ax1.legend(fontsize=7)
    th = times * np.sqrt(G / a)
    ax2.plot(th, h, label="hybridmpm")
    ax2.plot(exp.height_T, exp.height_H, "ko", ms=4, label="Martin & Moyce (1952)")
    ax2.set_xlim(0, 3)
    ax2.set_xlabel("T = t·sqrt(g/a)")
    ax2.set_ylabel("H = h / 2a")
    ax2.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(OUT / "dam_break_front.png", dpi=110)
    plt.close(fig)
    print(score)


if __name__ == "__main__":
    main()
