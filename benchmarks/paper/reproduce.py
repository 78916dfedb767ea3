#!/usr/bin/env python3
"""The quantitative claims of arXiv 2505.18926, measured on this machine in one run (docs/paper.md).

    python benchmarks/paper/reproduce.py [--quick] [--out DIR] [--seed S] [--write-page]
    python benchmarks/paper/reproduce.py --page-only            # the page and its figures from OUT/results.json, no experiment

One section per claim, each measured as ratios against a baseline timed in the same run:

* ``latency`` — the network at the paper's r_p = 1/1.75, r_t = 2 (same size as the next one) against the
  network at r_p = r_t = 1 (paper Sec. 3.1.1: 1.954 → 0.4048 ms), beside the shipped network (r_t = 4),
  full-resolution MPM, MPM at r_p and plain MPM on coarser grids (the plain-MPM front), water2d.
* ``hybrid`` — the paper's hybrid (its rule: s(t) < r_c, r_c = 0.8, the shipped network) against the
  network at r_p = r_t = 1 over T frames (paper Sec. 3.1.2, error-trajectory figure: 676.4 vs 1931.1 ms,
  0.0109 vs 0.0188 at the last step), water2d.
* ``rc_sweep`` — the hybrid at several r_c (paper Sec. 3.1.2, the threshold table): time per frame,
  grid-mass error, the network's share of steps, water2d.
* ``scenes`` — the hybrid at r_c = 0.8 against full-resolution MPM on the paper's seven scenes (paper
  abstract and Sec. 4.2: −11…29 % latency).
* ``control`` — grid RMSE at the last step of the diffusion controller, the constant-force baseline and PD
  on held-out reverse-simulation cases of water2d, sand2d, water3d, sand3d (paper Sec. 4.3, control table).

Every rollout is :func:`hybridmpm.sim.rollout` of a simulator built by
:func:`hybridmpm.bench.run.method_simulator`; every control run is
:func:`hybridmpm.control.control_episode`; the error is
:func:`hybridmpm.metrics.grid_mass_error` against full-resolution MPM from the same start, on every
``r_t``-th frame (every 20th in 3D, where a 64³ p2g per frame costs more than the rollout).

Seeds: ``--seed`` S (default 9100, used by no other benchmark or test) gives the simulation seeds S, S+1, …
and the control cases S+100, S+101, … (arrows and ovals alternating); dataset trajectories use 31-bit hashed
seeds, so none was trained on.

Resumable: each rollout (one method, scene, seed, frame count) and each control case is cached as JSON under
``--cache`` (default ``runs/paper/cells``, outside git) with its settings, and is skipped when present with the
same settings. Writes ``OUT/results.json`` (every number docs/paper.md quotes, the settings, the machine, the
date: :func:`hybridmpm.bench.harness.write_results`) and ``OUT/results.md``. ``--write-page`` (or
``--page-only``) then fills the tables of docs/paper.md between ``<!-- paper:begin NAME -->`` and
``<!-- paper:end NAME -->`` and draws ``docs/img/paper_*.png``, both from ``OUT/results.json`` alone
(``tests/test_paper_page.py`` checks the page against that file). Beside this script: ``paper_numbers.py`` (the
paper's numbers, scenes and methods) and ``paper_page.py`` (the page's tables and figures from the results file).

Budget on the 2 shared cores: ``--quick`` under 10 minutes (1 seed of 300 water2d frames, 1 seed of the other
scenes cut at 160 frames, 2 control cases per scene; 48 s measured at load 3-5); the full run under 30 minutes on
a quiet machine (5 water2d seeds at T = 1000, 4 seeds of the other scenes at the paper's T, 20 control cases per
scene; ``--control-cases N`` sets fewer, and the results file records it).
"""

from __future__ import annotations

import argparse
import hashlib
import json
import math
import os
import sys
import time
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Any

