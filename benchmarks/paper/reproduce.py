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
(``tests/test_paper_page.py`` checks the page against that file).

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
import re
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

from hybridmpm.bench.harness import REPO_ROOT, read_results, save_figure, script_argv, table, write_file, write_json, write_results  # noqa: E402

#: The paper's numbers (arXiv 2505.18926), each with where it stands.
PAPER: dict[str, Any] = {
    "latency": {
        "source": "Sec. 3.1.1 (Water 2D)",
        "full_ms": 1.954,
        "paper_ms": 0.4048,
        "reduction": 0.788,
        "r_p": "1/1.75",
        "r_t": 2,
    },
    "hybrid": {
        "source": "Sec. 3.1.2, error-trajectory figure (Water 2D)",
        "T": 1000,
        "hybrid_ms": 676.4,
        "network_ms": 1931.1,
        "hybrid_error": 0.0109,
        "network_error": 0.0188,
    },
    "rc_sweep": {
        "source": "Sec. 3.1.2, threshold table (Water 2D)",
        "r_c": [0.0, 0.1, 0.2, 0.3, 0.4, 0.5, 0.6, 0.7, 0.8, 0.9],
        "error": [0.0232, 0.0230, 0.0227, 0.0223, 0.0221, 0.0215, 0.0208, 0.0192, 0.0169, 0.0144],
        "ms": [0.4048, 0.4081, 0.4147, 0.4301, 0.4516, 0.4977, 0.5509, 0.6137, 0.6966, 0.7356],
    },
    "scenes": {
        "source": "abstract and Sec. 4.2",
        "range": [-0.11, -0.29],
        "examples": {
            "water_sand2d": {"mpm_ms": 114.0, "hybrid_ms": 80.0, "reduction": 0.298},
            "sand3d": {"mpm_ms": 1.02, "hybrid_ms": 0.90, "reduction": 0.118},
        },
    },
    "control": {
        "source": "Sec. 4.3, control table (grid RMSE at the last step)",
        "constant": {"water2d": 0.0908, "sand2d": 0.1151, "water3d": 0.0019, "sand3d": 0.0022},
        "diffusion": {"water2d": 0.0802, "sand2d": 0.0924, "water3d": 0.0013, "sand3d": 0.0019},
    },
}

#: The paper's scenes (its dataset table), in the order of its figures.
SCENES = ("water2d", "sand2d", "sand_ramps2d", "water_ramps2d", "water3d", "sand3d", "water_sand2d")
CONTROL_SCENES = ("water2d", "sand2d", "water3d", "sand3d")
CONTROL_METHODS = ("none", "constant", "pd", "diffusion")
#: The hybrid's r_c of the paper (its choice) and of the sweep.
PAPER_RC = 0.8
#: Frames between two error evaluations, by dimension (multiples of every r_t compared).
ERROR_STRIDE = {2: 4, 3: 20}
WARMUP = 24
#: MPM, the hybrid's onnxruntime and the networks alone all on one thread (see the top of the file).
THREADS = 1
VERDICTS = ("reproduced", "reproduced in part", "turned")
#: Numbers outside the generated blocks of the page that are not results (the paper's arXiv id).
NOT_RESULTS = ("2505.18926",)


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


# --------------------------------------------------------------------------- the page


def _f(x: float, nd: int = 3) -> str:
    if x is None or not math.isfinite(x):
        return "–"
    return f"{x:.{nd}g}" if abs(x) < 1e-2 else f"{x:.{nd}f}"


def _ms(x: float) -> str:
    return "–" if not math.isfinite(x) else f"{x:.3f}" if x < 10 else f"{x:.0f}"


def _x(x: float) -> str:
    return "–" if x is None or not math.isfinite(x) else f"{x:.2f}×"


def _pct(x: float, nd: int = 0) -> str:
    return "–" if not math.isfinite(x) else f"{100 * x:+.{nd}f} %"


def _front_words(v: dict[str, Any]) -> str:
    if math.isnan(v["ratio"]):
        return "faster than every plain MPM"
    if math.isinf(v["ratio"]):
        return "slower than full-resolution MPM"
    return f"{_x(v['ratio'])} the front's error at its time"


def _front(v: dict[str, Any]) -> str:
    if math.isnan(v["ratio"]):
        return "faster than every plain MPM"
    if math.isinf(v["ratio"]):
        return "above (full-resolution MPM is as fast)"
    return f"{_x(v['ratio'])} ({'below' if v['below'] else 'above'})"


