"""The hybrid simulator: neural physics by default, MPM when the flow gets complex.

Paper Sec. 3.1.2, Eq. 1, Table 2; docs/design.md "Safeguard". One *step* is one
coarse step of the neural model: ``r_t`` frames of ``dt_frame`` seconds, at the
model's particle resolution ``r_p`` (the scene is clustered once; MPM and the
network move the same particles).

Control (``r_c`` threshold, ``δ`` window, ``dwell``):

* the first ``T_in − 1`` steps are MPM (they fill the network's history);
* on the neural solver, a step whose score ``s(t) < r_c`` hands the next
  step to MPM (neural → MPM conversion, :mod:`hybridmpm.hybrid.convert`);
* on MPM, the score keeps being computed on the MPM trajectory; after
  ``dwell`` consecutive steps with ``s(t) ≥ r_c`` the network takes over
  again from the last ``T_in`` positions;
* ``r_c ≤ 0`` switches the complexity trigger off (neural only, as the
  paper's Table 2 reads r_c = 0; the mean cosine can dip below 0 in a splash);
  ``r_c > 1`` can never be met: MPM only.

Failure handling (always on, whatever ``r_c``): a neural step that predicts a
non-finite position, moves a particle more than ``escape_cells`` cells (default
4) beyond the model's domain bounds farther than its own last step carries it
(a particle on a wall keeps its speed for one step before the wall clips it;
:mod:`hybridmpm.sim.neural`), raises the
kinetic energy above ``ke_factor`` × the energy available at the start
(kinetic + potential above the floor), or packs the particles so that their
mean number of neighbours within R exceeds ``degree_factor`` (2) × that of the
initial condition (sand and water are nearly incompressible: a collapsing
network shows there first, and its graph, hence its cost, grows with it) is
discarded (:class:`~hybridmpm.sim.neural.NeuralSimulator`'s failure checks),
and the step is redone by MPM from the last good state (``Frame.event`` says
which). The network then has to wait ``dwell·2^k``
calm steps, ``k`` its failures since its last healthy stint of ``2·dwell``
steps (backoff: a model that keeps collapsing is not handed the flow every
few steps). MPM itself halves its substep and retries a frame that goes
non-finite or violates the CFL condition (Rust ``step_frame``).

MPM audit (``audit_every``, ``audit_tol``; not in the paper): ``s(t)``
measures only the trajectory's self-consistency, so a network that is smooth
but wrong (a column that stands where MPM lets it fall) passes it. Every
``audit_every``-th step of a network stint (its first step included) is also
taken by MPM from the same converted state (the neural → MPM conversion a
fallback uses; none at a stint's first step, where the MPM solver still
holds the state), and the two predictions are compared: the RMS over fluid
particles of the position difference divided by ``dt_step²``, in units of
``g`` (:data:`~hybridmpm.conventions.G`), is the step's *audit* error
(``Frame.audit``). Above ``audit_tol`` the network's step is discarded, MPM's
is kept (nothing is recomputed), and the hybrid falls back (event
"fallback:audit", counted with the failures for the backoff). Cost: one MPM
step at ``r_p`` per ``audit_every`` network steps (``stats.audit_seconds``);
``audit_every = 0`` switches it off, and so does ``r_c ≤ 0`` (neural only).

Switching rules (``safeguard``; docs/hybrid.md "Switching rules"):

* ``"audit"`` (default): the complexity score ``s(t)`` against ``r_c`` and
  the MPM audit every ``audit_every`` network steps, as above;
* ``"paper"``: the score alone (the paper's rule; no audit);
* ``"error"``: the network's error alone, the score only reported. The MPM
  audit runs at a stint's first step and then at an interval that doubles
  (up to ``audit_max``) after each audit within ``audit_tol``; an audit
  beyond it hands the flow to MPM, and the next stint starts again at 1
  (docs/hybrid.md: doubling only below half the tolerance audited almost
  every step and cost more than MPM). Every network step also
  computes its *density residual* — the RMS correction the density
  relaxation applied to the network's prediction, as an acceleration
  ``|Δx| / dt_step²`` in ``g`` (``last_residual``): a network that
  compresses the fluid is being corrected, and a residual above
  ``residual_tol`` and above :data:`RESIDUAL_GROWTH` × the residual of the
  stint's last passing audit brings the audit forward to this step (after
  an impact the residual stays above ``residual_tol``: compared with the
  level an audit accepted, only its growth triggers). Back on MPM, the
  network takes over again after ``dwell·2^k`` steps (the backoff below),
  whatever the score.

``r_c ≤ 0`` switches every rule off (the network alone) and ``r_c > 1``
runs MPM only, whatever the rule.

Control (paper Sec. 3.2): while a ``forcing`` is set the hybrid runs MPM,
which applies it (a network step in progress hands over first, event
"switch:mpm"); once it is cleared the usual ``dwell`` rule hands the flow
back to the network.

Moving obstacles (docs/obstacles.md, "Moving obstacles"): the network sees
an obstacle as static boundary particles where the scene put it. While an
obstacle moves in a step (a keyframed path, :meth:`HybridSimulator.move_obstacle`)
or stands anywhere else, the hybrid runs MPM, as for a forcing; once every
obstacle is back where the scene put it and still, the ``dwell`` rule
applies again. The frames' boundary particles stand at each obstacle's
current pose (MPM's :attr:`~hybridmpm.sim.MpmSimulator.obstacle_offsets`).

The hybrid composes an :class:`~hybridmpm.sim.mpm.MpmSimulator` and a
:class:`~hybridmpm.sim.neural.NeuralSimulator` on the same particles (the
scene clustered once to the model's ``r_p``) through their public methods.
"""

