"""What an MPM frame costs for its size: the cost curves per particle count
and thread count, the half grid against MPM at ``r_p``, and the page's 3D
session frame (docs/engine.md, "Cost per frame").

    python benchmarks/bench_frame_cost.py curves [--repeats 3] [--out benchmarks/results/frame_cost]
    python benchmarks/bench_frame_cost.py ratios [--seeds 4100 4101 4102] [--frames 200]
    python benchmarks/bench_frame_cost.py session [--frames 300]
    python benchmarks/bench_frame_cost.py turns [--seeds 4100 4101 4102 4103] [--frames 200]

``curves``: water released as a dam break (a lattice block at 2 particles
per cell per axis, dt = 0.02·dx as in ``bench_mpm.py``), 2D from 484 to
262,144 particles and 3D from 512 to 262,144, each on one and on two threads;
both solvers of a size live in one process and their timed blocks of
``--block`` frames alternate (one thread, two threads, one, ...), so a slow
spell of the machine lands on both; every size is timed over the same frames
of its dam break (frames 4 to 4 + block · repeats). Per case: the median wall ms per frame of the engine's
``step_frame`` and ns per particle-substep, and the share of frames the
solver's mode choice gave to the team.

``ratios``: each scene's half grid (2D 64², 3D 32³, 2 particles per cell per
axis: ``MpmSimulator(scene, n_grid=...)``) against MPM at ``r_p``
(``r_p=PAPER_R_P`` on the scene's grid), two threads, blocks of 10 frames
alternating between the two over the same frames of the rollout; the ratio
is of the summed frame times (``MpmSimulator.advance``, the frame as a
session or the benchmark sees it), beside the ratio of their
particle-substeps (the work each does: the half grid holds 0.44× the
particles in 2D, 0.22× in 3D, and takes half the substeps).

``session``: dam_break3d and paddle3d at ``r_p = 1`` (the page's scenes), two
threads: frames per second of ``MpmSimulator.advance``.

``turns``: solvers stepped in turn in one process (a hybrid's two MPMs, a
server's sessions): one water2d half grid (64²) per seed, all on one thread
each and then all on two threads each (twice, in that order), one frame of
each in turn; the mean wall ms per frame. With one pool per thread count in
the process (``hybridmpm_mpm::shared_pool``) two threads cost about what one
does; with a pool per solver they cost more (docs/engine.md, "Solvers stepped
in turn").

Every mode writes ``<out>/<mode>.json`` and prints its rows; ``curves`` also
draws ``<out>/frame_cost.png`` (``--png`` another path). Timings are wall
time: compare figures only within one run, and say the load.
"""

from __future__ import annotations

import argparse
import functools
import time
from pathlib import Path

import numpy as np

from hybridmpm.bench.harness import write_results
from hybridmpm.conventions import MATERIAL_WATER
from hybridmpm.mpm import MpmParams
from hybridmpm.scenes import PAPER_R_P, Scene, lattice, make_scene
from hybridmpm.sim import MpmSimulator

#: (grid, substeps per 2.5 ms frame, lattice sides) per dimension: the grid
#: holds the largest block at 2 particles per cell per axis.
CURVES = {
    2: (512, 64, [22, 32, 45, 64, 90, 128, 181, 256, 362, 512]),
    3: (64, 8, [8, 10, 13, 16, 20, 25, 32, 40, 50, 64]),
}
#: Scenes of the half-grid ratio and their half grids.
HALF_GRID = {"water2d": 64, "sand2d": 64, "dam_break2d": 64, "water3d": 32, "sand3d": 32}


def block_scene(dim: int, side: int) -> Scene:
    """A ``side^dim`` lattice block of water at 2 particles per cell per axis, at rest."""
    n_grid, substeps, _ = CURVES[dim]
    spacing = 0.5 / n_grid
    lo = np.array((0.2, 0.05) if dim == 2 else (0.2, 0.05, 0.2))
    x = lattice(lo, lo + side * spacing, spacing)
    params = MpmParams(dim=dim, n_grid=n_grid, substeps=substeps)
    mats = np.full(len(x), MATERIAL_WATER, np.int32)
    return Scene(f"block{dim}d", params, x, mats, np.zeros_like(x), volumes=np.full(len(x), spacing**dim, np.float32))


