"""The correction inside the solver: forcing callables for
:class:`~hybridmpm.sim.MpmSimulator` on the coarse grid, so that every
corrected, labelled or oracle run goes through the one rollout
(:func:`hybridmpm.sim.rollout`).

:class:`CorrectionForcing` applies a :class:`~experiments.learned_correction.model.Correction`
(or none); :class:`LabelledForcing` does the same and, every ``every`` frames,
labels the state it is about to step (the teacher's velocity minus one plain
coarse frame's, :mod:`experiments.learned_correction.teacher`) for DAgger;
:class:`OracleForcing` applies the teacher's own answer, the best any
correction trained on that target can do.
"""

from __future__ import annotations

import numpy as np

from experiments.learned_correction.features import particle_features
from experiments.learned_correction.model import Correction
from experiments.learned_correction.teacher import teacher_frame
from hybridmpm.errors import SimulationError
from hybridmpm.mpm import MpmParams
from hybridmpm.scenes.core import Scene
from hybridmpm.scenes.resolution import on_grid
from hybridmpm.sim.mpm import MpmSimulator, probe_frame


def coarse_simulator(scene: Scene, n_grid: int, *, threads: int = 1) -> MpmSimulator:
    """MPM on ``n_grid`` cells of ``scene``'s domain at 2 particles per cell per axis (the coarse student)."""
    return MpmSimulator(on_grid(scene, n_grid, 2), threads=threads)


def cell_average(positions: np.ndarray, masses: np.ndarray, values: np.ndarray, n_grid: int) -> np.ndarray:
    """Mass-weighted mean of ``values`` [N, K] over the particles of each particle's cell of an ``n_grid`` grid, [N, K]."""
    n, d = positions.shape
    cell = np.clip(np.floor(positions * n_grid).astype(np.int64), 0, n_grid - 1) @ (n_grid ** np.arange(d - 1, -1, -1))
    _, inv = np.unique(cell, return_inverse=True)
    m = np.bincount(inv, weights=masses)
    out = np.stack([np.bincount(inv, weights=masses * values[:, k]) / m for k in range(values.shape[1])], axis=1)
    return out[inv]


class CorrectionForcing:
    """``sim.forcing = CorrectionForcing(sim, model)``: before every frame, the
    acceleration [m/s²] ``scale ×`` ``model``'s (zero without a model), from
    the features of ``sim``'s solver state."""

    def __init__(self, sim: MpmSimulator, model: Correction | None, *, scale: float = 1.0) -> None:
        self.sim, self.model, self.scale = sim, model, float(scale)
        self.n_grid = sim.solver.n_grid
        self.dt = float(sim.dt_frame)

    def acceleration(self, features: np.ndarray) -> np.ndarray:
        if self.model is None:
            return np.zeros((features.shape[0], self.sim.particles.dim), np.float32)
        return (self.scale * self.model.acceleration(features, self.n_grid, self.dt)).astype(np.float32)

    def __call__(self, frame: int, positions: np.ndarray, velocities: np.ndarray) -> np.ndarray:
        return self.acceleration(particle_features(self.sim.solver, self.dt))


class LabelledForcing(CorrectionForcing):
    """A :class:`CorrectionForcing` that also labels every ``every``-th
    frame's starting state: features ``x`` float32 [N, F] and target ``y``
    float32 [N, D], the teacher's velocity minus that of one plain coarse
    frame from the same state [cells per frame], averaged over each coarse
    cell when ``smooth``. The state is put back before the frame runs; a
    frame the teacher cannot finish is not labelled."""

    def __init__(self, sim: MpmSimulator, model: Correction | None, fine_params: MpmParams, *, every: int, smooth: bool, scale: float = 1.0) -> None:
        super().__init__(sim, model, scale=scale)
        self.fine_params, self.every, self.smooth = fine_params, int(every), bool(smooth)
        self.xs: list[np.ndarray] = []
        self.ys: list[np.ndarray] = []

    def target(self) -> np.ndarray:
        """One frame's target at the solver's current state (restored afterwards) [cells per frame], float64 [N, D]."""
        s = self.sim.solver
        ck = s.checkpoint()
        try:
            _, vt = teacher_frame(s, self.fine_params, self.dt)
            s.external_acceleration = np.zeros_like(vt, np.float32)
            probe_frame(s, self.dt)
            y = (vt - np.asarray(s.velocities, np.float64)) * self.dt * self.n_grid
            if self.smooth:
                y = cell_average(np.asarray(s.positions, np.float64), np.asarray(s.masses, np.float64), y, self.n_grid)
            return y
        finally:
            s.restore(ck)

    def __call__(self, frame: int, positions: np.ndarray, velocities: np.ndarray) -> np.ndarray:
        x = particle_features(self.sim.solver, self.dt)
        if frame % self.every == 0:
            try:
                y = self.target()
            except SimulationError:
                pass
            else:
                self.xs.append(x)
                self.ys.append(y.astype(np.float32))
        return self.acceleration(x)


class OracleForcing(LabelledForcing):
    """The perfect one-frame correction: before every frame, the acceleration
    that gives each particle the teacher's velocity change (its unsmoothed
    target, :meth:`LabelledForcing.target`, over one frame). An upper bound on
    any correction learned on that target."""

    def __init__(self, sim: MpmSimulator, fine_params: MpmParams) -> None:
        super().__init__(sim, None, fine_params, every=1, smooth=False)

    def __call__(self, frame: int, positions: np.ndarray, velocities: np.ndarray) -> np.ndarray:
        return (self.target() / (self.n_grid * self.dt * self.dt)).astype(np.float32)


__all__ = ["CorrectionForcing", "LabelledForcing", "OracleForcing", "cell_average", "coarse_simulator"]