from __future__ import annotations

import math
import time
from collections import deque
from pathlib import Path
from typing import Any

import numpy as np

from hybridmpm.conventions import (
    AUDIT_EVERY,
    AUDIT_MAX,
    AUDIT_TOL,
    DELTA,
    FAILURE_DEGREE_FACTOR,
    FAILURE_ESCAPE_CELLS,
    FAILURE_KE_FACTOR,
    R_C,
    RESIDUAL_TOL,
    SAFEGUARD,
    SAFEGUARDS,
    G,
)
from hybridmpm.errors import InvalidInputError
from hybridmpm.models import shipped_switching
from hybridmpm.neural.runtime import GnsRuntime
from hybridmpm.scenes import make_scene
from hybridmpm.scenes.core import Clusters, Scene
from hybridmpm.scenes.resolution import at_resolution
from hybridmpm.sim.base import (
    MPM,
    NEURAL,
    Forcing,
    Frame,
    SimStats,
    check_count,
    check_forcing,
    check_int,
    check_positions,
    check_step_index,
    new_lock,
    reading_state,
    serialised,
)
from hybridmpm.sim.coarse import COARSE, CoarseMpmHalf
from hybridmpm.sim.convert import VELOCITY_ESTIMATES, mpm_history
from hybridmpm.sim.mpm import MpmSimulator
from hybridmpm.sim.neural import RELAX_ITERATIONS, REST_PERCENTILE, NeuralSimulator, load_model
from hybridmpm.sim.safeguard import ACCEL_FLOOR, complexity_score

#: The hybrid's cheap halves: the network (the paper's hybrid) or plain MPM on
#: a coarser grid of the same particles (its classical twin, :mod:`hybridmpm.sim.coarse`).
CHEAP_HALVES = ("neural", "mpm-coarse")
#: Default dwell (steps of s ≥ r_c on MPM before the network takes over again);
#: see docs/hybrid.md for the measurement behind it.
DWELL = 5
#: "error" rule: a density residual this many times that of the last passing
#: audit (and above ``residual_tol``) brings the next audit forward.
RESIDUAL_GROWTH = 2.0
#: After a failure fallback the dwell doubles per failure since the network's
#: last healthy stint (2·dwell steps without failure), up to 2**MAX_BACKOFF.
MAX_BACKOFF = 6
_STATE_VERSION = 2


def _check(name: str, ok: bool, msg: str) -> None:
    if not ok:
        raise InvalidInputError(f"{name}: {msg}", name)


def _finite(v: Any) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)