def team_share(sim: MpmSimulator) -> float:
    """The share of the simulator's frame attempts the team of threads ran (``MpmSolver.mode_runs``)."""
    alone, team = sim.solver.mode_runs
    return team / max(alone + team, 1)


def timed(step, frames: int) -> list[float]:
    """Wall seconds of each of ``frames`` calls of ``step``."""
    out = []
    for _ in range(frames):
        t = time.perf_counter()
        step()
        out.append(time.perf_counter() - t)
    return out


def work_of(sim: MpmSimulator, work: dict[str, int], key: str) -> None:
    """``sim.advance()``, adding its particle-substeps to ``work[key]`` (an integer add after the frame)."""
    work[key] += sim.advance().substeps * sim.solver.num_particles


def curve_case(dim: int, side: int, frames: int, repeats: int) -> list[dict]:
    """One size on one and on two threads, alternating blocks of frames."""
    scene = block_scene(dim, side)
    n_grid, substeps, _ = CURVES[dim]
    sims = {t: MpmSimulator(scene, threads=t) for t in (1, 2)}
    times: dict[int, list[float]] = {1: [], 2: []}
    for s in sims.values():
        for _ in range(3):
            s.advance()
    for _ in range(repeats):
        for t, s in sims.items():
            times[t] += timed(s.advance, frames)
    rows = []
    for t, s in sims.items():
        n = s.solver.num_particles
        med = float(np.median(times[t]))
        rows.append(
            {
                "dim": dim,
                "n_grid": n_grid,
                "particles": n,
                "threads": t,
                "substeps": substeps,
                "ms_per_frame": med * 1e3,
                "ns_per_particle_substep": med * 1e9 / (substeps * n),
                "team_share": team_share(s),
            }
        )
    return rows


def curves(args) -> list[dict]:
    rows = []
    for dim, (_, _, sides) in CURVES.items():
        for side in sides:
            # every size over the same frames of its dam break (a block that
            # has spread over more frames is sparser, and costs more per particle)
            for r in curve_case(dim, side, args.block, args.repeats):
                rows.append(r)
                print(
                    f"{dim}D N={r['particles']:7d} t={r['threads']}: {r['ms_per_frame']:8.3f} ms/frame,"
                    f" {r['ns_per_particle_substep']:6.1f} ns per particle-substep, team {r['team_share']:.2f}",
                    flush=True,
                )
    return rows