# One thread everywhere (MPM, onnxruntime, k-means, BLAS): on a shared 2-core machine a second thread waits on a
# descheduled first (a 2-thread MPM frame measured 60× slower than one thread at load 6), and ratios of
# one-thread timings are what stays comparable. Set before numpy and scikit-learn load.
for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

from hybridmpm.bench.harness import REPO_ROOT, read_results, script_argv, write_json, write_results  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))  # the reproduction's modules beside this script
from paper_numbers import CONTROL_METHODS, CONTROL_SCENES, PAPER, PAPER_RC, SCENES  # noqa: E402
from paper_page import render_blocks, write_page  # noqa: E402

#: Frames between two error evaluations, by dimension (multiples of every r_t compared).
ERROR_STRIDE = {2: 4, 3: 20}
WARMUP = 24
#: MPM, the hybrid's onnxruntime and the networks alone all on one thread (see above).
THREADS = 1


@dataclass(frozen=True)
class Settings:
    """What a mode runs."""

    mode: str
    water_seeds: int  # seeds of water2d (claims latency, hybrid, rc_sweep)
    water_frames: int  # T of water2d
    scene_seeds: int  # seeds of the other scenes (claim scenes)
    scene_frames: int | None  # cap on the paper's T of the other scenes (None: the paper's T)
    control_cases: int  # per scene, arrows and ovals alternating
    r_cs: tuple[float, ...]


MODES = {
    "full": Settings("full", 5, 1000, 4, None, 20, tuple(round(0.1 * i, 1) for i in range(10))),
    "quick": Settings("quick", 1, 300, 1, 160, 2, (0.0, 0.4, 0.8, 0.9)),
}


# --------------------------------------------------------------------------- the experiments


def _sha(path: str | None) -> str | None:
    """A model's digest (a file, or a directory's files): a cell is reused only with the same model."""
    if path is None:
        return None
    p = Path(path)
    h = hashlib.sha256()
    for f in sorted(p.rglob("*")) if p.is_dir() else [p]:
        if f.is_file():
            h.update(f.name.encode() + f.read_bytes())
    return h.hexdigest()[:16]


def _cached(path: Path, key: dict[str, Any]) -> dict[str, Any] | None:
    if not path.is_file():
        return None
    try:
        doc = json.loads(path.read_text())
    except (OSError, ValueError):
        return None
    return doc if doc.get("key") == key else None


def scene_frames(scene: str, s: Settings) -> int:
    from hybridmpm.bench import default_frames

    if scene == "water2d":
        return s.water_frames
    t = default_frames(scene)
    return t if s.scene_frames is None else min(t, s.scene_frames)


def scene_methods(scene: str, s: Settings, seed: int) -> list[Any]:
    """The methods run on ``scene``: plain MPM (full resolution, r_p, the coarser grids: the front) and the
    paper's hybrid at r_c = 0.8; on water2d also the networks alone and the r_c sweep."""
    from hybridmpm.bench.methods import Method, methods_for

    water = scene == "water2d"
    listed = methods_for(scene, r_cs=(), variants=water, error_tols=(), seed=seed)
    out = [m for m in listed if m.kind == "mpm" and m.key != "mpm_full"]  # full resolution: the reference cell
    shipped = next(m for m in listed if m.key == "neural")
    if water:
        nets = [m for m in listed if m.kind == "neural"]
        full = next(m for m in nets if m.role == "full")
        paper = min((m for m in nets if m.r_t == 2 and m.r_p < 1), key=lambda m: m.params)
        out += [full, paper, shipped]
    rcs = s.r_cs if water else (PAPER_RC,)
    for r in sorted(set(rcs) | {PAPER_RC}):
        label = f"hybrid, paper's rule, r_c = {r:.1f}"
        out.append(Method(f"hybrid_paper_rc{r:.1f}", "hybrid", label, shipped.r_p, shipped.r_t, r, shipped.model, "hybrid", shipped.params, "paper"))
    return out


