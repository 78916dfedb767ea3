"""Regenerate the figures of docs/materials.md.

    python docs/make_material_figures.py                # both figures
    python docs/make_material_figures.py --only checks  # materials_checks.png alone
    python docs/make_material_figures.py --only scenes  # material_scenes.png alone

Writes

* docs/img/materials_checks.png: the cantilever's tip deflection against beam
  theory, the stopped Bingham slump against the lubrication shape, and a jelly
  and a snow block dropped on the floor (start and end), each as the tests in
  rust/mpm/tests/ set them up (2D, 128²);
* docs/img/material_scenes.png: the registered 2D material scenes
  (jelly_dam_break2d, snowball2d, mud_slump2d; seed 0, MPM at 128²), one row
  each, at their first, middle and last frame (the scene's registered frame
  count, as the docs table lists it), particles coloured by material as the
  render GIFs colour them (hybridmpm.render.gif.particle_colours).

Every scene runs through hybridmpm.sim.rollout. On two cores the scenes figure
takes about 15 s, the checks figure about 10 s.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np

from hybridmpm.conventions import (
    DT_FRAME,
    GNS_ELASTIC,
    GNS_GOOP,
    GNS_SNOW,
    GNS_TYPE_OF_MATERIAL,
    MATERIAL_ELASTIC,
    MATERIAL_SNOW,
    MATERIAL_VISCOPLASTIC,
    NAME_OF_GNS_TYPE,
)
from hybridmpm.mpm import ElasticParams, MpmParams, ViscoplasticParams, WallFace, WallParams
from hybridmpm.render.gif import SNOW_BACKGROUND, particle_colours
from hybridmpm.scenes import Scene
from hybridmpm.scenes.core import lattice, wall_face
from hybridmpm.sim import MpmSimulator, make_simulator, rollout

OUT = Path(__file__).with_name("img")
N = 128
DX = 1.0 / N
#: the registered 2D material scenes (docs/materials.md "Scenes"), one row each
SCENES = ("jelly_dam_break2d", "snowball2d", "mud_slump2d")
#: legend names of the scenes' materials (GNS type → label; the rest by NAME_OF_GNS_TYPE)
LABELS = {GNS_ELASTIC: "jelly (elastic)", GNS_SNOW: "snow", GNS_GOOP: "mud (viscoplastic)"}


def run(params: MpmParams, x: np.ndarray, code: int, frames: int) -> np.ndarray:
    """Positions [frames + 1, N, 2] of the particles ``x`` of material ``code`` at rest."""
    scene = Scene("check", params, x, np.full(len(x), code, np.int32), np.zeros_like(x))
    return rollout(MpmSimulator(scene), frames).fluid_positions


def cantilever(ax: plt.Axes) -> None:
    length, h, e, rho, g = 0.5, 0.1, 3.0e6, 1000.0, 9.8
    params = MpmParams(
        n_grid=N,
        elastic=ElasticParams(density=rho, youngs_modulus=e, poisson_ratio=0.0),
        walls=WallParams(faces={"x-": WallFace(condition="sticky")}),
    )
    face = wall_face(params)
    x = lattice([DX, 0.5 - h / 2], [face + length, 0.5 + h / 2], DX / 2)
    tip = x[:, 0] > face + length - DX / 2
    frames = 400
    traj = run(params, x, MATERIAL_ELASTIC, frames)
    defl = float(x[tip, 1].mean()) - traj[1:, tip, 1].mean(axis=1)
    i, a = h**3 / 12, h
    q = rho * g * a
    want = q * length**4 / (8 * e * i) + q * length**2 / (2 * 5 / 6 * (e / 2) * a)
    t = (np.arange(frames) + 1) * DT_FRAME
    ax.plot(t, 1e3 * np.asarray(defl), label="MPM tip deflection")
    ax.axhline(1e3 * want, color="k", ls="--", label="Euler–Bernoulli + shear (static)")
    ax.axhline(1e3 * float(np.mean(defl)), color="C1", ls=":", label="MPM mean")
    ax.set(xlabel="t [s]", ylabel="deflection [mm]", title="Cantilever, E = 3 MPa, ν = 0")
    ax.legend(fontsize=7)


def slump(ax: plt.Axes) -> None:
    tau_y, rho, g, side = 100.0, 1000.0, 9.8, 0.14
    params = MpmParams(
        n_grid=N,
        viscoplastic=ViscoplasticParams(density=rho, youngs_modulus=1e6, poisson_ratio=0.3, yield_stress=tau_y, viscosity=0.0),
        walls=WallParams(faces={"y-": WallFace(condition="sticky")}),
    )
    floor = wall_face(params)
    x0 = lattice([0.5 - side / 2, floor], [0.5 + side / 2, floor + side], DX / 2)
    x = run(params, x0, MATERIAL_VISCOPLASTIC, 300)[-1]
    k = tau_y / (rho * g)
    half = (3 * side * side / (4 * np.sqrt(2 * k))) ** (2 / 3)
    xs = np.linspace(-half, half, 200)
    ax.scatter(x0[:, 0] - 0.5, x0[:, 1] - floor, s=0.3, c="0.8", label="start")
    ax.scatter(x[:, 0] - x[:, 0].mean(), x[:, 1] - floor, s=0.3, c="saddlebrown", label="stopped")
    ax.plot(xs, np.sqrt(2 * k * (half - np.abs(xs))), "k--", label="√(2k(L − |x|))")
    ax.set(xlabel="x [m]", ylabel="height [m]", title="Bingham slump, τ_y = 100 Pa", aspect="equal")
    ax.legend(fontsize=7, markerscale=10)


def dropped(ax: plt.Axes, code: int, color: str, title: str) -> None:
    params = MpmParams(n_grid=N, elastic=ElasticParams(youngs_modulus=1e6, poisson_ratio=0.3))
    x0 = lattice([0.4, 0.25], [0.4 + 40 * DX / 2, 0.25 + 40 * DX / 2], DX / 2)
    x = run(params, x0, code, 240)[-1]
    ax.scatter(x0[:, 0], x0[:, 1], s=0.3, c="0.8", label="start")
    ax.scatter(x[:, 0], x[:, 1], s=0.3, c=color, label="after 0.6 s")
    ax.set(xlim=(0.3, 0.7), ylim=(0.0, 0.45), aspect="equal", title=title, xlabel="x [m]")
    ax.legend(fontsize=7, markerscale=10)


def checks_figure() -> Path:
    """docs/img/materials_checks.png."""
    fig, axes = plt.subplots(1, 4, figsize=(16, 4))
    cantilever(axes[0])
    slump(axes[1])
    dropped(axes[2], MATERIAL_ELASTIC, "tab:red", "Jelly dropped, E = 1 MPa")
    dropped(axes[3], MATERIAL_SNOW, "tab:blue", "Snow dropped (Stomakhin 2013)")
    fig.tight_layout()
    path = OUT / "materials_checks.png"
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def scene_row(axes: np.ndarray, name: str) -> set[int]:
    """Draw ``name`` (seed 0, MPM) at its first, middle and last registered
    frame on the three ``axes``; returns the GNS types drawn."""
    sim = make_simulator(name, "mpm", seed=0)
    frames = int(sim.scene.frames)
    start = time.perf_counter()
    traj = rollout(sim, frames)
    if traj.failure is not None:
        raise RuntimeError(f"{name}: rollout failed at frame {traj.frame_index[-1]}: {traj.failure} {traj.failure_detail or ''}")
    print(f"{name}: {frames} frames, {sim.particles.num_fluid} particles, {time.perf_counter() - start:.0f} s")
    types = np.array([GNS_TYPE_OF_MATERIAL[int(c)] for c in sim.particles.material])
    colours = particle_colours(types)
    background = SNOW_BACKGROUND if GNS_SNOW in types else "white"
    face = wall_face(sim.scene.params)
    for ax, frame in zip(axes, (0, frames // 2, frames), strict=True):
        i = int(np.searchsorted(traj.frame_index, traj.frame_index[0] + frame))
        p = traj.fluid_positions[i]
        ax.set_facecolor(background)
        ax.add_patch(plt.Rectangle((face, face), 1 - 2 * face, 1 - 2 * face, fill=False, lw=0.6, ec="0.3"))
        ax.scatter(p[:, 0], p[:, 1], s=0.8, c=colours, linewidths=0)
        ax.set(xlim=(0, 1), ylim=(0, 1), aspect="equal", xticks=[], yticks=[])
        ax.set_title(f"frame {frame}, t = {frame * sim.scene.dt_frame:.2f} s", fontsize=9)
    axes[0].set_ylabel(name, fontsize=10)
    return set(types.tolist())


def scenes_figure() -> Path:
    """docs/img/material_scenes.png."""
    fig, axes = plt.subplots(len(SCENES), 3, figsize=(9, 8))
    drawn: set[int] = set()
    for row, name in zip(axes, SCENES, strict=True):
        drawn |= scene_row(row, name)
    from matplotlib.patches import Patch

    handles = [Patch(fc=particle_colours(np.array([t]))[0], ec="0.3", lw=0.5, label=LABELS.get(t, NAME_OF_GNS_TYPE[t])) for t in sorted(drawn)]
    fig.legend(handles=handles, loc="lower center", ncol=len(handles), fontsize=9, frameon=False)
    fig.tight_layout(rect=(0, 0.03, 1, 1))
    path = OUT / "material_scenes.png"
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--only", choices=("checks", "scenes"), help="regenerate this figure alone (default: both)")
    args = parser.parse_args()
    OUT.mkdir(exist_ok=True)
    figures = {"checks": checks_figure, "scenes": scenes_figure}
    for key, make in figures.items():
        if args.only in (None, key):
            start = time.perf_counter()
            path = make()
            print(f"{path} ({time.perf_counter() - start:.0f} s)")


if __name__ == "__main__":
    main()