def ratios(args) -> list[dict]:
    rows = []
    for name, grid in HALF_GRID.items():
        for seed in args.seeds:
            scene = make_scene(name, seed=seed)
            half = MpmSimulator(scene, n_grid=grid, seed=seed, threads=2)
            rp = MpmSimulator(scene, r_p=PAPER_R_P, seed=seed, threads=2)
            t = {"half": 0.0, "rp": 0.0}
            work = {"half": 0, "rp": 0}  # particle-substeps (each frame's, added after it: about a microsecond, both sides)
            for _ in range(args.frames // 10):
                for key, sim in (("half", half), ("rp", rp)):
                    t[key] += sum(timed(functools.partial(work_of, sim, work, key), 10))
            n = args.frames // 10 * 10
            row = {
                "scene": name,
                "seed": seed,
                "half_grid": grid,
                "half_particles": half.solver.num_particles,
                "rp_particles": rp.solver.num_particles,
                "half_ms": t["half"] / n * 1e3,
                "rp_ms": t["rp"] / n * 1e3,
                "ratio": t["half"] / t["rp"],
                "work_ratio": work["half"] / work["rp"],
                "half_team_share": team_share(half),
            }
            rows.append(row)
            print(
                f"{name} seed {seed}: half {grid} ({row['half_particles']}) {row['half_ms']:.3f} ms,"
                f" r_p ({row['rp_particles']}) {row['rp_ms']:.3f} ms, ratio {row['ratio']:.3f}"
                f" (particle-substeps {row['work_ratio']:.3f})",
                flush=True,
            )
    return rows


def session(args) -> list[dict]:
    rows = []
    for name in ("dam_break3d", "paddle3d"):
        sim = MpmSimulator(make_scene(name, seed=args.seeds[0]), seed=args.seeds[0], threads=2)
        for _ in range(5):
            sim.advance()
        t = timed(sim.advance, args.frames)
        row = {
            "scene": name,
            "particles": sim.solver.num_particles,
            "frames": args.frames,
            "fps_mean": len(t) / sum(t),
            "ms_median": float(np.median(t)) * 1e3,
            "team_share": team_share(sim),
        }
        rows.append(row)
        print(f"{name} ({row['particles']}): {row['fps_mean']:.1f} frames/s, median {row['ms_median']:.2f} ms", flush=True)
    return rows


def turns(args) -> list[dict]:
    rows = []
    for rnd in range(2):
        for threads in (1, 2):
            sims = [MpmSimulator(make_scene("water2d", seed=s), n_grid=HALF_GRID["water2d"], seed=s, threads=threads) for s in args.seeds]
            for sim in sims:
                for _ in range(5):
                    sim.advance()
            t = 0.0
            for _ in range(args.frames):
                for sim in sims:
                    t += timed(sim.advance, 1)[0]
            row = {"round": rnd, "threads": threads, "solvers": len(sims), "ms_per_frame": t / (args.frames * len(sims)) * 1e3}
            rows.append(row)
            print(f"round {rnd}: {len(sims)} water2d half grids in turn, {threads} thread(s) each: {row['ms_per_frame']:.3f} ms a frame", flush=True)
    return rows


def chart(rows: list[dict]):
    """The cost curves (ms per frame, ns per particle-substep) against particles, per dimension and thread count."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(10, 4), sharey=False)
    for ax, key, label in ((axes[0], "ms_per_frame", "ms per frame"), (axes[1], "ns_per_particle_substep", "ns per particle-substep")):
        for dim, marker in ((2, "o"), (3, "s")):
            for threads, style in ((1, "--"), (2, "-")):
                pts = sorted((r["particles"], r[key]) for r in rows if r["dim"] == dim and r["threads"] == threads)
                if pts:
                    x, y = zip(*pts, strict=True)
                    ax.plot(x, y, style, marker=marker, label=f"{dim}D, {threads} thread{'s' * (threads > 1)}")
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xlabel("particles")
        ax.set_ylabel(label)
        ax.grid(True, which="both", alpha=0.3)
    axes[0].legend()
    fig.suptitle("MPM frame cost (water dam break, 2.5 ms frames; 2D 64, 3D 8 substeps)")
    fig.tight_layout()
    return fig


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("mode", choices=("curves", "ratios", "session", "turns"))
    ap.add_argument("--repeats", type=int, default=3, help="curves: timed blocks per thread count")
    ap.add_argument("--frames", type=int, default=200, help="ratios, session, turns: frames")
    ap.add_argument("--block", type=int, default=8, help="curves: frames per timed block")
    ap.add_argument("--seeds", type=int, nargs="+", default=[4100, 4101, 4102])
    ap.add_argument("--out", default="benchmarks/results/frame_cost")
    ap.add_argument("--png", default=None, help="curves: the chart's path (default <out>/frame_cost.png)")
    args = ap.parse_args()
    rows = {"curves": curves, "ratios": ratios, "session": session, "turns": turns}[args.mode](args)
    out = Path(args.out)
    figures = {}
    if args.mode == "curves":
        figures[str(Path(args.png).resolve()) if args.png else "frame_cost.png"] = chart(rows)
    write_results(out, args.mode, doc={"rows": rows}, figures=figures, dpi=100)  # the load is in the provenance


if __name__ == "__main__":
    main()
