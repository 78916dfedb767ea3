"""Plain MPM over grids: cost against work, and error against time, per scene.

For each scene and seed, in one process and one run: full-resolution MPM on
the scene's grid (the reference), MPM at the paper's ``r_p`` on it, and MPM on
the coarser grids of the bench (3/4 and 1/2 of the scene's, 2 particles per
cell per axis; ramps scenes refuse them), each at ``r_p = 1`` and ``r_p``.
Reports per configuration the mean ms per frame after a warm-up (the
fastest of ``--repeats`` runs, default 2, taken round the configurations:
frames of a few hundred µs move by ±30% with the machine), particles,
substeps per frame, particles x substeps per frame (the work), and the mean
grid-mass error against the reference; ratios to MPM at ``r_p`` in the same
run. Writes ``OUT/grids.json``, ``OUT/grids.md`` and the chart
``OUT/mpm_cost_grids.png`` (ms per frame against particles x substeps per
frame, one marker per grid, log-log: cost follows work when the points of
every grid lie on one line).

    python benchmarks/bench_grids.py --out benchmarks/results/grids            # every scene, 3 seeds
    python benchmarks/bench_grids.py water2d sand2d --seeds 1 --frames 200     # quicker

Time it on a quiet machine (``uptime``: load near 0).
"""

from __future__ import annotations

import argparse
import math
from pathlib import Path

import numpy as np
from tqdm import tqdm

from hybridmpm.bench.harness import round_robin, write_results
from hybridmpm.bench.methods import mpm_grid_methods
from hybridmpm.metrics import grid_mass_error
from hybridmpm.scenes import PAPER_R_P, make_scene
from hybridmpm.sim import MpmSimulator, rollout

SCENES = ("water2d", "sand2d", "water_sand2d", "dam_break2d", "water_ramps2d", "water3d", "sand3d")
#: Seeds no benchmark, tune or dataset uses.
SEED0 = 4100
WARMUP = 24


def run_scene(scene: str, seeds: list[int], frames: int, threads: int, repeats: int = 2) -> list[dict]:
    """Every configuration of ``scene`` on every seed. The repeats go round the
    configurations (all of them once, then again), so that a slow spell of
    the machine lands on several configurations' runs, not on all of one's."""
    rows = []
    methods = [("mpm_full", None, 1.0), ("mpm_rp", None, PAPER_R_P)]
    methods += [(m.key, m.n_grid, m.r_p) for m in mpm_grid_methods(scene, PAPER_R_P, seeds[0])[0]]
    for seed in seeds:
        base = make_scene(scene, seed=seed)

        def run(method: tuple, base=base, seed=seed) -> tuple:
            key, n_grid, r_p = method
            sim = MpmSimulator(base, r_p=r_p, n_grid=n_grid, seed=seed, threads=threads)
            ro = rollout(sim, frames)
            if ro.failure:
                raise SystemExit(f"{scene} seed {seed} {key}: {ro.failure_detail}")
            return float(ro.frame_seconds(after=WARMUP).mean() * 1e3), sim, ro

        # the same bits each time; the fastest mean is the least disturbed
        results = dict(zip((key for key, _, _ in methods), round_robin(methods, repeats, run)))
        times = {key: [t for t, _, _ in res] for key, res in results.items()}
        runs = {key: res[-1][1:] for key, res in results.items()}
        ref = runs[methods[0][0]][1].fluid_positions
        for key, _, r_p in methods:
            sim, ro = runs[key]
            subs = float(ro.substeps[1 + WARMUP :].mean())
            err = float(grid_mass_error(ro.fluid_positions, ref, base.params.resolved_n_grid()).mean())
            n = sim.scene.num_particles
            rows.append(
                {"scene": scene, "seed": seed, "method": key, "n_grid": sim.scene.params.resolved_n_grid(), "r_p": r_p, "particles": n,
                 "substeps_per_frame": subs, "work": n * subs, "ms_mean": min(times[key]), "error_mean": err}
            )  # fmt: skip
    return rows


def ratios(rows: list[dict]) -> list[dict]:
    """Per scene and method: the ranges over seeds of time and error as ratios to MPM at r_p of the same seed."""
    out = []
    for scene in dict.fromkeys(r["scene"] for r in rows):
        rs = [r for r in rows if r["scene"] == scene]
        for key in dict.fromkeys(r["method"] for r in rs):
            t, e = [], []
            for r in (r for r in rs if r["method"] == key):
                rp = next(x for x in rs if x["seed"] == r["seed"] and x["method"] == "mpm_rp")
                t.append(r["ms_mean"] / rp["ms_mean"])
                e.append(r["error_mean"] / rp["error_mean"] if rp["error_mean"] > 0 else math.nan)
            one = next(r for r in rs if r["method"] == key)
            out.append(
                {"scene": scene, "method": key, "n_grid": one["n_grid"], "r_p": one["r_p"], "seeds": len(t), "time_min": min(t), "time_max": max(t),
                 "time_mean": float(np.mean(t)), "error_min": min(e), "error_max": max(e), "error_mean": float(np.mean(e)),
                 "ns_per_particle_substep": float(np.mean([r["ms_mean"] * 1e6 / r["work"] for r in rs if r["method"] == key]))}
            )  # fmt: skip
    return out