def reference_cell(scene: str, seed: int, frames: int, cache: Path, cfg: Any) -> tuple[dict[str, Any], Any]:
    """Full-resolution MPM of ``seed``: its cell (timing) and its fluid positions every stride-th frame."""
    import numpy as np

    from hybridmpm.scenes import make_scene
    from hybridmpm.sim import reference

    sc = make_scene(scene, seed=seed)
    stride = ERROR_STRIDE[sc.dim]
    key = {"scene": scene, "seed": seed, "frames": frames, "stride": stride, "warmup": WARMUP, "threads": cfg.mpm_threads}
    cell_path, npz = cache / scene / f"mpm_full_s{seed}_f{frames}.json", cache / scene / f"ref_s{seed}_f{frames}.npz"
    cell = _cached(cell_path, key)
    if cell is not None and npz.is_file():
        with np.load(npz) as z:
            return cell, np.asarray(z["positions"])
    t0 = time.perf_counter()
    ro = reference(sc, frames, threads=cfg.mpm_threads)
    pos = ro.fluid_positions[::stride]
    npz.parent.mkdir(parents=True, exist_ok=True)
    tmp = npz.with_name(npz.stem + ".tmp.npz")
    np.savez(tmp, positions=pos)
    tmp.replace(npz)
    ms = ro.frame_seconds(after=WARMUP) * 1e3
    n = len(pos)
    cell = {
        "key": key, "method": "mpm_full", "kind": "mpm", "label": "MPM full resolution", "seed": seed, "frames_done": frames, "failure": None,
        "ms_mean": float(ms.mean()), "total_ms": float(ro.seconds[1:].sum() * 1e3), "error_mean": 0.0, "error_last": 0.0, "neural_share": 0.0,
        "particles": int(ro.num_fluid), "series": {"frame": list(range(0, n * stride, stride)), "error": [0.0] * n, "neural": [0] * n},
        "seconds": time.perf_counter() - t0,
    }  # fmt: skip
    write_json(cell_path, cell, indent=None)
    return cell, pos


