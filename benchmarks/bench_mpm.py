"""MPM solver benchmark: wall time per frame and per substep for the standard
scenes, scaling with particle count and threads, grid-size independence,
memory per particle, and (optionally) Taichi's CPU backend in the same run.

    python benchmarks/bench_mpm.py [--quick] [--taichi] [--out benchmarks/results]

Scenes (particles on a lattice at spacing dx/2, zero velocity, released as a
dam break; the same as benchmarks/taichi_peer.py):
  water2d   4096 water, 128², origin (0.1, 0.1), 16 substeps per 2.5 ms frame
  sand2d    4096 sand, same
  water3d   4096 water, 64³, origin (0.3, 0.1, 0.3), 8 substeps
  water3d_128  4096 water at 2 per cell on 128³ (8x the domain's cells), 16 substeps (dx halves); compare per substep
  water3d_32k  32768 water, 64³, origin (0.25, 0.1, 0.25), 8 substeps
  sand3d    4096 sand, 64³, 8 substeps
  water_sand2d  the water2d block, its left half water and its right half sand
Targets are checked from these rows: sand against water at equal
particle count, water+sand against the average of the two, one thread
against two. Scaling runs 1k-262k particles in 2D and 3D, each case in a
fresh process (time, and memory as the growth of its resident set).
Timing: 5 warm-up frames, then the median and p95 of per-frame wall times;
start-up is excluded (as the paper's App. C does for Taichi).
"""

from __future__ import annotations

import argparse
import collections
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np

from hybridmpm.bench.harness import load_average, round_robin, write_results
from hybridmpm.conventions import MATERIAL_SAND, MATERIAL_WATER
from hybridmpm.mpm import MpmParams
from hybridmpm.scenes import Scene, lattice
from hybridmpm.sim import MpmSimulator, rollout

SCENES = {
    # name: (dim, n_grid, origin, side, material, substeps, spacing in units of 1/64 or 1/128 -> see make)
    "water2d": (2, 128, (0.1, 0.1), 64, MATERIAL_WATER, 16),
    "sand2d": (2, 128, (0.1, 0.1), 64, MATERIAL_SAND, 16),
    "water3d": (3, 64, (0.3, 0.1, 0.3), 16, MATERIAL_WATER, 8),
    # the same 4096 particles (2 per cell per dimension) in a domain of 8x the volume
    "water3d_128": (3, 128, (0.3, 0.1, 0.3), 16, MATERIAL_WATER, 16),
    "water3d_32k": (3, 64, (0.25, 0.1, 0.25), 32, MATERIAL_WATER, 8),
    "sand3d": (3, 64, (0.3, 0.1, 0.3), 16, MATERIAL_SAND, 8),
    # water and sand in one grid: the left half of the block water, the right half sand
    "water_sand2d": (2, 128, (0.1, 0.1), 64, (MATERIAL_WATER, MATERIAL_SAND), 16),
}

# Scaling cases: (dim, n_grid, substeps per frame, lattice sides). The grid is
# large enough for the biggest block at 2 particles per cell per dimension;
# substeps keep dt = 0.02·dx as in the standard scenes.
SCALING = {
    2: (512, 64, [32, 64, 128, 256, 512]),
    3: (64, 8, [10, 20, 32, 40, 64]),
}


def make(dim, n_grid, origin, side, material, substeps, threads):
    """Particles on a lattice at spacing dx/2 (2 per cell per dimension).

    water3d_128 has the same particle count and substeps as water3d on a grid
    of 8x the cells: the same occupied cells in a larger domain, so equal cost
    means the cost does not follow the domain volume."""
    spacing = 0.5 / n_grid
    lo = np.array(origin)
    x = lattice(lo, lo + side * spacing, spacing)
    params = MpmParams(dim=dim, n_grid=n_grid, substeps=substeps)
    if isinstance(material, tuple):
        # (left, right): split at the block's middle along x
        mats = np.where(x[:, 0] < lo[0] + 0.5 * side * spacing, material[0], material[1]).astype(np.int32)
    else:
        mats = np.full(len(x), material, np.int32)
    scene = Scene(f"bench{dim}d", params, x, mats, np.zeros_like(x), volumes=np.full(len(x), spacing**dim, np.float32))
    return MpmSimulator(scene, threads=threads)


