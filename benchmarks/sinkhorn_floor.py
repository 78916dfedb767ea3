"""The floor of the Sinkhorn divergence's point reduction: what it scores where the answer is (nearly) 0.

A set of more than ``SINKHORN_MAX_POINTS`` particles is reduced before Sinkhorn's iterations
(:mod:`hybridmpm.metrics.transport`). Two rules are measured against each other and against the
divergence of the whole sets (no reduction, the truth; slow):

* ``index``: a fixed-seed draw of 300 particle indices (masses renormalised),
  re-implemented here for comparison only;
* ``lattice``: the shipped rule (:func:`~hybridmpm.metrics.transport.bin_width`,
  :func:`~hybridmpm.metrics.transport.binned_set`): the cells of a lattice shared by both sets,
  each a point at its mass-weighted centroid.

Cases: 2,000 particles of a block (2D 50×40 at 0.01 m, 3D 20×10×10 at 0.025 m) against a random
permutation of themselves (the same distribution: 0), and against the block plus 7 particles drawn
inside it (nearly the same); then the realistic signal, water2d's
MPM at ``r_p`` (and full resolution from a start moved by N(0, 1 µm), the jitter) against
full-resolution MPM, 400 frames, seeds 1000-1002, as ``benchmarks/metric_floor.py`` scores them.

    python benchmarks/sinkhorn_floor.py               # a few minutes on 2 cores
    python benchmarks/sinkhorn_floor.py --exact       # and the whole sets (one draw, the first seed): ~30 min more
"""

from __future__ import annotations

import argparse
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
from threadpoolctl import threadpool_limits

from hybridmpm.bench.harness import table, write_results
from hybridmpm.metrics import SINKHORN_BLUR, SINKHORN_MAX_POINTS, sinkhorn_frames, sinkhorn_series
from hybridmpm.metrics.transport import entropic_ot, self_ot

ROOT = Path(__file__).resolve().parents[1]


def index_series(pred: np.ndarray, ref: np.ndarray, pw: np.ndarray, rw: np.ndarray, max_points: int = SINKHORN_MAX_POINTS) -> np.ndarray:
    """The index draw: ``max_points`` indices drawn once with seed 0 (all of a smaller set), masses renormalised."""

    def pick(n: int) -> np.ndarray:
        return np.arange(n) if n <= max_points else np.sort(np.random.default_rng(0).choice(n, max_points, replace=False))

    ip, ir = pick(pred.shape[1]), pick(ref.shape[1])
    a, c = pw[ip] / pw[ip].sum(), rw[ir] / rw[ir].sum()
    eps = SINKHORN_BLUR**2
    out = []
    with threadpool_limits(limits=1, user_api="blas"):
        for t in range(pred.shape[0]):
            x, y = pred[t][ip].astype(np.float64), ref[t][ir].astype(np.float64)
            out.append(max(entropic_ot(x, y, a, c, eps) - 0.5 * (self_ot(x, a, eps) + self_ot(y, c, eps)), 0.0))
    return np.array(out)


def score(rule: str, pred: np.ndarray, ref: np.ndarray, pw: np.ndarray, rw: np.ndarray) -> tuple[float, float]:
    """(mean divergence [m²], seconds) of ``pred`` [F, N, D] against ``ref`` [F, M, D] under ``rule``."""
    t0 = time.perf_counter()
    if rule == "index":
        v = index_series(pred, ref, pw, rw)
    elif rule == "lattice":
        v = sinkhorn_series(pred, ref, pw, rw)
    else:  # the whole sets
        v = sinkhorn_series(pred, ref, pw, rw, max_points=max(pred.shape[1], ref.shape[1]))
    return float(np.mean(v)), time.perf_counter() - t0


def block(n_side: tuple[int, ...], lo: float, spacing: float) -> np.ndarray:
    axes = [lo + spacing * (np.arange(k) + 0.5) for k in n_side]
    return np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, len(n_side))


def synthetic(rules: list[str], draws: int) -> list[dict]:
    rows = []
    for dim, x in (("2D", block((50, 40), 0.1, 0.01)), ("3D", block((20, 10, 10), 0.1, 0.025))):
        w = np.ones(len(x))
        for case in ("permutation", "block + 7"):
            for s in range(draws):
                rng = np.random.default_rng(s)
                if case == "permutation":
                    perm = rng.permutation(len(x))
                    y, wy = x[perm], w[perm]
                else:
                    y = np.concatenate([x, x.min(0) + rng.uniform(0, 1, (7, x.shape[1])) * (x.max(0) - x.min(0))])
                    wy = np.ones(len(y))
                for rule in rules:
                    if rule == "exact" and (case == "permutation" or s > 0):
                        continue  # the whole sets take minutes: one draw of the block + 7, a permutation is 0 by construction
                    v, sec = score(rule, x[None], y[None], w, wy)
                    rows.append({"dim": dim, "case": case, "draw": s, "rule": rule, "sinkhorn": v, "seconds": sec})
                    print(f"{dim} {case} draw {s} {rule}: {v:.3g} m² ({sec:.1f} s)", flush=True)
    return rows


