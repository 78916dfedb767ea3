"""Why plain MPM on a coarser grid errs more on sand than on water: the error of
``bench_grids.py`` taken apart (docs/engine.md, "Coarse grids and sand").

Per scene (sand2d, water2d) and seed (4100 on, those of ``bench_grids.py``),
all against full-resolution MPM on the scene's grid (the reference) with the
grid-mass error of ``bench_grids.py`` (mean over the rollout):

* **the ratio's two terms**: MPM at ``r_p`` on the scene's grid and MPM on
  3/4 and 1/2 of it, and their ratio averaged over the first 100, 200 and all
  frames (sand comes to rest, water keeps moving);
* **predictability**: the reference with its initial positions nudged by up
  to 1e-5 m (how fast the flow forgets its start: the floor of any method);
* **particles or grid**: the half grid with 4 particles per cell per axis
  (the reference's particle count on the coarse grid), the scene's grid with
  1 (the half grid's particle count on the fine grid), and the half grid with
  the reference's substeps (its time step);
* **the floor**: the half grid and the scene's grid with a sticky floor (no
  friction coefficient), the deposit's length as a ratio coarse / fine;
* **convergence** (sand): the deposit's length (0.5-99.5th percentile of x
  at the last frame) on 64², 96², 128² and 256², and the error against 256².

Plus the granular column of ``tests/test_sand_validation.py`` (a = 0.5,
32 × 16 cells of 128²) on each grid: its runout ``(L∞ − L0)/L0``. And a sand
layer sliding on the rough floor (μ = tan 30°, 1.5 m/s, 2 cells
of 64² thick): its centroid's travel on 128², 96² and 64² against
``v²/(2μg)``. Writes ``OUT/coarse_sand.md`` and ``OUT/coarse_sand.json``.

    python benchmarks/coarse_sand.py --out benchmarks/results/coarse_sand          # 3 seeds, 400 frames, about 12 min
    python benchmarks/coarse_sand.py --seeds 1 --frames 300 --out /tmp/coarse_sand  # quicker
    python benchmarks/coarse_sand.py sand2d --seed0 1000 --out benchmarks/results/coarse_sand/seeds1000
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path

import numpy as np

from hybridmpm.bench.harness import write_results
from hybridmpm.metrics import grid_mass_error
from hybridmpm.mpm import MpmParams, WallParams
from hybridmpm.scenes import PAPER_R_P, Block, SceneSpec, make_scene, wall_face
from hybridmpm.scenes.core import Scene
from hybridmpm.scenes.resolution import at_resolution
from hybridmpm.sim import MpmSimulator, rollout

SEED0 = 4100
HORIZONS = (100, 200)


def horizons(frames: int) -> list[int]:
    """The horizons the ratio is averaged over: those of :data:`HORIZONS` shorter than the rollout, and the rollout."""
    return [h for h in HORIZONS if h < frames] + [frames]


def build(spec: SceneSpec, n: int | None = None, ppc: int | None = None, substeps: int | None = None, floor: str | None = None) -> Scene:
    """``spec`` on grid ``n`` (None: its own) with ``ppc`` particles per cell per axis, a fixed substep count, a floor condition."""
    scene = (spec if n is None and ppc is None else spec.on_grid(n or spec.params.resolved_n_grid(), ppc)).build()
    if substeps is not None or floor is not None:
        d = scene.params.to_dict()
        if substeps is not None:
            d["substeps"] = int(substeps)
        if floor is not None:
            d["walls"] = {**d["walls"], "faces": {**(d["walls"].get("faces") or {}), "y-": {"condition": floor}}}
        scene.params = MpmParams.from_dict(d)
    return scene


def run(scene: Scene, frames: int) -> tuple[np.ndarray, float]:
    """Positions [frames + 1, N, D] and the mean substeps per frame."""
    ro = rollout(MpmSimulator(scene, threads=1), frames)
    if ro.failure:
        raise SystemExit(f"{scene.name}: {ro.failure_detail}")
    return ro.fluid_positions, float(np.mean(ro.substeps[1:]))


def length(x: np.ndarray) -> float:
    """The deposit's length [m]: 0.5th to 99.5th percentile of x (stray particles left out)."""
    return float(np.percentile(x[:, 0], 99.5) - np.percentile(x[:, 0], 0.5))