def time_frames(sim, frames, warmup=5):
    """Median and p95 wall ms per frame over ``frames`` frames after ``warmup``."""
    start = sim.frame.frame_index  # read before the rollout advances it
    t = rollout(sim, warmup + frames).frame_seconds(after=start + warmup)
    return float(np.median(t) * 1e3), float(np.percentile(t, 95) * 1e3)


def team_share(sim):
    """The share of a simulator's frame attempts that its team of threads ran
    (the rest ran on the calling thread alone, as the solver's mode choice
    decided: ``MpmSolver.mode_runs``); None if it made none."""
    alone, team = sim.solver.mode_runs
    return team / (alone + team) if alone + team else None


def rss_mb():
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmRSS"):
            return int(line.split()[1]) / 1024
    return float("nan")


def frame_loop_isa():
    """The instruction set of the frame loop's copy the solver chose for this CPU (docs/engine.md, "Two compiled copies")."""
    return make(*SCENES["water2d"], 1).solver.isa


def scaling_case(dim, side, threads, frames):
    """One scaling case (run in a fresh process by ``scaling``): water
    released as a dam break; ms per frame and the growth of the resident set
    from before the scene is built to after the timed frames (state, the g2p
    double buffer, the sort, the grid blocks and the thread pool)."""
    n_grid, substeps, _ = SCALING[dim]
    origin = (0.2, 0.05) if dim == 2 else (0.2, 0.05, 0.2)
    before = rss_mb()
    sim = make(dim, n_grid, origin, side, MATERIAL_WATER, substeps, threads)
    med, _ = time_frames(sim, frames, warmup=2)
    n = sim.particles.num_fluid
    grown = rss_mb() - before
    return {
        "dim": dim,
        "n_grid": n_grid,
        "particles": n,
        "threads": threads,
        "substeps": substeps,
        "ms_per_frame": med,
        "us_per_substep": med * 1e3 / substeps,
        "ns_per_particle_substep": med * 1e6 / substeps / n,
        "rss_mb": grown,
        "bytes_per_particle": grown * 2**20 / n,
    }


def scaling(frames, quick):
    """Every scaling case in its own process (so that memory is measured from
    a clean heap); returns their rows."""
    rows = []
    for dim, (_, _, sides) in SCALING.items():
        for side in sides[:-1] if quick else sides:
            for threads in (1, 2):
                here = str(Path(__file__).parent)
                code = f"import json, sys; sys.path.insert(0, {here!r}); import bench_mpm as b; print(json.dumps(b.scaling_case({dim}, {side}, {threads}, {frames})))"
                r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
                if r.returncode != 0:
                    raise RuntimeError(f"scaling case dim={dim} side={side} threads={threads} failed: {r.stderr[-2000:]}")
                row = json.loads(r.stdout.strip().splitlines()[-1])
                rows.append(row)
                print(
                    f"scaling {dim}D N={row['particles']:7d} t={threads}: {row['us_per_substep']:9.1f} us/substep,"
                    f" {row['ns_per_particle_substep']:5.1f} ns per particle-substep, {row['bytes_per_particle']:6.0f} B/particle",
                    flush=True,
                )
    return rows


def targets(rows):
    """The speed targets' ratios from the standard scenes (same run): sand / water at
    equal particle count, water+sand / the average of water and sand, and one
    thread / two threads."""
    ms = {(x["scene"], x["threads"]): x["ms_per_frame"] for x in rows}
    out = []
    for t in (1, 2):
        for dim in (2, 3):
            w, sd = ms.get((f"water{dim}d", t)), ms.get((f"sand{dim}d", t))
            if w and sd:
                out.append({"check": f"sand{dim}d / water{dim}d", "threads": t, "value": sd / w, "target": "≤ 1.3"})
        w, sd, mix = ms.get(("water2d", t)), ms.get(("sand2d", t)), ms.get(("water_sand2d", t))
        if w and sd and mix:
            out.append({"check": "water_sand2d / mean(water2d, sand2d)", "threads": t, "value": mix / (0.5 * (w + sd)), "target": "≤ 1.0"})
    for name in SCENES:
        one, two = ms.get((name, 1)), ms.get((name, 2))
        if one and two:
            out.append({"check": f"{name}: 1 thread / 2 threads", "threads": 2, "value": one / two, "target": "≤ 1.6"})
    return out


PEER_SCENES = {"water2d": "water2d", "sand2d": "sand2d", "water3d": "water3d_4k", "water3d_32k": "water3d_32k"}