class HybridSimulator:
    """Neural physics with an MPM fallback (paper Sec. 3.1.2).

    Parameters
    ----------
    scene:
        A :class:`~hybridmpm.scenes.Scene` at full resolution (or a registered
        scene name / scene file, built with ``seed``).
    model:
        :class:`~hybridmpm.neural.GnsRuntime`, ``.onnx`` path, or None for the
        shipped model of the scene.
    r_c, delta, dwell:
        Safeguard threshold (default 0.8), window δ in steps (10), and steps
        of ``s ≥ r_c`` on MPM before returning to the network (default
        :data:`DWELL`).
    seed:
        Seed of the scene (if a name) and of the r_p clustering.
    affine, volume_ratio:
        APIC ``C`` after neural → MPM: "fit" (neighbour least squares) or
        "zero"; water's ``J``: "density" (from the local density) or "one".
    velocity:
        MPM's velocities after neural → MPM: "last" (the last finite
        difference, default) or "second" (second-order backward difference);
        :func:`~hybridmpm.sim.convert.velocities_from_history`.
    accel_floor:
        [m/s²] particles calmer than this count as cos = 1 in s(t).
    audit_every, audit_tol:
        MPM audit of the network (module doc): network steps per audit
        (default :data:`AUDIT_EVERY`; 0 = off; the "audit" rule) and
        tolerance [g] (default :data:`AUDIT_TOL`; the "audit" and "error" rules).
    safeguard, residual_tol, audit_max:
        The switching rule, one of :data:`~hybridmpm.conventions.SAFEGUARDS`
        (module doc). Unset, ``safeguard`` and ``audit_tol`` are those chosen
        for the scene's shipped model when ``model`` is None
        (:func:`~hybridmpm.models.shipped_switching`), else
        :data:`~hybridmpm.conventions.SAFEGUARD` and ``AUDIT_TOL``; and
        the "error" rule's density-residual trigger [g] (default
        :data:`~hybridmpm.conventions.RESIDUAL_TOL`) and longest audit
        interval [network steps] (default :data:`~hybridmpm.conventions.AUDIT_MAX`).
    ke_factor, escape_cells, degree_factor, detect_failures:
        The network's failure checks (:class:`~hybridmpm.sim.neural.NeuralSimulator`).
    relax, rest_percentile:
        The density relaxation after each network step (:class:`~hybridmpm.sim.neural.NeuralSimulator`; ``relax`` = 0: off).
    cheap, cheap_grid:
        The cheap half (:data:`CHEAP_HALVES`): ``"neural"`` (the network,
        the paper's hybrid) or ``"mpm-coarse"``, the classical twin: MPM on
        a coarser grid (``cheap_grid`` cells per side, default half the
        scene's) with the same particles, handed over bit for bit
        (:class:`~hybridmpm.sim.coarse.CoarseMpmHalf`); the model then only
        sets ``r_p`` and ``r_t``. Its steps are counted and labelled
        ``"coarse"`` (``cheap_kind``).
    mpm_threads, nn_threads:
        Threads of the MPM solver (0 = all cores) and of onnxruntime.
    clusters:
        The :attr:`~hybridmpm.scenes.Scene.clusters` of an earlier simulator of
        the scene at the model's ``r_p``: rebuilt without the k-means.

    ``mpm`` and ``neural`` are the two composed simulators. Raises
    :class:`InvalidInputError` naming the parameter for out-of-range values
    or a model that does not fit the scene.
    """

    kind = "hybrid"

    def __init__(
        self,
        scene: Scene | str,
        model: GnsRuntime | str | Path | None = None,
        *,
        r_c: float = R_C,
        delta: int = DELTA,
        dwell: int = DWELL,
        seed: int = 0,
        affine: str = "fit",
        volume_ratio: str = "density",
        velocity: str = "last",
        accel_floor: float = ACCEL_FLOOR,
        audit_every: int = AUDIT_EVERY,
        audit_tol: float | None = None,
        safeguard: str | None = None,
        residual_tol: float = RESIDUAL_TOL,
        audit_max: int = AUDIT_MAX,
        ke_factor: float = FAILURE_KE_FACTOR,
        escape_cells: float = FAILURE_ESCAPE_CELLS,
        degree_factor: float = FAILURE_DEGREE_FACTOR,
        detect_failures: bool = True,
        relax: int = RELAX_ITERATIONS,
        rest_percentile: float = REST_PERCENTILE,
        mpm_threads: int = 0,
        nn_threads: int = 1,
        clusters: Clusters | None = None,
        cheap: str = "neural",
        cheap_grid: int | None = None,
    ) -> None:

        self._lock = new_lock()
        _check("r_c", _finite(r_c), f"must be a finite number, got {r_c!r}")
        _check("delta", isinstance(delta, int) and not isinstance(delta, bool) and delta >= 1, f"must be an integer >= 1, got {delta!r}")
        _check("dwell", isinstance(dwell, int) and not isinstance(dwell, bool) and dwell >= 1, f"must be an integer >= 1, got {dwell!r}")
        _check("affine", affine in ("fit", "zero"), f"must be 'fit' or 'zero', got {affine!r}")
        _check("volume_ratio", volume_ratio in ("density", "one"), f"must be 'density' or 'one', got {volume_ratio!r}")
        _check("velocity", velocity in VELOCITY_ESTIMATES, f"must be one of {', '.join(map(repr, VELOCITY_ESTIMATES))}, got {velocity!r}")
        _check("accel_floor", _finite(accel_floor) and accel_floor >= 0, f"must be >= 0 [m/s²], got {accel_floor!r}")
        _check(
            "audit_every",
            isinstance(audit_every, int) and not isinstance(audit_every, bool) and audit_every >= 0,
            f"must be an integer >= 0 (0 = no audit), got {audit_every!r}",
        )
        _check("residual_tol", _finite(residual_tol) and residual_tol > 0, f"must be > 0 [g], got {residual_tol!r}")
        _check(
            "audit_max",
            isinstance(audit_max, int) and not isinstance(audit_max, bool) and 1 <= audit_max <= 1024,
            f"must be an integer in [1, 1024] [network steps], got {audit_max!r}",
        )
        if isinstance(scene, str):
            scene = make_scene(scene, seed=seed)
        # the shipped model's rule (models/switching.json) where neither setting is given
        shipped = shipped_switching(scene.name) if model is None and scene.name else {}
        if safeguard is None:
            safeguard = shipped.get("safeguard", SAFEGUARD)
        if audit_tol is None:
            audit_tol = shipped["audit_tol"] if shipped.get("safeguard") == safeguard and "audit_tol" in shipped else AUDIT_TOL
        _check("audit_tol", _finite(audit_tol) and audit_tol > 0, f"must be > 0 [g], got {audit_tol!r}")
        _check("safeguard", safeguard in SAFEGUARDS, f"must be one of {', '.join(map(repr, SAFEGUARDS))}, got {safeguard!r}")
        _check("cheap", cheap in CHEAP_HALVES, f"must be one of {', '.join(map(repr, CHEAP_HALVES))}, got {cheap!r}")
        self.scene_full = scene
        self.model = load_model(model, scene.name, check_int("nn_threads", nn_threads, 0))
        self.r_c = float(r_c)
        self.delta = delta
        self.dwell = dwell
        self.affine = affine
        self.volume_ratio = volume_ratio
        self.velocity = velocity
        self.accel_floor = float(accel_floor)
        self.audit_every = audit_every
        self.audit_tol = float(audit_tol)
        self.safeguard = safeguard
        self.residual_tol = float(residual_tol)
        self.audit_max = audit_max
        self.last_residual = float("nan")
        self._interval = 1
        self._since_audit = 0
        self._residual_ref = 0.0
        self.scene = at_resolution(scene, self.model.r_p, seed, clusters)
        self.cheap = cheap
        self.neural: NeuralSimulator | CoarseMpmHalf
        if cheap == "neural":
            self.cheap_kind = NEURAL
            self.neural = NeuralSimulator(
                self.scene, self.model, detect_failures=detect_failures, ke_factor=ke_factor, escape_cells=escape_cells,
                degree_factor=degree_factor, warmup=False, relax=relax, rest_percentile=rest_percentile, mpm_threads=mpm_threads,
            )  # fmt: skip
        else:  # the classical twin: the model only sets the particles (r_p) and the step (r_t); its network never runs
            self.cheap_kind = COARSE
            self.neural = CoarseMpmHalf(self.scene, r_t=self.model.r_t, n_grid=cheap_grid, threads=mpm_threads)
        self.mpm = MpmSimulator(self.scene, r_t=self.model.r_t, threads=mpm_threads)
        self.particles = self.mpm.particles
        self.r_t = self.model.r_t
        self.t_in = self.model.t_in
        self.dt_frame = float(self.scene.dt_frame)
        self.dt_step = self.dt_frame * self.r_t
        self._buffer: deque[np.ndarray] = deque(maxlen=max(2 * delta + 2, self.t_in))
        self._buffer.append(self.mpm.fluid_positions)
        self.solver_name = MPM
        self._calm = 0
        self._strikes = 0
        self._neural_run = 0
        self.step_index = 0
        self.stats = SimStats(steps={MPM: 0, self.cheap_kind: 0})
        self.last_score = float("nan")
        self._frame = self.mpm.frame

    # ------------------------------------------------------------ properties
    @property
    def n_fluid(self) -> int:
        return self.particles.num_fluid

    @property
    def particle_type(self) -> np.ndarray:
        """GNS particle types int64 [N + B]."""
        return self.particles.particle_type

    @property
    def positions(self) -> np.ndarray:
        """Current positions with boundary particles, float32 [N + B, D] (each
        obstacle's at its current pose)."""
        return self.particles.pad(self._buffer[-1], self.mpm.obstacle_offsets)

    @property
    def frame(self) -> Frame:
        """The last :class:`Frame` (the initial condition before the first step)."""
        return self._frame

    @property
    def velocities(self) -> np.ndarray:
        """Current fluid velocities [m/s], float32 [N, D]: MPM's when MPM made
        the last step, else the network's last finite difference."""
        if self._frame.solver == self.cheap_kind:
            return self.neural.velocities
        return self.mpm.velocities

    @property
    def mean_degree(self) -> float:
        """Mean neighbours per particle of the network's graph for its next step; nan when the next step is MPM's."""
        return self.neural.mean_degree if self.solver_name == self.cheap_kind else float("nan")

    @property
    def initial_degree(self) -> float:
        """Mean neighbours per particle of the initial condition (the fluid at rest spacing)."""
        return self.neural.initial_degree

    @property
    def safeguard_on(self) -> bool:
        return self.r_c > 0.0

    @property
    def forcing(self) -> Forcing:
        """External acceleration of the fluid particles (see :mod:`hybridmpm.sim.base`);
        while set, the hybrid runs MPM."""
        return self.mpm.forcing

    @forcing.setter
    @serialised
    def forcing(self, value: Forcing) -> None:
        self.mpm.forcing = check_forcing(value, self.particles.num_fluid, self.particles.dim)

    @property
    def obstacle_centers(self) -> np.ndarray:
        """Each obstacle's centre now [m], float64 [C, D] (MPM's; see :attr:`~hybridmpm.sim.MpmSimulator.obstacle_centers`)."""
        return self.mpm.obstacle_centers

    @serialised
    def move_obstacle(self, index: int, center: Any, velocity: Any = None) -> None:
        """Move obstacle ``index`` during the next :meth:`advance`, as
        :meth:`~hybridmpm.sim.MpmSimulator.move_obstacle` (same arguments and errors); the
        step then runs on MPM (module doc)."""
        self.mpm.move_obstacle(index, center, velocity)

    # ------------------------------------------------------------ stepping
    def _to_mpm(self) -> None:
        if isinstance(self.neural, CoarseMpmHalf):  # the same particles on the fine grid, bit for bit
            self.mpm.solver.restore_particles(self.neural.handover_state())
            return
        hist = np.stack(list(self._buffer)[-3:])
        self.mpm.load_history(hist, self.dt_step, affine=self.affine, affine_radius=self.model.radius, volume_ratio=self.volume_ratio, velocity=self.velocity)

    def _to_neural(self) -> None:
        # called after an MPM step: the buffer's newest entry is the solver's state
        if isinstance(self.neural, CoarseMpmHalf):
            self.neural.take_over(self.mpm.solver)
            return
        self.neural.set_history(mpm_history(self.mpm.fluid_positions, np.stack(list(self._buffer)[-self.t_in : -1]), self.t_in))

    def _fall_back(self, convert: bool = True) -> None:
        if convert:
            self._to_mpm()
        self.solver_name = MPM
        self._calm = 0
        self.stats.switches += 1

    def _mpm_holds_state(self) -> bool:
        """Whether the MPM solver holds the current state itself (the last
        step was MPM's, e.g. at a stint's first network step): then a fallback
        or an audit needs no neural → MPM conversion and loses nothing."""
        return self._frame.solver == MPM

    @property
    def mpm_only(self) -> bool:
        return self.r_c > 1.0

    def _density_residual(self, proposal: Any) -> float:
        """The "error" rule's density residual [g] of a proposal: RMS over
        fluid particles of (relaxed − predicted) / dt_step² (module doc)."""
        if proposal.positions is None:
            return float("nan")
        corr = self.particles.fluid(proposal.positions).astype(np.float64) - self.particles.fluid(proposal.predicted)
        rms = float(np.sqrt(np.mean(np.sum(corr * corr, axis=1)))) if len(corr) else 0.0
        return rms / (self.dt_step * self.dt_step) / G

    def _audit_due(self, residual: float) -> bool:
        # the audit belongs to the safeguard: r_c <= 0 (neural only, paper Table 2) switches it off too
        if not self.safeguard_on:
            return False
        if self.safeguard == "audit":
            return self.audit_every > 0 and self._neural_run % self.audit_every == 0
        if self.safeguard == "error":
            trigger = max(self.residual_tol, RESIDUAL_GROWTH * self._residual_ref)
            return self._neural_run == 0 or residual > trigger or self._since_audit + 1 >= self._interval
        return False

    def _adapt_interval(self, audit: float) -> None:
        """The "error" rule's audit interval after an audit of ``audit`` [g]: doubled within the tolerance, else 1."""
        self._since_audit = 0
        self._interval = min(2 * self._interval, self.audit_max) if audit <= self.audit_tol else 1

    def _audit(self, proposed: np.ndarray) -> tuple[float, Frame]:
        """MPM's step from the state the network started from (converted as a
        fallback would, unless MPM holds it already), compared with the
        network's ``proposed`` fluid positions float32 [N, D]: returns the
        audit error [g] (module doc) and MPM's :class:`Frame`. Leaves
        ``self.mpm`` at the end of MPM's step."""
        t0 = time.perf_counter()
        if not self._mpm_holds_state():
            self._to_mpm()
        self.mpm.step_index = self.step_index
        fr = self.mpm.advance()
        diff = proposed.astype(np.float64) - self.particles.fluid(fr.positions)
        rms = float(np.sqrt(np.mean(np.sum(diff * diff, axis=1)))) if len(diff) else 0.0
        self.stats.audits += 1
        self.stats.audit_seconds += time.perf_counter() - t0
        return rms / (self.dt_step * self.dt_step) / G, fr

    @serialised
    def advance(self) -> Frame:
        """One coarse step (``r_t`` frames); returns its :class:`Frame`.

        Raises :class:`~hybridmpm.errors.SimulationError` if MPM fails even
        with ``max_substeps`` (the simulator state is then that before the step).
        """
        t0 = time.perf_counter()
        event: str | None = None
        retries = substeps = 0
        controlled = False
        self.mpm.step_index = self.step_index  # the obstacles' paths and the forcing's frame clock are the hybrid's
        forced = self.mpm.forcing is not None or self.mpm.obstacles_moving or self.mpm.obstacles_displaced
        if self.solver_name == self.cheap_kind and forced:
            self._fall_back(convert=not self._mpm_holds_state())
            event = "switch:mpm"
        ran = self.solver_name
        audit = float("nan")
        audited: Frame | None = None
        if ran == self.cheap_kind:
            proposal = self.neural.propose()
            failure = proposal.failure
            self.last_residual = self._density_residual(proposal) if self.safeguard == "error" else float("nan")
            if failure is None and self._audit_due(self.last_residual):
                assert proposal.positions is not None
                audit, audited = self._audit(self.particles.fluid(proposal.positions))
                if self.safeguard == "error":
                    self._adapt_interval(audit)
                    # a residual the audit passed is the network's own level: only growth beyond it is news
                    self._residual_ref = self.last_residual if audit <= self.audit_tol else 0.0
                if not (audit <= self.audit_tol):
                    failure = "audit"
            elif failure is None:
                self._since_audit += 1
            if failure is None:
                pos = self.particles.fluid(self.neural.commit(proposal)).copy()
                self._neural_run += 1
                if self._neural_run >= 2 * self.dwell:
                    self._strikes = 0  # a healthy stint: forgive earlier failures
            else:
                event = f"fallback:{failure}"
                self._strikes += 1
                self.stats.fallbacks[failure] = self.stats.fallbacks.get(failure, 0) + 1
                # after a failed audit MPM has already taken this step
                self._fall_back(convert=audited is None and not self._mpm_holds_state())
                ran = MPM
        if ran == MPM:
            if audited is None:
                self.mpm.step_index = self.step_index  # the forcing's frame clock is the hybrid's
                audited = self.mpm.advance()
            fr = audited
            pos = self.particles.fluid(fr.positions).copy()
            retries, substeps, controlled = fr.mpm_retries, fr.substeps, fr.controlled
        self._buffer.append(pos)
        self.step_index += 1
        self.stats.steps[ran] += 1
        self.stats.mpm_retries += retries

        # safeguard on the trajectory, whichever solver made it
        score = complexity_score(np.stack(self._buffer), self.dt_step, self.delta, self.accel_floor) if self.safeguard_on else float("nan")
        self.last_score = score
        warm = self.step_index >= self.t_in - 1
        by_score = self.safeguard != "error" or self.mpm_only
        if self.solver_name == self.cheap_kind:
            if self.safeguard_on and by_score and not (score >= self.r_c):
                self._fall_back()
                event = event or "switch:mpm"
        elif warm and not forced:
            ok = (not self.safeguard_on) or (score >= self.r_c if by_score else True)
            self._calm = self._calm + 1 if ok else 0
            # after the warm-up a calm score hands over at once; after a switch it must hold for `dwell`
            # steps, doubled for each failure of the network since its last healthy stint (backoff)
            if self.stats.steps[self.cheap_kind] == 0 and self.stats.switches == 0:
                need = 1
            else:
                need = self.dwell * 2 ** min(self._strikes, MAX_BACKOFF)
            if self._calm >= need and len(self._buffer) >= self.t_in:
                self._to_neural()
                self.solver_name = self.cheap_kind
                self._neural_run = 0
                self._interval, self._since_audit, self._residual_ref = 1, 0, 0.0
                if self.stats.steps[self.cheap_kind] > 0 or self.stats.switches > 0:
                    self.stats.switches += 1
                    event = event or "switch:neural"
        self._frame = Frame(
            self.step_index,
            self.step_index * self.r_t,
            self.step_index * self.dt_step,
            self.particles.pad(pos, self.mpm.obstacle_offsets),
            ran,
            time.perf_counter() - t0,
            score,
            event,
            retries,
            substeps,
            controlled,
            audit,
            self.mpm.frame_centers(),
        )
        return self._frame

    # ------------------------------------------------------------ checkpoint
    @serialised
    def state(self) -> dict[str, Any]:
        """The whole hybrid state (picklable dict): both simulators' states,
        the position buffer, the solver in charge, counters."""
        return {
            "kind": self.kind,
            "version": _STATE_VERSION,
            "mpm": self.mpm.state(),
            "neural": self.neural.state(),
            "buffer": np.stack(list(self._buffer)).copy(),
            "solver_name": self.solver_name,
            "frame_solver": self._frame.solver,
            "calm": self._calm,
            "strikes": self._strikes,
            "neural_run": self._neural_run,
            "interval": self._interval,
            "since_audit": self._since_audit,
            "residual_ref": self._residual_ref,
            "step_index": self.step_index,
            "stats": self.stats.to_dict(),
            "last_score": self.last_score,
            "n_fluid": self.n_fluid,
        }

    @serialised
    def restore(self, state: dict[str, Any]) -> None:
        """Restore a :meth:`state` of this simulator (same scene and model),
        all or nothing: the whole state — both simulators' states, the
        position buffer (its shape, finite), the solver names, the counters
        (integers within :data:`~hybridmpm.limits.MAX_FRAME_INDEX`) — is
        validated before anything changes. Raises :class:`InvalidInputError`
        (field ``state``…) for a foreign or malformed state; the simulator is
        then unchanged."""
        with reading_state("hybrid"):
            if not isinstance(state, dict) or state.get("kind") != self.kind or state.get("version") != _STATE_VERSION:
                raise InvalidInputError("state: not a state of this hybrid simulator (kind or version differ)", "state")
            if check_int("state.n_fluid", state["n_fluid"], 0) != self.n_fluid:
                raise InvalidInputError(f"state.n_fluid: this simulator has {self.n_fluid} fluid particles", "state.n_fluid")
            buf = state["buffer"]
            depth = np.shape(buf)[0] if np.ndim(buf) == 3 else 0
            if not 1 <= depth <= self._buffer.maxlen:  # type: ignore[operator]
                raise InvalidInputError(
                    f"state.buffer: expected [T, {self.n_fluid}, {self.particles.dim}] with 1 <= T <= {self._buffer.maxlen}", "state.buffer"
                )
            buf = check_positions("state.buffer", buf, (depth, self.n_fluid, self.particles.dim))
            solver_name, frame_solver = state["solver_name"], state["frame_solver"]
            if solver_name not in (MPM, self.cheap_kind) or frame_solver not in (MPM, self.cheap_kind):
                raise InvalidInputError(f"state.solver_name: must be {MPM!r} or {self.cheap_kind!r}", "state.solver_name")
            counters = {k: check_count(f"state.{k}", state[k]) for k in ("calm", "strikes", "neural_run")}
            # the "error" rule's audit schedule (absent from states written before the rule existed)
            interval = max(1, check_count("state.interval", state.get("interval", 1)))
            since_audit = check_count("state.since_audit", state.get("since_audit", 0))
            residual_ref = state.get("residual_ref", 0.0)
            if isinstance(residual_ref, bool) or not isinstance(residual_ref, (int, float)) or not (math.isfinite(residual_ref) and residual_ref >= 0):
                raise InvalidInputError("state.residual_ref: must be a finite number >= 0 [g]", "state.residual_ref")
            step = check_step_index("state.step_index", state["step_index"], self.r_t)
            stats = SimStats.from_dict(state["stats"])
            last_score = state["last_score"]
            if isinstance(last_score, bool) or not isinstance(last_score, (int, float)) or math.isinf(last_score):
                raise InvalidInputError("state.last_score: must be a finite number (or NaN before the first score)", "state.last_score")
            commit_mpm = self.mpm._prepare_restore(state["mpm"])
            commit_neural = self.neural._prepare_restore(state["neural"])
        commit_mpm()  # the one step that can fail, and it changes nothing then
        commit_neural()
        self._buffer = deque([b for b in buf], maxlen=self._buffer.maxlen)
        self.solver_name = solver_name
        self._calm, self._strikes, self._neural_run = counters["calm"], counters["strikes"], counters["neural_run"]
        self._interval, self._since_audit, self._residual_ref = interval, since_audit, float(residual_ref)
        self.step_index = step
        self.stats = stats
        self.last_score = float(last_score)
        self._frame = Frame(
            self.step_index, self.step_index * self.r_t, self.step_index * self.dt_step, self.positions, frame_solver,
            score=self.last_score, obstacle_centers=self.mpm.frame_centers(),
        )  # fmt: skip


__all__ = ["CHEAP_HALVES", "DWELL", "MAX_BACKOFF", "RESIDUAL_GROWTH", "HybridSimulator"]
