"""Control datasets: reverse-simulation cases on disk, made by
``hybridmpm generate-control`` and read by ``hybridmpm train-control``.

Layout: ``ROOT/SCENE/case_SEED.npz``, one file per case
(:func:`hybridmpm.control.data.make_case`), written atomically, so that a
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
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from hybridmpm.control.sketch import Sketch
from hybridmpm.errors import InvalidInputError

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

    from hybridmpm.control.data import make_case
    from hybridmpm.scenes import make_scene

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
            "gravity": np.asarray(sim.scene.params.to_dict()["gravity"], np.float32),
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


__all__ = ["HELD_OUT_SEED", "MAX_CASES", "CaseRecord", "case_path", "generate_control", "iter_cases", "load_case"]