def one_seed(scene: str, seed: int, frames: int) -> dict:
    spec = make_scene(scene, seed=seed).spec
    ref, subs = run(build(spec), frames)

    def err(x: np.ndarray, against: np.ndarray = ref) -> np.ndarray:
        return grid_mass_error(x, against, 128)

    out: dict = {"scene": scene, "seed": seed, "particles": int(ref.shape[1]), "substeps": subs}
    base = build(spec)
    nudged = base.positions + np.random.default_rng(seed).uniform(-1e-5, 1e-5, base.positions.shape)
    base.positions = nudged.astype(np.float32)
    runs = {
        "rp": run(at_resolution(build(spec), PAPER_R_P, seed=seed), frames)[0],
        "g96": run(build(spec, 96), frames)[0],
        "g64": run(build(spec, 64), frames)[0],
        "nudged": run(base, frames)[0],
        "g64_ppc4": run(build(spec, 64, ppc=4), frames)[0],
        "g128_ppc1": run(build(spec, None, ppc=1), frames)[0],
        "g64_fine_dt": run(build(spec, 64, substeps=round(subs)), frames)[0],
    }
    errs = {k: err(x) for k, x in runs.items()}
    out["error"] = {k: float(e.mean()) for k, e in errs.items()}
    out["error_last"] = {k: float(e[-1]) for k, e in errs.items()}
    out["error_frame0"] = {k: float(e[0]) for k, e in errs.items()}
    out["ratio"] = {k: {str(h): float(errs[k][: h + 1].mean() / errs["rp"][: h + 1].mean()) for h in horizons(frames)} for k in ("g96", "g64")}
    if scene.startswith("sand"):
        sticky = {n: run(build(spec, n, floor="sticky"), frames)[0][-1] for n in (64, None)}
        out["sticky_length_ratio"] = length(sticky[64]) / length(sticky[None])
        out["length_ratio"] = length(runs["g64"][-1]) / length(ref[-1])
        fine, _ = run(build(spec, 256), frames)
        out["length"] = {"64": length(runs["g64"][-1]), "96": length(runs["g96"][-1]), "128": length(ref[-1]), "256": length(fine[-1])}
        out["error_vs_256"] = {"64": float(err(runs["g64"], fine).mean()), "128": float(err(ref, fine).mean()), "rp": float(err(runs["rp"], fine).mean())}
    return out


def sliding_layer(frames: int = 200, speed: float = 1.5) -> dict:
    """A sand layer 2 cells of 64² thick sliding on the rough floor: the centroid's travel per grid."""
    mu = math.tan(math.radians(30.0))
    params = MpmParams(dim=2, n_grid=128, walls=WallParams(friction=mu))
    face = wall_face(params)
    spec = SceneSpec("slide", params, [Block("sand", [0.1, face], [0.4, face + 2 / 64], [speed, 0.0])], frames=frames)
    travel = {}
    for n in (128, 96, 64):
        x, _ = run(build(spec, None if n == 128 else n), frames)
        travel[str(n)] = float(x[-1, :, 0].mean() - x[0, :, 0].mean())
    return {"travel": travel, "rigid": speed**2 / (2 * mu * 9.81)}


def column_runout(n: int, frames: int = 300) -> float:
    """Runout ``(L∞ − L0)/L0`` of the a = 0.5 column of ``tests/test_sand_validation.py`` (32 × 16 cells of 128², φ = 30°) on grid ``n``."""
    face = wall_face(MpmParams(dim=2, n_grid=128))
    mu = math.tan(math.radians(30.0))
    params = MpmParams(dim=2, n_grid=128, walls=WallParams(friction=mu))
    spec = SceneSpec("column", params, [Block("sand", [face, face], [face + 32 / 128, face + 16 / 128])], frames=frames)
    x, _ = run(build(spec, None if n == 128 else n), frames)
    spacing = 0.5 / n
    return float((x[-1, :, 0].max() + 0.5 * spacing - face) / (32 / 128) - 1.0)


