"""Benchmark: hybridmpm._core.radius_graph vs the scipy cKDTree path.

Both sides produce the same outputs: directed edges with self-edges, sorted by
receiver then sender (int64), displacement p[sender] - p[receiver] (float32,
[E, D]) and distance (float32, [E]). The scipy path is

    pairs = cKDTree(pos).query_pairs(R, output_type="ndarray")
    + both directions + self edges (np.concatenate), np.lexsort by (receiver, sender)
    + displacement / distance with numpy.

Cases (as the criterion bench rust/bench/benches/radius_graph.rs):
  2D: 64x64 lattice, spacing 0.005, deterministic jitter, R = 0.015 (4096 particles)
  3D: 32^3 lattice, spacing 0.5/64, deterministic jitter, R = 2.5 spacing (32768)
  3D shuffled: the 3D cloud in a random particle order

Each thread count runs in its own subprocess (RAYON_NUM_THREADS=1, 2); inside
it the two implementations are timed alternately (interleaved repeats) and the
medians are compared.

Usage:
    python benchmarks/bench_radius_graph.py [--threads 1 2] [--reps-2d 61] [--reps-3d 21]
        [--out benchmarks/results/radius_graph.md]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from hybridmpm.bench.harness import write_results


def _jitter_stream(seed: int, count: int) -> np.ndarray:
    """The LCG of the criterion bench: s = s*1664525 + 1013904223 (mod 2^32)."""
    out = np.empty(count, np.float32)
    s = seed
    for i in range(count):
        s = (s * 1664525 + 1013904223) & 0xFFFFFFFF
        out[i] = np.float32(s >> 8) / np.float32(1 << 24) - np.float32(0.5)
    return out


def case_2d() -> tuple[np.ndarray, float]:
    h = np.float32(0.005)
    j = _jitter_stream(1, 64 * 64 * 2).reshape(64, 64, 2)  # [y, x, (jx, jy)]
    y, x = np.meshgrid(np.arange(64, dtype=np.float32), np.arange(64, dtype=np.float32), indexing="ij")
    c = np.float32(0.2)
    px = np.float32(0.1) + (x + c * j[..., 0]) * h
    py = np.float32(0.1) + (y + c * j[..., 1]) * h
    return np.stack([px, py], -1).reshape(-1, 2).astype(np.float32), 0.015


def case_3d() -> tuple[np.ndarray, float]:
    h = np.float32(0.5) / np.float32(64.0)
    j = _jitter_stream(2, 32**3 * 3).reshape(32, 32, 32, 3)  # [z, y, x, (jx, jy, jz)]
    z, y, x = np.meshgrid(*(np.arange(32, dtype=np.float32),) * 3, indexing="ij")
    c = np.float32(0.2)
    comps = [np.float32(0.1) + (g + c * j[..., k]) * h for k, g in enumerate((x, y, z))]
    return np.stack(comps, -1).reshape(-1, 3).astype(np.float32), float(np.float32(2.5) * h)


def scipy_path(pos: np.ndarray, r: float):
    from scipy.spatial import cKDTree

    n = len(pos)
    pairs = cKDTree(pos).query_pairs(r, output_type="ndarray")
    ar = np.arange(n, dtype=np.int64)
    s = np.concatenate([pairs[:, 0], pairs[:, 1], ar])
    rv = np.concatenate([pairs[:, 1], pairs[:, 0], ar])
    order = np.lexsort((s, rv))
    s = s[order]
    rv = rv[order]
    disp = pos[s] - pos[rv]
    dist = np.sqrt(np.einsum("ij,ij->i", disp, disp))
    return s, rv, disp, dist


def ours(pos: np.ndarray, r: float):
    from hybridmpm import _core

    return _core.radius_graph(pos, r)


def worker(reps_2d: int, reps_3d: int) -> dict:
    results = []
    p3, r3 = case_3d()
    # Same cloud with the particle order shuffled: neighbour indices are no
    # longer spatially coherent (as after particles have mixed).
    shuffled = (p3[np.random.default_rng(0).permutation(len(p3))], r3)
    cases = (
        ("2D", case_2d(), reps_2d),
        ("3D", (p3, r3), reps_3d),
        ("3D shuffled", shuffled, reps_3d),
    )
    for name, (pos, r), reps in cases:
        a = ours(pos, r)
        b = scipy_path(pos, r)
        same_edges = np.array_equal(a[0], b[0]) and np.array_equal(a[1], b[1])
        if same_edges:
            np.testing.assert_array_equal(a[2], b[2])
            np.testing.assert_allclose(a[3], b[3], rtol=1e-6)
        del a, b
        t_ours, t_scipy = [], []
        for k in range(reps):
            # Interleaved, alternating which goes first.
            fns = [(ours, t_ours), (scipy_path, t_scipy)]
            for fn, acc in fns if k % 2 == 0 else fns[::-1]:
                t0 = time.perf_counter()
                out = fn(pos, r)
                acc.append(time.perf_counter() - t0)
                del out
        results.append(
            {
                "case": name,
                "n": len(pos),
                "dim": pos.shape[1],
                "radius": r,
                "edges": int(len(ours(pos, r)[0])),
                "same_edges": bool(same_edges),
                "reps": reps,
                "ours_ms": float(np.median(t_ours) * 1e3),
                "ours_min_ms": float(np.min(t_ours) * 1e3),
                "scipy_ms": float(np.median(t_scipy) * 1e3),
                "scipy_min_ms": float(np.min(t_scipy) * 1e3),
            }
        )
    return {"threads": os.environ.get("RAYON_NUM_THREADS", "default"), "results": results}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--threads", type=int, nargs="+", default=[1, 2])
    ap.add_argument("--reps-2d", type=int, default=61)
    ap.add_argument("--reps-3d", type=int, default=21)
    ap.add_argument("--out", default=None, help="markdown file to write the table to (FILE.md)")
    ap.add_argument("--worker", action="store_true", help=argparse.SUPPRESS)
    args = ap.parse_args()

    if args.worker:
        print(json.dumps(worker(args.reps_2d, args.reps_3d)))
        return

    runs = []
    for t in args.threads:
        # OpenBLAS (loaded by numpy) is not used by either path; one thread
        # keeps its idle workers from competing for the cores.
        env = dict(os.environ, RAYON_NUM_THREADS=str(t), OPENBLAS_NUM_THREADS="1")
        cmd = [sys.executable, __file__, "--worker", "--reps-2d", str(args.reps_2d), "--reps-3d", str(args.reps_3d)]
        res = subprocess.run(cmd, env=env, capture_output=True, text=True, check=True)
        runs.append(json.loads(res.stdout.strip().splitlines()[-1]))

    import scipy

    lines = [
        "| case | N | edges E | rayon threads | hybridmpm median [ms] | scipy path median [ms] | speedup (median) | speedup (min) |",
        "|---|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for run in runs:
        for r in run["results"]:
            lines.append(
                f"| {r['case']} | {r['n']} | {r['edges']} | {run['threads']} | {r['ours_ms']:.2f} | "
                f"{r['scipy_ms']:.1f} | {r['scipy_ms'] / r['ours_ms']:.1f}x | "
                f"{r['scipy_min_ms'] / r['ours_min_ms']:.1f}x |"
            )
    table = "\n".join(lines)
    notes = []
    for run in runs:
        for r in run["results"]:
            if not r["same_edges"]:
                notes.append(f"- NOTE: {r['case']} ({run['threads']} threads): edge arrays differ from scipy's.")
    print(table)
    print("\n".join(notes))

    if args.out:
        md = f"""# Radius graph: hybridmpm vs scipy cKDTree