def _verdict_line(v: str) -> str:
    return f"**Verdict: {v}.**"


def render_blocks(res: dict[str, Any]) -> dict[str, str]:
    """The generated parts of docs/paper.md, by marker name, from ``results.json``'s document alone."""
    c, p, st = res["claims"], res["paper"], res["settings"]
    prov = res["provenance"]
    out: dict[str, str] = {}
    load = prov.get("load_before", [float("nan")])[0], prov.get("load_after", [float("nan")])[0]
    horizon = "the paper's T" if st["scene_frames"] is None else f"at most {st['scene_frames']} frames"
    out["run"] = "\n".join([
        f"Mode: **{res['mode']}** (`{prov['command']}`); held-out seeds {res['seeds']['simulation'][0]}–{res['seeds']['simulation'][-1]} "
        f"(simulations) and {res['seeds']['control'][0]}–{res['seeds']['control'][-1]} (control cases).  ",
        f"Settings: water2d {st['water_seeds']} seed(s) × {st['water_frames']} frames; the other scenes {st['scene_seeds']} seed(s) × "
        f"{horizon}; {st['control_cases']} control cases per scene; "
        f"r_c {', '.join(f'{r:.1f}' for r in st['r_cs'])}.  ",
        f"Machine: {prov['machine']}, {prov['cores']} cores, shared; load average {load[0]:.1f} before, {load[1]:.1f} after; "
        f"hybridmpm {prov['hybridmpm']} (commit {prov['commit']}), onnxruntime {prov['onnxruntime']}.  ",
        f"Run: {prov['started']} to {prov['date']}; this invocation {res['wall_seconds'] / 60:.1f} min, "
        f"the cells' own compute {res['cells_seconds'] / 60:.1f} min (cached cells are reused).",
    ])  # fmt: skip

    out["summary"] = "\n".join(summary_table(res))

    a = c["latency"]
    rows = a["rows"]
    tab = table(
        ["configuration", "r_p", "r_t", "ms / frame", "× network r_p = r_t = 1", "× MPM full", "grid-mass error (mean)", "vs the plain-MPM front"],
        [
            [_label(k, rows, a), f"{rows[k]['r_p']:.3g}", str(rows[k]["r_t"]), _ms(rows[k]["ms_mean"]), _x(rows[k]["ms_mean"] / rows[a["full"]]["ms_mean"]),
             _x(rows[k]["ms_mean"] / rows["mpm_full"]["ms_mean"]), _f(rows[k]["error_mean"]), _front(_vs(c, k)) if rows[k]["kind"] != "mpm" else "–"]
            for k in rows
        ],
        "lccrrrrl",
    )  # fmt: skip
    out["latency"] = "\n".join([
        f"| | paper, {p['latency']['source']} | this machine |", "|---|---:|---:|",
        f"| network r_p = r_t = 1, ms / frame | {p['latency']['full_ms']} | {_ms(rows[a['full']]['ms_mean'])} |",
        f"| network at r_p = 1/1.75, r_t = 2, ms / frame | {p['latency']['paper_ms']} | {_ms(rows[a['paper']]['ms_mean'])} |",
        f"| change | {_pct(-p['latency']['reduction'], 1)} | {_pct(-a['reduction'], 1)} |",
        "", *tab, "", _verdict_line(a["verdict"]),
    ])  # fmt: skip

    b = c["hybrid"]
    h, n = b["hybrid"], b["network"]
    out["hybrid"] = "\n".join([
        f"| over T frames (paper T = {p['hybrid']['T']}; here T = {b['T']}) | paper: hybrid | paper: network r_p = r_t = 1 | hybrid, r_c = {PAPER_RC} | network r_p = r_t = 1 | MPM at r_p |",
        "|---|---:|---:|---:|---:|---:|",
        f"| time for T frames, ms | {p['hybrid']['hybrid_ms']} | {p['hybrid']['network_ms']} | {_ms(h['total_ms'])} | {_ms(n['total_ms'])} | {_ms(b['mpm_rp']['total_ms'])} |",
        f"| grid-mass error at the last frame | {p['hybrid']['hybrid_error']} | {p['hybrid']['network_error']} | {_f(h['error_last'])} | {_f(n['error_last'])} | {_f(b['mpm_rp']['error_last'])} |",
        f"| grid-mass error, mean over the frames | – | – | {_f(h['error_mean'])} | {_f(n['error_mean'])} | {_f(b['mpm_rp']['error_mean'])} |",
        f"| network's share of steps | – | – | {100 * h['neural_share']:.0f} % | {100 * n['neural_share']:.0f} % | 0 % |",
        "",
        f"Hybrid ÷ network: time {_x(b['time_ratio'])} (paper {_x(p['hybrid']['hybrid_ms'] / p['hybrid']['network_ms'])}), error at the last frame "
        f"{_x(b['error_last_ratio'])} (paper {_x(p['hybrid']['hybrid_error'] / p['hybrid']['network_error'])}), mean error {_x(b['error_mean_ratio'])}. "
        f"Hybrid ÷ MPM at r_p: time per frame {_x(b['vs_mpm_rp']['time'])}, mean error {_x(b['vs_mpm_rp']['error'])}. "
        f"Hybrid against the plain-MPM front at its time: {_front(b['vs_front'])}."
        + ("" if not n["failures"] else f" The network alone broke off ({', '.join(n['failures'])}) after {n['frames_done']:.0f} frames on average; its figures are over the frames it made."),
        "", _verdict_line(b["verdict"]),
    ])  # fmt: skip

    sw = c["rc_sweep"]
    pr = p["rc_sweep"]
    paper_at = dict(zip(pr["r_c"], zip(pr["error"], pr["ms"], strict=True), strict=True))
    tab = table(
        ["r_c", "paper: error", "paper: ms / step", "ms / frame", "× MPM at r_p", "grid-mass error (mean)", "× MPM at r_p", "network's share", "vs the plain-MPM front"],
        [
            [f"{r['r_c']:.1f}", paper_at[r["r_c"]][0], paper_at[r["r_c"]][1], _ms(r["ms_mean"]), _x(r["time_vs_mpm_rp"]), _f(r["error_mean"]),
             _x(r["error_vs_mpm_rp"]), f"{100 * r['neural_share']:.0f} %", _front(r["vs_front"])]
            for r in sw["rows"]
        ],
        "crrrrrrrl",
    )  # fmt: skip
    out["rc_sweep"] = "\n".join([
        *tab, "",
        f"MPM at r_p: {_ms(sw['mpm_rp']['ms_mean'])} ms / frame, error {_f(sw['mpm_rp']['error_mean'])}. "
        f"Higher r_c {'lowers the error and raises the time, as in the paper' if sw['trend'] else 'does not both lower the error and raise the time here'}.",
        "", _verdict_line(sw["verdict"]),
    ])  # fmt: skip

    d = c["scenes"]
    tab = table(
        ["scene", "seeds × frames", "MPM full ms / frame", "hybrid ms / frame", "latency change", "× MPM at r_p (time)", "× MPM at r_p (error)", "network's share", "vs the plain-MPM front"],
        [
            [r["scene"], f"{r['seeds']} × {r['frames']}", _ms(r["mpm_full_ms"]), _ms(r["hybrid_ms"]), _pct(r["change"]), _x(r["time_vs_mpm_rp"]),
             _x(r["error_vs_mpm_rp"]), f"{100 * r['neural_share']:.0f} %", _front(r["vs_front"])]
            for r in d["rows"]
        ],
        "lcrrrrrrl",
    )  # fmt: skip
    out["scenes"] = "\n".join([
        *tab, "",
        f"Paper: {_pct(p['scenes']['range'][0])} to {_pct(p['scenes']['range'][1])} latency against MPM (Water-Sand 2D {_paper_example(p, 'water_sand2d')}, "
        f"Sand 3D {_paper_example(p, 'sand3d')}). "
        f"Here: {_pct(d['change_min'])} to {_pct(d['change_max'])}; the hybrid is faster than full-resolution MPM on {d['holds']} of {len(d['rows'])} scenes "
        f"and below the plain-MPM front on {d['below']} of {len(d['rows'])}.",
        "", _verdict_line(d["verdict"]),
    ])  # fmt: skip

    e = c["control"]
    tab = table(
        ["scene", "cases", "paper: constant", "paper: diffusion", "paper: ratio", "none", "constant", "PD", "diffusion", "diffusion ÷ constant", "diffusion ÷ PD", "diffusion better than constant"],
        [
            [r["scene"], r["cases"], PAPER["control"]["constant"][r["scene"]], PAPER["control"]["diffusion"][r["scene"]], _x(r["paper_ratio"]),
             *[_f(r["methods"][m]["rmse_m"]) for m in CONTROL_METHODS], _x(r["diffusion_vs_constant"]), _x(r["diffusion_vs_pd"]), f"{100 * r['better_than_constant']:.0f} %"]
            for r in e["rows"]
        ],
        "lrrrrrrrrrrr",
    )  # fmt: skip
    tab2 = table(
        ["scene", "none", "constant", "PD", "diffusion", "effort g: constant / PD / diffusion"],
        [
            [r["scene"], *[_f(r["methods"][m]["grid_mass_error"]) for m in CONTROL_METHODS],
             " / ".join(f"{r['methods'][m]['effort_mean_g']:.1f}" for m in ("constant", "pd", "diffusion"))]
            for r in e["rows"]
        ],
        "lrrrrr",
    )  # fmt: skip
    out["control"] = "\n".join([
        "Grid RMSE_m̃ at the last step (root mean square over the grid's nodes of the normalised mass difference, `rmse_m`), mean over the cases:", "",
        *tab, "", "The same cases by the relative grid-mass error at the last step (docs/design.md), with the mean effort:", "", *tab2, "",
        _verdict_line(e["verdict"]),
    ])  # fmt: skip
    return out


