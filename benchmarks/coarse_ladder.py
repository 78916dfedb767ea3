"""The coarse-grid ladder: how much of the half grid's excess error over MPM at ``r_p`` each rung removes
(docs/correction.md).

Every rung is judged alike: on validation seeds of their own stream (:data:`FIT_SEEDS` to fit,
:data:`HELD_OUT` to score; no benchmark, test or dataset uses 7100-7115), 400 frames, the mean
grid-mass error against full-resolution MPM on the scene's grid, and the share

    f = (plain half grid - row) / (plain half grid - MPM at r_p)

of the half grid's excess error it removes (from the errors' means over the seeds; the spread is
the range of the per-seed shares), and its ms per frame as a ratio to MPM at ``r_p``'s in the same
run (one thread, the fastest of two runs taken round the configurations).

Subcommands:

* ``rung0 SCENE...``: plain guards, no learning. The half grid with 2 (the default), 2.5 and 3
  particles per cell per axis; and each error twice, on the scene's grid (the bench's) and with
  every field deposited on the half grid (the deposit kernel matched to the coarse particles'
  spacing, applied to every method alike: it asks how much of the error is the splat of fewer
  particles rather than wrong dynamics). Writes ``OUT/rung0.{json,md,png}``.
* ``rung1-fit SCENE``: CMA-ES (the ``cma`` package; bench extra) on the coarse material's
  parameters of :data:`FIT_PARAMS` (bounded by :data:`hybridmpm.mpm.params.CALIBRATION_BOUNDS`,
  searched in [0, 1] per parameter), minimising the mean 400-frame error of the half grid on the
  fitting seeds. Resumable: every evaluation is logged in ``RUNS/fit_<scene>_g<n>/evals.jsonl`` and
  each generation's sample is drawn from a seed of its own, so a restarted fit asks for the same
  points and finds them logged. Writes the fit to ``python/hybridmpm/models/calibrated/<scene>_g<n>.json``
  and its curve ``.png``.
* ``rung1-eval SCENE``: the held-out seeds: MPM at ``r_p``, the plain half grid and the calibrated
  one (``MpmSimulator(..., n_grid=n, calibrated=True)``, the shipped fit); writes the held-out
  figures into the fit's JSON, its card ``.md`` and ``OUT/rung1_<scene>.json``.

Full-resolution references are cached in ``data/coarse_ladder/`` (gitignored).

    python benchmarks/coarse_ladder.py rung0 sand2d sand3d
    python benchmarks/coarse_ladder.py rung1-fit sand2d                 # 84 evaluations; resumable
    python benchmarks/coarse_ladder.py rung1-eval sand2d
"""

from __future__ import annotations

import argparse
import json
import pickle
import time
from dataclasses import replace
from multiprocessing import get_context
from pathlib import Path
from typing import Any

import numpy as np

from hybridmpm.bench.harness import provenance, save_figure, write_file, write_json, write_results
from hybridmpm.metrics import grid_mass_error
from hybridmpm.models.calibrated import fit_name
from hybridmpm.mpm.params import CALIBRATION_BOUNDS, with_calibration
from hybridmpm.scenes import PAPER_R_P, make_scene, scene_spec
from hybridmpm.scenes.core import Scene
from hybridmpm.scenes.resolution import on_grid
from hybridmpm.sim import MpmSimulator, rollout

FIT_SEEDS = tuple(range(7100, 7108))
HELD_OUT = tuple(range(7108, 7116))
FRAMES = 400
WARMUP = 24
#: The fit's objective reads every 4th frame's error (the held-out scores every frame's): a quarter of the metric's cost.
FIT_STRIDE = 4
CACHE = Path("data/coarse_ladder")
RUNS = Path("runs/coarse_ladder")
OUT = Path("benchmarks/results/coarse_ladder")
CALIBRATED = Path("python/hybridmpm/models/calibrated")
#: The coarse material's parameters each scene's fit sets (keys of CALIBRATION_BOUNDS). Sand: friction angle,
#: floor friction and Young's modulus (cohesion only made the half grid worse: rung 1 in docs/correction.md).
FIT_PARAMS = {
    "sand2d": ("sand.friction_angle_deg", "walls.faces.y-.friction", "sand.youngs_modulus"),
    "sand3d": ("sand.friction_angle_deg", "walls.faces.y-.friction", "sand.youngs_modulus"),
    "water2d": ("water.bulk_modulus", "water.viscosity"),
    "water_sand2d": ("sand.friction_angle_deg", "walls.faces.y-.friction", "water.bulk_modulus"),
}


