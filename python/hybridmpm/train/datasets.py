"""Dataset generation: MPM rollouts of random initial conditions in the GNS layout.

``hybridmpm generate SCENE --trajectories M --out DIR`` runs :func:`generate_dataset`:
trajectory ``i`` starts from the scene's random initial condition for the seed
``trajectory_seed(S, i)``, optionally downsampled to ``r_p`` (k-means, see
:mod:`hybridmpm.scenes.resolution`) and stored every ``r_t`` frames. Trajectories
run in parallel worker processes (or on a Ray cluster, ``executor="ray"``);
each finished one is written atomically to ``DIR/parts/`` so an interrupted run
resumes without redoing finished work, and the result is byte-identical to an
uninterrupted run. When all are done, the parts are assembled into
``train.npz``/``valid.npz``/``test.npz`` and ``metadata.json`` (GNS layout,
:mod:`hybridmpm.data.gns`) plus ``scenes.json`` (the seed and spec of every
trajectory, so any of them can be re-simulated).

Low-resolution data (``r_p < 1``) is, by default, produced by *simulating the
clustered initial condition with MPM* (``lowres="simulate"``): it is exactly
the dynamics the hybrid simulator's MPM fallback runs on the same particle set.
``lowres="centroids"`` instead follows the cluster centroids of the
full-resolution rollout (see docs/datasets.md for the comparison).
"""

from __future__ import annotations

import json
import math
import os
import time
from collections.abc import Callable, Iterator, Mapping
from concurrent.futures import FIRST_COMPLETED, Future, ProcessPoolExecutor, wait
from dataclasses import asdict, dataclass, field
from multiprocessing import get_context
from pathlib import Path
from typing import Any, Literal

import numpy as np

from hybridmpm import _core
from hybridmpm.conventions import GNS_KINEMATIC, GNS_SAND, GNS_WATER, SPLITS
from hybridmpm.data import gns
from hybridmpm.errors import HybridMpmError, InvalidInputError, SimulationError
from hybridmpm.limits import check_allocation
from hybridmpm.scenes import DOMAINS, SceneSpec, scene_spec
from hybridmpm.scenes.resolution import check_r_p, check_r_t, cluster_centroids, downsample_scene
from hybridmpm.sim import MpmSimulator, rollout

LowRes = Literal["simulate", "centroids"]
Executor = Literal["process", "ray"]


def trajectory_seed(seed: int, index: int) -> int:
    """Seed of trajectory ``index`` of a dataset generated with ``seed`` (independent streams)."""
    return int(np.random.SeedSequence([int(seed), int(index)]).generate_state(1, np.uint32)[0] >> 1)


def trajectory_id(index: int) -> str:
    """GNS trajectory key of trajectory ``index``."""
    return f"simulation_trajectory_{index:05d}"