def run_taichi_one(scene, threads, frames):
    """One Taichi (serial-p2g variant) run in a subprocess; returns its row."""
    script = Path(__file__).with_name("taichi_peer.py")
    out = Path(f"/tmp/taichi_peer_{os.getpid()}.json")
    cmd = [sys.executable, str(script), "--scenes", scene, "--threads", str(threads), "--variants", "serial", "--frames", str(frames), "--json", str(out)]
    r = subprocess.run(cmd, capture_output=True, text=True)
    if r.returncode != 0 or not out.exists():
        print("taichi peer failed:", r.stderr[-2000:], file=sys.stderr)
        return None
    rows = json.loads(out.read_text())["results"]
    return rows[0] if rows else None


def peer_comparison(frames, repeats):
    """Ours and Taichi's strongest variant, alternated back to back, `repeats`
    times per (scene, threads); each side keeps its lowest median (the least
    disturbed run on a shared machine)."""
    table = []
    for ours_name, peer_name in PEER_SCENES.items():
        spec = SCENES[ours_name]
        for threads in (1, 2):

            def one(side, spec=spec, threads=threads, peer_name=peer_name):
                if side == "ours":
                    sim = make(*spec, threads)
                    return (*time_frames(sim, frames), team_share(sim))
                row = run_taichi_one(peer_name, threads, frames)
                return (row["median_ms"], row["p95_ms"]) if row else None

            ours, peer = round_robin(["ours", "taichi"], repeats, one)
            best_ours = min(ours, key=lambda x: x[0])
            best_peer = min((p for p in peer if p), key=lambda x: x[0], default=None)
            entry = {
                "scene": ours_name,
                "threads": threads,
                "substeps": spec[5],
                "ours_ms": best_ours[0],
                "ours_p95_ms": best_ours[1],
                "ours_team_share": best_ours[2],
            }
            if best_peer:
                entry.update(taichi_ms=best_peer[0], taichi_p95_ms=best_peer[1], speedup=best_peer[0] / best_ours[0])
            table.append(entry)
            print(
                f"peer {ours_name:12s} t={threads}: ours {best_ours[0]:.2f} ms, taichi {entry.get('taichi_ms', float('nan')):.2f} ms,"
                f" ratio {entry.get('speedup', float('nan')):.2f}x",
                flush=True,
            )
    return table


def _ours_in(python, scene, threads, frames):
    """``time_frames`` of ``scene`` in a subprocess of ``python`` (a virtual
    environment's interpreter, with its own build of the engine) on the
    ``bench_mpm.py`` beside this file; returns (median ms, team share)."""
    code = (
        f"import sys, json; sys.path.insert(0, {str(Path(__file__).parent)!r}); import bench_mpm as b; "
        f"sim = b.make(*b.SCENES[{scene!r}], {threads}); m, _ = b.time_frames(sim, {frames}); print(json.dumps([m, b.team_share(sim)]))"
    )
    r = subprocess.run([python, "-c", code], capture_output=True, text=True)
    if r.returncode != 0:
        print(f"{python} failed:", r.stderr[-2000:], file=sys.stderr)
        return None
    return tuple(json.loads(r.stdout.strip().splitlines()[-1]))


def builds_against_taichi(other_python, rounds=9, frames=100, scene="water2d", threads=2):
    """Two builds of the engine and Taichi's serial-p2g variant on ``scene``,
    in turn (the order rotated every round), each run in its own subprocess:
    this environment's build, the one of ``other_python`` (say
    ``/work/main/.venv/bin/python``) and Taichi. Prints each round's times,
    the load and the per-round ratios to Taichi (Taichi's time moves between
    regimes from run to run: compare within a round)."""
    sides = {
        "this": lambda: _ours_in(sys.executable, scene, threads, frames),
        "other": lambda: _ours_in(other_python, scene, threads, frames),
        "taichi": lambda: (row["median_ms"], None) if (row := run_taichi_one(PEER_SCENES[scene], threads, frames)) else None,
    }
    names = list(sides)
    rows = []
    for r in range(rounds):
        load = load_average()[0]
        order = names[r % 3 :] + names[: r % 3]
        got = {k: sides[k]() for k in order}
        if any(v is None for v in got.values()):
            continue
        row = {"round": r, "load": load, **{f"{k}_ms": v[0] for k, v in got.items()}, "this_team": got["this"][1], "other_team": got["other"][1]}
        rows.append(row)
        print(
            f"round {r} load {load:.2f}: this {row['this_ms']:.3f} ms (team {_share(row['this_team'])}), other {row['other_ms']:.3f} ms"
            f" (team {_share(row['other_team'])}), taichi {row['taichi_ms']:.3f} ms; ratios this {row['this_ms'] / row['taichi_ms']:.3f},"
            f" other {row['other_ms'] / row['taichi_ms']:.3f}",
            flush=True,
        )
    return rows


