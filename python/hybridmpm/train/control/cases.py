"""Control cases by reverse simulation (paper Sec. 3.2): the data the
controllers are measured on and the diffusion model trains on.

A case: a scene's seeded initial condition, clustered to ``r_p`` as the
hybrid's MPM runs it, simulated ``preroll`` frames into the flow; from there
``X_1 … X_T`` forward (``T = T_ctr``); the controlled run starts from ``X_T``
with every velocity (and APIC affine matrix) negated and should end on
``X_1``. The sketch is made from that controlled run (App. C); the target
fields are the paper's kinematic one and the tracking one solved through MPM
(:mod:`hybridmpm.control.reverse`), the latter being what a model learns
(:attr:`ControlCase.target_field` says why it is not smoothed afterwards).

On disk (made by ``hybridmpm generate-control``, read by ``hybridmpm
train-control``): ``ROOT/SCENE/case_SEED.npz``, one file per case
(:func:`make_case`), written atomically, so that a
stopped generation resumes where it stopped (existing files are kept). Seeds
``first_seed … first_seed + cases − 1``; even seeds get arrows and odd seeds
ovals. The held-out cases of ``benchmarks/bench_control.py`` use seeds 5000+:
training seeds must stay below :data:`HELD_OUT_SEED`.

A case file holds float32 arrays ``positions`` and ``velocities`` [N, D] (the
controlled start: fluid at ``X_T``, velocities reversed, m and m/s),
``target`` [N, D] (``X_1``), ``tracking`` and ``kinematic`` [T − 1, N, D]
(m/s², :mod:`hybridmpm.control.reverse`), ``path`` [T, N, D] (the
positions the controlled run should pass through, ``X_T … X_1``) and
``free_path`` [T, N, D] (the uncontrolled motion from the start), int64 ``particle_type`` [N] (GNS
codes), ``gravity`` [D], and the JSON strings ``sketch`` and ``info``
(scene, seed, kind, preroll, r_p, dt_frame).
"""

from __future__ import annotations

import json
import os
import zlib
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from hybridmpm.control.reverse import reverse_kinematic, reverse_tracking, smooth
from hybridmpm.control.sketch import Sketch, sketch_from_trajectory
from hybridmpm.conventions import T_CTR
from hybridmpm.errors import InvalidInputError
from hybridmpm.scenes import make_scene
from hybridmpm.sim import MpmSimulator, rollout

#: Resolution of the controlled MPM: the shipped networks' r_p (the hybrid's MPM).
CONTROL_R_P = 0.5714


@dataclass
class ControlCase:
    """One case: ``scene`` and ``seed``; ``start`` the controlled run's start
    state (an :class:`~hybridmpm.sim.MpmSimulator` state); ``target`` float32
    [N, D] the positions it should end on (``X_1``); ``sketch``; the fields
    ``kinematic`` and ``tracking`` float32 [T − 1, N, D] (controlled frame
    ``k`` → ``k + 1``); ``path`` float32 [T, N, D] the positions the
    controlled run should pass through, ``y_k = X_{T−k}`` (``path[0]`` the
    start, ``path[-1]`` the target); ``free_path`` float32 [T, N, D] the
    uncontrolled motion from the same start (what a blank sketch should
    leave alone); ``r_p``, ``preroll``."""

    scene: str
    seed: int
    kind: str
    r_p: float
    preroll: int
    start: dict[str, Any]
    target: np.ndarray
    sketch: Sketch
    kinematic: np.ndarray
    tracking: np.ndarray
    path: np.ndarray | None = None
    free_path: np.ndarray | None = None

    @property
    def target_field(self) -> np.ndarray:
        """What a controller should output, float32 [T − 1, N, D]: the tracking
        field as solved. Smoothing it afterwards as App. D does (λ = 0.1,
        β = 2) breaks the landing — the replay then misses ``X_1`` by ~3 cm
        instead of ~3 mm on water2d (``benchmarks/bench_control.py``,
        method "smoothed") — while the tracking field is already smooth
        (mean cosine of consecutive frames ≈ 0.9); so it is used as it is."""
        return self.tracking

    @property
    def smoothed_field(self) -> np.ndarray:
        """The tracking field smoothed afterwards (App. D, λ = 0.1, β = 2), for comparison."""
        return smooth(self.tracking)

    def simulator(self, threads: int = 1) -> MpmSimulator:
        """A fresh simulator at the case's start state."""
        sim = MpmSimulator(make_scene(self.scene, seed=self.seed), r_p=self.r_p, seed=self.seed, threads=threads)
        sim.restore(self.start)
        return sim


