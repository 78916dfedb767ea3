"""Running the benchmark: every method × seed from the same held-out initial
condition, per-frame latency and every score of :data:`~hybridmpm.metrics.ROLLOUT_METRICS`
against full-resolution MPM (the grid-mass error every stored frame; the
others, :func:`~hybridmpm.metrics.rollout_metrics`, on the frames every method
stores), with what the scores cost against the rollout's own time.

One *cell* is one method on one seed. Cells are written as JSON under
``OUT/cells/`` as they finish; a rerun skips finished cells (resumable), and
the full-resolution reference positions and masses of each seed are cached in
``OUT/cells/ref_seed<S>.npz``. A cell made before the scores it lacks
(:data:`METRICS_VERSION`) or on other common frames is rerun.

Latency (paper App. C): wall time of each step (a step covers ``r_t``
frames; MPM methods step one frame), divided by ``r_t``, for the frames after
the first ``warmup`` frames (the network's MPM history frames and
onnxruntime's first runs). Start-up (scene build, r_p clustering, model
load) is never timed. Reported: median, p95 and mean over frames; the mean
is the throughput a user sees and is what the charts plot.
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from hybridmpm.bench.cost import gnn_flops
from hybridmpm.bench.harness import provenance, write_json
from hybridmpm.bench.methods import Method
from hybridmpm.errors import InvalidInputError, SimulationError
from hybridmpm.limits import check_seed
from hybridmpm.metrics import dam_break_front, dam_break_geometry, grid_mass_error, rollout_metrics
from hybridmpm.scenes import make_scene
from hybridmpm.sim import MPM, HybridSimulator, MpmSimulator, NeuralSimulator, Rollout, Simulator, reference, rollout

#: Held-out seeds: trajectory seeds of generated datasets are 31-bit hashes
#: (:func:`hybridmpm.train.datasets.trajectory_seed`), so small integers never
#: coincide with a training trajectory. Test seeds start at 1000, validation
#: seeds (``hybridmpm tune``) at 2000.
TEST_SEED0 = 1000
VALID_SEED0 = 2000

#: Frames at the start of every rollout that are not timed.
WARMUP_FRAMES = 24

#: A network run alone breaks off ("collapsed") once its graph holds this many
#: times the neighbours per particle of the initial condition: particles have
#: piled up, the rollout is physically meaningless, and every step costs
#: ~this factor more (a collapsed full-resolution water2d rollout ran for
#: over 10 minutes). The hybrid falls back to MPM at 2× (``degree_factor``).
COLLAPSE_FACTOR = 8.0

#: The scores a cell records; a cell of another version (or none: made before them) is rerun. 2: the Sinkhorn
#: divergence reduces a large set on a lattice, not by a draw of particle indices (:mod:`hybridmpm.metrics.transport`).
METRICS_VERSION = 2


@dataclass
class BenchConfig:
    """Settings of one benchmark run (stored in ``OUT/bench.json``; a resumed
    run must match them).

    ``scene`` registered scene; ``seeds`` initial conditions; ``frames``
    frames per rollout; ``warmup`` untimed frames; ``mpm_threads`` MPM threads
    (0 = all cores); ``nn_threads`` onnxruntime threads of the hybrid (one:
    its MPM frames follow its network steps, and a spinning onnxruntime
    worker would slow them); ``nn_alone_threads`` those of the networks run
    alone (0 = all cores, as MPM: nothing else runs then; "two
    onnxruntime threads when MPM is idle").
    """

    scene: str
    seeds: tuple[int, ...]
    frames: int
    warmup: int = WARMUP_FRAMES
    mpm_threads: int = 0
    nn_threads: int = 1
    nn_alone_threads: int = 0

    def validate(self) -> BenchConfig:
        if not self.seeds:
            raise InvalidInputError("seeds: at least one seed", "seeds")
        for seed in self.seeds:
            check_seed(seed, "seeds")
        if not isinstance(self.frames, int) or self.frames < 2:
            raise InvalidInputError(f"frames: must be an integer >= 2, got {self.frames!r}", "frames")
        if not isinstance(self.warmup, int) or not (0 <= self.warmup < self.frames):
            raise InvalidInputError(f"warmup: must be an integer in [0, frames), got {self.warmup!r}", "warmup")
        for name in ("mpm_threads", "nn_threads", "nn_alone_threads"):
            v = getattr(self, name)
            if not isinstance(v, int) or v < 0:
                raise InvalidInputError(f"{name}: must be an integer >= 0, got {v!r}", name)
        return self

    def fingerprint(self) -> dict[str, Any]:
        return {
            "scene": self.scene,
            "frames": self.frames,
            "warmup": self.warmup,
            "mpm_threads": self.mpm_threads,
            "nn_threads": self.nn_threads,
            "nn_alone_threads": self.nn_alone_threads,
        }


def _latency(per_frame: np.ndarray) -> dict[str, float]:
    if len(per_frame) == 0:
        return {"ms_median": float("nan"), "ms_p95": float("nan"), "ms_mean": float("nan")}
    ms = np.asarray(per_frame) * 1e3
    return {"ms_median": float(np.median(ms)), "ms_p95": float(np.percentile(ms, 95)), "ms_mean": float(ms.mean())}


def reference_cell(cfg: BenchConfig, seed: int, cells: Path, stride: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """Full-resolution MPM of ``seed``: its fluid positions every frame
    [frames + 1, N, D] and masses [N], cached in ``cells/ref_seed<S>.npz``
    together with the ``mpm_full`` cell (its timing; ``stride`` the common
    frames of its scores); both are (re)made when either is missing or stale."""
    path, cell = cells / f"ref_seed{seed}.npz", cells / f"mpm_full_seed{seed}.json"
    if path.is_file() and _cell_current(cell, None, stride):
        with np.load(path) as z:
            if int(z["frames"]) == cfg.frames and "masses" in z:
                return np.asarray(z["positions"]), np.asarray(z["masses"])
    scene = make_scene(cfg.scene, seed=seed)
    ro = reference(scene, cfg.frames, threads=cfg.mpm_threads)
    pos, masses = ro.fluid_positions, fluid_masses(ro)
    tmp = path.with_name(path.stem + ".tmp.npz")
    np.savez(tmp, positions=pos, masses=masses, frames=np.int64(cfg.frames))
    tmp.replace(path)
    _write_json(cell, _reference_record(cfg, seed, scene, ro, stride))
    return pos, masses


def fluid_masses(ro: Rollout) -> np.ndarray:
    """The fluid particles' masses of rollout ``ro`` [kg], float [num_fluid] (the Sinkhorn divergence's and the
    kinetic energy's weights); :class:`SimulationError` if the simulator recorded none."""
    if ro.masses is None:
        raise SimulationError("rollout: the simulator recorded no particle masses")
    return ro.masses[: ro.num_fluid]


def method_simulator(method: Method, scene: Any, seed: int, cfg: BenchConfig) -> Simulator:
    """The simulator of a benchmarked method (the network alone without the
    hybrid's failure checks: it breaks off at :data:`COLLAPSE_FACTOR` instead)."""
    if method.kind == "mpm":
        return MpmSimulator(
            scene, r_p=method.r_p, seed=seed, threads=cfg.mpm_threads, n_grid=method.n_grid, calibrated=method.calibrated, integrator=method.integrator
        )
    if method.kind == "neural":
        return NeuralSimulator(scene, method.model, seed=seed, detect_failures=False, mpm_threads=cfg.mpm_threads, nn_threads=cfg.nn_alone_threads)
    rule: dict[str, Any] = {} if method.safeguard is None else {"safeguard": method.safeguard}
    if method.audit_tol is not None:
        rule["audit_tol"] = method.audit_tol
    if method.cheap_particles is not None:  # the classical twin with the coarse grid's own particle set
        rule["cheap_particles"] = method.cheap_particles
    return HybridSimulator(
        scene, method.model, r_c=float(method.r_c or 0.0), seed=seed, mpm_threads=cfg.mpm_threads, nn_threads=cfg.nn_threads, cheap=method.cheap, **rule
    )


def collapsed(frame: Any, sim: Any) -> str | None:
    """Stop rule of a network run alone: "collapsed" once its graph holds
    :data:`COLLAPSE_FACTOR` × the initial neighbours per particle."""
    return "collapsed" if sim.mean_degree > COLLAPSE_FACTOR * sim.initial_degree else None


def held_still(positions: np.ndarray, frame_index: np.ndarray, warmup: int) -> np.ndarray:
    """The trivial model every network must beat: ``positions`` [F, N, D]
    (frames ``frame_index`` [F], which must include ``warmup``) with every
    frame after ``warmup`` replaced by the positions at ``warmup`` (the
    particles held still after the network's MPM warm-up, see
    :func:`hybridmpm.sim.warmup_frames`). Returns a new array."""
    still = positions.copy()
    still[frame_index > warmup] = positions[frame_index == warmup][0]
    return still


def run_cell(method: Method, cfg: BenchConfig, seed: int, ref: tuple[np.ndarray, np.ndarray], stride: int = 1) -> dict[str, Any]:
    """One method on one seed against ``ref`` (:func:`reference_cell`'s
    positions and masses): the cell's record (errors per stored frame, solver
    per stored frame, latency, MPM share, switches, failure, and every score
    of :func:`~hybridmpm.metrics.rollout_metrics` on the stored frames that
    are multiples of ``stride``, the largest ``r_t`` compared, with their cost
    ``metric_seconds`` and ``metric_cost`` = their sum ÷ ``rollout_seconds``).
    Raises :class:`SimulationError` if an MPM method fails."""
    scene = make_scene(cfg.scene, seed=seed)
    sim = method_simulator(method, scene, seed, cfg)
    ro = rollout(sim, cfg.frames, stop=collapsed if method.kind == "neural" else None)
    if method.kind == "mpm" and ro.failure is not None:
        raise SimulationError(f"{method.key} seed {seed}: {ro.failure_detail or ro.failure}")
    steps = ro.stats["steps"]
    if method.kind == "mpm":
        substeps, mflop = float(ro.substeps[1:].mean()), 0.0
    elif method.cheap != "neural":  # the classical twin runs no network
        substeps, mflop = float("nan"), 0.0
    else:
        # the network's arithmetic per frame on the initial graph (nodes: fluid and boundary particles)
        meta = sim.model.meta  # type: ignore[attr-defined]
        nodes = sim.particles.num_total
        if "latent" in meta:  # a GNS; a grid model's cost is its U-Net's, not counted here
            flops = gnn_flops(int(meta["latent"]), int(meta["layers"]), sim.scene.dim, nodes, int(round(sim.initial_degree * nodes)), sim.t_in)  # type: ignore[attr-defined]
            substeps, mflop = float("nan"), flops / sim.r_t / 1e6
        else:
            substeps, mflop = float("nan"), float("nan")
    frames_of = ro.frame_index
    keep = frames_of <= cfg.frames
    pos, frames_of, neural = ro.fluid_positions[keep], frames_of[keep], (ro.solver[keep] != MPM).astype(np.int8)  # the cheap half's frames
    ref_pos, ref_masses = ref
    t0 = time.perf_counter()
    err = grid_mass_error(pos, ref_pos[frames_of], scene.params.resolved_n_grid())
    grid_s = time.perf_counter() - t0
    common = frames_of % int(stride) == 0
    scores = rollout_metrics(
        pos[common], ref_pos[frames_of[common]], frames_of[common] * scene.dt_frame, scene.params.resolved_n_grid(), errors=err[common],
        pred_weights=fluid_masses(ro), ref_weights=ref_masses, dam_break=dam_break_geometry(scene.info),
    )  # fmt: skip
    return {
        "method": method.key, "seed": int(seed), "particles": int(ro.num_fluid), "frames_done": int(frames_of[-1]),
        "failure": ro.failure, "error_mean": float(err.mean()), "error_last": float(err[-1]),
        **_latency(ro.frame_seconds(after=cfg.warmup)), "mpm_share": steps["mpm"] / max(1, sum(steps.values())),
        "switches": int(ro.stats["switches"]), "substeps_per_frame": substeps, "mflop_per_frame": mflop,
        "series": {"frame": frames_of.tolist(), "error": [float(e) for e in err], "neural": neural.tolist(), "scores": scores["series"]},
        **_scores(scores, grid_s, float(ro.seconds.sum()), stride),
    }  # fmt: skip


def _scores(scores: dict[str, Any], grid_s: float, rollout_s: float, stride: int) -> dict[str, Any]:
    """A cell's scores (besides the grid-mass error's mean and last) and their cost against the rollout's wall time."""
    seconds = {**scores["seconds"], "grid_mass": grid_s}
    return {
        **{k: scores[k] for k in ("short_error", "sinkhorn", "ke_error", "front_rms")},
        "metric_seconds": seconds, "rollout_seconds": rollout_s, "metric_cost": sum(seconds.values()) / rollout_s if rollout_s > 0 else float("nan"),
        "metrics_version": METRICS_VERSION, "metric_stride": int(stride),
    }  # fmt: skip


def _reference_record(cfg: BenchConfig, seed: int, scene: Any, ro: Rollout, stride: int) -> dict[str, Any]:
    """The ``mpm_full`` cell: the reference itself (every score against itself 0 by
    definition; the dam break's front against the experiment its own) and its timing."""
    n = cfg.frames + 1
    geo = dam_break_geometry(scene.info)
    t0 = time.perf_counter()
    common = ro.frame_index % int(stride) == 0
    front = dam_break_front(ro.fluid_positions[common], ro.frame_index[common] * scene.dt_frame, geo) if geo is not None else None
    scores = {
        "short_error": 0.0, "sinkhorn": 0.0, "ke_error": 0.0, "front_rms": float("nan") if front is None or front["rms"] is None else front["rms"],
        "seconds": {"front": time.perf_counter() - t0}, "series": {},
    }  # fmt: skip
    return {
        "method": "mpm_full", "seed": int(seed), "particles": int(scene.num_particles), "frames_done": cfg.frames, "failure": None,
        "error_mean": 0.0, "error_last": 0.0, **_latency(ro.frame_seconds(after=cfg.warmup)), "mpm_share": 1.0, "switches": 0,
        "substeps_per_frame": float(np.mean(ro.substeps[1:])), "mflop_per_frame": 0.0,
        "series": {"frame": list(range(n)), "error": [0.0] * n, "neural": [0] * n},
        **_scores(scores, 0.0, float(ro.seconds.sum()), stride),
    }  # fmt: skip


def model_digest(method: Method) -> str | None:
    """sha256 of the method's ONNX file (None for MPM): a finished cell is
    reused only if it was made with the same model bytes."""
    if method.model is None:
        return None
    import hashlib

    return hashlib.sha256(Path(method.model).read_bytes()).hexdigest()


def _cell_current(path: Path, digest: str | None, stride: int) -> bool:
    """A finished cell made with the model of ``digest`` (cells written before
    cells recorded their model count as current only for MPM methods), with
    the scores of :data:`METRICS_VERSION` on the frames that are multiples of ``stride``."""
    if not path.is_file():
        return False
    try:
        cell = json.loads(path.read_text())
    except (OSError, ValueError):
        return False  # a torn or foreign file: recompute it
    return cell.get("model_sha256") == digest and cell.get("metrics_version") == METRICS_VERSION and cell.get("metric_stride") == stride


def _write_json(path: Path, obj: Any) -> None:
    """``obj`` as compact JSON at ``path``, atomically (:func:`hybridmpm.bench.harness.write_json`)."""
    write_json(path, obj, indent=None)


def run_bench(
    cfg: BenchConfig,
    methods: list[Method],
    out: str | Path,
    progress: bool = True,
) -> list[dict[str, Any]]:
    """Run (or resume) every method × seed; returns the cell records in
    (method, seed) order. Writes ``out/bench.json`` and ``out/cells/*.json``.
    A finished cell is reused only if it was made with the same model file
    (its sha256, recorded in the cell); one made with another model, e.g.
    before a model was re-shipped, is recomputed.

    Raises :class:`InvalidInputError` (field ``out``) if ``out`` holds a
    benchmark made with other settings (frames, warm-up, threads, scene).
    """
    from tqdm import tqdm

    cfg.validate()
    out = Path(out)
    cells = out / "cells"
    cells.mkdir(parents=True, exist_ok=True)
    meta_path = out / "bench.json"
    if meta_path.is_file():
        old = json.loads(meta_path.read_text()).get("settings", {})
        if old and "nn_alone_threads" not in old:  # written before the setting: the networks alone ran as the hybrid
            old["nn_alone_threads"] = old.get("nn_threads")
        if old and old != cfg.fingerprint():
            diff = ", ".join(f"{k} {old.get(k)!r} → {v!r}" for k, v in cfg.fingerprint().items() if old.get(k) != v)
            raise InvalidInputError(f"out: {out} holds a benchmark with other settings ({diff}); use another --out or delete it", "out")
    env = provenance()  # the one machine description (the harness's): machine, commit, versions, load, command
    _write_json(meta_path, {"settings": cfg.fingerprint(), "environment": env})
    keys = [m.key for m in methods]
    if len(set(keys)) != len(keys):
        raise InvalidInputError("methods: duplicate method keys", "methods")
    digests = {m.key: model_digest(m) for m in methods}
    stride = max(m.r_t for m in methods)  # the scores are computed on the frames every method stores
    todo = [(m, s) for s in cfg.seeds for m in methods if not _cell_current(cells / f"{m.key}_seed{s}.json", digests[m.key], stride)]
    bar = tqdm(
        total=len(methods) * len(cfg.seeds), initial=len(methods) * len(cfg.seeds) - len(todo), desc=f"bench {cfg.scene}", unit="cell", disable=not progress
    )
    refs: dict[int, tuple[np.ndarray, np.ndarray]] = {}
    for m, s in todo:
        bar.set_postfix_str(f"{m.key} seed {s}", refresh=True)
        if s not in refs:
            refs = {s: reference_cell(cfg, s, cells, stride)}  # one seed's reference in memory at a time; writes the mpm_full cell
        path = cells / f"{m.key}_seed{s}.json"
        if not _cell_current(path, digests[m.key], stride):
            _write_json(path, {**run_cell(m, cfg, s, refs[s], stride), "model_sha256": digests[m.key]})
        bar.update()
    bar.close()
    return [json.loads((cells / f"{m.key}_seed{s}.json").read_text()) for m in methods for s in cfg.seeds]
