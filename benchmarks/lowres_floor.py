"""Grid-mass error of MPM at low spatial resolution against MPM at full resolution.

For each 2D domain and a few seeds (the first test-split seeds of a dataset
generated with ``--seed 0``), runs from the same initial condition, for the
paper's T frames:

* MPM at full resolution (N_h particles): the reference;
* MPM at ``r_p`` (the clustered initial condition simulated with MPM: how
  ``hybridmpm generate --r-p`` makes low-resolution data, and what the
  hybrid simulator's fallback runs);
* the cluster centroids of the full-resolution rollout (the alternative
  way to make low-resolution data, ``--lowres centroids``);
* MPM at full resolution with the initial positions jittered by 1e-6 m
  (Gaussian): how fast the flow itself forgets its initial condition (chaos),
  the floor no method can go below.

It reports the grid-mass error (docs/design.md: p2g of 1/N per particle on the
128² grid, normalised; mean over the rollout and last frame), the same error
with each particle weighted by its mass, and the error at frame 0 (the
clustering alone). This is the floor the hybrid simulator can reach (paper
Fig. 5 and 9).

    python benchmarks/lowres_floor.py --seeds 5 --out benchmarks/results/lowres_floor
"""

from __future__ import annotations

import argparse
import time
from concurrent.futures import ProcessPoolExecutor
from multiprocessing import get_context
from pathlib import Path

import numpy as np

from hybridmpm.bench.harness import write_results

SCENES = ["water2d", "sand2d", "water_ramps2d", "sand_ramps2d", "water_sand2d"]


def run_one(args: tuple[str, int, float, int | None]) -> dict:
    from dataclasses import replace

    from hybridmpm.metrics import grid_mass_error
    from hybridmpm.scenes import make_scene
    from hybridmpm.scenes.resolution import cluster_centroids, downsample_scene
    from hybridmpm.sim import MpmSimulator, rollout
    from hybridmpm.train.datasets import trajectory_seed

    name, k, r_p, frames = args
    seed = trajectory_seed(0, 10_000 + k)
    full = make_scene(name, seed=seed, frames=frames)
    down = downsample_scene(full, r_p, seed=seed)
    T = full.frames
    out: dict = {"scene": name, "seed": seed, "frames": T, "n_h": full.num_particles, "n_l": down.scene.num_particles}
    trajs = {}
    jittered = replace(full, positions=full.positions + np.random.default_rng(seed).normal(0.0, 1e-6, full.positions.shape).astype(np.float32))
    for label, scene in (("full", full), ("low", down.scene), ("jitter", jittered)):
        sim = MpmSimulator(scene, threads=1)
        t0 = time.perf_counter()
        ro = rollout(sim, T)
        out[f"ms_per_frame_{label}"] = (time.perf_counter() - t0) / T * 1e3
        trajs[label] = (ro.fluid_positions, sim.particles.masses.astype(np.float64))
    (xf, mf), (xl, ml), (xj, _) = trajs["full"], trajs["low"], trajs["jitter"]
    xc = cluster_centroids(xf, down.labels, mf)
    n_grid = full.params.resolved_n_grid()
    for label, x, m in (("mpm_rp", xl, ml), ("centroids", xc, ml), ("jitter", xj, mf)):
        e = grid_mass_error(x, xf, n_grid)
        ew = grid_mass_error(x, xf, n_grid, pred_weights=m, ref_weights=mf)
        out[label] = {
            "mean": float(e.mean()),
            "last": float(e[-1]),
            "frame0": float(e[0]),
            "mean_mass_weighted": float(ew.mean()),
            "last_mass_weighted": float(ew[-1]),
        }
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seeds", type=int, default=5)
    ap.add_argument("--r-p", type=float, default=1 / 1.75)
    ap.add_argument("--frames", type=int, default=None, help="override the paper's T (for a quick look)")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--scenes", default=",".join(SCENES))
    ap.add_argument("--out", default="benchmarks/results/lowres_floor")
    a = ap.parse_args()
    from tqdm import tqdm

    tasks = [(s, k, a.r_p, a.frames) for s in a.scenes.split(",") for k in range(a.seeds)]
    rows = []
    with ProcessPoolExecutor(a.workers, mp_context=get_context("spawn")) as pool:
        for r in tqdm(pool.map(run_one, tasks), total=len(tasks), desc="lowres floor"):
            rows.append(r)
    out = Path(a.out)
    meta = {"r_p": a.r_p, "seeds": a.seeds}
    lines = [
        f"# Grid-mass error of MPM at r_p = {a.r_p:.4f} against MPM at full resolution",
        "",
        f"{a.seeds} seeds per scene, the paper's T frames,",
        "128² reference grid. Error = ‖m̃_pred − m̃_ref‖₂/‖m̃_ref‖₂ (docs/design.md, 1/N per particle), mean over frames ± std over seeds;",
        "'mass-weighted' splats each particle's mass instead; 'frame 0' is the clustering alone.",
        "",
        "| scene | T | N_h | N_l | MPM@r_p mean | MPM@r_p last | MPM@r_p mean (mass-weighted) | centroids mean | centroids last | frame 0 | chaos: full MPM, 1 µm jitter, mean | last | full MPM ms/frame | MPM@r_p ms/frame |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for s in a.scenes.split(","):
        rs = [r for r in rows if r["scene"] == s]

        def ms(key: str, sub: str, rs: list = rs) -> str:
            v = np.array([r[key][sub] for r in rs])
            return f"{v.mean():.4f} ± {v.std():.4f}"

        lines.append(
            f"| {s} | {rs[0]['frames']} | {np.mean([r['n_h'] for r in rs]):.0f} | {np.mean([r['n_l'] for r in rs]):.0f} | "
            f"{ms('mpm_rp', 'mean')} | {ms('mpm_rp', 'last')} | {ms('mpm_rp', 'mean_mass_weighted')} | {ms('centroids', 'mean')} | "
            f"{ms('centroids', 'last')} | {ms('mpm_rp', 'frame0')} | {ms('jitter', 'mean')} | {ms('jitter', 'last')} | {np.median([r['ms_per_frame_full'] for r in rs]):.2f} | "
            f"{np.median([r['ms_per_frame_low'] for r in rs]):.2f} |"
        )
    lines.append("")
    lines.append("ms/frame: one thread per run, two runs in parallel (2 workers), median over seeds; the machine is shared (±30%).")
    write_results(out.parent, out.name, doc={"meta": meta, "rows": rows}, markdown="\n".join(lines))
    print("\n".join(lines))


if __name__ == "__main__":
    main()