def run_cell(method: Any, scene: str, seed: int, frames: int, ref_pos: Any, cache: Path, cfg: Any) -> dict[str, Any]:
    """One method on one seed: time per frame (after the warm-up), total time, grid-mass error (mean and last
    of the stride-th frames), the network's share of steps; cached."""
    from hybridmpm.bench.run import collapsed, method_simulator
    from hybridmpm.metrics import grid_mass_error
    from hybridmpm.scenes import make_scene
    from hybridmpm.sim import MPM, rollout

    sc = make_scene(scene, seed=seed)
    stride = ERROR_STRIDE[sc.dim]
    key = {
        "config": method.config(), "model": _sha(method.model), "scene": scene, "seed": seed, "frames": frames, "stride": stride, "warmup": WARMUP,
        "threads": [cfg.mpm_threads, cfg.nn_threads, cfg.nn_alone_threads],
    }  # fmt: skip
    path = cache / scene / f"{method.key}_s{seed}_f{frames}.json"
    cell = _cached(path, key)
    if cell is not None:
        return cell
    t0 = time.perf_counter()
    sim = method_simulator(method, sc, seed, cfg)
    ro = rollout(sim, frames, stop=collapsed if method.kind == "neural" else None)
    fi = ro.frame_index
    keep = (fi % stride == 0) & (fi <= frames)
    err = grid_mass_error(ro.fluid_positions[keep], ref_pos[fi[keep] // stride], sc.params.resolved_n_grid())
    steps = ro.stats["steps"]
    ms = ro.frame_seconds(after=WARMUP) * 1e3
    cell = {
        "key": key, "method": method.key, "kind": method.kind, "label": method.label, "seed": seed, "frames_done": int(fi[-1]),
        "failure": ro.failure, "ms_mean": float(ms.mean()) if len(ms) else float("nan"), "total_ms": float(ro.seconds[1:].sum() * 1e3),
        "error_mean": float(err.mean()), "error_last": float(err[-1]), "neural_share": 1.0 - steps.get("mpm", 0) / max(1, sum(steps.values())),
        "particles": int(ro.num_fluid),
        "series": {"frame": fi[keep].tolist(), "error": [round(float(e), 5) for e in err], "neural": (ro.solver[keep] != MPM).astype(int).tolist()},
        "seconds": time.perf_counter() - t0,
    }  # fmt: skip
    write_json(path, cell, indent=None)
    return cell


def control_cell(scene: str, seed: int, kind: str, cache: Path) -> dict[str, Any]:
    """One held-out reverse-simulation case (:func:`hybridmpm.train.control.cases.make_case`, the paper's
    benchmark): every controller of :data:`CONTROL_METHODS` from the same start, its final-shape errors."""
    from hybridmpm.control import Controller, control_episode
    from hybridmpm.control.controller import shipped_control_model
    from hybridmpm.train.control.cases import make_case

    key = {"scene": scene, "seed": seed, "kind": kind, "methods": list(CONTROL_METHODS), "model": _sha(str(shipped_control_model(scene)))}
    path = cache / "control" / f"{scene}_s{seed}.json"
    cell = _cached(path, key)
    if cell is not None:
        return cell
    t0 = time.perf_counter()
    case = make_case(scene, seed, kind, tracking=False)
    frames = len(case.path) - 1
    res: dict[str, Any] = {}
    for m in CONTROL_METHODS:
        sim = case.simulator()
        ctl = Controller.for_scene(scene, m, frames=frames, seed=seed) if m == "diffusion" else Controller(m, frames=frames, seed=seed)
        ep = control_episode(sim, case.sketch, ctl, target=case.target)
        res[m] = {k: float(ep.metrics[k]) for k in ("grid_mass_error", "rmse_m", "effort_mean_g", "plan_ms") if k in ep.metrics}
    cell = {"key": key, "scene": scene, "seed": seed, "kind": kind, "methods": res, "seconds": time.perf_counter() - t0}
    write_json(path, cell, indent=None)
    return cell


def run_experiments(s: Settings, seed0: int, cache: Path, progress: bool = True) -> dict[str, Any]:
    """Every cell of mode ``s`` (cached ones read back); returns the raw cells by scene and the control cases."""
    from tqdm import tqdm

    from hybridmpm.bench.run import BenchConfig

    plan: list[tuple[str, int, int, list[Any]]] = []
    for scene in SCENES:
        n = s.water_seeds if scene == "water2d" else s.scene_seeds
        frames = scene_frames(scene, s)
        for i in range(n):
            plan.append((scene, seed0 + i, frames, scene_methods(scene, s, seed0)))
    cases = [(scene, seed0 + 100 + i, "arrow" if i % 2 == 0 else "oval") for scene in CONTROL_SCENES for i in range(s.control_cases)]
    total = sum(1 + len(ms) for *_, ms in plan) + len(cases)
    bar = tqdm(total=total, desc=f"paper ({s.mode})", unit="cell", disable=not progress)
    cells: dict[str, list[dict[str, Any]]] = {}
    for scene, seed, frames, methods in plan:
        cfg = BenchConfig(scene, (seed,), frames, WARMUP, THREADS, THREADS, THREADS).validate()
        bar.set_postfix_str(f"{scene} seed {seed} reference", refresh=True)
        ref, ref_pos = reference_cell(scene, seed, frames, cache, cfg)
        cells.setdefault(scene, []).append(ref)
        bar.update()
        for m in methods:  # one seed's methods back to back: their time ratios share the machine's state
            bar.set_postfix_str(f"{scene} seed {seed} {m.key}", refresh=True)
            cells[scene].append(run_cell(m, scene, seed, frames, ref_pos, cache, cfg))
            bar.update()
    control = []
    for scene, seed, kind in cases:
        bar.set_postfix_str(f"control {scene} seed {seed} {kind}", refresh=True)
        control.append(control_cell(scene, seed, kind, cache))
        bar.update()
    bar.close()
    return {"cells": cells, "control": control}


# --------------------------------------------------------------------------- from cells to claims


def _mean(xs: list[float]) -> float:
    xs = [x for x in xs if x is not None and math.isfinite(x)]
    return sum(xs) / len(xs) if xs else float("nan")


def aggregate(cells: list[dict[str, Any]]) -> dict[str, dict[str, Any]]:
    """One row per method: means over seeds of its per-seed figures."""
    by: dict[str, list[dict[str, Any]]] = {}
    for c in cells:
        by.setdefault(c["method"], []).append(c)
    rows = {}
    for k, cs in by.items():
        rows[k] = {
            "key": k, "kind": cs[0]["kind"], "label": cs[0]["label"], "seeds": len(cs),
            "r_p": cs[0]["key"].get("config", {}).get("r_p", 1.0), "r_t": cs[0]["key"].get("config", {}).get("r_t", 1),
            **{f: _mean([c[f] for c in cs]) for f in ("ms_mean", "total_ms", "error_mean", "error_last", "neural_share", "frames_done")},
            "failures": sorted({c["failure"] for c in cs if c["failure"]}),
        }  # fmt: skip
    return rows


def front_of(rows: dict[str, dict[str, Any]]) -> list[dict[str, Any]]:
    from hybridmpm.bench.report import mpm_front

    return mpm_front(list(rows.values()), "error_mean")


def vs_front(rows: dict[str, dict[str, Any]], key: str) -> dict[str, Any]:
    """A method's long-horizon error against the plain-MPM front's at its time: ratio (NaN: faster than every
    plain MPM measured) and whether it is below."""
    from hybridmpm.bench.report import front_error_at

    r = rows[key]
    f = front_error_at(front_of(rows), r["ms_mean"], "error_mean")
    if not math.isfinite(f):  # faster than every plain MPM measured: on the front by construction
        return {"front_error": f, "ratio": float("nan"), "below": not r["failures"]}
    ratio = r["error_mean"] / f if f > 0 else float("inf")  # f = 0: full-resolution MPM is as fast
    return {"front_error": f, "ratio": ratio, "below": bool(ratio < 1.0) and not r["failures"]}


def verdict(holds: list[bool], beats: list[bool]) -> str:
    """The rule of docs/paper.md: "turned" where the paper's comparison fails everywhere here; "reproduced"
    where it holds everywhere and the paper's method is also below the strongest plain baseline everywhere;
    "reproduced in part" otherwise."""
    if not any(holds):
        return "turned"
    return "reproduced" if all(holds) and all(beats) else "reproduced in part"


def claims(raw: dict[str, Any], s: Settings) -> dict[str, Any]:
    cells = raw["cells"]
    rows = {scene: aggregate(cs) for scene, cs in cells.items()}
    w = rows["water2d"]
    nets = [k for k in w if w[k]["kind"] == "neural"]
    full = next(k for k in nets if "full" in k)
    paper = next(k for k in nets if "rt2" in k)
    rc = f"hybrid_paper_rc{PAPER_RC:.1f}"
    out: dict[str, Any] = {}

    # (a) latency of the paper's r_p, r_t against r_p = r_t = 1
    red = 1.0 - w[paper]["ms_mean"] / w[full]["ms_mean"]
    fr = vs_front(w, paper)
    out["latency"] = {
        "rows": {k: w[k] for k in [full, paper, "neural", "mpm_full", "mpm_rp"]},
        "full": full, "paper": paper, "reduction": red, "paper_vs_mpm_full": w[paper]["ms_mean"] / w["mpm_full"]["ms_mean"],
        "shipped_vs_mpm_full": w["neural"]["ms_mean"] / w["mpm_full"]["ms_mean"], "vs_front": fr, "front": front_of(w),
        "networks_vs_front": {k: vs_front(w, k) for k in (full, paper, "neural")},
        "verdict": verdict([red > 0], [fr["below"]]),
    }  # fmt: skip

    # (b) the hybrid against the network at r_p = r_t = 1 over T frames
    t_ratio = w[rc]["total_ms"] / w[full]["total_ms"]
    e_ratio = w[rc]["error_last"] / w[full]["error_last"]
    fr = vs_front(w, rc)
    seed0 = min(c["seed"] for c in cells["water2d"])
    series = {c["method"]: c["series"] for c in cells["water2d"] if c["seed"] == seed0 and c["method"] in (full, rc, "mpm_rp")}
    out["hybrid"] = {
        "T": s.water_frames, "hybrid": w[rc], "network": w[full], "mpm_rp": w["mpm_rp"], "time_ratio": t_ratio, "error_last_ratio": e_ratio,
        "error_mean_ratio": w[rc]["error_mean"] / w[full]["error_mean"], "vs_mpm_rp": {"time": w[rc]["ms_mean"] / w["mpm_rp"]["ms_mean"],
        "error": w[rc]["error_mean"] / w["mpm_rp"]["error_mean"]}, "vs_front": fr, "series_seed": seed0, "series": series,
        "verdict": verdict([t_ratio < 1 and e_ratio < 1], [fr["below"]]) if (t_ratio < 1) == (e_ratio < 1) else "reproduced in part",
    }  # fmt: skip

    # (c) the r_c sweep
    sweep = []
    for r in sorted(set(s.r_cs) | {PAPER_RC}):
        k = f"hybrid_paper_rc{r:.1f}"
        fr = vs_front(w, k)
        sweep.append({"r_c": r, **{f: w[k][f] for f in ("ms_mean", "error_mean", "error_last", "neural_share")}, "time_vs_mpm_rp": w[k]["ms_mean"] / w["mpm_rp"]["ms_mean"],
                      "error_vs_mpm_rp": w[k]["error_mean"] / w["mpm_rp"]["error_mean"], "vs_front": fr})  # fmt: skip
    lo, hi = sweep[0], sweep[-1]
    trend = hi["error_mean"] < lo["error_mean"] and hi["ms_mean"] > lo["ms_mean"]
    out["rc_sweep"] = {"rows": sweep, "mpm_rp": w["mpm_rp"], "trend": trend, "verdict": verdict([trend], [any(r["vs_front"]["below"] for r in sweep)])}

    # (d) the hybrid against MPM across scenes
    per = []
    for scene in SCENES:
        r = rows[scene]
        fr = vs_front(r, rc)
        per.append({
            "scene": scene, "seeds": r["mpm_full"]["seeds"], "frames": scene_frames(scene, s), "mpm_full_ms": r["mpm_full"]["ms_mean"], "hybrid_ms": r[rc]["ms_mean"],
            "change": r[rc]["ms_mean"] / r["mpm_full"]["ms_mean"] - 1.0, "mpm_rp_ms": r["mpm_rp"]["ms_mean"], "time_vs_mpm_rp": r[rc]["ms_mean"] / r["mpm_rp"]["ms_mean"],
            "error": r[rc]["error_mean"], "error_vs_mpm_rp": r[rc]["error_mean"] / r["mpm_rp"]["error_mean"], "neural_share": r[rc]["neural_share"], "vs_front": fr,
            "holds": r[rc]["ms_mean"] < r["mpm_full"]["ms_mean"],
        })  # fmt: skip
    changes = [p["change"] for p in per]
    out["scenes"] = {
        "rows": per, "change_min": min(changes), "change_max": max(changes), "holds": sum(p["holds"] for p in per), "below": sum(p["vs_front"]["below"] for p in per),
        "verdict": verdict([p["holds"] for p in per], [p["vs_front"]["below"] for p in per]),
    }  # fmt: skip

    # (e) control
    ctl = []
    for scene in CONTROL_SCENES:
        cs = [c for c in raw["control"] if c["scene"] == scene]
        m = {k: {f: _mean([c["methods"][k][f] for c in cs]) for f in ("rmse_m", "grid_mass_error", "effort_mean_g")} for k in CONTROL_METHODS}
        d, c0, pd = m["diffusion"]["rmse_m"], m["constant"]["rmse_m"], m["pd"]["rmse_m"]
        better = _mean([float(c["methods"]["diffusion"]["rmse_m"] < c["methods"]["constant"]["rmse_m"]) for c in cs])
        ctl.append({
            "scene": scene, "cases": len(cs), "methods": m, "diffusion_vs_constant": d / c0, "diffusion_vs_pd": d / pd, "better_than_constant": better,
            "paper_ratio": PAPER["control"]["diffusion"][scene] / PAPER["control"]["constant"][scene], "holds": d < c0, "beats_pd": d < pd,
        })  # fmt: skip
    out["control"] = {"rows": ctl, "verdict": verdict([r["holds"] for r in ctl], [r["beats_pd"] for r in ctl])}
    return out


# --------------------------------------------------------------------------- main


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="the short run (under 10 minutes on 2 cores)")
    ap.add_argument("--out", default="benchmarks/results/paper", help="where results.json and results.md go")
    ap.add_argument("--cache", default="runs/paper/cells", help="the resumable cells (outside git)")
    ap.add_argument("--seed", type=int, default=9100, help="held-out seed base: simulations S, S+1, …; control cases S+100, …")
    ap.add_argument("--write-page", action="store_true", help="then fill docs/paper.md's tables and draw docs/img/paper_*.png from OUT/results.json")
    ap.add_argument("--page-only", action="store_true", help="only --write-page from an existing OUT/results.json")
    ap.add_argument("--page", default=str(REPO_ROOT / "docs" / "paper.md"))
    ap.add_argument("--img", default=str(REPO_ROOT / "docs" / "img"))
    ap.add_argument("--control-cases", type=int, default=None, help="control cases per scene (default: the mode's)")
    ap.add_argument("--no-progress", action="store_true")
    args = ap.parse_args(argv)
    if not 0 <= args.seed < 2**31 - 200:
        ap.error(f"--seed: must be in [0, {2**31 - 200}), got {args.seed}")
    out = Path(args.out)
    if not args.page_only:
        s = MODES["quick" if args.quick else "full"]
        if args.control_cases is not None:
            if args.control_cases < 1:
                ap.error(f"--control-cases: must be >= 1, got {args.control_cases}")
            s = replace(s, control_cases=args.control_cases)
        t0 = time.perf_counter()
        raw = run_experiments(s, args.seed, Path(args.cache), progress=not args.no_progress)
        cells_s = sum(c["seconds"] for cs in raw["cells"].values() for c in cs) + sum(c["seconds"] for c in raw["control"])
        doc = {
            "mode": s.mode, "settings": asdict(s), "seeds": {"simulation": [args.seed + i for i in range(max(s.water_seeds, s.scene_seeds))],
            "control": [args.seed + 100 + i for i in range(s.control_cases)]}, "paper": PAPER, "claims": claims(raw, s),
            "wall_seconds": time.perf_counter() - t0, "cells_seconds": cells_s,
        }  # fmt: skip
        doc = json.loads(json.dumps(doc, default=float))  # plain JSON (NaN kept), as read back by the page
        write_results(out, "results", doc=doc, argv=script_argv(__file__, argv))
        res = read_results(out / "results.json")
        blocks = render_blocks(res)
        md = [f"# arXiv 2505.18926, claim by claim ({s.mode} run)", *[f"## {k}\n\n{v}" for k, v in blocks.items()]]
        write_results(out, "results", markdown=md, argv=script_argv(__file__, argv))
        for name in ("latency", "hybrid", "rc_sweep", "scenes", "control"):
            print(f"{name}: {res['claims'][name]['verdict']}")
    if args.write_page or args.page_only:
        write_page(read_results(out / "results.json"), Path(args.page), Path(args.img))
        print(f"wrote {args.page} and {args.img}/paper_*.png from {out / 'results.json'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