def water(rules: list[str], seeds: list[int], frames: int, r_p: float, exact_seeds: int) -> list[dict]:
    from hybridmpm.scenes import make_scene
    from hybridmpm.sim import MpmSimulator, rollout

    rows = []
    for seed in seeds:
        full = make_scene("water2d", seed=seed, frames=frames)
        jittered = replace(full, positions=full.positions + np.random.default_rng(seed).normal(0.0, 1e-6, full.positions.shape).astype(np.float32))
        runs = {}
        for label, scene, rp in (("ref", full, 1.0), ("jitter", jittered, 1.0), ("mpm_rp", full, r_p)):
            ro = rollout(MpmSimulator(scene, r_p=rp, seed=seed, threads=1), frames)
            sel = sinkhorn_frames(ro.frame_index)
            runs[label] = (ro.fluid_positions[sel], ro.masses[: ro.num_fluid])
        ref, rw = runs["ref"]
        perm = np.random.default_rng(seed).permutation(ref.shape[1])
        runs["permuted reference"] = (ref[:, perm], rw[perm])
        for label in ("mpm_rp", "jitter", "permuted reference"):
            pos, pw = runs[label]
            for rule in rules:
                if rule == "exact" and (label == "permuted reference" or seed not in seeds[:exact_seeds]):
                    continue
                v, sec = score(rule, pos, ref, pw, rw)
                rows.append({"seed": seed, "run": label, "rule": rule, "sinkhorn": v, "seconds": sec, "particles": [int(pos.shape[1]), int(ref.shape[1])]})
                print(f"water2d seed {seed} {label} {rule}: {v:.3g} m² ({sec:.1f} s)", flush=True)
    return rows


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--exact", action="store_true", help="also the divergence of the whole sets (slow: minutes a pair of 2,000 particles)")
    ap.add_argument("--exact-seeds", type=int, default=1, help="water2d seeds (the first ones) scored on the whole sets with --exact")
    ap.add_argument("--draws", type=int, default=3)
    ap.add_argument("--seeds", type=int, default=3)
    ap.add_argument("--frames", type=int, default=400)
    ap.add_argument("--r-p", type=float, default=1 / 1.75)
    ap.add_argument("--out", type=Path, default=ROOT / "benchmarks" / "results" / "sinkhorn_floor")
    a = ap.parse_args(argv)
    rules = ["index", "lattice"] + (["exact"] if a.exact else [])
    syn = synthetic(rules, a.draws)
    wat = water(rules, [1000 + k for k in range(a.seeds)], a.frames, a.r_p, a.exact_seeds)

    def cell(rows: list[dict], rule: str) -> str:
        v = [r["sinkhorn"] for r in rows if r["rule"] == rule]
        return "" if not v else f"{min(v):.2g}" if min(v) == max(v) else f"{min(v):.2g} – {max(v):.2g}"

    syn_rows = []
    for dim in ("2D", "3D"):
        for case in ("permutation", "block + 7"):
            rs = [r for r in syn if r["dim"] == dim and r["case"] == case]
            syn_rows.append([dim, case, *(cell(rs, rule) for rule in rules)])
    wat_rows = []
    for run in ("mpm_rp", "jitter", "permuted reference"):
        for seed in sorted({r["seed"] for r in wat}):
            rs = [r for r in wat if r["seed"] == seed and r["run"] == run]
            wat_rows.append([run, seed, *(cell(rs, rule) for rule in rules)])
    names = {"index": "index draw", "lattice": "lattice (shipped)", "exact": "whole sets"}
    sections = [
        "# The floor of the Sinkhorn divergence's point reduction",
        f"Blur {SINKHORN_BLUR:g} m, at most {SINKHORN_MAX_POINTS} points a set; the divergence [m²] under each rule "
        f"(range over {a.draws} draws; the whole sets: one draw).",
        "\n".join(table(["set", "against", *(names[r] for r in rules)], syn_rows)),
        f"water2d, {a.frames} frames, mean over {len(sinkhorn_frames(np.arange(a.frames + 1)))} frames, against full-resolution MPM: MPM at r_p = {a.r_p:.3g}, "
        "full resolution from a start moved by N(0, 1 µm) (jitter), and the reference itself with its particles permuted.",
        "\n".join(table(["run", "seed", *(names[r] for r in rules)], wat_rows)),
    ]
    write_results(a.out.parent, a.out.name, doc={"synthetic": syn, "water2d": wat}, markdown=sections, argv=argv)
    print("\n\n".join(sections))


if __name__ == "__main__":
    main()
