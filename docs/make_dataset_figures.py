"""Regenerate the figures of docs/datasets.md.

    python docs/make_dataset_figures.py

Writes docs/img/domains.png (each domain's random initial condition for seed
1 and the MPM state a third of the way through its T frames; 3D domains are
shown from the front, coloured by depth) and docs/img/clustering.png (a water
block at full resolution and at r_p = 1/1.75, with the grid-mass field of
each, mass-weighted and 1/N).
"""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt

from hybridmpm import grid_mass
from hybridmpm.scenes import DOMAINS, make_scene
from hybridmpm.scenes.resolution import PAPER_R_P, downsample_scene
from hybridmpm.sim import MpmSimulator, rollout

OUT = Path(__file__).with_name("img")
COLOURS = {5: "#2b7bba", 6: "#d8a641", 3: "#444444"}


def _scatter(ax, x, ptype, title):
    for t, c in COLOURS.items():
        m = ptype == t
        if m.any():
            ax.scatter(x[m, 0], x[m, 1], s=0.6 if t != 3 else 0.8, c=c, linewidths=0)
    ax.set_xlim(0, 1)
    ax.set_ylim(0, 1)
    ax.set_aspect("equal")
    ax.set_xticks([])
    ax.set_yticks([])
    ax.set_title(title, fontsize=8)


def domains() -> None:
    names = sorted(DOMAINS)
    fig, axes = plt.subplots(2, len(names), figsize=(2.0 * len(names), 4.2))
    for j, name in enumerate(names):
        scene = make_scene(name, seed=1)
        pt = scene.particle_type()
        steps = scene.frames // 3
        ro = rollout(MpmSimulator(scene), steps)
        _scatter(axes[0, j], ro.positions[0], pt, f"{name}\nN={scene.num_particles}, t=0")
        _scatter(axes[1, j], ro.positions[-1], pt, f"t = {steps * scene.dt_frame:.2f} s")
    fig.tight_layout()
    fig.savefig(OUT / "domains.png", dpi=110)
    plt.close(fig)


def clustering() -> None:
    scene = make_scene("water2d", seed=4)
    low = downsample_scene(scene, PAPER_R_P, seed=4).scene
    fig, axes = plt.subplots(1, 5, figsize=(13.5, 3.0))
    lo, hi = scene.positions.min(0) - 0.01, scene.positions.max(0) + 0.01
    for k, (s, label) in enumerate(((scene, f"N_h = {scene.num_particles}"), (low, f"r_p = 1/1.75: N_l = {low.num_particles}"))):
        ax = axes[k]
        sizes = 2.0 if s is scene else 2.0 * (s.masses / s.masses.min())
        ax.scatter(s.positions[:, 0], s.positions[:, 1], s=sizes, c="#2b7bba", linewidths=0)
        ax.set_xlim(lo[0], lo[0] + 0.12)
        ax.set_ylim(lo[1], lo[1] + 0.12)
        ax.set_aspect("equal")
        ax.set_title(label + ("\n(dot area ∝ cluster mass)" if s is low else "\n(zoom)"), fontsize=8)
    gm_h = grid_mass(scene.positions, 128)
    gm_l = grid_mass(low.positions, 128, low.masses)
    gm_n = grid_mass(low.positions, 128)
    vmax = gm_h.max()
    panels = ((gm_h, "grid mass m̃, N_h"), (gm_l, "m̃ of N_l, each its mass"), (gm_n, "m̃ of N_l, 1/N each (docs/design.md)"))
    for k, (g, label) in enumerate(panels):
        ax = axes[2 + k]
        ax.imshow(g.T, origin="lower", extent=(0, 1, 0, 1), vmin=0, vmax=vmax, cmap="Blues")
        ax.set_xlim(lo[0], hi[0])
        ax.set_ylim(lo[1], hi[1])
        ax.set_title(label, fontsize=8)
        ax.set_xticks([])
        ax.set_yticks([])
    fig.tight_layout()
    fig.savefig(OUT / "clustering.png", dpi=110)
    plt.close(fig)


def main() -> None:
    OUT.mkdir(exist_ok=True)
    domains()
    clustering()


if __name__ == "__main__":
    main()