# ------------------------------------------------------------------ shared


def half_grid(scene: str) -> int:
    """The half grid of ``scene``: 64² for 128², 32³ for 64³."""
    return scene_spec(scene, seed=FIT_SEEDS[0]).params.resolved_n_grid() // 2


def reference(scene: str, seed: int, frames: int = FRAMES) -> np.ndarray:
    """Full-resolution MPM's fluid positions, float32 [frames + 1, N, D], cached in :data:`CACHE`."""
    path = CACHE / f"{scene}_{seed}_{frames}.npy"
    if path.is_file():
        return np.load(path)
    ro = rollout(MpmSimulator(make_scene(scene, seed=seed), threads=1), frames)
    if ro.failure:
        raise SystemExit(f"{scene} seed {seed} reference: {ro.failure_detail}")
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.stem + ".tmp.npy")
    np.save(tmp, ro.fluid_positions.astype(np.float32))
    tmp.replace(path)
    return ro.fluid_positions


def run(sim: MpmSimulator, frames: int, what: str) -> tuple[np.ndarray, float]:
    """Fluid positions [frames + 1, N, D] and the mean ms per frame after :data:`WARMUP` frames."""
    ro = rollout(sim, frames)
    if ro.failure:
        raise SystemExit(f"{what}: {ro.failure_detail}")
    return ro.fluid_positions, float(ro.frame_seconds(after=WARMUP).mean() * 1e3)