def summary_table(res: dict[str, Any]) -> list[str]:
    """One line per claim: the paper's figure, this run's, against the strongest plain baseline, the verdict."""
    c, p = res["claims"], res["paper"]
    a, b, sw, d, e = c["latency"], c["hybrid"], c["rc_sweep"], c["scenes"], c["control"]
    ra, lo, hi = a["rows"], sw["rows"][0], sw["rows"][-1]
    pr = p["rc_sweep"]
    below = sum(r["vs_front"]["below"] for r in sw["rows"])
    ctl = e["rows"]
    dc = [r["diffusion_vs_constant"] for r in ctl]
    dp = [r["diffusion_vs_pd"] for r in ctl]
    pc = [r["paper_ratio"] for r in ctl]
    rows = [
        ["r_p, r_t cut the network's latency (water2d)",
         f"{p['latency']['full_ms']} → {p['latency']['paper_ms']} ms ({_pct(-p['latency']['reduction'], 1)})",
         f"{_ms(ra[a['full']]['ms_mean'])} → {_ms(ra[a['paper']]['ms_mean'])} ms ({_pct(-a['reduction'], 1)})",
         f"network at r_p, r_t: {_front_words(a['networks_vs_front'][a['paper']])}", a["verdict"]],
        [f"the hybrid against the network over T frames (here T = {b['T']})",
         f"{p['hybrid']['hybrid_ms']} vs {p['hybrid']['network_ms']} ms; {p['hybrid']['hybrid_error']} vs {p['hybrid']['network_error']}",
         f"{_ms(b['hybrid']['total_ms'])} vs {_ms(b['network']['total_ms'])} ms; {_f(b['hybrid']['error_last'])} vs {_f(b['network']['error_last'])}",
         f"hybrid: {_front_words(b['vs_front'])}; {_x(b['vs_mpm_rp']['time'])} MPM at r_p's time", b["verdict"]],
        [f"higher r_c: lower error, more time (r_c {lo['r_c']:.1f} → {hi['r_c']:.1f})",
         f"{pr['error'][pr['r_c'].index(lo['r_c'])]} → {pr['error'][pr['r_c'].index(hi['r_c'])]}; "
         f"{pr['ms'][pr['r_c'].index(lo['r_c'])]} → {pr['ms'][pr['r_c'].index(hi['r_c'])]} ms",
         f"{_f(lo['error_mean'])} → {_f(hi['error_mean'])}; {_ms(lo['ms_mean'])} → {_ms(hi['ms_mean'])} ms",
         f"below the front at {below} of {len(sw['rows'])} r_c", sw["verdict"]],
        [f"the hybrid's latency against MPM, {len(d['rows'])} scenes", f"{_pct(p['scenes']['range'][0])} to {_pct(p['scenes']['range'][1])}",
         f"{_pct(d['change_min'])} to {_pct(d['change_max'])}", f"below the front on {d['below']} of {len(d['rows'])} scenes", d["verdict"]],
        ["diffusion control against the constant force, grid RMSE at the last step", f"{_x(min(pc))} to {_x(max(pc))}",
         f"{_x(min(dc))} to {_x(max(dc))}; lower on {sum(r['holds'] for r in ctl)} of {len(ctl)} scenes",
         f"against PD {_x(min(dp))} to {_x(max(dp))}; lower on {sum(r['beats_pd'] for r in ctl)} of {len(ctl)}", e["verdict"]],
    ]  # fmt: skip
    return table(["claim", "paper", "this run", "against the strongest plain baseline", "verdict"], rows)


