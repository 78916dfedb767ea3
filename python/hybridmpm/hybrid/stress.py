"""Stress suite (issue 5): neural-only, MPM-only and hybrid through the cases
where methods fail, over long rollouts (``hybridmpm stress SCENE``).

Cases (:data:`CASES`), each built from the scene's own spec for a seed:

* ``baseline``: the scene as generated (in distribution);
* ``fast``: every block's initial velocity doubled (twice the training range);
* ``obstacle``: a round obstacle (never seen in training: the datasets hold
  none, or box ramps) of radius 0.08 m on the floor in the middle;
* ``dense``: 3 particles per cell and dimension instead of 2 (2.25× the
  particles in 2D, 3.4× in 3D, same mass): a particle density the network
  never saw.

Per case and method the suite records frames until failure and its mode
(``nan``, ``escaped``, ``energy``, ``compressed`` for the network; ``mpm`` for a frame MPM
could not finish even with its smallest substep), and the grid-mass error
(mean and last frame) against full-resolution MPM from the same initial
condition over the frames simulated.
"""

from __future__ import annotations

import copy
import time
from dataclasses import dataclass
from typing import Any

import numpy as np

from hybridmpm.errors import InvalidInputError, SimulationError
from hybridmpm.hybrid.simulator import NEURAL, HybridSimulator
from hybridmpm.mpm import Sphere
from hybridmpm.scenes.core import Scene

CASES = ("baseline", "fast", "obstacle", "dense")
METHODS = ("neural", "mpm", "hybrid")


def case_scene(name: str, case: str, seed: int = 0) -> Scene:
    """The scene ``name`` (registered domain) for ``seed`` under stress ``case``."""
    from hybridmpm.scenes import scene_spec

    if case not in CASES:
        raise InvalidInputError(f"case: must be one of {', '.join(CASES)}, got {case!r}", "case")
    spec = copy.deepcopy(scene_spec(name, seed=seed))
    if case == "fast":
        for b in spec.blocks:
            if b.velocity is not None:
                b.velocity = [2.0 * float(v) for v in b.velocity]
    elif case == "obstacle":
        # on the floor, where every flow ends up, so that it cannot be missed
        centre = [0.5, 0.1] + [0.5] * (spec.dim - 2)
        spec.params.colliders = [*spec.params.colliders, Sphere(center=centre, radius=0.08)]
    elif case == "dense":
        spec.particles_per_cell = 3
    scene = spec.build()
    scene.name = name  # the model of the domain serves its stress cases
    return scene


@dataclass
class StressResult:
    scene: str
    case: str
    method: str
    particles: int
    frames: int
    frames_done: int
    failure: str | None
    error_mean: float
    error_last: float
    ms_per_frame: float
    mpm_share: float
    switches: int
    fallbacks: dict[str, int]

    def row(self) -> dict[str, Any]:
        return dict(self.__dict__)