def make_case(
    scene: str,
    seed: int,
    kind: str = "arrow",
    *,
    frames: int = T_CTR,
    preroll: int | None = None,
    r_p: float = CONTROL_R_P,
    threads: int = 1,
    tracking: bool = True,
) -> ControlCase:
    """Build the case of registered ``scene`` and ``seed`` (``kind`` "arrow"
    or "oval"; ``preroll`` default drawn from [20, 80] by the seed; ``tracking`` False
    skips the tracking field — two thirds of the cost — and leaves it empty
    [0, N, D], for training data that needs only the path). Raises
    :class:`InvalidInputError` naming a bad argument."""
    if kind not in ("arrow", "oval"):
        raise InvalidInputError(f"kind: must be 'arrow' or 'oval', got {kind!r}", "kind")
    rng = np.random.default_rng([int(seed), zlib.crc32(scene.encode())])
    pre = int(rng.integers(20, 81)) if preroll is None else int(preroll)
    sim = MpmSimulator(make_scene(scene, seed=seed), r_p=r_p, seed=seed, threads=threads)
    rollout(sim, pre)
    forward = rollout(sim, frames - 1).fluid_positions.astype(np.float64)  # X_1 … X_T
    v_end = sim.velocities
    # the controlled start: X_T with the motion reversed
    sim.solver.velocities = -v_end
    sim.solver.affine = -np.asarray(sim.solver.affine)
    start = sim.state()
    free = MpmSimulator(make_scene(scene, seed=seed), r_p=r_p, seed=seed, threads=threads)
    free.restore(start)
    free_path = rollout(free, frames - 1).fluid_positions.astype(np.float32)  # the start, then T − 1 frames
    g = sim.scene.params.resolved_gravity()
    kinematic = reverse_kinematic(forward, v_end, sim.dt_frame, g)
    tracking_field = reverse_tracking(sim, forward) if tracking else np.zeros((0, *forward.shape[1:]), np.float32)
    sketch = sketch_from_trajectory(forward[-1], forward[0], kind)
    return ControlCase(
        scene,
        int(seed),
        kind,
        float(r_p),
        pre,
        start,
        forward[0].astype(np.float32),
        sketch,
        kinematic,
        tracking_field,
        forward[::-1].astype(np.float32),
        free_path,
    )


#: First seed of the held-out benchmark cases (training seeds stay below).
HELD_OUT_SEED = 5000
#: Most cases one call may generate (a case is ≈ 1–3 MB).
MAX_CASES = 20000


@dataclass
class CaseRecord:
    """One stored case (module doc for the fields)."""

    positions: np.ndarray
    velocities: np.ndarray
    target: np.ndarray
    tracking: np.ndarray
    kinematic: np.ndarray
    path: np.ndarray
    free_path: np.ndarray
    particle_type: np.ndarray
    gravity: np.ndarray
    sketch: Sketch
    info: dict[str, Any]


def case_path(root: str | Path, scene: str, seed: int) -> Path:
    return Path(root) / scene / f"case_{int(seed):05d}.npz"