def errors(x: np.ndarray, ref: np.ndarray, n0: int) -> dict[str, float]:
    """Mean grid-mass error on the scene's grid (``grid``: the bench's) and on the half grid (``half``: every field
    deposited with the kernel matched to the coarse particles' spacing)."""
    return {"grid": float(grid_mass_error(x, ref, n0).mean()), "half": float(grid_mass_error(x, ref, n0 // 2).mean())}


def timed(configs: dict[str, Any], frames: int, repeats: int = 2) -> tuple[dict[str, np.ndarray], dict[str, float]]:
    """Run every simulator factory of ``configs`` ``repeats`` times round the configurations; positions and the fastest ms per frame."""
    pos: dict[str, np.ndarray] = {}
    ms: dict[str, list[float]] = {k: [] for k in configs}
    for _ in range(repeats):
        for key, make in configs.items():
            pos[key], t = run(make(), frames, key)
            ms[key].append(t)
    return pos, {k: min(v) for k, v in ms.items()}


def share(plain: float, rp: float, row: float) -> float:
    """f: the share of the half grid's excess error over MPM at r_p that ``row`` removes."""
    return (plain - row) / (plain - rp) if plain != rp else float("nan")


def summarise(rows: list[dict], keys: list[str], metric: str = "grid") -> dict[str, dict]:
    """Per configuration over the seeds: mean error, f (of the means) and its per-seed range, the error and time ratios to MPM at r_p."""
    mean = {k: float(np.mean([r["error"][k][metric] for r in rows])) for k in ["rp", *keys]}
    out = {}
    for k in keys:
        per = [share(r["error"]["plain"][metric], r["error"]["rp"][metric], r["error"][k][metric]) for r in rows]
        err_ratio = [r["error"][k][metric] / r["error"]["rp"][metric] for r in rows]
        t_ratio = [r["ms"][k] / r["ms"]["rp"] for r in rows]
        out[k] = {
            "error": mean[k],
            "f": share(mean["plain"], mean["rp"], mean[k]),
            "f_seeds": [float(np.min(per)), float(np.median(per)), float(np.max(per))],
            "error_ratio": [float(np.min(err_ratio)), float(np.median(err_ratio)), float(np.max(err_ratio))],
            "time_ratio": [float(np.min(t_ratio)), float(np.median(t_ratio)), float(np.max(t_ratio))],
        }
    out["rp"] = {"error": mean["rp"]}
    return out


def rng3(v: list[float], fmt: str = ".2f") -> str:
    """``median (min to max)``."""
    return f"{v[1]:{fmt}} ({v[0]:{fmt}} to {v[2]:{fmt}})"


# ------------------------------------------------------------------ rung 0


def lattice_scene(base: Scene, n: int, ppc: float) -> Scene:
    """``base`` reseeded on grid ``n`` at ``ppc`` particles per cell per axis, a fraction allowed (each block's lattice stretched
    to its sides, each particle its share of the volume: :meth:`SceneSpec.build`)."""
    if float(ppc).is_integer():
        return on_grid(base, n, int(ppc))
    spec = replace(base.spec.on_grid(n, 2), particles_per_cell=ppc)  # type: ignore[union-attr, arg-type]
    scene = spec.build()
    scene.name = base.name
    return scene


RUNG0_PPC = (2, 2.5, 3)


def rung0_seed(scene: str, seed: int, frames: int) -> dict:
    base = make_scene(scene, seed=seed)
    n0 = base.params.resolved_n_grid()
    n = n0 // 2
    ref = reference(scene, seed, frames)
    configs: dict[str, Any] = {"rp": lambda: MpmSimulator(base, r_p=PAPER_R_P, seed=seed, threads=1)}
    for ppc in RUNG0_PPC:
        key = "plain" if ppc == 2 else f"ppc{ppc:g}"
        configs[key] = lambda ppc=ppc: MpmSimulator(lattice_scene(base, n, ppc), threads=1)
    pos, ms = timed(configs, frames)
    return {
        "scene": scene,
        "seed": seed,
        "particles": {k: int(v.shape[1]) for k, v in pos.items()} | {"full": int(ref.shape[1])},
        "ms": ms,
        "error": {k: errors(v, ref, n0) for k, v in pos.items()},
    }


def rung0(a: argparse.Namespace) -> None:
    from tqdm import tqdm

    rows = []
    jobs = [(s, sd) for s in a.scenes for sd in a.seeds]
    for scene, sd in tqdm(jobs, desc="rung0"):
        rows.append(rung0_seed(scene, sd, a.frames))
    keys = ["plain", *(f"ppc{p:g}" for p in RUNG0_PPC if p != 2)]
    doc: dict[str, Any] = {"rows": rows, "summary": {}, "seeds": list(a.seeds), "frames": a.frames}
    for scene in a.scenes:
        rs = [r for r in rows if r["scene"] == scene]
        doc["summary"][scene] = {m: summarise(rs, keys, m) for m in ("grid", "half")}
    written = write_results(a.out, "rung0", doc=doc, markdown=rung0_markdown(doc, keys), figures={"rung0.png": rung0_chart(doc, keys)}, dpi=80)
    print(written["md"].read_text())


def rung0_markdown(doc: dict, keys: list[str]) -> str:
    """Rung 0's table (the harness's header, with the command, the machine and the load, goes under its title)."""
    lines = [
        "# Rung 0: more particles on the half grid, and the error's own deposit",
        "",
        f"Seeds {doc['seeds'][0]}-{doc['seeds'][-1]}, {doc['frames']} frames; error = mean grid-mass error against full-resolution MPM, "
        "on the scene's grid (`grid`) and deposited on the half grid (`half`: the kernel matched to the coarse spacing, every method alike); "
        "f = (plain half grid - row) / (plain half grid - MPM at r_p) of the means; per seed: median (min to max); "
        "ratios to MPM at r_p per seed: median (min to max); one thread.",
        "",
        "| scene | half grid, particles per cell per axis | particles / full | error (grid) | f (grid) | error (half) | f (half) | "
        "error / r_p's (grid) | time / r_p's |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for scene, s in doc["summary"].items():
        rs = [r for r in doc["rows"] if r["scene"] == scene]
        g, h = s["grid"], s["half"]
        lines.append(f"| {scene} | MPM at r_p | {np.mean([r['particles']['rp'] / r['particles']['full'] for r in rs]):.2f} | "
                     f"{g['rp']['error']:.3f} | 1 | {h['rp']['error']:.3f} | 1 | 1 | 1 |")  # fmt: skip
        for k in keys:
            label = "2 (plain)" if k == "plain" else k[3:]
            frac = np.mean([r["particles"][k] / r["particles"]["full"] for r in rs])
            lines.append(
                f"| {scene} | {label} | {frac:.2f} | {g[k]['error']:.3f} | {g[k]['f']:+.2f}; {rng3(g[k]['f_seeds'])} | {h[k]['error']:.3f} | "
                f"{h[k]['f']:+.2f}; {rng3(h[k]['f_seeds'])} | {rng3(g[k]['error_ratio'])} | {rng3(g[k]['time_ratio'])} |"
            )
    return "\n".join(lines) + "\n"


def rung0_chart(doc: dict, keys: list[str]) -> Any:
    """Error against time, each relative to MPM at r_p's, one panel per scene (the figure: the harness saves it)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    scenes = list(doc["summary"])
    fig, axes = plt.subplots(1, len(scenes), figsize=(4.2 * len(scenes), 3.4), squeeze=False)
    for ax, scene in zip(axes[0], scenes):
        g = doc["summary"][scene]["grid"]
        ax.scatter([1], [1], c="k", marker="s", label="MPM at r_p")
        for k, c in zip(keys, ("C0", "C1", "C2")):
            t, e = g[k]["time_ratio"], g[k]["error_ratio"]
            ax.errorbar([t[1]], [e[1]], xerr=[[t[1] - t[0]], [t[2] - t[1]]], yerr=[[e[1] - e[0]], [e[2] - e[1]]], fmt="o", c=c,
                        label="half grid, " + ("2 per axis" if k == "plain" else f"{k[3:]} per axis"))  # fmt: skip
        ax.set_xlabel("time / MPM at r_p's")
        ax.set_ylabel("error / MPM at r_p's")
        ax.set_title(f"{scene}: median (range) over seeds", fontsize=9)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7)
    fig.tight_layout()
    return fig


# ------------------------------------------------------------------ rung 1


def coarse_scene(scene: str, seed: int, values: dict[str, float]) -> Scene:
    """The plain half grid of ``scene`` for ``seed`` with the coarse material ``values`` (what a fit evaluates)."""
    s = on_grid(make_scene(scene, seed=seed), half_grid(scene))
    return replace(s, params=with_calibration(s.params, values))


def _fit_error(job: tuple[str, int, int, dict[str, float]]) -> tuple[float, float]:
    """The fit's objective on one seed: the mean grid-mass error over every :data:`FIT_STRIDE`-th frame of the rollout; and the
    CPU seconds it took."""
    scene, seed, frames, values = job
    t0 = time.process_time()
    ref = reference(scene, seed, frames)
    x, _ = run(MpmSimulator(coarse_scene(scene, seed, values), threads=1), frames, f"{scene} seed {seed} {values}")
    err = float(grid_mass_error(x[::FIT_STRIDE], ref[::FIT_STRIDE], make_scene(scene, seed=seed).params.resolved_n_grid()).mean())
    return err, time.process_time() - t0


def _rp_error(job: tuple[str, int, int]) -> float:
    scene, seed, frames = job
    x, _ = run(MpmSimulator(make_scene(scene, seed=seed), r_p=PAPER_R_P, seed=seed, threads=1), frames, f"{scene} seed {seed} r_p")
    ref = reference(scene, seed, frames)
    return float(grid_mass_error(x[::FIT_STRIDE], ref[::FIT_STRIDE], make_scene(scene, seed=seed).params.resolved_n_grid()).mean())


def _cache_reference(job: tuple[str, int, int]) -> None:
    reference(*job)


def physical(keys: tuple[str, ...], u: np.ndarray) -> dict[str, float]:
    """Parameters from the search's unit cube."""
    return {k: float(CALIBRATION_BOUNDS[k][0] + float(np.clip(v, 0, 1)) * (CALIBRATION_BOUNDS[k][1] - CALIBRATION_BOUNDS[k][0])) for k, v in zip(keys, u)}


def defaults(scene: str, keys: tuple[str, ...]) -> dict[str, float]:
    """The scene's own values of ``keys`` on its half grid."""
    d = on_grid(make_scene(scene, seed=FIT_SEEDS[0]), half_grid(scene)).params.to_dict()
    out = {}
    for k in keys:
        node: Any = d
        for part in k.split("."):
            node = node.get(part) if isinstance(node, dict) else None
        if node is None and k.startswith("walls.faces."):
            node = d["walls"]["friction"]  # a face without an override has the walls' friction
        out[k] = float(node)
    return out


def rung1_fit(a: argparse.Namespace) -> None:
    import cma
    from tqdm import tqdm

    scene = a.scene
    keys = FIT_PARAMS[scene]
    n = half_grid(scene)
    name = fit_name(scene, n)
    state = a.runs / f"fit_{name}"
    state.mkdir(parents=True, exist_ok=True)
    log_path = state / "evals.jsonl"
    logged: dict[str, dict] = {}
    if log_path.is_file():
        for line in log_path.read_text().splitlines():
            e = json.loads(line)
            logged[json.dumps(e["u"])] = e
    pool = get_context("fork").Pool(a.workers)
    seeds = list(a.seeds)

    def evaluate(u: np.ndarray, gen: int) -> float:
        uu = [round(float(np.clip(v, 0, 1)), 6) for v in u]
        key = json.dumps(uu)
        if key not in logged:
            values = physical(keys, np.array(uu))
            t0 = time.time()
            res = pool.map(_fit_error, [(scene, sd, a.frames, values) for sd in seeds])
            errs = [r[0] for r in res]
            e = {"u": uu, "values": values, "per_seed": errs, "objective": float(np.mean(errs)), "generation": gen, "seconds": time.time() - t0}
            e["cpu_seconds"] = float(sum(r[1] for r in res))
            logged[key] = e
            write_file(log_path, "".join(json.dumps(x) + "\n" for x in logged.values()))  # the whole log, atomically: a kill leaves it whole
        return float(logged[key]["objective"])

    pool.map(_cache_reference, [(scene, sd, a.frames) for sd in seeds])  # the references first (cached on disk)
    d0 = defaults(scene, keys)
    u0 = np.array([(d0[k] - CALIBRATION_BOUNDS[k][0]) / (CALIBRATION_BOUNDS[k][1] - CALIBRATION_BOUNDS[k][0]) for k in keys])
    bar = tqdm(total=a.evals, desc=f"CMA-ES {name}", initial=min(len(logged), a.evals))
    plain = evaluate(u0, 0)
    es = cma.CMAEvolutionStrategy(list(u0), a.sigma0, {"bounds": [0, 1], "maxfevals": a.evals, "seed": 1, "verbose": -9, "popsize": a.popsize})
    gen = 0
    while not es.stop():
        gen += 1
        np.random.seed(1000 + gen)  # the sample of a generation: the same after a restart, so logged points are found
        X = es.ask()
        before = len(logged)
        F = [evaluate(np.asarray(x), gen) for x in X]
        es.tell(X, F)
        bar.update(len(logged) - before)
        bar.set_postfix(best=f"{min(e['objective'] for e in logged.values()):.4f}", plain=f"{plain:.4f}")
        write_file(state / "es.pkl", pickle.dumps({"generation": gen, "xbest": es.result.xbest}))
    bar.close()
    rp = pool.map(_rp_error, [(scene, sd, a.frames) for sd in seeds])
    pool.close()
    evals = sorted(logged.values(), key=lambda e: (e["generation"], e.get("seconds", 0)))
    best = min(evals, key=lambda e: e["objective"])
    # CPU time of the evaluations (wall time x workers for those logged before it was recorded)
    core_s = float(sum(e.get("cpu_seconds", e["seconds"] * a.workers) for e in evals))
    fit = {
        "name": name,
        "scene": scene,
        "n_grid": n,
        "base_n_grid": int(scene_spec(scene, seed=FIT_SEEDS[0]).params.resolved_n_grid()),
        "particles_per_cell": 2,
        "params": best["values"],
        "defaults": d0,
        "bounds": {k: list(CALIBRATION_BOUNDS[k]) for k in keys},
        "objective": f"mean over the fitting seeds of the mean grid-mass error of the half grid against full-resolution MPM (on the scene's grid) "
        f"over frames 0, {FIT_STRIDE}, ..., {a.frames}",
        "fit_seeds": seeds,
        "frames": a.frames,
        "optimizer": f"CMA-ES (cma {cma.__version__}), sigma0 {a.sigma0} of each range, popsize {a.popsize}, {len(evals)} evaluations",
        "fit": {"plain": plain, "calibrated": best["objective"], "rp": float(np.mean(rp)), "f": share(plain, float(np.mean(rp)), best["objective"])},
        "curve": [e["objective"] for e in evals],
        "core_hours": core_s / 3600.0,
        "wall_hours": float(sum(e["seconds"] for e in evals)) / 3600.0,  # the evaluations' wall time, over every (resumed) run
        "command": a.cmd,
        "held_out": None,
    }
    write_json(CALIBRATED / f"{name}.json", fit)  # package data: the fit a user runs
    save_figure(curve_chart(fit), CALIBRATED / f"{name}.png", dpi=80)
    print(json.dumps({k: fit[k] for k in ("params", "defaults", "fit", "core_hours")}, indent=1))


def curve_chart(fit: dict) -> Any:
    """The fit's evaluations and its best so far, beside the plain half grid and MPM at r_p (the figure)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    c = np.array(fit["curve"])
    fig, ax = plt.subplots(figsize=(4.5, 2.8))
    ax.plot(np.arange(len(c)), c, ".", c="C0", ms=3, label="evaluation")
    ax.plot(np.arange(len(c)), np.minimum.accumulate(c), c="C0", label="best so far")
    ax.axhline(fit["fit"]["plain"], c="C3", ls="--", lw=1, label="plain half grid")
    ax.axhline(fit["fit"]["rp"], c="k", ls=":", lw=1, label="MPM at r_p")
    ax.set_xlabel("evaluation (8 seeds x 400 frames each)", fontsize=8)
    ax.set_ylabel("mean grid-mass error", fontsize=8)
    ax.set_title(f"{fit['name']}: CMA-ES on the fitting seeds", fontsize=9)
    ax.legend(fontsize=7)
    ax.grid(alpha=0.3)
    fig.tight_layout()
    return fig


def rung1_seed(scene: str, seed: int, frames: int) -> dict:
    """MPM at r_p, the plain and the calibrated half grid on one seed: errors and ms per frame (one run)."""
    base = make_scene(scene, seed=seed)
    n0 = base.params.resolved_n_grid()
    ref = reference(scene, seed, frames)
    n = n0 // 2
    configs = {
        "rp": lambda: MpmSimulator(base, r_p=PAPER_R_P, seed=seed, threads=1),
        "plain": lambda: MpmSimulator(base, n_grid=n, threads=1),
        "calibrated": lambda: MpmSimulator(base, n_grid=n, threads=1, calibrated=True),  # the shipped fit, as a user runs it
    }
    pos, ms = timed(configs, frames)
    return {"scene": scene, "seed": seed, "ms": ms, "error": {k: errors(v, ref, n0) for k, v in pos.items()}}


def rung1_eval(a: argparse.Namespace) -> None:
    from tqdm import tqdm

    scene = a.scene
    name = fit_name(scene, half_grid(scene))
    path = CALIBRATED / f"{name}.json"
    fit = json.loads(path.read_text())
    rows = [rung1_seed(scene, sd, a.frames) for sd in tqdm(a.seeds, desc=f"held-out {name}")]
    summary = {m: summarise(rows, ["plain", "calibrated"], m) for m in ("grid", "half")}
    g = summary["grid"]
    fit["held_out"] = {
        "seeds": list(a.seeds),
        "frames": a.frames,
        "error": {"rp": g["rp"]["error"], "plain": g["plain"]["error"], "calibrated": g["calibrated"]["error"]},
        "per_seed": {str(r["seed"]): {k: r["error"][k]["grid"] for k in ("rp", "plain", "calibrated")} for r in rows},
        "f": g["calibrated"]["f"],
        "f_seeds": g["calibrated"]["f_seeds"],
        "error_ratio": {k: g[k]["error_ratio"] for k in ("plain", "calibrated")},
        "time_ratio": {k: g[k]["time_ratio"] for k in ("plain", "calibrated")},
        "f_half_grid_deposit": summary["half"]["calibrated"]["f"],
        "command": a.cmd,
    }
    write_json(path, fit)
    write_results(a.out, f"rung1_{scene}", doc={"fit": fit, "rows": rows, "summary": summary})
    write_file(CALIBRATED / f"{name}.md", card(fit, provenance()))
    print((CALIBRATED / f"{name}.md").read_text())


def card(fit: dict, prov: dict) -> str:
    """The fit's card (package data beside it), its held-out timings with the machine and load of ``prov`` (the harness's provenance)."""
    h = fit["held_out"]
    vals = "\n".join(f"| `{k}` | {fit['defaults'][k]:.4g} | {v:.4g} | [{fit['bounds'][k][0]:g}, {fit['bounds'][k][1]:g}] |" for k, v in fit["params"].items())
    er, tr = h["error_ratio"], h["time_ratio"]
    return f"""# Calibrated coarse material: {fit["scene"]} on {fit["n_grid"]}^{2 if fit["base_n_grid"] > 64 else 3}

Plain MPM on half the scene's grid ({fit["n_grid"]} for {fit["base_n_grid"]}, 2 particles per cell per axis) with
constitutive parameters fitted so that it follows full-resolution MPM more closely; nothing else changes and it costs
nothing at run time (docs/correction.md, "Rung 1"). Run it with
`hybridmpm simulate {fit["scene"]} --solver mpm --n-grid {fit["n_grid"]} --calibrated` or
`MpmSimulator(scene, n_grid={fit["n_grid"]}, calibrated=True)`.

| parameter | scene's value | calibrated | bounds searched |
|---|---|---|---|
{vals}

- **Objective**: {fit["objective"]}.
- **Fitting seeds**: {fit["fit_seeds"][0]}-{fit["fit_seeds"][-1]} ({len(fit["fit_seeds"])} seeds, {fit["frames"]} frames); {fit["optimizer"]};
  {fit["core_hours"]:.2f} core-hours ({fit["wall_hours"]:.2f} h wall on a shared 2-core machine).
- **On the fitting seeds**: plain {fit["fit"]["plain"]:.3f}, calibrated {fit["fit"]["calibrated"]:.3f}, MPM at r_p {fit["fit"]["rp"]:.3f}:
  f = {fit["fit"]["f"]:+.2f} of the half grid's excess error over MPM at r_p removed.
- **Held-out seeds** {h["seeds"][0]}-{h["seeds"][-1]} ({len(h["seeds"])} seeds, {h["frames"]} frames): plain {h["error"]["plain"]:.3f},
  calibrated {h["error"]["calibrated"]:.3f}, MPM at r_p {h["error"]["rp"]:.3f}; **f = {h["f"]:+.2f}** (per seed {rng3(h["f_seeds"])});
  error / MPM at r_p's: plain {rng3(er["plain"])}, calibrated {rng3(er["calibrated"])} (median, range over seeds);
  time / MPM at r_p's: plain {rng3(tr["plain"])}, calibrated {rng3(tr["calibrated"])} (one thread, one run;
  {prov["machine"]}, load {prov["load_after"][0]:.1f}). With every field deposited on the half grid: f = {h["f_half_grid_deposit"]:+.2f}.

![the fit's curve]({fit["name"]}.png)

Fit: `{fit["command"]}`

Held-out scores: `{h["command"]}`
"""


# ------------------------------------------------------------------ main


def main() -> None:
    import sys

    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = ap.add_subparsers(dest="cmd_name", required=True)
    p0 = sub.add_parser("rung0", help="more particles per cell on the half grid; the error's own deposit")
    p0.add_argument("scenes", nargs="*", default=["sand2d", "sand3d"])
    p1 = sub.add_parser("rung1-fit", help="CMA-ES fit of the coarse material on the fitting seeds (resumable)")
    p1.add_argument("scene", choices=sorted(FIT_PARAMS))
    p1.add_argument("--evals", type=int, default=84, help="the fit's budget of evaluations (each: every fitting seed, every frame)")
    p1.add_argument("--sigma0", type=float, default=0.25, help="CMA-ES's initial step, a share of each parameter's range")
    p1.add_argument("--popsize", type=int, default=6)
    p1.add_argument("--workers", type=int, default=2)
    p1.add_argument("--runs", type=Path, default=RUNS, help="the fit's state (evals.jsonl, es.pkl)")
    p2 = sub.add_parser("rung1-eval", help="score the shipped fit on the held-out seeds; writes its card")
    p2.add_argument("scene", choices=sorted(FIT_PARAMS))
    for p in (p0, p1, p2):
        p.add_argument("--frames", type=int, default=FRAMES)
        p.add_argument("--out", type=Path, default=OUT)
    p0.add_argument("--seeds", type=int, nargs="+", default=list(HELD_OUT))
    p1.add_argument("--seeds", type=int, nargs="+", default=list(FIT_SEEDS))
    p2.add_argument("--seeds", type=int, nargs="+", default=list(HELD_OUT))
    a = ap.parse_args()
    a.cmd = "python benchmarks/coarse_ladder.py " + " ".join(sys.argv[1:])
    {"rung0": rung0, "rung1-fit": rung1_fit, "rung1-eval": rung1_eval}[a.cmd_name](a)


if __name__ == "__main__":
    main()
