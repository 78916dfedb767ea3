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
"""

from __future__ import annotations

import zlib
from dataclasses import dataclass
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
    g = np.asarray(sim.scene.params.to_dict()["gravity"], np.float64)
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


__all__ = ["CONTROL_R_P", "ControlCase", "make_case"]