def reference_rollout(scene: Scene, frames: int, stride: int, threads: int = 0) -> np.ndarray:
    """Full-resolution MPM positions every ``stride`` frames, float32 [⌈frames/stride⌉ + 1, N, D]
    (like the hybrid, it runs whole strides: ``⌈frames/stride⌉·stride`` frames): the dataset
    generator's rollout (:func:`~hybridmpm.data.generate.simulate_trajectory`) of the scene's spec.
    Raises :class:`InvalidInputError` for a scene built without a spec."""
    from hybridmpm.data.generate import simulate_trajectory

    if scene.spec is None:
        raise InvalidInputError("scene: the reference is rebuilt from the scene's spec; this scene has none", "scene")
    total = -(-frames // stride) * stride
    out = simulate_trajectory(scene.spec, int(scene.info.get("seed", 0)), total, r_t=stride, num_threads=threads)
    return np.asarray(out["positions"][:, : scene.num_particles], np.float32)


def run_method(scene: Scene, method: str, frames: int, model: Any = None, seed: int = 0, **kw: Any) -> tuple[np.ndarray, str | None, HybridSimulator, float]:
    """Roll out ``method`` ("neural", "mpm", "hybrid") for ``frames`` frames.

    Neural-only is the hybrid with the complexity trigger off whose first
    failure ends the rollout (no fallback); MPM-only is the hybrid with
    ``r_c = 2`` (never met). Returns (fluid positions every coarse step
    [K + 1, N, D], failure mode or None, the simulator, wall seconds).
    """
    r_c = {"neural": 0.0, "mpm": 2.0, "hybrid": kw.pop("r_c", 0.8)}[method]
    sim = HybridSimulator(scene, model, r_c=r_c, seed=seed, **kw)
    out = [np.asarray(sim.initial_frame().positions[: sim.n_fluid])]
    failure = None
    t0 = time.perf_counter()
    try:
        for fr in sim.step(frames):
            if method == "neural" and fr.event and fr.event.startswith("fallback:"):
                failure = fr.event.split(":", 1)[1]
                break
            p = fr.positions[: sim.n_fluid]
            if not np.isfinite(p).all():
                failure = "nan"
                break
            out.append(np.asarray(p))
    except SimulationError:
        failure = "mpm"
    return np.stack(out), failure, sim, time.perf_counter() - t0


def stress(
    name: str,
    *,
    cases: tuple[str, ...] = CASES,
    methods: tuple[str, ...] = METHODS,
    frames: int = 1000,
    seed: int = 0,
    model: Any = None,
    threads: int = 1,
    progress: bool = True,
) -> list[StressResult]:
    """Run the stress suite on registered scene ``name``; one :class:`StressResult` per case × method."""
    from tqdm import tqdm

    from hybridmpm.metrics import grid_mass_error
    from hybridmpm.neural.runtime import NeuralModel
    from hybridmpm.models import shipped_model

    nm = model if isinstance(model, NeuralModel) else NeuralModel(model or shipped_model(name))
    results = []
    bar = tqdm(total=len(cases) * (len(methods) + 1), desc=f"stress {name}", disable=not progress)
    for case in cases:
        scene = case_scene(name, case, seed)
        ref = reference_rollout(scene, frames, nm.r_t, threads)
        bar.update()
        for method in methods:
            pos, failure, sim, secs = run_method(scene, method, frames, nm, seed=seed, mpm_threads=threads)
            k = len(pos)
            err = grid_mass_error(pos, ref[:k], scene.params.resolved_n_grid(), ref_weights=None) if k else np.array([np.nan])
            steps = sim.stats.steps
            total = max(1, steps["mpm"] + steps[NEURAL])
            results.append(
                StressResult(
                    name, case, method, sim.n_fluid, frames, (k - 1) * sim.r_t, failure,
                    float(np.mean(err)), float(err[-1]), 1e3 * secs / max(1, (k - 1) * sim.r_t),
                    steps["mpm"] / total, sim.stats.switches, dict(sim.stats.fallbacks),
                )
            )  # fmt: skip
            bar.update()
    bar.close()
    return results


def markdown_table(results: list[StressResult]) -> str:
    """The stress results as a markdown table."""
    lines = [
        "| scene | case | N_l | method | frames until failure | failure | grid-mass error mean | last | ms/frame | MPM share | switches | fallbacks |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in results:
        until = f"{r.frames_done}" if r.failure else f"≥ {r.frames} (none)"
        fb = ", ".join(f"{k} {v}" for k, v in sorted(r.fallbacks.items())) or "–"
        lines.append(
            f"| {r.scene} | {r.case} | {r.particles} | {r.method} | {until} | {r.failure or '–'} | {r.error_mean:.3f} | {r.error_last:.3f} "
            f"| {r.ms_per_frame:.2f} | {100 * r.mpm_share:.0f}% | {r.switches} | {fb} |"
        )
    return "\n".join(lines) + "\n"


__all__ = ["CASES", "METHODS", "StressResult", "case_scene", "markdown_table", "reference_rollout", "run_method", "stress"]
