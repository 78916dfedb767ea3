"""A jelly pressed against an obstacle: does it keep its shape, and how deep do its particles go?

A cube of a solid (default the ``jello`` preset, 0.12 m, on the floor behind
the paddle where the page's palette drops it) is poured into ``paddle3d``; the
surge carries it onto the paddle's back face and the water then calms. Every
``--every`` frames the script reads, from the particles' positions alone:

- ``rms``, ``median``, ``p99``, ``max``: each particle's distance from where
  the best rigid motion of the cube puts it (Kabsch's fit by scipy), in
  fractions of the side;
- ``gap``: the largest distance from a particle to its nearest neighbour, in
  initial spacings (a particle that leaves the body makes it grow);
- ``deepest``: the deepest any particle has been inside the paddle so far, in
  cells (a solid's particle is put back from ``SOLID_PROJECT_DEPTH_CELLS``).

    python benchmarks/solid_contact.py --frames 2400 --out benchmarks/results/solid_contact

docs/materials.md (Limits) quotes its figures.
"""

from __future__ import annotations

import argparse
import sys

import numpy as np
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

import hybridmpm as hm
from hybridmpm import _core
from hybridmpm.bench.harness import script_argv, write_results
from hybridmpm.scenes import make_scene
from hybridmpm.sim.pour import pour_block

#: The cube's side [m] (the palette's jelly).
SIDE = 0.12


def run(material: str, keys: dict[str, float], frames: int, every: int) -> list[dict[str, float]]:
    """One row per ``every`` frames after the pour (see the module's docstring for the keys)."""
    scene = make_scene("paddle3d")
    sim = hm.make_simulator(scene, "mpm")
    paddle = scene.params.colliders[0]
    dx = 1.0 / scene.params.n_grid
    centre = np.array([0.75, scene.params.walls.cells * dx + SIDE / 2 + 0.01, 0.5])
    n0 = sim.solver.num_particles
    pour_block(sim, {"material": material, **keys, "lo": (centre - SIDE / 2).tolist(), "hi": (centre + SIDE / 2).tolist()})
    cube = np.arange(n0, sim.solver.num_particles)
    rest = np.asarray(sim.solver.positions)[cube].astype(np.float64)
    spacing = float(cKDTree(rest).query(rest, k=2)[0][:, 1].max())
    a = rest - rest.mean(0)
    rows, deepest = [], 0.0
    for frame in range(1, frames + 1):
        hm.rollout(sim, 1)
        p = np.asarray(sim.solver.positions)[cube].astype(np.float64)
        deepest = max(deepest, float(-(np.abs(p - paddle.center) - paddle.half_extents).max(axis=1).min()) / dx)
        if frame % every:
            continue
        b = p - p.mean(0)
        rot, _ = Rotation.align_vectors(b, a)
        off = np.linalg.norm(rot.apply(a) - b, axis=1) / SIDE
        gap = float(cKDTree(p).query(p, k=2)[0][:, 1].max()) / spacing
        row = {"frame": frame, "rms": float(np.sqrt(np.mean(off**2))), "median": float(np.median(off))}
        row.update(p99=float(np.percentile(off, 99)), max=float(off.max()), gap=gap, deepest=deepest, x_min=float(p[:, 0].min()))
        rows.append(row)
        print(" ".join(f"{k} {v:.4g}" for k, v in row.items()), file=sys.stderr, flush=True)
    return rows


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--material", default="jello", help="a model or a preset")
    ap.add_argument("--E", type=float, default=None, help="Young's modulus [Pa] over the preset's")
    ap.add_argument("--frames", type=int, default=1200)
    ap.add_argument("--every", type=int, default=200)
    ap.add_argument("--out", required=True, help="output folder")
    args = ap.parse_args(argv)
    keys = {} if args.E is None else {"E": args.E}
    rows = run(args.material, keys, args.frames, args.every)
    lines = [
        f"# A {args.material} cube ({SIDE} m{', E ' + format(args.E, 'g') + ' Pa' if keys else ''}) pressed against paddle3d's paddle",
        f"A solid's particle is put back out of the paddle from {_core.SOLID_PROJECT_DEPTH_CELLS} cells deep. Off a rigid motion "
        "in fractions of the side; the nearest-neighbour gap in initial spacings; the deepest inside the paddle so far in cells.",
        "\n".join(
            [
                "| frame | RMS | median | p99 | max | gap | deepest |",
                "|---|---|---|---|---|---|---|",
                *(
                    f"| {r['frame']} | {r['rms']:.4f} | {r['median']:.4f} | {r['p99']:.3f} | {r['max']:.3f} | {r['gap']:.2f} | {r['deepest']:.2f} |"
                    for r in rows
                ),
            ]
        ),
    ]
    write_results(
        args.out, "solid_contact", doc={"material": args.material, "keys": keys, "rows": rows}, markdown=lines, argv=script_argv("solid_contact.py", argv)
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
