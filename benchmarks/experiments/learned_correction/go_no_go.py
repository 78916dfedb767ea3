"""Go/no-go of the learned correction of coarse MPM, with the bounds that explain it.

Per scene (default water2d and sand2d): trains the correction
(:func:`experiments.learned_correction.train.train_correction`, DAgger, the defaults
of :class:`~experiments.learned_correction.train.CorrectionTrainConfig` unless told),
then on its validation seeds (400 frames; none of the training's) reports
the mean grid-mass error against full-resolution MPM of:

* MPM at ``r_p`` on the scene's grid, and plain MPM on half the grid
  (2 particles per cell per axis: a quarter of the particles in 2D);
* the learned correction (its best round, at its best scale);
* the *oracle*: the coarse MPM given, before every frame, the exact
  one-frame target the correction is trained on
  (:class:`~experiments.learned_correction.forcing.OracleForcing`), the best any
  correction of that target can do;
* the *floor*: full-resolution MPM itself seen through the coarse
  particles (the mass-weighted mean of the fine particles each coarse
  particle stood for at frame 0, followed to the end): what a coarse particle
  set that follows the fine solution exactly would score.

and which fraction of the coarse grid's excess error over MPM at ``r_p``
each removes (the go/no-go asks for a quarter).

    python benchmarks/experiments/learned_correction/go_no_go.py --out benchmarks/results/correction
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from dataclasses import asdict
from multiprocessing import get_context
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from hybridmpm.bench.harness import read_results, write_results
from hybridmpm.metrics import grid_mass_error
from hybridmpm.scenes import make_scene
from hybridmpm.sim import MpmSimulator, rollout
from hybridmpm.train.datasets import trajectory_seed

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))  # benchmarks/: the experiment's modules are experiments.learned_correction.*
from experiments.learned_correction.forcing import OracleForcing, coarse_simulator  # noqa: E402
from experiments.learned_correction.model import Correction  # noqa: E402
from experiments.learned_correction.train import VAL_STREAM, CorrectionTrainConfig, coarse_grid, train_correction  # noqa: E402


def bounds(args: tuple[str, int, int, int]) -> dict:
    """The oracle's and the floor's errors, with the plain coarse grid's ms per frame, for one validation seed."""
    scene_name, sd, n, frames = args
    base = make_scene(scene_name, seed=sd)
    n0 = base.params.resolved_n_grid()
    ref = rollout(MpmSimulator(base, threads=1), frames).fluid_positions
    sim = coarse_simulator(base, n)
    coarse0 = sim.fluid_positions
    cmass = np.asarray(sim.solver.masses, np.float64)
    sim.forcing = OracleForcing(sim, base.params)
    oracle = rollout(sim, frames).fluid_positions
    # the floor: each fine particle's coarse parent at frame 0, the group's mass-weighted mean position thereafter
    fmass = np.asarray(base.make_solver(num_threads=1).masses, np.float64)
    parent = cKDTree(coarse0).query(ref[0])[1]
    wsum = np.bincount(parent, weights=fmass, minlength=len(coarse0))
    means = np.stack([np.stack([np.bincount(parent, weights=fmass * f[:, k], minlength=len(coarse0)) for k in range(f.shape[1])], 1) for f in ref])
    means = means / np.maximum(wsum, 1e-30)[None, :, None]
    return {
        "seed": sd,
        "oracle": float(grid_mass_error(oracle, ref, n0).mean()),
        "floor": float(grid_mass_error(means[:, wsum > 0], ref, n0, pred_weights=wsum[wsum > 0]).mean()),
        "coarse_mass_matches": bool(np.isclose(cmass.sum(), fmass.sum(), rtol=1e-4)),
    }


def timing(scene_name: str, sd: int, n: int, model: Correction, scale: float, frames: int) -> dict:
    """ms per frame (after 24) of MPM at r_p, the plain coarse grid and the corrected one, one process, back to back."""
    from experiments.learned_correction.forcing import CorrectionForcing
    from hybridmpm.scenes import PAPER_R_P

    base = make_scene(scene_name, seed=sd)
    out = {}
    rp = rollout(MpmSimulator(base, r_p=PAPER_R_P, seed=sd, threads=1), frames)
    out["rp"] = float(rp.frame_seconds(after=24).mean() * 1e3)
    for key, m in (("plain", None), ("corrected", model)):
        sim = coarse_simulator(base, n)
        if m is not None:
            sim.forcing = CorrectionForcing(sim, m, scale=scale)
        out[key] = float(rollout(sim, frames).frame_seconds(after=24).mean() * 1e3)
    return out