def _paper_example(p: dict[str, Any], scene: str) -> str:
    """One of the paper's examples of claim 4, in its own units (seconds per frame or ms)."""
    ex = p["scenes"]["examples"][scene]
    if ex["mpm_ms"] >= 10:
        times = f"{ex['mpm_ms'] / 1e3:g} s → {ex['hybrid_ms'] / 1e3:g} s per frame"
    else:
        times = f"{ex['mpm_ms']:.2f} ms → {ex['hybrid_ms']:.2f} ms"
    return f"{times}, {_pct(-ex['reduction'], 1)}"


def _label(k: str, rows: dict[str, Any], a: dict[str, Any]) -> str:
    """The latency table's and the chart's name of a water2d configuration."""
    if k == a["full"]:
        return "network r_p = r_t = 1 (16 × 2 variant)"
    if k == a["paper"]:
        return "network r_p = 1/1.75, r_t = 2 (the paper's; 16 × 2 variant)"
    if k == "neural":
        return "network r_p = 1/1.75, r_t = 4 (shipped)"
    return rows[k]["label"]


def _vs(c: dict[str, Any], k: str) -> dict[str, Any]:
    return c["latency"]["networks_vs_front"][k]


BLOCK = re.compile(r"<!-- paper:begin (?P<name>[a-z_]+) -->\n(?P<body>.*?)<!-- paper:end (?P=name) -->", re.S)


