"""Stress suite: neural-only, MPM-only and the hybrid under each switching
rule (the score with the MPM audit, the score alone, the error rule) through
the cases where methods fail, over long rollouts (``hybridmpm stress SCENE``).

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
condition over the frames simulated; for the hybrid also what its MPM audit
caught (``fallbacks`` "audit"), the frame of its first fallback of any kind
(when the rule first caught the network) and what the audit cost per frame.
"""

from __future__ import annotations

import copy
import time
from dataclasses import dataclass
from typing import Any

import numpy as np

from hybridmpm.conventions import R_C
from hybridmpm.errors import InvalidInputError
from hybridmpm.metrics import grid_mass_error
from hybridmpm.models import shipped_model
from hybridmpm.mpm import Sphere
from hybridmpm.neural.runtime import GnsRuntime
from hybridmpm.scenes import scene_spec
from hybridmpm.scenes.core import Scene
from hybridmpm.sim import HybridSimulator, MpmSimulator, NeuralSimulator, Rollout, Simulator, reference, rollout

CASES = ("baseline", "fast", "obstacle", "dense")
METHODS = ("neural", "mpm", "hybrid", "hybrid_noaudit", "hybrid_error")


def case_scene(name: str, case: str, seed: int = 0) -> Scene:
    """The scene ``name`` (registered domain) for ``seed`` under stress ``case``."""
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
    audit_ms_per_frame: float = 0.0
    first_catch_frame: int | None = None

    def row(self) -> dict[str, Any]:
        return dict(self.__dict__)


def method_simulator(scene: Scene, method: str, model: GnsRuntime, seed: int = 0, threads: int = 1, r_c: float = R_C, **kw: Any) -> Simulator:
    """The simulator of a stress ``method``: "neural" the network alone (its
    first rejected step ends the rollout), "mpm" MPM alone at the model's
    ``r_p`` and ``r_t``, "hybrid" the hybrid at ``r_c`` (``kw`` go to it),
    "hybrid_noaudit" the same without its MPM audit (the paper's rule,
    ``safeguard="paper"``), "hybrid_error" the hybrid under the "error" rule."""
    if method == "neural":
        return NeuralSimulator(scene, model, seed=seed, mpm_threads=threads)
    if method == "mpm":
        return MpmSimulator(scene, r_p=model.r_p, r_t=model.r_t, seed=seed, threads=threads)
    if method == "hybrid":
        return HybridSimulator(scene, model, r_c=r_c, seed=seed, mpm_threads=threads, **kw)
    if method == "hybrid_noaudit":
        return HybridSimulator(scene, model, r_c=r_c, seed=seed, mpm_threads=threads, **{**kw, "safeguard": "paper"})
    if method == "hybrid_error":
        return HybridSimulator(scene, model, r_c=r_c, seed=seed, mpm_threads=threads, **{**kw, "safeguard": "error"})
    raise InvalidInputError(f"method: must be one of {', '.join(METHODS)}, got {method!r}", "method")


def run_method(scene: Scene, method: str, frames: int, model: GnsRuntime, seed: int = 0, **kw: Any) -> tuple[Rollout, float]:
    """Roll out ``method`` ("neural", "mpm", "hybrid") for ``frames`` frames;
    returns the :class:`~hybridmpm.sim.Rollout` (``failure`` says why it broke
    off, if it did) and the wall seconds."""
    sim = method_simulator(scene, method, model, seed, **kw)
    t0 = time.perf_counter()
    ro = rollout(sim, frames)
    return ro, time.perf_counter() - t0


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

    nm = model if isinstance(model, GnsRuntime) else GnsRuntime(model or shipped_model(name))
    results = []
    bar = tqdm(total=len(cases) * (len(methods) + 1), desc=f"stress {name}", disable=not progress)
    for case in cases:
        scene = case_scene(name, case, seed)
        ref = reference(scene, frames, stride=nm.r_t, threads=threads).fluid_positions
        bar.update()
        for method in methods:
            ro, secs = run_method(scene, method, frames, nm, seed=seed, threads=threads)
            k = len(ro.positions)
            err = grid_mass_error(ro.fluid_positions, ref[:k], scene.params.resolved_n_grid(), ref_weights=None)
            steps = ro.stats["steps"]
            total = max(1, sum(steps.values()))
            catches = [k * ro.r_t for k, e in ro.events if e and e.startswith("fallback")]
            results.append(
                StressResult(
                    name, case, method, ro.num_fluid, frames, ro.frames_done, ro.failure,
                    float(np.mean(err)), float(err[-1]), 1e3 * secs / max(1, ro.frames_done),
                    steps["mpm"] / total, int(ro.stats["switches"]), dict(ro.stats["fallbacks"]),
                    1e3 * float(ro.stats.get("audit_seconds", 0.0)) / max(1, ro.frames_done), catches[0] if catches else None,
                )
            )  # fmt: skip
            bar.update()
    bar.close()
    return results


def markdown_table(results: list[StressResult]) -> str:
    """The stress results as a markdown table."""
    lines = [
        "| scene | case | N_l | method | frames until failure | failure | grid-mass error mean | last | ms/frame | of which audit | MPM share | switches | fallbacks | first caught at frame |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in results:
        until = f"{r.frames_done}" if r.failure else f"≥ {r.frames} (none)"
        fb = ", ".join(f"{k} {v}" for k, v in sorted(r.fallbacks.items())) or "–"
        lines.append(
            f"| {r.scene} | {r.case} | {r.particles} | {r.method} | {until} | {r.failure or '–'} | {r.error_mean:.3f} | {r.error_last:.3f} "
            f"| {r.ms_per_frame:.2f} | {r.audit_ms_per_frame:.2f} | {100 * r.mpm_share:.0f}% | {r.switches} | {fb} | {'–' if r.first_catch_frame is None else r.first_catch_frame} |"
        )
    return "\n".join(lines) + "\n"


__all__ = ["CASES", "METHODS", "StressResult", "case_scene", "markdown_table", "method_simulator", "run_method", "stress"]