def markdown(rows: list[dict], slide: dict, column: dict, frames: int) -> str:
    h = horizons(frames)
    lines = [
        "# Coarse grids and sand: the error taken apart",
        "",
        "Grid-mass error against full-resolution MPM on the scene's grid (mean over the rollout); "
        "`g64` / `g96`: MPM on 64² / 96²; `nudged`: the reference with its start moved by up to 1e-5 m; "
        "`g64_ppc4`: 64² with 4 particles per cell per axis; `g128_ppc1`: 128² with 1; `g64_fine_dt`: 64² with the reference's substeps.",
        "",
        "| scene | seed | particles | r_p | nudged | 96² | 64² | 64², 4 ppc | 128², 1 ppc | 64², fine dt | 64² / r_p over the first "
        + ", ".join(map(str, h))
        + " frames |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        e = r["error"]
        lines.append(
            f"| {r['scene']} | {r['seed']} | {r['particles']} | {e['rp']:.3f} | {e['nudged']:.3f} | {e['g96']:.3f} | {e['g64']:.3f} | "
            f"{e['g64_ppc4']:.3f} | {e['g128_ppc1']:.3f} | {e['g64_fine_dt']:.3f} | " + " / ".join(f"{r['ratio']['g64'][str(k)]:.2f}" for k in h) + " |"
        )
    f0 = [r["error_frame0"]["g64"] for r in rows]
    lines += ["", f"At frame 0 (the lattices alone) 64² errs {min(f0):.3f}-{max(f0):.3f}."]
    sand = [r for r in rows if "length" in r]
    if sand:
        lines += [
            "",
            "Sand: the deposit's length [m] per grid (0.5-99.5th percentile of x, last frame), 64² / 128² with the scene's rough floor and with a "
            "sticky one, and the error against 256².",
            "",
            "| seed | 64² | 96² | 128² | 256² | 64² / 128², rough | 64² / 128², sticky | error vs 256²: 64² | 128² | r_p |",
            "|---|---|---|---|---|---|---|---|---|---|",
        ]
        for r in sand:
            n, e = r["length"], r["error_vs_256"]
            lines.append(
                f"| {r['seed']} | {n['64']:.3f} | {n['96']:.3f} | {n['128']:.3f} | {n['256']:.3f} | {r['length_ratio']:.2f} | "
                f"{r['sticky_length_ratio']:.2f} | {e['64']:.3f} | {e['128']:.3f} | {e['rp']:.3f} |"
            )
    c = ", ".join(f"{v:.2f} ({k}²)" for k, v in column.items())
    lines += ["", f"The a = 0.5 granular column (`tests/test_sand_validation.py`): runout (L∞ − L0)/L0 = {c}."]
    t = slide["travel"]
    lines += [
        "",
        f"A sand layer sliding on the rough floor (1.5 m/s, 2 cells of 64² thick): centroid travel {t['128']:.4f} m (128²), {t['96']:.4f} (96²), "
        f"{t['64']:.4f} (64²); a rigid block stops after v²/(2μg) = {slide['rigid']:.4f} m.",
        "",
    ]
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("scenes", nargs="*", default=["sand2d", "water2d"])
    ap.add_argument("--seeds", type=int, default=3)
    ap.add_argument("--frames", type=int, default=400)
    ap.add_argument("--seed0", type=int, default=SEED0, help="the first seed (default that of bench_grids.py)")
    ap.add_argument("--out", default="benchmarks/results/coarse_sand")
    a = ap.parse_args()
    out = Path(a.out)
    rows = []
    for scene in a.scenes:
        for i in range(a.seeds):
            rows.append(one_seed(scene, a.seed0 + i, a.frames))
            print(json.dumps(rows[-1]), flush=True)
    slide = sliding_layer()
    column = {str(n): column_runout(n) for n in (64, 96, 128, 256)}
    md = markdown(rows, slide, column, a.frames)
    write_results(out, "coarse_sand", doc={"rows": rows, "sliding_layer": slide, "column_runout": column}, markdown=md)
    print(md)


if __name__ == "__main__":
    main()
