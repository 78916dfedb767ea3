"""The socket of the hybrid's cheap half: what the hybrid calls of whatever stands where the network stood.

The hybrid (:class:`~hybridmpm.sim.HybridSimulator`, paper Sec. 3.1.2) runs MPM on the scene's grid and
a *cheap half* on the same particles, and switches between them by its rule
(:mod:`hybridmpm.sim.switching`). It knows the cheap half only through :class:`CheapHalf`:

* :meth:`~CheapHalf.propose` a step of ``r_t`` frames without taking it (the failure checks
  :class:`FailureChecks` applied where the half can fail so), and :meth:`~CheapHalf.commit` it,
  once the rule's MPM audit (if any) accepted it — a rejected proposal is left behind;
* :meth:`~CheapHalf.take_over` from MPM (after an MPM step: MPM's solver holds the state, the
  hybrid's trajectory the positions before it) and :meth:`~CheapHalf.hand_back` to MPM (the state of
  the last committed step, i.e. the start of a pending proposal, written into MPM's solver: a
  fallback, or the MPM audit of a proposal);
* ``kind`` the label of its frames and step counts, ``name`` the ``cheap`` setting that builds it,
  ``t_in`` the trajectory it needs before it can take over, its ``velocities`` and its state for
  checkpoints (:meth:`~CheapHalf.state`, :meth:`~CheapHalf.prepare_restore`).

Two halves implement it: the network (:class:`~hybridmpm.sim.neural.NeuralSimulator`, the paper's
hybrid; a handover converts the state, :mod:`hybridmpm.sim.convert`) and MPM on a coarser grid
(:class:`~hybridmpm.sim.coarse.CoarseMpmHalf`, the classical twin; the same particles move bit for
bit). A new cheap half is one class that satisfies :class:`CheapHalf` and one entry in
:data:`hybridmpm.sim.hybrid.CHEAP_HALVES`.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Protocol, runtime_checkable

import numpy as np

from hybridmpm.conventions import FAILURE_DEGREE_FACTOR, FAILURE_ESCAPE_CELLS, FAILURE_KE_FACTOR
from hybridmpm.errors import InvalidInputError
from hybridmpm.mpm import MpmSolver
from hybridmpm.neural.runtime import Graph
from hybridmpm.scenes.particles import ParticleSet


@dataclass
class Proposal:
    """A cheap step not yet taken (:meth:`CheapHalf.propose`).

    ``acceleration`` and ``predicted`` float32 [N + B, D] (the raw prediction; the network's
    output, the coarse grid's positions); ``positions`` the prediction as it would be kept
    (clipped to the domain and relaxed; None if rejected before that); ``graph`` the radius graph
    of ``positions`` (senders, receivers, displacement, distance;
    :data:`hybridmpm.neural.runtime.Graph`) reused by the next network step, or None;
    ``failure`` None or the failure mode ("nan", "escaped", "energy", "compressed", "mpm").
    """

    acceleration: np.ndarray
    predicted: np.ndarray
    positions: np.ndarray | None
    graph: Graph | None
    failure: str | None


def _positive(name: str, value: Any, lo: float, closed: bool) -> float:
    ok = isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value) and (value >= lo if closed else value > lo)
    if not ok:
        raise InvalidInputError(f"{name}: must be a finite number {'>=' if closed else '>'} {lo:g}, got {value!r}", name)
    return float(value)


@dataclass(frozen=True)
class FailureChecks:
    """The failure checks of a cheap step (docs/hybrid.md "Failures, and what happens"; the network's
    in :mod:`hybridmpm.sim.neural`): a step that predicts a non-finite position ("nan"), moves a
    particle more than ``escape_cells`` cells beyond the domain farther than its own last step
    carries it ("escaped"), raises the kinetic energy above ``ke_factor`` × the energy available at
    the start ("energy"), or packs the particles more than ``degree_factor`` × the initial
    condition ("compressed") is rejected. ``detect_failures`` False: every prediction is taken.
    Raises :class:`InvalidInputError` naming the field."""

    detect_failures: bool = True
    ke_factor: float = FAILURE_KE_FACTOR
    escape_cells: float = FAILURE_ESCAPE_CELLS
    degree_factor: float = FAILURE_DEGREE_FACTOR

    def __post_init__(self) -> None:
        object.__setattr__(self, "detect_failures", bool(self.detect_failures))
        object.__setattr__(self, "ke_factor", _positive("ke_factor", self.ke_factor, 0.0, False))
        object.__setattr__(self, "escape_cells", _positive("escape_cells", self.escape_cells, 0.0, True))
        object.__setattr__(self, "degree_factor", _positive("degree_factor", self.degree_factor, 1.0, False))


@runtime_checkable
class CheapHalf(Protocol):
    """What the hybrid calls of its cheap half (module doc). Shapes: N fluid and B boundary
    particles of the hybrid's particle set, D dimensions; positions float32 [m]."""

    #: The label of its frames (``Frame.solver``) and step counts (``stats.steps``).
    kind: str
    #: The ``cheap`` setting of the hybrid that builds it.
    name: str
    #: The model whose resolution (``r_p``, ``r_t``, ``t_in``) it runs at: a :class:`~hybridmpm.neural.base.Runtime`
    #: (the network), its :class:`~hybridmpm.neural.base.ModelHeader` (the twin), or None.
    model: Any
    particles: ParticleSet
    #: Frames per step.
    r_t: int
    #: Positions of the trajectory (one step apart) it needs to take over from MPM.
    t_in: int

    @property
    def velocities(self) -> np.ndarray:
        """Fluid velocities [m/s] float32 [N, D] of its last committed step."""
        ...

    @property
    def mean_degree(self) -> float:
        """Mean neighbours per particle of the graph of its next step (nan: no graph)."""
        ...

    @property
    def initial_degree(self) -> float:
        """Mean neighbours per particle of the initial condition (nan: no graph)."""
        ...

    def propose(self, checks: FailureChecks | None = None) -> Proposal:
        """Its next step, not taken; ``checks`` the failure checks (None: its own)."""
        ...

    def commit(self, proposal: Proposal) -> np.ndarray:
        """Take a proposal without failure; returns its positions float32 [N + B, D]. Raises
        :class:`InvalidInputError` (field ``proposal``) for a rejected one."""
        ...

    def take_over(self, fine: MpmSolver, trajectory: np.ndarray) -> None:
        """Continue from the state of MPM's solver ``fine``, which has just made a step; ``trajectory``
        float32 [T, N, D] holds the fluid positions of the last T >= ``t_in`` steps, oldest first,
        the newest MPM's. ``fine`` is left as it was."""
        ...

    def hand_back(self, fine: MpmSolver, trajectory: np.ndarray) -> None:
        """Write the state of its last committed step into MPM's solver ``fine``; ``trajectory`` as
        for :meth:`take_over`, its newest entry that step's positions."""
        ...

    def state(self) -> dict[str, Any]:
        """Its whole state, a picklable dict."""
        ...

    def prepare_restore(self, state: dict[str, Any]) -> Callable[[], None]:
        """Validate a :meth:`state` whole without changing anything; returns the commit, which
        cannot fail. Raises :class:`InvalidInputError` (field ``state``…)."""
        ...


__all__ = ["CheapHalf", "FailureChecks", "Proposal"]