@dataclass
class GenerateConfig:
    """What :func:`generate_dataset` produces; stored as ``DIR/generate.json``.

    ``scene`` a registered domain; ``trajectories`` M ≥ 3 (split into
    train/valid/test by ``split`` fractions, at least one each); ``frames`` T
    per trajectory at ``dt_frame`` (None: the paper's T for the domain);
    ``seed`` the dataset seed; ``r_p ∈ (0, 1]``, ``r_t ≥ 1`` the
    spatial/temporal downsampling; ``lowres`` how low-resolution data is made.
    """

    scene: str
    trajectories: int
    frames: int | None = None
    seed: int = 0
    r_p: float = 1.0
    r_t: int = 1
    lowres: LowRes = "simulate"
    split: tuple[float, float, float] = (0.8, 0.1, 0.1)

    def validate(self) -> GenerateConfig:
        if self.scene not in DOMAINS:
            raise InvalidInputError(f"scene: unknown scene {self.scene!r} (available: {', '.join(sorted(DOMAINS))})", "scene")
        if not isinstance(self.trajectories, int) or self.trajectories < 3:
            raise InvalidInputError(f"trajectories: need at least 3 (one per split), got {self.trajectories!r}", "trajectories")
        if isinstance(self.seed, bool) or not isinstance(self.seed, (int, np.integer)) or not 0 <= int(self.seed) < 2**63:
            raise InvalidInputError(f"seed: must be an integer in [0, 2^63), got {self.seed!r}", "seed")
        if self.frames is not None and (not isinstance(self.frames, int) or self.frames < 1):
            raise InvalidInputError(f"frames: must be an integer >= 1, got {self.frames!r}", "frames")
        check_r_p(self.r_p)
        check_r_t(self.r_t)
        frames = self.resolved_frames()
        if frames // self.r_t < 2:
            raise InvalidInputError(f"frames: need at least 2·r_t = {2 * self.r_t} frames to store 3 positions, got {frames}", "frames")
        # one trajectory in memory (the rollout and its stored copy), sized on the domain's first scene
        scene = scene_spec(self.scene, seed=0).build()
        n = scene.num_particles + scene.num_boundary
        check_allocation("frames", 3.0 * (frames // self.r_t + 1) * n * scene.dim * 4, f"a trajectory of {frames} frames of about {n} particles")
        if self.lowres not in ("simulate", "centroids"):
            raise InvalidInputError(f"lowres: must be 'simulate' or 'centroids', got {self.lowres!r}", "lowres")
        s = tuple(float(v) for v in self.split)
        if len(s) != 3 or any(not math.isfinite(v) or v < 0 for v in s) or abs(sum(s) - 1.0) > 1e-6:
            raise InvalidInputError(f"split: three non-negative fractions summing to 1, got {self.split!r}", "split")
        self.split = (s[0], s[1], s[2])
        return self

    def resolved_frames(self) -> int:
        return int(self.frames) if self.frames is not None else scene_spec(self.scene, seed=0).frames

    def split_of(self) -> list[str]:
        """Split name of each trajectory index: the first ones train, then valid, then test."""
        m = self.trajectories
        n_valid = max(1, int(round(self.split[1] * m)))
        n_test = max(1, int(round(self.split[2] * m)))
        n_train = m - n_valid - n_test
        if n_train < 1:
            raise InvalidInputError(f"trajectories: {m} is too few for the split {self.split}", "trajectories")
        return ["train"] * n_train + ["valid"] * n_valid + ["test"] * n_test

    def to_json(self) -> dict[str, Any]:
        d = asdict(self)
        d["split"] = list(self.split)
        d["frames"] = self.resolved_frames()
        return d


# --------------------------------------------------------------------------- one trajectory
def simulate_trajectory(
    scene: str | SceneSpec,
    seed: int,
    frames: int,
    r_p: float = 1.0,
    r_t: int = 1,
    lowres: LowRes = "simulate",
    num_threads: int = 1,
) -> dict[str, Any]:
    """Run one MPM rollout of a scene's random initial condition.

    Returns a dict: ``positions`` float32 [T//r_t + 1, N_l + B, D] (solver
    particles, then static boundary particles), ``particle_type`` int64
    [N_l + B], ``material`` int32 [N_l], ``masses`` float32 [N_l] (kg),
    ``spec`` (the scene spec as a dict), ``seed``, ``n_h`` (particles before
    downsampling), ``substeps`` (total MPM substeps over the ``(T//r_t)·r_t``
    frames run), ``wall_s``.
    Raises :class:`~hybridmpm.errors.SimulationError` if MPM fails.
    """
    t0 = time.perf_counter()
    spec = scene_spec(scene, seed=seed, frames=frames) if isinstance(scene, str) else scene
    full = spec.build()
    down = downsample_scene(full, r_p, seed=seed)
    if lowres == "centroids" and r_p < 1.0:
        run_scene, labels = full, down.labels
    else:
        run_scene, labels = down.scene, None
    sim = MpmSimulator(run_scene, r_t=r_t, threads=num_threads)
    ro = rollout(sim, (frames // r_t) * r_t)
    if ro.failure is not None:
        raise SimulationError(f"MPM failed after {ro.frames_done} frames: {ro.failure_detail or ro.failure}")
    traj = ro.fluid_positions
    substeps = int(ro.substeps.sum())
    masses = np.asarray(sim.particles.masses, np.float32)
    if labels is not None:  # follow the clusters of the full-resolution rollout
        traj = cluster_centroids(traj, labels, masses)
        masses = np.asarray(down.scene.masses, np.float32)
    low = down.scene
    return {
        "positions": low.with_boundary(traj),
        "particle_type": low.particle_type(),
        "material": np.asarray(low.material, np.int32),
        "masses": masses,
        "spec": spec.to_dict(),
        "seed": int(seed),
        "n_h": int(full.num_particles),
        "substeps": int(substeps),
        "wall_s": time.perf_counter() - t0,
    }


def _task(args: tuple[str, int, int, int, float, int, str, int]) -> tuple[int, dict[str, Any]]:
    """One trajectory; an MPM failure is returned as ``{"error": message}`` so
    that it does not stop the other trajectories."""
    scene, index, seed, frames, r_p, r_t, lowres, threads = args
    try:
        return index, simulate_trajectory(scene, seed, frames, r_p, r_t, lowres, num_threads=threads)  # type: ignore[arg-type]
    except SimulationError as e:
        return index, {"error": f"seed {seed}: {e}"}


# --------------------------------------------------------------------------- executors
def _map_process(tasks: list[tuple], workers: int) -> Iterator[tuple[int, dict[str, Any]]]:
    if workers == 1:
        for t in tasks:
            yield _task(t)
        return
    # spawn: workers start clean (no inherited thread pools), the same on every OS
    with ProcessPoolExecutor(max_workers=workers, mp_context=get_context("spawn")) as pool:
        pending: set[Future] = {pool.submit(_task, t) for t in tasks}
        try:
            while pending:
                done, pending = wait(pending, return_when=FIRST_COMPLETED)
                for fut in done:
                    yield fut.result()
        finally:
            for fut in pending:
                fut.cancel()


def _map_ray(tasks: list[tuple], workers: int) -> Iterator[tuple[int, dict[str, Any]]]:
    """Run the tasks on Ray: the cluster named by ``RAY_ADDRESS`` if set, else a
    local Ray instance with ``workers`` CPUs. The driver writes all files, so
    the workers need no shared filesystem."""
    try:
        import ray
    except ImportError as e:  # pragma: no cover - depends on the environment
        raise HybridMpmError("executor: 'ray' needs Ray: pip install 'hybridmpm[cluster]'") from e
    started = False
    if not ray.is_initialized():
        address = os.environ.get("RAY_ADDRESS")
        kwargs: dict[str, Any] = {"include_dashboard": False, "log_to_driver": False}
        if address:
            ray.init(address=address, **kwargs)
        else:
            ray.init(num_cpus=workers, **kwargs)
        started = True
    try:
        remote = ray.remote(num_cpus=1)(_task)
        pending = [remote.remote(t) for t in tasks]
        while pending:
            done, pending = ray.wait(pending, num_returns=1)
            for ref in done:
                yield ray.get(ref)
    finally:
        if started:
            ray.shutdown()


EXECUTORS: dict[str, Callable[[list[tuple], int], Iterator[tuple[int, dict[str, Any]]]]] = {"process": _map_process, "ray": _map_ray}


# --------------------------------------------------------------------------- files
def _atomic_savez(path: Path, **arrays: Any) -> None:
    tmp = path.with_name(path.name + ".tmp")
    with open(tmp, "wb") as f:
        np.savez(f, **arrays)
    os.replace(tmp, path)


def _write_part(path: Path, result: dict[str, Any]) -> None:
    _atomic_savez(
        path,
        positions=result["positions"],
        particle_type=result["particle_type"],
        material=result["material"],
        masses=result["masses"],
        seed=np.int64(result["seed"]),
        n_h=np.int64(result["n_h"]),
        substeps=np.int64(result["substeps"]),
        wall_s=np.float64(result["wall_s"]),
        spec=np.array(json.dumps(result["spec"], sort_keys=True)),
    )


def _read_part(path: Path) -> dict[str, Any] | None:
    """A finished part, or None if missing or unreadable (it is then redone)."""
    try:
        with np.load(path, allow_pickle=False) as z:
            d = {k: z[k] for k in z.files}
        d["spec"] = json.loads(str(d["spec"]))
        if d["positions"].ndim != 3 or not np.all(np.isfinite(d["positions"])):
            return None
        return d
    except Exception:  # noqa: BLE001 - any unreadable part is regenerated
        return None


def _part_info(path: Path) -> dict[str, Any]:
    """The small members of a finished part (npz members load lazily: the
    positions are not read)."""
    with np.load(path, allow_pickle=False) as z:
        return {
            "seed": int(z["seed"]),
            "n_h": int(z["n_h"]),
            "n_l": int(len(z["material"])),
            "num_boundary": int((z["particle_type"] == GNS_KINEMATIC).sum()),
            "substeps": int(z["substeps"]),
            "spec": json.loads(str(z["spec"])),
        }


class _LazySplit(Mapping[str, tuple[np.ndarray, np.ndarray]]):
    """Trajectories of one split, read from the part files on access (low memory)."""

    def __init__(self, parts: dict[str, Path]) -> None:
        self._parts = parts

    def __getitem__(self, key: str) -> tuple[np.ndarray, np.ndarray]:
        with np.load(self._parts[key], allow_pickle=False) as z:
            return z["positions"], z["particle_type"]

    def __iter__(self) -> Iterator[str]:
        return iter(self._parts)

    def __len__(self) -> int:
        return len(self._parts)


@dataclass
class GenerateReport:
    """What :func:`generate_dataset` did: trajectories simulated now / found done,
    wall time [s] in all and of the assembly into split files, dataset size on
    disk [bytes] per file, failures (index → message)."""

    out: Path
    simulated: int = 0
    resumed: int = 0
    wall_s: float = 0.0
    assemble_s: float = 0.0
    sizes: dict[str, int] = field(default_factory=dict)
    failures: dict[int, str] = field(default_factory=dict)


def generate_dataset(
    config: GenerateConfig,
    out: str | Path,
    *,
    workers: int = 2,
    executor: Executor = "process",
    keep_parts: bool = False,
    compress: bool = False,
    progress: bool = True,
) -> GenerateReport:
    """Generate (or resume) a GNS-layout dataset in ``out`` (see the module docstring).

    ``workers`` parallel trajectories; ``executor`` "process" (a local process
    pool) or "ray"; ``keep_parts`` keeps ``out/parts/``; ``compress`` deflates
    the split files (~13% smaller, slower); ``progress`` shows a progress bar.

    Raises :class:`InvalidInputError` if ``out`` holds a different generation
    (the message names the differing field) or an argument is out of range;
    :class:`HybridMpmError` if some trajectories failed (the finished ones are
    kept; rerunning retries only the failed ones).
    """
    from tqdm import tqdm

    config.validate()
    if not isinstance(workers, int) or workers < 1:
        raise InvalidInputError(f"workers: must be an integer >= 1, got {workers!r}", "workers")
    if executor not in EXECUTORS:
        raise InvalidInputError(f"executor: must be one of {sorted(EXECUTORS)}, got {executor!r}", "executor")
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    manifest = out / "generate.json"
    cfg = config.to_json()
    if manifest.exists():
        try:
            old = json.loads(manifest.read_text())
        except ValueError as e:
            raise InvalidInputError(f"out: {manifest} is not valid JSON; remove it or choose another --out", "out") from e
        for k, v in cfg.items():
            if old.get(k) != v:
                raise InvalidInputError(
                    f"{k}: {out} holds a dataset generated with {k} = {old.get(k)!r}, not {v!r}; use the same settings to resume or another --out",
                    k,
                )
    else:
        tmp = manifest.with_name("generate.json.tmp")
        tmp.write_text(json.dumps(cfg, indent=2, sort_keys=True))
        tmp.replace(manifest)

    report = GenerateReport(out)
    t_start = time.perf_counter()
    splits = config.split_of()
    frames = config.resolved_frames()
    parts_dir = out / "parts"
    done_marker = out / "metadata.json"
    if done_marker.exists() and all((out / f"{s}.npz").exists() for s in SPLITS):
        report.resumed = config.trajectories
        report.sizes = {p.name: p.stat().st_size for p in sorted(out.glob("*.npz"))}
        return report
    parts_dir.mkdir(exist_ok=True)
    todo = []
    for i in range(config.trajectories):
        if _read_part(parts_dir / f"{i:05d}.npz") is not None:
            report.resumed += 1
        else:
            threads = 0 if workers == 1 else 1
            todo.append((config.scene, i, trajectory_seed(config.seed, i), frames, config.r_p, config.r_t, config.lowres, threads))
    bar = tqdm(total=config.trajectories, initial=report.resumed, desc=f"generate {config.scene}", unit="traj", disable=not progress)
    try:
        for index, result in EXECUTORS[executor](todo, workers) if todo else iter(()):
            if "error" in result:
                report.failures[index] = result["error"]
                bar.update(1)
                continue
            _write_part(parts_dir / f"{index:05d}.npz", result)
            report.simulated += 1
            bar.set_postfix(last=f"{result['wall_s']:.1f}s")
            bar.update(1)
    finally:
        bar.close()
    if report.failures:
        lines = "; ".join(f"#{i}: {m}" for i, m in sorted(report.failures.items()))
        raise HybridMpmError(f"{len(report.failures)} trajectories failed ({lines}); the others are saved in {parts_dir}, rerun to retry")
    t_assemble = time.perf_counter()
    if progress:
        print(f"assembling {', '.join(f'{s}.npz' for s in SPLITS)} and metadata.json ...", flush=True)
    _assemble(config, out, parts_dir, splits, compress)
    if not keep_parts:
        for p in [*parts_dir.glob("*.npz"), *parts_dir.glob("*.tmp")]:
            p.unlink()
        parts_dir.rmdir()
    report.assemble_s = time.perf_counter() - t_assemble
    report.wall_s = time.perf_counter() - t_start
    report.sizes = {p.name: p.stat().st_size for p in sorted(out.glob("*.npz"))}
    return report


def _assemble(config: GenerateConfig, out: Path, parts_dir: Path, splits: list[str], compress: bool) -> None:
    parts = {i: parts_dir / f"{i:05d}.npz" for i in range(config.trajectories)}
    infos = [_part_info(parts[i]) for i in range(config.trajectories)]
    spec0 = SceneSpec.from_dict(infos[0]["spec"])
    dim = spec0.dim
    n_grid = spec0.params.resolved_n_grid()
    by_split: dict[str, dict[str, Path]] = {s: {} for s in SPLITS}
    scenes: dict[str, Any] = {}
    for i, s in enumerate(splits):
        by_split[s][trajectory_id(i)] = parts[i]
        scenes[trajectory_id(i)] = {"index": i, "split": s, **infos[i]}
    hashes = {}
    for s in SPLITS:
        gns.write_split(out / f"{s}.npz", _LazySplit(by_split[s]), compress=compress)
        hashes[s] = gns.file_sha256(out / f"{s}.npz")
    stats = gns.compute_statistics(_LazySplit(by_split["train"]).values(), exclude_types=(GNS_KINEMATIC,))
    wall = (spec0.params.walls.cells - 1) / n_grid
    frames = config.resolved_frames()

    meta = {
        "bounds": [[wall, 1.0 - wall]] * dim,
        "sequence_length": frames // config.r_t,
        "default_connectivity_radius": spec0.connectivity_radius,
        "dim": dim,
        "dt": spec0.dt_frame * config.r_t,
        **{k: [float(v) for v in np.asarray(stats[k]).ravel()] for k in ("vel_mean", "vel_std", "acc_mean", "acc_std")},
        # hybridmpm extras (GNS readers ignore them)
        "scene": config.scene,
        "n_grid": n_grid,
        "dt_frame": spec0.dt_frame,
        "frames": frames,
        "r_p": config.r_p,
        "r_t": config.r_t,
        "lowres": config.lowres,
        "particle_types": {"boundary": GNS_KINEMATIC, "water": GNS_WATER, "sand": GNS_SAND},
        "trajectories": {s: len(by_split[s]) for s in SPLITS},
        "seed": config.seed,
        "sha256": hashes,
        "generator": f"hybridmpm {_core.__version__}",
    }
    tmp = out / "scenes.json.tmp"
    tmp.write_text(json.dumps(scenes, sort_keys=True))
    tmp.replace(out / "scenes.json")
    gns.write_metadata(out / "metadata.json", meta)


__all__ = [
    "EXECUTORS",
    "SPLITS",
    "GenerateConfig",
    "GenerateReport",
    "generate_dataset",
    "simulate_trajectory",
    "trajectory_id",
    "trajectory_seed",
]