def generate_control(scene: str, root: str | Path, cases: int, first_seed: int = 0, *, tracking: bool = False, progress: bool = True) -> list[Path]:
    """Make (or complete) ``cases`` control cases of registered ``scene``
    under ``root`` (module doc); returns every case path. Cases already on
    disk are kept (resumable). ``tracking`` also solves and stores the
    tracking field (3× the cost; the model trains on ``path``). Raises :class:`InvalidInputError` naming
    ``cases`` or ``first_seed`` when out of range (seeds must stay below
    :data:`HELD_OUT_SEED`, the benchmark's)."""
    from tqdm import tqdm

    if isinstance(cases, bool) or not isinstance(cases, int) or not 1 <= cases <= MAX_CASES:
        raise InvalidInputError(f"cases: must be an integer in [1, {MAX_CASES}], got {cases!r}", "cases")
    if isinstance(first_seed, bool) or not isinstance(first_seed, int) or first_seed < 0 or first_seed + cases > HELD_OUT_SEED:
        raise InvalidInputError(f"first_seed: seeds must lie in [0, {HELD_OUT_SEED}) (the benchmark holds out {HELD_OUT_SEED}+)", "first_seed")
    make_scene(scene, seed=first_seed)  # unknown scene → InvalidInputError naming it
    (Path(root) / scene).mkdir(parents=True, exist_ok=True)
    paths = [case_path(root, scene, s) for s in range(first_seed, first_seed + cases)]
    todo = [(s, p) for s, p in zip(range(first_seed, first_seed + cases), paths) if not p.exists()]
    for seed, path in tqdm(todo, desc=f"control cases {scene}", unit="case", disable=not progress):
        case = make_case(scene, seed, "arrow" if seed % 2 == 0 else "oval", tracking=tracking)
        sim = case.simulator()
        p = sim.particles
        info = {"scene": scene, "seed": seed, "kind": case.kind, "preroll": case.preroll, "r_p": case.r_p, "dt_frame": sim.dt_frame}
        arrays = {
            "positions": p.fluid(sim.positions).astype(np.float32),
            "velocities": np.asarray(sim.velocities, np.float32),
            "target": case.target.astype(np.float32),
            "tracking": case.tracking.astype(np.float32),
            "kinematic": case.kinematic.astype(np.float32),
            "path": np.asarray(case.path, np.float32),
            "free_path": np.asarray(case.free_path, np.float32),
            "particle_type": p.particle_type[: p.num_fluid].astype(np.int64),
            "gravity": sim.scene.params.resolved_gravity().astype(np.float32),
            "sketch": np.array(json.dumps(case.sketch.to_json())),
            "info": np.array(json.dumps(info)),
        }
        tmp = path.with_name(path.stem + ".tmp.npz")
        np.savez(tmp, **arrays)  # type: ignore[arg-type]
        os.replace(tmp, path)
    return paths


def load_case(path: str | Path) -> CaseRecord:
    """Read one case file. Raises :class:`InvalidInputError` (field ``path``)
    for a missing or malformed file."""
    try:
        with np.load(path, allow_pickle=False) as z:
            rec = CaseRecord(
                positions=z["positions"],
                velocities=z["velocities"],
                target=z["target"],
                tracking=z["tracking"],
                kinematic=z["kinematic"],
                path=z["path"],
                free_path=z["free_path"],
                particle_type=z["particle_type"],
                gravity=z["gravity"],
                sketch=Sketch.from_json(str(z["sketch"])),
                info=json.loads(str(z["info"])),
            )
    except (OSError, KeyError, ValueError) as e:
        raise InvalidInputError(f"path: {path} is not a control case file ({e})", "path") from e
    n, d = rec.positions.shape
    if rec.path.ndim != 3 or rec.path.shape[1:] != (n, d) or rec.velocities.shape != (n, d):
        raise InvalidInputError(f"path: {path} has inconsistent shapes", "path")
    return rec


def iter_cases(root: str | Path, scene: str) -> Iterator[Path]:
    """The case files of ``scene`` under ``root``, sorted by seed."""
    yield from sorted((Path(root) / scene).glob("case_*[0-9].npz"))


__all__ = ["CONTROL_R_P", "HELD_OUT_SEED", "MAX_CASES", "CaseRecord", "ControlCase", "case_path", "generate_control", "iter_cases", "load_case", "make_case"]
