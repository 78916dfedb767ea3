#!/usr/bin/env python3
"""Figures of docs/control.md: reverse-simulation cases (a held-out arrow and
oval per scene), the sketch, and where each controller takes the fluid
(the diffusion controller: the shipped model of the scene).

    python docs/make_control_figures.py [SCENE,SCENE...]     # -> docs/img/control_SCENE.png (default: the four scenes)
"""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from hybridmpm.control import Controller, control_episode  # noqa: E402
from hybridmpm.control.prior import free_motion_of, prior_path  # noqa: E402
from hybridmpm.train.control.cases import make_case  # noqa: E402

OUT = Path(__file__).with_name("img")
METHODS = (
    ("none", "no control"),
    ("constant", "constant force"),
    ("pd", "PD attraction"),
    ("diffusion", "diffusion (ours)"),
    ("prior", "its prior alone (no network)"),
    ("oracle_path", "true path tracked (oracle)"),
)


def controller(method: str, case, scene: str) -> Controller:  # type: ignore[no-untyped-def]
    frames = len(case.path) - 1
    if method == "oracle_path":
        return Controller("oracle", frames=frames, oracle_path=case.path)
    if method == "diffusion":
        return Controller.for_scene(scene, "diffusion", frames=frames, seed=case.seed)
    if method == "prior":  # the coarse free motion bent onto the sketch, tracked (hybridmpm.control.prior)
        sim = case.simulator()
        return Controller("oracle", frames=frames, oracle_path=prior_path(free_motion_of(sim, frames), sim.particles.fluid(sim.positions), case.sketch))
    return Controller(method, frames=frames)


def figure(scene: str, seeds: tuple[int, int]) -> Path:
    fig, axes = plt.subplots(2, 1 + len(METHODS), figsize=(2.3 * (1 + len(METHODS)), 4.8))
    for row, (seed, kind) in enumerate(zip(seeds, ("arrow", "oval"))):
        case = make_case(scene, seed, kind, tracking=False)
        sk = case.sketch
        line = np.concatenate([sk.points, sk.points[:1]]) if kind == "oval" else sk.points
        start = case.simulator().particles.fluid(case.simulator().positions)
        ax = axes[row, 0]
        ax.scatter(start[:, 0], start[:, 1], s=0.4, c="#1f77b4", linewidths=0)
        ax.scatter(case.target[:, 0], case.target[:, 1], s=0.4, c="#bbbbbb", linewidths=0)
        ax.plot(line[:, 0], line[:, 1], color="#d62728", lw=1.5)
        ax.set_title(f"{kind}: start (blue),\ntarget X_1 (grey)", fontsize=8)
        for col, (m, label) in enumerate(METHODS, start=1):
            sim = case.simulator()
            ep = control_episode(sim, sk, controller(m, case, scene), target=case.target)
            end = sim.particles.fluid(sim.positions)
            ax = axes[row, col]
            ax.scatter(case.target[:, 0], case.target[:, 1], s=0.4, c="#dddddd", linewidths=0)
            ax.scatter(end[:, 0], end[:, 1], s=0.4, c="#1f77b4", linewidths=0)
            ax.plot(line[:, 0], line[:, 1], color="#d62728", lw=1.0, alpha=0.7)
            ax.set_title(f"{label}\nerror {ep.metrics['grid_mass_error']:.2f}", fontsize=8)
    for ax in axes.ravel():
        ax.set_xlim(0, 1)
        ax.set_ylim(0, 1)
        ax.set_aspect("equal")
        ax.set_xticks([])
        ax.set_yticks([])
    view = " (3D, seen along −z)" if case.target.shape[1] == 3 else ""
    fig.suptitle(f"{scene}{view}: sketch control after T_ctr = 100 frames (grid-mass error against X_1)", fontsize=9)
    fig.tight_layout()
    OUT.mkdir(exist_ok=True)
    path = OUT / f"control_{scene}.png"
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


if __name__ == "__main__":
    import sys

    for scene in sys.argv[1].split(",") if len(sys.argv) > 1 else ("water2d", "sand2d", "water3d", "sand3d"):
        print(figure(scene, (5000, 5001)))
