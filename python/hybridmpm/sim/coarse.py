"""MPM on a coarser grid as the hybrid's cheap half: the classical twin of the
paper's hybrid (arXiv 2505.18926, Sec. 3.1.2), where plain MPM on a grid of
half the resolution stands where the network stood.

:class:`CoarseMpmHalf` runs the hybrid's particles (the scene clustered to
``r_p``) on the coarse grid and hands them to MPM on the scene's grid and back
without any conversion: the same particles move between the two grids bit for
bit (:meth:`~hybridmpm.mpm.MpmSolver.restore_particles`: positions,
velocities, APIC affine matrices, deformation, J). It is a
:class:`~hybridmpm.sim.cheap.CheapHalf` — :meth:`propose` a step,
:meth:`commit` it, :meth:`take_over` from MPM, :meth:`hand_back` to it — so
the switching rules (``s(t)`` against ``r_c``, the MPM audit, the error rule)
apply unchanged. Any learned cheap half has to beat this one.

No network runs and none is loaded: the twin moves the particle set of a
network's resolution (``r_p``, ``r_t``, ``T_in``), read from the model file's
metadata (:func:`hybridmpm.neural.base.read_header`).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np

from hybridmpm.conventions import T_IN
from hybridmpm.errors import InvalidInputError, SimulationError
from hybridmpm.mpm import MpmSolver
from hybridmpm.neural.base import ModelHeader
from hybridmpm.scenes.core import Scene
from hybridmpm.scenes.resolution import on_grid
from hybridmpm.sim.base import reading_state
from hybridmpm.sim.cheap import FailureChecks, Proposal
from hybridmpm.sim.convert import merge_state, split_state
from hybridmpm.sim.mpm import MpmSimulator

#: The coarse grid by default: half the scene's grid (64² of 128², 32³ of 64³).
COARSE_FRACTION = 0.5
#: The label of the twin's cheap half in frames and step counts.
COARSE = "coarse"
_STATE_VERSION = 1


def coarse_grid(scene: Scene, n_grid: int | None) -> int:
    """The cheap half's grid: ``n_grid``, or (None) :data:`COARSE_FRACTION` of the scene's. Raises
    :class:`InvalidInputError` (field ``n_grid``) outside [16, the scene's grid]."""
    n0 = scene.params.resolved_n_grid()
    n = int(round(COARSE_FRACTION * n0)) if n_grid is None else n_grid
    if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or not 16 <= int(n) <= n0:
        raise InvalidInputError(f"n_grid: the cheap half's grid must be an integer in [16, {n0}] (the scene's), got {n!r}", "n_grid")
    return int(n)


class CoarseMpmHalf:
    """MPM on a coarser grid of ``scene`` (already at the hybrid's ``r_p``),
    ``r_t`` frames per step, with the same particles (``keep_particles``).

    ``n_grid`` the coarse grid (default :data:`COARSE_FRACTION` of the
    scene's); ``threads`` its solver threads; ``t_in`` the trajectory
    positions the hybrid keeps before handing over to it (the network's
    ``T_in``: the same warm-up as the paper's hybrid); ``model`` the header
    of the network whose resolution the particles are at (or None). Raises
    :class:`InvalidInputError` naming ``n_grid`` for a grid the scene refuses
    (:func:`~hybridmpm.scenes.resolution.on_grid`).
    """

    kind = COARSE
    #: The hybrid's ``cheap`` setting that builds it.
    name = "mpm-coarse"

    def __init__(self, scene: Scene, *, r_t: int, n_grid: int | None = None, threads: int = 0, t_in: int = T_IN, model: ModelHeader | None = None) -> None:
        n = coarse_grid(scene, n_grid)
        self.sim = MpmSimulator(on_grid(scene, n, keep_particles=True), r_t=r_t, threads=threads)
        self.n_grid = n
        self.particles = self.sim.particles
        self.r_t = r_t
        self.t_in = t_in
        self.model = model
        self._before: bytes | None = None  # the state a pending proposal started from

    # ------------------------------------------------------------ the cheap half (hybridmpm.sim.cheap)
    def propose(self, checks: FailureChecks | None = None) -> Proposal:
        """Take ``r_t`` frames on the coarse grid; the step counts once
        committed (a rejected one is left behind: the next hand-over from the
        fine grid overwrites it). A frame MPM cannot finish is failure "mpm",
        its only check (``checks``, the network's, do not apply)."""
        self._before = self.sim.solver.checkpoint()
        try:
            fr = self.sim.advance()
        except SimulationError:
            self.sim.solver.restore(self._before)
            return Proposal(np.zeros(0), np.zeros(0), None, None, "mpm")
        pos = fr.positions
        return Proposal(np.zeros(0), pos, pos, None, None)

    def commit(self, proposal: Proposal) -> np.ndarray:
        """Keep a proposed step; returns its positions float32 [N + B, D]."""
        if proposal.failure is not None or proposal.positions is None:
            raise InvalidInputError(f"proposal: a rejected step ({proposal.failure}) cannot be committed", "proposal")
        self._before = None
        return proposal.positions

    def handover_state(self) -> bytes:
        """The checkpoint MPM on the scene's grid takes over from: the start of
        a pending proposal's step (an audit replays it), else the current state."""
        return self._before if self._before is not None else self.sim.solver.checkpoint()

    def hand_back(self, fine: MpmSolver, trajectory: np.ndarray | None = None) -> None:
        """Write :meth:`handover_state` into the fine grid's solver: the same
        particles, bit for bit (``trajectory`` is not needed)."""
        fine.restore_particles(self.handover_state())

    def take_over(self, fine: MpmSolver, trajectory: np.ndarray | None = None) -> None:
        """Continue from the fine grid's state (same particles, bit for bit;
        ``trajectory`` is not needed).

        The one exception: the coarse solver's domain ``[dx, 1 − dx]`` is a
        fine cell narrower at each side than the fine one's, and a particle
        the fine grid pushed into that strip (inside the wall band, past the
        faces both grids share) is moved onto the coarse domain's edge, less
        than one fine cell. ``fine`` is left as it was."""
        blob = fine.checkpoint()
        lo, hi = self.sim.solver.domain_bounds
        pos = fine.positions
        if (pos < lo).any() or (pos > hi).any():
            fine.positions = np.clip(pos, lo, hi)
            clamped = fine.checkpoint()
            fine.restore(blob)
            blob = clamped
        self.sim.solver.restore_particles(blob)
        self._before = None

    @property
    def velocities(self) -> np.ndarray:
        return self.sim.velocities

    @property
    def mean_degree(self) -> float:
        return float("nan")  # no graph

    @property
    def initial_degree(self) -> float:
        return float("nan")

    # ------------------------------------------------------------ checkpoint
    def state(self) -> dict[str, Any]:
        return {"kind": self.kind, "version": _STATE_VERSION, "n_grid": self.n_grid, "mpm": self.sim.state()}

    def prepare_restore(self, state: dict[str, Any]) -> Callable[[], None]:
        with reading_state("CoarseMpmHalf"):
            if not isinstance(state, dict) or state.get("kind") != self.kind or state.get("version") != _STATE_VERSION or state.get("n_grid") != self.n_grid:
                raise InvalidInputError("state: not a state of this coarse-grid half (kind, version or grid differ)", "state")
            commit_mpm = self.sim.prepare_restore(state["mpm"])

        def commit() -> None:
            commit_mpm()
            self._before = None

        return commit


class CoarseOwnHalf:
    """MPM on a coarser grid with the grid's own particle set as the hybrid's cheap half: the classical
    twin carrying fewer particles than the hybrid's (``particles="grid"``; docs/hybrid.md).

    ``scene`` the hybrid's particle set (the scene at ``r_p``); ``coarse`` the coarse grid's scene,
    each of its particles a group of ``scene``'s (``labels`` int64 [N], values ``0 .. N_c − 1``: the
    ``r_p`` clustering of ``scene`` to the count plain MPM puts on that grid), on its grid. A take-over
    merges the hybrid's particles into their groups and a hand-back splits them again
    (:func:`~hybridmpm.sim.convert.merge_state`, :func:`~hybridmpm.sim.convert.split_state`); each
    proposal's positions are the split of the coarse state (each particle at its group's position
    plus its offset, the offsets carried along by the group's APIC ``C`` and held within one coarse
    cell, ``max_offset`` [m], of the centre). ``conversions`` counts the
    merges and ``merge_residual`` [m/s] is the last one's measured error (the fine velocities the
    groups' affine fields do not carry). ``r_t``, ``threads``, ``t_in``, ``model`` as for
    :class:`CoarseMpmHalf`."""

    kind = COARSE
    name = "mpm-coarse"

    def __init__(
        self, scene: Scene, coarse: Scene, labels: np.ndarray, *, r_t: int, threads: int = 0, t_in: int = T_IN, model: ModelHeader | None = None
    ) -> None:
        self.sim = MpmSimulator(coarse, r_t=r_t, threads=threads)
        self.fine = scene.make_solver(num_threads=1)  # the hybrid's particles, for the split's fields and the padding
        self.particles = scene.particles(self.fine.masses)
        self.labels = np.asarray(labels, np.int64)
        self.n_grid = int(coarse.params.resolved_n_grid())
        self.r_t, self.t_in, self.model = r_t, t_in, model
        self.dt_step = float(scene.dt_frame) * r_t
        self.max_offset = float(self.sim.solver.dx)  # [m] the furthest a particle is placed from its group's centre
        self.offsets = np.zeros((self.particles.num_fluid, scene.dim))
        self.conversions = 0
        self.merge_residual = float("nan")
        self._before: tuple[bytes, np.ndarray] | None = None  # the coarse state and offsets a pending proposal started from
        self._pending = self.offsets  # the offsets after a pending proposal

    def _split(self, offsets: np.ndarray) -> np.ndarray:
        split_state(self.sim.solver, self.fine, self.labels, offsets)
        return np.asarray(self.fine.positions, np.float32)

    def propose(self, checks: FailureChecks | None = None) -> Proposal:
        """``r_t`` frames on the coarse grid, reported split onto the hybrid's particles; a frame MPM cannot finish is failure "mpm"."""
        self._before = (self.sim.solver.checkpoint(), self.offsets)
        try:
            self.sim.advance()
        except SimulationError:
            self.sim.solver.restore(self._before[0])
            return Proposal(np.zeros(0), np.zeros(0), None, None, "mpm")
        aff = np.asarray(self.sim.solver.affine, np.float64)[self.labels]
        pending = self.offsets + self.dt_step * np.einsum("nij,nj->ni", aff, self.offsets)  # carried by the group's affine field
        # at most one coarse cell from the group's centre: a stretching field grows the offsets without bound over a long spell
        # on the coarse grid, and a particle split far out of its group's kernel took the group's affine velocity there
        # (water_sand2d seed 1001: 1,948 m/s at a hand-back, which MPM refused)
        norm = np.linalg.norm(pending, axis=1, keepdims=True)
        self._pending = pending * np.minimum(1.0, self.max_offset / np.maximum(norm, 1e-30))
        pos = self.particles.pad(self._split(self._pending))
        return Proposal(np.zeros(0), pos, pos, None, None)

    def commit(self, proposal: Proposal) -> np.ndarray:
        if proposal.failure is not None or proposal.positions is None:
            raise InvalidInputError(f"proposal: a rejected step ({proposal.failure}) cannot be committed", "proposal")
        self.offsets, self._before = self._pending, None
        return proposal.positions

    def hand_back(self, fine: MpmSolver, trajectory: np.ndarray | None = None) -> None:
        """Split the state of the last committed step (the start of a pending proposal) into ``fine``."""
        if self._before is None:
            split_state(self.sim.solver, fine, self.labels, self.offsets)
            return
        now = self.sim.solver.checkpoint()
        self.sim.solver.restore(self._before[0])
        split_state(self.sim.solver, fine, self.labels, self._before[1])
        self.sim.solver.restore(now)

    def take_over(self, fine: MpmSolver, trajectory: np.ndarray | None = None) -> None:
        """Merge ``fine``'s particles into their groups on the coarse grid (``fine`` is left as it was)."""
        self.offsets, self.merge_residual = merge_state(fine, self.sim.solver, self.labels)
        self.conversions += 1
        self._before = None

    @property
    def velocities(self) -> np.ndarray:
        split_state(self.sim.solver, self.fine, self.labels, self.offsets)
        return np.asarray(self.fine.velocities, np.float32)

    mean_degree = initial_degree = property(lambda self: float("nan"))

    def state(self) -> dict[str, Any]:
        return {"kind": self.kind, "version": _STATE_VERSION, "n_grid": self.n_grid, "mpm": self.sim.state(), "offsets": self.offsets.copy()}

    def prepare_restore(self, state: dict[str, Any]) -> Callable[[], None]:
        with reading_state("CoarseOwnHalf"):
            if not isinstance(state, dict) or state.get("kind") != self.kind or state.get("n_grid") != self.n_grid or "offsets" not in state:
                raise InvalidInputError("state: not a state of this coarse-grid half with its own particles", "state")
            offsets = np.asarray(state["offsets"], np.float64)
            if offsets.shape != self.offsets.shape or not np.isfinite(offsets).all():
                raise InvalidInputError(f"state.offsets: expected finite [{len(self.offsets)}, {self.offsets.shape[1]}]", "state.offsets")
            commit_mpm = self.sim.prepare_restore(state["mpm"])

        def commit() -> None:
            commit_mpm()
            self.offsets, self._before = offsets.copy(), None

        return commit


__all__ = ["COARSE", "COARSE_FRACTION", "CoarseMpmHalf", "CoarseOwnHalf", "coarse_grid"]
