"""Benchmarks: error against latency for every method (paper Fig. 5,
Fig. 7, Fig. 8, Table 2), and the cheapest configuration within an error
budget.

:func:`bench` runs, from the same held-out initial conditions, MPM at full
resolution (the reference), MPM at ``r_p``, each neural model alone (the
shipped low-resolution model, and where shipped the full-resolution
``r_p = r_t = 1``, spatial-only and temporal-only variants) and the hybrid at
``r_c ∈ {0, 0.1, …, 0.9}``, and writes ``results.csv``,
``threshold_sweep.csv``, ``pareto.png|svg``, ``error_trajectory.png`` and
``report.md``. :func:`tune` benchmarks validation seeds and writes the
fastest configuration within an error budget.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from hybridmpm.bench import report
from hybridmpm.bench.methods import ERROR_TOL_SWEEP, GRID_FRACTIONS, R_C_SWEEP, Method, methods_for, mpm_grid_methods, shipped_default_method
from hybridmpm.bench.report import aggregate, pareto_front
from hybridmpm.bench.run import TEST_SEED0, VALID_SEED0, WARMUP_FRAMES, BenchConfig, run_bench
from hybridmpm.bench.tune import choose, write_tuned
from hybridmpm.conventions import R_C
from hybridmpm.errors import InvalidInputError
from hybridmpm.scenes import make_scene, scene_spec
from hybridmpm.sim.config import load_tuned, tuned_path


def default_frames(scene: str) -> int:
    """The paper's rollout length T of a registered scene."""

    return int(scene_spec(scene, seed=0).frames)


def bench(
    scene: str,
    *,
    seeds: list[int] | None = None,
    frames: int | None = None,
    out: str | Path | None = None,
    r_cs: tuple[float, ...] = R_C_SWEEP,
    error_tols: tuple[float, ...] = ERROR_TOL_SWEEP,
    model: str | Path | None = None,
    variants: bool = True,
    extra_models: tuple[str | Path, ...] = (),
    warmup: int = WARMUP_FRAMES,
    mpm_threads: int = 0,
    nn_threads: int = 1,
    nn_alone_threads: int = 0,
    trajectory_r_c: float = R_C,
    grids: tuple[float, ...] = GRID_FRACTIONS,
    command: str | None = None,
    progress: bool = True,
) -> dict[str, Any]:
    """Benchmark registered scene ``scene`` and write its files to ``out``
    (default ``runs/bench/SCENE``). Resumable: finished method × seed cells
    in ``out/cells`` are not rerun.

    ``seeds`` initial conditions (default: 3 held-out seeds from
    :data:`TEST_SEED0`); ``frames`` per rollout (default: the paper's T);
    ``r_cs`` hybrid thresholds (the "audit" rule), ``error_tols`` the
    "error" rule's audit tolerances [g] (docs/hybrid.md); ``model`` the hybrid's network (default: the
    shipped one); ``variants`` include the shipped variant networks;
    ``extra_models`` more ONNX files run alone; ``mpm_threads`` MPM threads
    (0 = all cores); ``nn_threads`` onnxruntime threads of the hybrid,
    ``nn_alone_threads`` of the networks run alone (0 = all cores:
    :class:`~hybridmpm.bench.run.BenchConfig`); ``trajectory_r_c`` the
    hybrid drawn in ``error_trajectory.png``; ``grids`` the coarser grids of
    plain MPM (fractions of the scene's grid) that, with the scene's grid and
    ``r_p``, make the classical front every method is judged against. Returns a dict with ``rows``
    (one per method, :func:`~hybridmpm.bench.report.aggregate`; the scene's
    shipped default, run beside the others, flagged ``shipped_default``), ``cells``,
    ``pareto`` (labels on the front), ``files`` and ``shipped_default`` (its key;
    None with another ``model``).
    Raises :class:`InvalidInputError` naming the bad parameter.
    """

    frames = default_frames(scene) if frames is None else frames
    seeds = list(seeds) if seeds is not None else [TEST_SEED0 + i for i in range(3)]
    if len(set(seeds)) != len(seeds):
        raise InvalidInputError("seeds: must be distinct", "seeds")
    cfg = BenchConfig(scene, tuple(seeds), frames, warmup, mpm_threads, nn_threads, nn_alone_threads).validate()
    methods = methods_for(scene, r_cs=r_cs, model=model, variants=variants, extra_models=extra_models, error_tols=error_tols, grids=grids, seed=seeds[0])
    # the scene's shipped default (what `hybridmpm simulate SCENE` runs): marked on every chart and in the report
    default = shipped_default_method(scene, methods) if model is None else None
    out = Path(out) if out is not None else Path("runs/bench") / scene
    stride = max(m.r_t for m in methods)
    cells = [report.on_common_frames(c, stride) for c in run_bench(cfg, methods, out, progress=progress)]
    env = json.loads((out / "bench.json").read_text())["environment"]
    settings = cfg.fingerprint()
    rows = aggregate(methods, cells)
    for r in rows:
        r["shipped_default"] = default is not None and r["key"] == default.key
    report.write_results_csv(out / "results.csv", scene, frames, settings, env, methods, cells)
    report.write_sweep_csv(out / "threshold_sweep.csv", rows)
    first = make_scene(scene, seed=seeds[0])
    title = f"{scene} ({first.dim}D): {len(seeds)} held-out seed(s) × {frames} frames"
    report.plot_pareto(out / "pareto.png", rows, title)
    files = {"pareto.png": "error against latency, every method"}
    files.update(report.plot_metric_charts(out, rows, title))  # one chart per score of a chaotic flow (pareto_METRIC.png)
    # error over time, first seed: the shipped neural model, MPM at r_p and the hybrid nearest trajectory_r_c
    hyb = [m for m in methods if m.key.startswith("hybrid_rc")]
    traj_keys = ["neural", "mpm_rp"]
    if hyb:
        traj_keys.append(min(hyb, key=lambda m: abs(float(m.r_c or 0) - trajectory_r_c)).key)
    if any(m.key == "hybrid_default" for m in methods):
        traj_keys.append("hybrid_default")
    by = {c["method"]: c for c in cells if c["seed"] == seeds[0]}
    labels = {m.key: m.label for m in methods}
    report.plot_error_trajectory(
        out / "error_trajectory.png", {k: by[k] for k in traj_keys if k in by}, labels, first.dt_frame, f"{scene}: error over time, seed {seeds[0]}"
    )
    files["error_trajectory.png"] = "error over time; frames the hybrid ran on MPM shaded"
    cmd = command or f"hybridmpm bench {scene}"
    main_r_p = next(m.r_p for m in methods if m.key == "mpm_rp")
    refused = mpm_grid_methods(scene, main_r_p, seeds[0], grids)[1]
    text = report.report_markdown(scene, settings, env, seeds, rows, cmd, files, n_grid=first.params.resolved_n_grid(), refused=refused)
    text += "\n" + "\n".join(report.default_section(scene, rows))
    if (out / "peer_taichi.json").is_file():  # written by `python benchmarks/taichi_peer.py --bench-scene SCENE`
        text += report.peer_markdown(json.loads((out / "peer_taichi.json").read_text()))
    (out / "report.md").write_text(text)
    return {
        "rows": rows,
        "cells": cells,
        "pareto": [r["label"] for r in sorted((r for r in rows if r["pareto"]), key=lambda r: r["ms_mean"])],
        "files": [
            str(out / f) for f in ("results.csv", "threshold_sweep.csv", "error_sweep.csv", "pareto.png", "pareto.svg", "error_trajectory.png", "report.md")
        ],
        "out": str(out),
        "shipped_default": None if default is None else default.key,
    }