def removed(plain: float, rp: float, value: float) -> str:
    """The fraction of the coarse grid's excess error over MPM at r_p that ``value`` removes."""
    return f"{(plain - value) / (plain - rp):+.0%}" if plain > rp else "–"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("scenes", nargs="*", default=["water2d", "sand2d"])
    ap.add_argument("--out", type=Path, default=Path("benchmarks/results/correction"))
    ap.add_argument("--runs", type=Path, default=Path("runs"), help="where the trainings write (model, log)")
    ap.add_argument("--frames", type=int, default=400)
    ap.add_argument("--val-seeds", type=int, default=4)
    ap.add_argument("--train-seeds", type=int, default=8)
    ap.add_argument("--rounds", type=int, default=2)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--retime", action="store_true", help="keep OUT/go_no_go.json's errors, time again (models from --runs) and rewrite the report")
    a = ap.parse_args()
    a.out.mkdir(parents=True, exist_ok=True)
    rows = []
    if a.retime:
        rows = read_results(a.out / "go_no_go.json")["rows"]
        for row in rows:
            model = Correction.load(a.runs / f"correction_{row['scene']}" / "model.npz")
            first = trajectory_seed(VAL_STREAM, 0)
            row["ms_per_frame"] = timing(row["scene"], first, coarse_grid(row["scene"], None), model, float(row["scale"]), a.frames)
        a.scenes = [r["scene"] for r in rows]
    for scene in [] if a.retime else a.scenes:
        t0 = time.time()
        cfg = CorrectionTrainConfig(scene=scene, train_seeds=a.train_seeds, val_seeds=a.val_seeds, frames=a.frames, rounds=a.rounds, workers=a.workers)
        res = train_correction(cfg, a.runs / f"correction_{scene}")
        train_s = time.time() - t0
        log = res["log"]
        best = log[res["best_round"]]
        n = coarse_grid(scene, None)
        val = [trajectory_seed(VAL_STREAM, i) for i in range(a.val_seeds)]
        with get_context("fork").Pool(a.workers) as pool:
            b = pool.map(bounds, [(scene, sd, n, a.frames) for sd in val])
        model = Correction.load(a.runs / f"correction_{scene}" / "model.npz")
        t = timing(scene, val[0], n, model, float(model.meta.get("scale", 1.0)), a.frames)
        per = best["per_seed"]
        row = {
            "scene": scene,
            "config": asdict(cfg),
            "train_wall_s": train_s,
            "one_step": [{"round": e["round"], "loss": e["one_step_val"], "no_correction": e["no_correction"], "val_error": e["val_error"]} for e in log],
            "best_round": res["best_round"],
            "scale": best["scale"],
            "rp": float(np.mean([per[str(s)]["rp"] for s in val])),
            "plain": float(np.mean([per[str(s)]["plain"] for s in val])),
            "corrected": float(np.mean([per[str(s)]["corrected"] for s in val])),
            "oracle": float(np.mean([x["oracle"] for x in b])),
            "floor": float(np.mean([x["floor"] for x in b])),
            "per_seed": {str(s): {**per[str(s)], **next(x for x in b if x["seed"] == s)} for s in val},
            "ms_per_frame": t,
        }
        rows.append(row)
        print(json.dumps({k: v for k, v in row.items() if k not in ("config", "per_seed")}), flush=True)
    lines = [
        "# The learned correction of coarse MPM: go/no-go",
        "",
        f"Validation seeds: {a.val_seeds} (stream {VAL_STREAM}), {a.frames} frames; error = mean grid-mass error against full-resolution MPM. "
        "'excess removed' = (plain coarse − row) / (plain coarse − MPM at r_p).",
        "",
        "| scene | MPM at r_p | plain coarse (half grid) | learned correction | oracle (exact one-frame target) | floor (fine solution seen through the coarse particles) | one-step loss ÷ no correction (best round) | excess removed: learned / oracle / floor |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        frac = lambda v, r=r: removed(r["plain"], r["rp"], v)  # noqa: E731
        one = r["one_step"][r["best_round"]]
        lines.append(
            f"| {r['scene']} | {r['rp']:.3f} | {r['plain']:.3f} | {r['corrected']:.3f} (round {r['best_round']}, ×{r['scale']}) | {r['oracle']:.3f} | {r['floor']:.3f} | "
            f"{one['loss'] / one['no_correction']:.2f} | {frac(r['corrected'])} / {frac(r['oracle'])} / {frac(r['floor'])} |"
        )
    lines += [
        "",
        "ms per frame (first validation seed, one process, back to back; the correction's features in numpy):",
        "",
        "| scene | MPM at r_p | plain coarse | corrected |",
        "|---|---|---|---|",
    ]
    for r in rows:
        t = r["ms_per_frame"]
        lines.append(f"| {r['scene']} | {t['rp']:.2f} | {t['plain']:.2f} | {t['corrected']:.2f} |")
    lines += ["", "Per seed (corrected / plain / r_p / oracle / floor):", ""]
    for r in rows:
        for s, p in r["per_seed"].items():
            lines.append(f"- {r['scene']} seed {s}: {p['corrected']:.3f} / {p['plain']:.3f} / {p['rp']:.3f} / {p['oracle']:.3f} / {p['floor']:.3f}")
    write_results(a.out, "go_no_go", doc={"rows": rows}, markdown="\n".join(lines))
    print("\n".join(lines))


if __name__ == "__main__":
    main()