def plot(rows: list[dict]):
    """ms per frame against particles x substeps per frame, one panel per dimension (the figure)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(11, 4.4), dpi=110)
    markers = {1.0: "o", 0.75: "s", 0.5: "^"}
    for ax, dim in zip(axes, (2, 3)):
        rs = [r for r in rows if (r["n_grid"] > 0) and make_dim(r["scene"]) == dim]
        scenes = list(dict.fromkeys(r["scene"] for r in rs))
        colors = {s: f"C{i}" for i, s in enumerate(scenes)}
        base = {s: max(r["n_grid"] for r in rs if r["scene"] == s) for s in scenes}
        for r in rs:
            frac = round(r["n_grid"] / base[r["scene"]], 2)
            ax.loglog(r["work"], r["ms_mean"], markers.get(frac, "x"), color=colors[r["scene"]], mfc="none" if r["r_p"] < 1 else colors[r["scene"]], ms=6)
        if rs:
            w = np.array([r["work"] for r in rs])
            m = np.array([r["ms_mean"] for r in rs])
            k = float(np.exp(np.mean(np.log(m / w))))
            xs = np.geomspace(w.min(), w.max(), 20)
            ax.loglog(xs, k * xs, "k--", lw=0.8, label=f"{k * 1e6:.0f} ns per particle-substep")
        for s in scenes:
            ax.plot([], [], "o", color=colors[s], label=s)
        for frac, mk in markers.items():
            ax.plot([], [], mk, color="gray", label=f"grid × {frac:g}")
        ax.plot([], [], "o", color="gray", mfc="none", label="hollow: r_p = 0.571")
        from matplotlib.ticker import NullFormatter

        ax.xaxis.set_minor_formatter(NullFormatter())
        ax.set_xlabel("particles × substeps per frame")
        ax.set_ylabel("ms per frame (mean)")
        ax.set_title(f"{dim}D: MPM's cost against its work, on every grid", fontsize=10)
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=7)
    fig.tight_layout()
    return fig


def make_dim(scene: str) -> int:
    return 3 if scene.endswith("3d") else 2


def markdown(rat: list[dict]) -> str:
    lines = [
        "# Plain MPM over grids",
        "",
        "Ratios to MPM at r_p = 0.571 on the scene's grid, same seed, same run (min-max over seeds); error = mean grid-mass error against "
        "full-resolution MPM on the scene's grid.",
        "",
        "| scene | method | grid | r_p | time / MPM at r_p | error / MPM at r_p | ns per particle-substep |",
        "|---|---|---|---|---|---|---|",
    ]
    for r in rat:
        lines.append(
            f"| {r['scene']} | {r['method']} | {r['n_grid']} | {r['r_p']:.3g} | {r['time_min']:.2f}-{r['time_max']:.2f} | "
            f"{r['error_min']:.2f}-{r['error_max']:.2f} | {r['ns_per_particle_substep']:.0f} |"
        )
    lines += ["", "![cost against work](mpm_cost_grids.png)", ""]
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("scenes", nargs="*", default=list(SCENES))
    ap.add_argument("--seeds", type=int, default=3)
    ap.add_argument("--seed0", type=int, default=SEED0, help=f"the first seed (default {SEED0}: seeds no benchmark, tune or dataset uses)")
    ap.add_argument("--frames", type=int, default=400)
    ap.add_argument("--threads", type=int, default=0)
    ap.add_argument("--repeats", type=int, default=2, help="runs of each configuration, round the configurations; its time is the fastest run's mean")
    ap.add_argument("--out", default="benchmarks/results/grids")
    a = ap.parse_args()
    out = Path(a.out)
    rows: list[dict] = []
    for scene in tqdm(a.scenes, desc="scenes"):
        seeds = [a.seed0] if scene == "dam_break2d" else [a.seed0 + i for i in range(a.seeds)]
        rows += run_scene(scene, seeds, a.frames, a.threads, a.repeats)
    rat = ratios(rows)
    write_results(out, "grids", doc={"rows": rows, "ratios": rat}, markdown=markdown(rat), figures={"mpm_cost_grids.png": plot(rows)})
    print(markdown(rat))


if __name__ == "__main__":
    main()