def page_blocks(text: str) -> dict[str, str]:
    """The generated blocks of a page, by name (each without its last newline)."""
    return {m["name"]: m["body"].removesuffix("\n") for m in BLOCK.finditer(text)}


def fill_page(text: str, blocks: dict[str, str]) -> str:
    missing = set(blocks) - set(page_blocks(text))
    if missing:
        raise SystemExit(f"docs/paper.md has no markers for {sorted(missing)}")
    return BLOCK.sub(
        lambda m: f"<!-- paper:begin {m['name']} -->\n{blocks.get(m['name'], m['body'].removesuffix(chr(10)))}\n<!-- paper:end {m['name']} -->", text
    )


def draw_figures(res: dict[str, Any], img: Path) -> dict[str, Path]:
    """docs/img/paper_*.png from the results document alone."""
    import matplotlib
    import matplotlib.ticker

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    c = res["claims"]
    written = {}
    # (b) error over time: the hybrid, the network at r_p = r_t = 1, MPM at r_p, first seed
    b = c["hybrid"]
    fig, ax = plt.subplots(figsize=(7, 3.4))
    names = {b["network"]["key"]: "network r_p = r_t = 1", f"hybrid_paper_rc{PAPER_RC:.1f}": f"hybrid, r_c = {PAPER_RC}", "mpm_rp": "MPM at r_p"}
    for k, s in b["series"].items():
        t = [f * 2.5e-3 for f in s["frame"]]
        ax.plot(t, s["error"], label=names.get(k, k), lw=1.3)
        if k.startswith("hybrid"):
            for i in range(1, len(t)):
                if not s["neural"][i]:
                    ax.axvspan(t[i - 1], t[i], color="gold", alpha=0.25, lw=0)
    ax.set_xlabel("simulated time [s]")
    ax.set_ylabel("grid-mass error")
    ax.set_title(f"water2d, seed {b['series_seed']}: error over time (shaded: the hybrid on MPM)")
    ax.legend(fontsize=8)
    written["paper_hybrid_error.png"] = save_figure(fig, img / "paper_hybrid_error.png", dpi=110, bbox_inches="tight")

    # (a, c) error against time per frame on water2d: the front, the networks, the r_c sweep
    a, sw = c["latency"], c["rc_sweep"]
    fig, ax = plt.subplots(figsize=(7, 4))
    fr = a["front"]
    ax.plot([r["ms_mean"] for r in fr], [r["error_mean"] for r in fr], "k--o", ms=4, label="plain-MPM front")
    for r in fr:
        ax.annotate(r["label"].replace("MPM ", ""), (r["ms_mean"], r["error_mean"]), fontsize=6, xytext=(3, 3), textcoords="offset points")
    for k, m in ((a["full"], "s"), (a["paper"], "D"), ("neural", "^")):
        r = a["rows"][k]
        ax.plot(r["ms_mean"], r["error_mean"], m, label=_label(k, a["rows"], a))
    ax.plot([r["ms_mean"] for r in sw["rows"]], [r["error_mean"] for r in sw["rows"]], "-o", color="tab:red", ms=4, label="hybrid, paper's rule, r_c sweep")
    ends = {sw["rows"][0]["r_c"], PAPER_RC, sw["rows"][-1]["r_c"]}
    for r in sw["rows"]:
        if r["r_c"] in ends:
            up = r["r_c"] == PAPER_RC
            ax.annotate(
                f"r_c = {r['r_c']:.1f}", (r["ms_mean"], r["error_mean"]), fontsize=7, color="tab:red", xytext=(4, 5 if up else -11), textcoords="offset points"
            )
    ax.set_xscale("log")
    ax.xaxis.set_major_formatter(matplotlib.ticker.FormatStrFormatter("%g"))
    ax.xaxis.set_minor_formatter(matplotlib.ticker.NullFormatter())
    ax.set_xticks([t for t in (0.1, 0.2, 0.5, 1, 2, 5, 10) if ax.get_xlim()[0] <= t <= ax.get_xlim()[1]])
    ax.set_xlabel("ms per frame (log)")
    ax.set_ylabel("grid-mass error, mean over the rollout")
    ax.set_title("water2d: error against latency, one run")
    ax.legend(fontsize=7)
    written["paper_water2d_front.png"] = save_figure(fig, img / "paper_water2d_front.png", dpi=110, bbox_inches="tight")

    # (d) latency change per scene
    d = c["scenes"]["rows"]
    fig, ax = plt.subplots(figsize=(7, 3.2))
    xs = range(len(d))
    ax.bar([x - 0.2 for x in xs], [100 * r["change"] for r in d], 0.4, label="hybrid vs MPM full")
    ax.bar([x + 0.2 for x in xs], [100 * (r["time_vs_mpm_rp"] - 1) for r in d], 0.4, label="hybrid vs MPM at r_p")
    lo, hi = res["paper"]["scenes"]["range"]
    ax.axhspan(100 * hi, 100 * lo, color="tab:green", alpha=0.15, label=f"paper: {100 * lo:.0f} to {100 * hi:.0f} %")
    ax.axhline(0, color="k", lw=0.8)
    ax.set_xticks(list(xs), [r["scene"] for r in d], fontsize=8, rotation=20)
    ax.set_ylabel("latency change [%]")
    ax.legend(fontsize=7)
    written["paper_scenes_latency.png"] = save_figure(fig, img / "paper_scenes_latency.png", dpi=110, bbox_inches="tight")

    # (e) control: diffusion ÷ constant and ÷ PD against the paper's ratio
    e = c["control"]["rows"]
    fig, ax = plt.subplots(figsize=(7, 3.2))
    xs = range(len(e))
    ax.bar([x - 0.27 for x in xs], [r["paper_ratio"] for r in e], 0.27, label="paper: diffusion ÷ constant")
    ax.bar(list(xs), [r["diffusion_vs_constant"] for r in e], 0.27, label="here: diffusion ÷ constant")
    ax.bar([x + 0.27 for x in xs], [r["diffusion_vs_pd"] for r in e], 0.27, label="here: diffusion ÷ PD")
    ax.axhline(1, color="k", lw=0.8)
    ax.set_xticks(list(xs), [r["scene"] for r in e])
    ax.set_ylabel("ratio of grid RMSE at the last step")
    ax.legend(fontsize=7)
    written["paper_control.png"] = save_figure(fig, img / "paper_control.png", dpi=110, bbox_inches="tight")
    return written


def write_page(res: dict[str, Any], page: Path, img: Path) -> None:
    write_file(page, fill_page(page.read_text(), render_blocks(res)))
    draw_figures(res, img)


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