def tune(
    scene: str,
    error_budget: float,
    *,
    seeds: list[int] | None = None,
    frames: int | None = None,
    metric: str = "error_mean",
    out: str | Path | None = None,
    work: str | Path | None = None,
    progress: bool = True,
    **bench_kw: Any,
) -> dict[str, Any]:
    """Benchmark ``scene`` on validation seeds (default 2 from
    :data:`VALID_SEED0`) into ``work`` (default ``runs/tune/SCENE``, resumable)
    and write the fastest configuration whose ``metric`` is within
    ``error_budget`` to ``out`` (default ``tuned/SCENE.json``); returns the
    written document. Raises :class:`InvalidInputError` (``error_budget``)
    for a bad budget."""
    if not (isinstance(error_budget, (int, float)) and error_budget >= 0):
        raise InvalidInputError(f"error_budget: must be a number >= 0, got {error_budget!r}", "error_budget")
    seeds = list(seeds) if seeds is not None else [VALID_SEED0 + i for i in range(2)]
    work = Path(work) if work is not None else Path("runs/tune") / scene
    res = bench(scene, seeds=seeds, frames=frames, out=work, progress=progress, command=f"hybridmpm tune {scene} --error-budget {error_budget:g}", **bench_kw)
    chosen = choose(res["rows"], float(error_budget), metric)
    settings = json.loads((work / "bench.json").read_text())["settings"]
    doc = write_tuned(tuned_path(scene, out), scene, float(error_budget), metric, chosen, res["rows"], seeds, settings)
    doc["path"] = str(tuned_path(scene, out))
    return doc


__all__ = [
    "ERROR_TOL_SWEEP", "R_C_SWEEP", "TEST_SEED0", "VALID_SEED0", "BenchConfig", "Method", "aggregate", "bench", "choose", "default_frames",
    "load_tuned", "methods_for", "pareto_front", "tune", "tuned_path",
]  # fmt: skip