scipy {scipy.__version__}.

Both sides return the same arrays: int64 senders/receivers with self-edges,
sorted by receiver then sender, float32 displacement `p[s] - p[r]` [E, D] and
float32 distance [E] (checked equal before timing). The scipy path is
`cKDTree(pos).query_pairs(R, output_type='ndarray')` + both directions + self
edges (`np.concatenate`) + `np.lexsort` + numpy displacement / distance; it is
single-threaded. Each thread count runs in its own process
(`RAYON_NUM_THREADS`, `OPENBLAS_NUM_THREADS=1`); inside it the two are timed alternately
({args.reps_2d} repeats for 2D, {args.reps_3d} for 3D) and the medians compared.
Timings include everything a caller pays: for hybridmpm the input copy and
the allocation and first touch of the output arrays, for scipy the tree
build. On a shared machine (see the load average) repeated runs vary; the
"min" column compares the least disturbed repeats.

Cases (as `rust/bench/benches/radius_graph.rs`): 2D = 64x64 lattice,
spacing 0.005, jitter +-0.1 spacing, R = 0.015; 3D = 32^3 lattice, spacing
0.5/64, jitter +-0.1 spacing, R = 2.5 spacing; "3D shuffled" = the 3D cloud
in a random particle order (indices no longer spatially coherent).

{table}
{chr(10).join(notes)}
"""
        out = Path(args.out)
        write_results(out.parent, out.stem, markdown=md)
        print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