def isa_comparison(frames, repeats):
    """The frame loop's portable copy against the one the solver chose for
    this CPU (``MpmSolver.isa``; docs/engine.md, "Two compiled copies"), one
    thread, alternated back to back ``repeats`` times per scene; each keeps
    its lowest median. Empty when the CPU runs only the portable copy."""
    chosen = make(*SCENES["water2d"], 1).solver.isa
    if chosen == "baseline":
        return []
    table = []
    for name, spec in SCENES.items():

        def one(isa, spec=spec):
            sim = make(*spec, 1)
            sim.solver.set_isa(isa)
            return time_frames(sim, frames)[0]

        best = dict(zip(("baseline", chosen), map(min, round_robin(["baseline", chosen], repeats, one))))
        table.append({"scene": name, "isa": chosen, "baseline_ms": best["baseline"], "isa_ms": best[chosen], "ratio": best[chosen] / best["baseline"]})
        print(f"isa {name:12s}: baseline {best['baseline']:.2f} ms, {chosen} {best[chosen]:.2f} ms, ratio {best[chosen] / best['baseline']:.3f}", flush=True)
    return table


def _share(x):
    return "–" if x is None else f"{100 * x:.0f}%"


def markdown(r):
    lines = [
        "# MPM solver benchmark",
        "",
        "- the machine is shared and noisy (±30%): compare only within one run",
        f'- frame loop: the copy compiled for {r.get("frame_loop_isa", "baseline")} (docs/engine.md, "Two compiled copies")',
        f"- {r['frames']} timed frames after 5 warm-up frames; a frame is 2.5 ms of simulated time;"
        f" every case the lowest median of {r.get('repeats', 1)} repeats (the standard scenes taken in turn)",
        "",
        "## Standard scenes",
        "",
        "Team: the share of the case's frame attempts (warm-up included) run by the pool's team of threads; the rest ran on the calling thread alone, "
        'which the solver\'s mode choice picks when the team measured slower (docs/engine.md, "A busy machine").',
        "",
        "| scene | threads | particles | substeps/frame | median ms/frame | p95 ms/frame | µs/substep | team |",
        "|---|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for x in r["rows"]:
        lines.append(
            f"| {x['scene']} | {x['threads']} | {x['particles']} | {x['substeps']} | {x['ms_per_frame']:.2f} | {x['p95_ms_per_frame']:.2f} | {x['us_per_substep']:.0f} |"
            f" {_share(x.get('team_share'))} |"
        )
    if r["taichi"]:
        lines += [
            "",
            "## Against Taichi's strongest CPU variant (serial p2g), alternated back to back",
            "",
            "| scene | threads | substeps | hybridmpm ms/frame | Taichi ms/frame | Taichi / hybridmpm | hybridmpm team |",
            "|---|---:|---:|---:|---:|---:|---:|",
        ]
        for x in r["taichi"]:
            lines.append(
                f"| {x['scene']} | {x['threads']} | {x['substeps']} | {x['ours_ms']:.2f} | {x.get('taichi_ms', float('nan')):.2f} | {x.get('speedup', float('nan')):.2f} |"
                f" {_share(x.get('ours_team_share'))} |"
            )
    if r.get("isa"):
        lines += [
            "",
            "## The frame loop's two compiled copies, one thread, alternated back to back",
            "",
            "The same source compiled for the portable x86-64 baseline and for the CPU's instruction set; the same bits (tested).",
            "",
            "| scene | baseline ms/frame | chosen copy | its ms/frame | ratio |",
            "|---|---:|---|---:|---:|",
        ]
        for x in r["isa"]:
            lines.append(f"| {x['scene']} | {x['baseline_ms']:.2f} | {x['isa']} | {x['isa_ms']:.2f} | {x['ratio']:.3f} |")
    lines += [
        "",
        "## Targets, from the standard scenes above",
        "",
        "| check | threads | value | target |",
        "|---|---:|---:|---|",
    ]
    for x in r.get("targets", []):
        lines.append(f"| {x['check']} | {x['threads']} | {x['value']:.2f} | {x['target']} |")
    lines += [
        "",
        "## Scaling with particle count and threads (water)",
        "",
        "Each case in a fresh process; memory is the growth of its resident set (state, the g2p "
        "double buffer, the sort, the grid blocks and, for the smallest cases mostly, the thread pool and the block index).",
        "",
        "| dim | grid | particles | threads | substeps | ms/frame | µs/substep | ns per particle-substep | bytes per particle |",
        "|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for x in r["scaling"]:
        lines.append(
            f"| {x['dim']} | {x['n_grid']} | {x['particles']} | {x['threads']} | {x['substeps']} | {x['ms_per_frame']:.2f} | {x['us_per_substep']:.0f} | {x['ns_per_particle_substep']:.0f} | {x['bytes_per_particle']:.0f} |"
        )
    mem = r["memory"]
    lines += [
        "",
        f"Memory: {mem['bytes_per_particle']:.0f} bytes per 2D particle (RSS growth for {mem['particles']} particles after one frame: state, the g2p double buffer, the sort and the grid blocks).",
    ]
    return "\n".join(lines) + "\n"


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="fewer frames and cases")
    ap.add_argument("--taichi", action="store_true", help="also time benchmarks/taichi_peer.py back to back")
    ap.add_argument(
        "--repeats", type=int, default=5, help="repeats of every case (the standard scenes in turn; ours and the peer alternated); each keeps its lowest median"
    )
    ap.add_argument("--frames", type=int, default=40)
    ap.add_argument("--out", default="benchmarks/results")
    args = ap.parse_args()
    frames = 15 if args.quick else args.frames
    out = Path(args.out)
    # the standard scenes taken in turn `repeats` times (a slow moment of the
    # machine then hits one repeat of several cases, not every repeat of one);
    # each case keeps its lowest median, as the peer rows do
    cases = [(name, spec, threads) for name, spec in SCENES.items() for threads in (1, 2)]
    done: collections.Counter = collections.Counter()

    def run_case(case):
        name, spec, threads = case
        sim = make(*spec, threads)
        med, p95 = time_frames(sim, frames)
        done[name, threads] += 1
        print(
            f"{name:12s} t={threads} N={sim.particles.num_fluid:6d}  {med:7.2f} ms/frame (p95 {p95:7.2f})  {med * 1e3 / spec[5]:8.1f} us/substep  (repeat {done[name, threads]})",
            flush=True,
        )
        return {
            "scene": name,
            "threads": threads,
            "particles": sim.particles.num_fluid,
            "substeps": spec[5],
            "ms_per_frame": med,
            "p95_ms_per_frame": p95,
            "us_per_substep": med * 1e3 / spec[5],
            "team_share": team_share(sim),
        }

    rows = [min(runs, key=lambda x: x["ms_per_frame"]) for runs in round_robin(cases, args.repeats, run_case)]

    # at least 20 frames: a solver's first frames measure both ways of running (see docs/engine.md)
    scaling_rows = scaling(max(20, frames // 2), args.quick)

    # memory per particle: RSS growth for 1M 2D particles (state + scratch after a frame)
    before = rss_mb()
    big = make(2, 2048, (0.1, 0.1), 1000, MATERIAL_WATER, 1, 0)
    big.advance()
    mem = {"particles": big.particles.num_fluid, "rss_mb": rss_mb() - before}
    mem["bytes_per_particle"] = mem["rss_mb"] * 2**20 / big.particles.num_fluid
    del big
    print(f"memory: {mem['bytes_per_particle']:.0f} bytes per 2D particle (1M particles)")

    taichi = peer_comparison(frames, args.repeats) if args.taichi else []
    isa_rows = isa_comparison(frames, args.repeats)

    result = {
        "frame_loop_isa": frame_loop_isa(),
        "frames": frames,
        "repeats": args.repeats,
        "rows": rows,
        "scaling": scaling_rows,
        "targets": targets(rows),
        "memory": mem,
        "taichi": taichi,
        "isa": isa_rows,
    }
    write_results(out, "mpm", doc=result, markdown=markdown(result))
    print(f"wrote {out / 'mpm.json'} and {out / 'mpm.md'}")


if __name__ == "__main__":
    main()
