"""The hybrid simulator (the paper's method): the cheap half steps, MPM takes over when the flow gets complex or the cheap half is wrong.

Paper Sec. 3.1.2, Eq. 1, Table 2; docs/hybrid.md. One *step* is one coarse step of the cheap half:
``r_t`` frames of ``dt_frame`` seconds, at its particle resolution ``r_p`` (the scene is clustered
once; MPM on the scene's grid and the cheap half move the same particles).

The hybrid is three parts and a loop:

* the **cheap half** (:class:`~hybridmpm.sim.cheap.CheapHalf`): the network
  (:class:`~hybridmpm.sim.neural.NeuralSimulator`, the paper's hybrid) or MPM on a coarser grid
  (:class:`~hybridmpm.sim.coarse.CoarseMpmHalf`, its classical twin), which proposes a step, commits
  it, takes over from MPM and hands back to it;
* the **switching rule** (:mod:`hybridmpm.sim.switching`): the paper's score ``s(t)`` against
  ``r_c``, the MPM audit, the error rule; its settings and counters;
* the **failure checks** (:class:`~hybridmpm.sim.cheap.FailureChecks`) every proposal passes: a
  rejected one is redone by MPM from the last good state (``Frame.event`` "fallback:<mode>");
* :meth:`HybridSimulator.advance`: the first ``T_in − 1`` steps are MPM (they fill the trajectory the
  cheap half takes over from); then each step is the cheap half's, audited by MPM where the rule asks
  (the RMS over fluid particles of the difference of the two predicted positions divided by
  ``dt_step²``, in ``g``: ``Frame.audit``; beyond the rule's tolerance MPM's step is kept, event
  "fallback:audit"), or MPM's, until the rule hands the flow back (event "switch:neural").

Control (paper Sec. 3.2): while a ``forcing`` is set the hybrid runs MPM, which applies it (a cheap
stint in progress hands over first, event "switch:mpm"); once it is cleared the rule hands the flow
back. Moving obstacles (docs/obstacles.md): while an obstacle moves in a step or stands anywhere but
where the scene put it, the hybrid runs MPM likewise; the frames' boundary particles stand at each
obstacle's current pose (MPM's :attr:`~hybridmpm.sim.MpmSimulator.obstacle_offsets`).
"""

from __future__ import annotations

import time
from collections import deque
from collections.abc import Callable
from dataclasses import fields
from pathlib import Path
from typing import Any

import numpy as np

from hybridmpm.conventions import G
from hybridmpm.errors import InvalidInputError
from hybridmpm.materials import refuse_untrained
from hybridmpm.models import shipped_switching
from hybridmpm.mpm.bodies import refuse_bodies
from hybridmpm.neural.base import Runtime, open_model, read_header
from hybridmpm.scenes import make_scene
from hybridmpm.scenes.core import Clusters, Scene
from hybridmpm.scenes.resolution import at_resolution, downsample_scene, on_grid
from hybridmpm.sim.base import (
    MPM,
    Forcing,
    Frame,
    SimStats,
    check_forcing,
    check_int,
    check_positions,
    check_step_index,
    new_lock,
    reading_state,
    serialised,
)
from hybridmpm.sim.cheap import CheapHalf, FailureChecks
from hybridmpm.sim.coarse import CoarseMpmHalf, CoarseOwnHalf, coarse_grid
from hybridmpm.sim.convert import Conversion
from hybridmpm.sim.mpm import MpmSimulator
from hybridmpm.sim.neural import NeuralSimulator
from hybridmpm.sim.switching import SETTINGS, SwitchingRule, make_rule

_STATE_VERSION = 2


def _network_half(scene: Scene, model: Any, seed: int, clusters: Clusters | None, threads: int, nn_threads: int, **kw: Any) -> tuple[Scene, CheapHalf]:
    """The paper's cheap half: the network (any learned kind), on the scene clustered to its ``r_p``."""
    runtime = open_model(model, scene.name, nn_threads)
    low = at_resolution(scene, runtime.r_p, seed, clusters)
    kw.pop("cheap_grid", None)
    return low, NeuralSimulator(low, runtime, warmup=False, mpm_threads=threads, **kw)


#: What the classical twin's coarse grid carries (``cheap_particles``): the hybrid's particles
#: (the network's ``r_p`` set, handed over bit for bit) or the grid's own set (merged and split at each handover).
TWIN_PARTICLES = ("network", "grid")


def _coarse_half(scene: Scene, model: Any, seed: int, clusters: Clusters | None, threads: int, nn_threads: int, **kw: Any) -> tuple[Scene, CheapHalf]:
    """The classical twin: MPM on ``cheap_grid`` (default half the scene's grid) with the particles of the
    network's resolution, read from the model file's metadata (:func:`~hybridmpm.neural.base.read_header`;
    no network loaded), or (``cheap_particles="grid"``) with the coarse grid's own particle set, as many as
    plain MPM puts on that grid, each a group of the hybrid's (:class:`~hybridmpm.sim.coarse.CoarseOwnHalf`)."""
    cheap_grid, particles = kw.pop("cheap_grid", None), kw.pop("cheap_particles", "network")
    kw.pop("checks", None), kw.pop("conversion", None)  # the network's: checked, and not used by MPM
    if kw:
        name = next(iter(kw))
        raise InvalidInputError(f"{name}: a setting of the network cheap half, not of 'mpm-coarse'", name)
    if particles not in TWIN_PARTICLES:
        raise InvalidInputError(f"cheap_particles: must be one of {', '.join(map(repr, TWIN_PARTICLES))}, got {particles!r}", "cheap_particles")
    header = read_header(model, scene.name)
    low = at_resolution(scene, header.r_p, seed, clusters)
    if particles == "network":
        return low, CoarseMpmHalf(low, r_t=header.r_t, n_grid=cheap_grid, threads=threads, t_in=header.t_in, model=header)
    n = coarse_grid(low, cheap_grid)
    groups = downsample_scene(low, min(1.0, on_grid(scene, n).num_particles / low.num_particles), seed)
    coarse = on_grid(groups.scene, n, keep_particles=True)
    return low, CoarseOwnHalf(low, coarse, groups.labels, r_t=header.r_t, threads=threads, t_in=header.t_in, model=header)


#: The hybrid's cheap halves by the name ``cheap`` takes: a builder ``(scene, model, seed, clusters,
#: mpm_threads, nn_threads, **settings) -> (the scene at the half's r_p, the half)``.
CHEAP_HALVES: dict[str, Callable[..., tuple[Scene, CheapHalf]]] = {"neural": _network_half, "mpm-coarse": _coarse_half}


def _split(settings: dict[str, Any], names: Any) -> dict[str, Any]:
    return {k: settings.pop(k) for k in list(settings) if k in names}


def _rule_setting(name: str) -> Any:
    return property(lambda self: getattr(self.rule, name, None), doc=f"The rule's ``{name}`` (None where the rule has none).")


class HybridSimulator:
    """A cheap half with an MPM fallback (paper Sec. 3.1.2; module doc).

    Two ways to build one:

    * ``HybridSimulator.compose(scene, cheap, rule, checks)``: ``scene`` the particle set both solvers
      move (at the cheap half's ``r_p``), ``cheap`` a :class:`~hybridmpm.sim.cheap.CheapHalf` of it,
      ``rule`` a :class:`~hybridmpm.sim.switching.SwitchingRule`, ``checks`` the
      :class:`~hybridmpm.sim.cheap.FailureChecks` (None: the defaults); ``mpm_threads`` MPM's threads;
    * ``HybridSimulator(scene, model=None, *, cheap="neural", **settings)``, from plain settings:
      ``scene`` a full-resolution :class:`~hybridmpm.scenes.Scene` or a registered scene name / scene
      file (built with ``seed``); ``model`` a run-time model, an ``.onnx`` path or None (the scene's
      shipped model); ``cheap`` a name of :data:`CHEAP_HALVES` ("neural", the network; "mpm-coarse",
      MPM on ``cheap_grid`` cells per side, default half the scene's, with the particles of the
      model's ``r_p``, handed over bit for bit; its steps are labelled ``"coarse"``); ``seed`` also
      seeds the ``r_p`` clustering, ``clusters`` an earlier simulator's (:attr:`~hybridmpm.scenes.Scene.clusters`:
      no k-means); ``mpm_threads`` (0: all cores) and ``nn_threads`` (onnxruntime). ``settings``:
      the rule's (``safeguard``, ``r_c``, ``delta``, ``dwell``, ``accel_floor``, ``audit_every``,
      ``audit_tol``, ``residual_tol``, ``audit_max``: :func:`~hybridmpm.sim.switching.make_rule`; with
      the shipped model and ``safeguard`` unset, the rule chosen for the scene,
      :func:`~hybridmpm.models.shipped_switching`), or ``rule`` itself; the failure checks'
      (``detect_failures``, ``ke_factor``, ``escape_cells``, ``degree_factor``) or ``checks``; the
      conversion's (``affine``, ``volume_ratio``, ``velocity``: :class:`~hybridmpm.sim.convert.Conversion`);
      and the network's own (``relax``, ``rest_percentile``, ... :class:`~hybridmpm.sim.neural.NeuralSimulator`).

    ``mpm`` is MPM on the scene's grid, ``half`` the cheap half (``neural``, its older name), ``rule``
    the rule. Raises :class:`InvalidInputError` naming the setting for out-of-range values, or
    ``model`` for a model that does not fit the scene.
    """

    kind = "hybrid"

    def __init__(
        self,
        scene: Scene | str,
        model: Runtime | str | Path | None = None,
        *,
        cheap: str = "neural",
        rule: SwitchingRule | None = None,
        checks: FailureChecks | None = None,
        seed: int = 0,
        clusters: Clusters | None = None,
        mpm_threads: int = 0,
        nn_threads: int = 1,
        **settings: Any,
    ) -> None:
        if cheap not in CHEAP_HALVES:
            raise InvalidInputError(f"cheap: must be one of {', '.join(map(repr, CHEAP_HALVES))}, got {cheap!r}", "cheap")
        nn_threads = check_int("nn_threads", nn_threads, 0)
        if isinstance(scene, str):
            scene = make_scene(scene, seed=seed)
        if cheap == "neural":
            refuse_untrained(scene.material, "learned simulator")
        # the network never saw a body, and the coarse grid's hand-over carries particles only
        refuse_bodies(len(scene.params.bodies), "learned simulator" if cheap == "neural" else "hybrid's coarse half")
        ruled = _split(settings, set(SETTINGS) | {"safeguard"})
        if rule is None:
            rule = make_rule(shipped=shipped_switching(scene.name) if model is None and scene.name else None, **ruled)
        elif ruled:
            raise InvalidInputError(f"{next(iter(ruled))}: a setting of the rule; with rule= given, set it there", next(iter(ruled)))
        checked = _split(settings, {f.name for f in fields(FailureChecks)})
        if checks is None:
            checks = FailureChecks(**checked)
        elif checked:
            raise InvalidInputError(f"{next(iter(checked))}: a failure check; with checks= given, set it there", next(iter(checked)))
        conversion = Conversion(**_split(settings, {f.name for f in fields(Conversion)}))
        low, half = CHEAP_HALVES[cheap](scene, model, seed, clusters, mpm_threads, nn_threads, checks=checks, conversion=conversion, **settings)
        self._setup(low, half, rule, checks, mpm_threads)
        self.scene_full = scene

    @classmethod
    def compose(cls, scene: Scene, cheap: CheapHalf, rule: SwitchingRule, checks: FailureChecks | None = None, *, mpm_threads: int = 0) -> HybridSimulator:
        """The hybrid of ``cheap`` and MPM on ``scene``'s grid (the particle set ``cheap`` moves), switched by ``rule``
        (class doc). Raises :class:`InvalidInputError` (field ``cheap``) for a cheap half of other particles."""
        sim = cls.__new__(cls)
        sim._setup(scene, cheap, rule, FailureChecks() if checks is None else checks, mpm_threads)
        sim.scene_full = scene
        return sim

    def _setup(self, scene: Scene, half: CheapHalf, rule: SwitchingRule, checks: FailureChecks, mpm_threads: int) -> None:
        self._lock = new_lock()
        self.scene = scene
        self.half = half
        self.rule = rule
        self.checks = checks
        self.mpm = MpmSimulator(scene, r_t=half.r_t, threads=mpm_threads)
        self.particles = self.mpm.particles
        if (half.particles.num_fluid, half.particles.num_total) != (self.particles.num_fluid, self.particles.num_total):
            raise InvalidInputError(f"cheap: its particle set ({half.particles.num_fluid} fluid) is not the scene's ({self.particles.num_fluid})", "cheap")
        self.r_t = half.r_t
        self.t_in = half.t_in
        self.dt_frame = float(scene.dt_frame)
        self.dt_step = self.dt_frame * self.r_t
        self._buffer: deque[np.ndarray] = deque(maxlen=max(2 * rule.delta + 2, self.t_in))
        self._buffer.append(self.mpm.fluid_positions)
        self.solver_name = MPM
        self.step_index = 0
        self.stats = SimStats(steps={MPM: 0, half.kind: 0})
        self.last_score = float("nan")
        #: The last cheap step's reading for the rule (the error rule's density residual [g]; nan for the others).
        self.last_residual = float("nan")
        self._frame = self.mpm.frame

    # ------------------------------------------------------------ properties
    @property
    def cheap(self) -> str:
        """The cheap half's name (a key of :data:`CHEAP_HALVES`)."""
        return self.half.name

    @property
    def cheap_kind(self) -> str:
        """The label of the cheap half's frames and step counts ("neural", "coarse")."""
        return self.half.kind

    @property
    def neural(self) -> CheapHalf:
        """The cheap half, by its older name."""
        return self.half

    @property
    def model(self) -> Any:
        """The model whose resolution the particles are at (the cheap half's: a run-time model, or the twin's header)."""
        return self.half.model

    @property
    def safeguard(self) -> str:
        """The rule's name (:data:`~hybridmpm.conventions.SAFEGUARDS`)."""
        return self.rule.name

    # the rule's settings, read as the hybrid's (None where this rule has none)
    r_c = _rule_setting("r_c")
    delta = _rule_setting("delta")
    dwell = _rule_setting("dwell")
    accel_floor = _rule_setting("accel_floor")
    audit_every = _rule_setting("audit_every")
    audit_tol = _rule_setting("audit_tol")
    residual_tol = _rule_setting("residual_tol")
    audit_max = _rule_setting("audit_max")

    @property
    def n_fluid(self) -> int:
        return self.particles.num_fluid

    @property
    def particle_type(self) -> np.ndarray:
        """GNS particle types int64 [N + B]."""
        return self.particles.particle_type

    @property
    def positions(self) -> np.ndarray:
        """Current positions with boundary particles, float32 [N + B, D] (each obstacle's at its current pose)."""
        return self.particles.pad(self._buffer[-1], self.mpm.obstacle_offsets)

    @property
    def frame(self) -> Frame:
        """The last :class:`Frame` (the initial condition before the first step)."""
        return self._frame

    @property
    def velocities(self) -> np.ndarray:
        """Current fluid velocities [m/s], float32 [N, D]: MPM's when MPM made the last step, else the cheap half's."""
        return self.half.velocities if self._frame.solver == self.cheap_kind else self.mpm.velocities

    @property
    def mean_degree(self) -> float:
        """Mean neighbours per particle of the cheap half's graph for its next step; nan when the next step is MPM's."""
        return self.half.mean_degree if self.solver_name == self.cheap_kind else float("nan")

    @property
    def initial_degree(self) -> float:
        """Mean neighbours per particle of the initial condition (the fluid at rest spacing)."""
        return self.half.initial_degree

    @property
    def safeguard_on(self) -> bool:
        return self.rule.active

    @property
    def mpm_only(self) -> bool:
        return self.rule.mpm_only

    @property
    def forcing(self) -> Forcing:
        """External acceleration of the fluid particles (see :mod:`hybridmpm.sim.base`); while set, the hybrid runs MPM."""
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
    @serialised
    def advance(self) -> Frame:
        """One coarse step (``r_t`` frames); returns its :class:`Frame`.

        Raises :class:`~hybridmpm.errors.SimulationError` if MPM fails even
        with ``max_substeps`` (the simulator state is then that before the step).
        """
        t0 = time.perf_counter()
        event: str | None = None
        self.mpm.step_index = self.step_index  # the obstacles' paths and the forcing's frame clock are the hybrid's
        forced = self.mpm.forcing is not None or self.mpm.obstacles_moving or self.mpm.obstacles_displaced
        if self.solver_name == self.cheap_kind and forced:
            self._fall_back(convert=not self._mpm_holds_state())
            event = "switch:mpm"
        ran, pos, fr, audit = self.solver_name, None, None, float("nan")
        if ran == self.cheap_kind:
            pos, fr, audit, failure = self._cheap_step()
            if failure is not None:
                event, ran = f"fallback:{failure}", MPM
        if ran == MPM:
            if fr is None:  # (after a failed audit MPM has taken this step already)
                self.mpm.step_index = self.step_index  # the forcing's frame clock is the hybrid's
                fr = self.mpm.advance()
            pos = self.particles.fluid(fr.positions).copy()
        assert pos is not None
        self._buffer.append(pos)
        self.step_index += 1
        self.stats.steps[ran] += 1
        retries, substeps, controlled = (fr.mpm_retries, fr.substeps, fr.controlled) if fr is not None else (0, 0, False)
        self.stats.mpm_retries += retries
        self.last_score = score = self.rule.score(np.stack(self._buffer), self.dt_step)
        switched = self._switch(score, forced)
        self._frame = Frame(
            self.step_index, self.step_index * self.r_t, self.step_index * self.dt_step, self.particles.pad(pos, self.mpm.obstacle_offsets), ran,
            time.perf_counter() - t0, score, event or switched, retries, substeps, controlled, audit, self.mpm.frame_centers(),
        )  # fmt: skip
        return self._frame

    def _cheap_step(self) -> tuple[np.ndarray | None, Frame | None, float, str | None]:
        """The cheap half's step, checked and audited as the rule says: its fluid positions float32
        [N, D] (None if rejected), MPM's :class:`Frame` of the step (None unless a failed audit made it), the audit
        error [g] (nan if none), and the failure (None if kept). A rejected step hands over to MPM,
        and MPM's frame of it comes back when a failed audit made it."""
        proposal = self.half.propose(self.checks)
        self.last_residual = self.rule.residual(proposal, self.particles, self.dt_step)
        failure, audit, audited = proposal.failure, float("nan"), None
        if failure is None and self.rule.audit_due(self.last_residual):
            assert proposal.positions is not None
            audit, audited = self._audit(self.particles.fluid(proposal.positions))
            failure = None if self.rule.audited(audit, self.last_residual) else "audit"
        elif failure is None:
            self.rule.not_audited()
        if failure is None:
            self.rule.kept()
            return self.particles.fluid(self.half.commit(proposal)).copy(), None, audit, None
        self.rule.failed()
        self.stats.fallbacks[failure] = self.stats.fallbacks.get(failure, 0) + 1
        self._fall_back(convert=audited is None and not self._mpm_holds_state())  # an audit left MPM at the end of its step
        return None, audited, audit, failure

    def _switch(self, score: float, forced: bool) -> str | None:
        """Hand the next step to the other solver where the rule says so (none while ``forced``, nor
        during the warm-up of ``T_in − 1`` steps); returns the event."""
        if self.solver_name == self.cheap_kind:
            if self.rule.stays(score):
                return None
            self._fall_back()
            return "switch:mpm"
        if forced or self.step_index < self.t_in - 1:
            return None
        first = self.stats.steps[self.cheap_kind] == 0 and self.stats.switches == 0  # after the warm-up: no fallback to doubt
        if not (self.rule.returns(score, first) and len(self._buffer) >= self.t_in):
            return None
        self.half.take_over(self.mpm.solver, np.stack(self._buffer))
        self.solver_name = self.cheap_kind
        self.rule.took_over()
        if first:
            return None
        self.stats.switches += 1
        return "switch:neural"

    def _fall_back(self, convert: bool = True) -> None:
        if convert:
            self.half.hand_back(self.mpm.solver, np.stack(self._buffer))
        self.solver_name = MPM
        self.rule.fell_back()
        self.stats.switches += 1

    def _mpm_holds_state(self) -> bool:
        """Whether the MPM solver holds the current state itself (the last step was MPM's, e.g. at a
        stint's first cheap step): then a fallback or an audit needs no hand-back and loses nothing."""
        return self._frame.solver == MPM

    def _audit(self, proposed: np.ndarray) -> tuple[float, Frame]:
        """MPM's step from the state the cheap half started from (handed back, unless MPM holds it
        already), compared with the cheap half's ``proposed`` fluid positions float32 [N, D]: returns
        the audit error [g] (module doc) and MPM's :class:`Frame`. Leaves ``self.mpm`` at the end of MPM's step."""
        t0 = time.perf_counter()
        if not self._mpm_holds_state():
            self.half.hand_back(self.mpm.solver, np.stack(self._buffer))
        self.mpm.step_index = self.step_index
        fr = self.mpm.advance()
        diff = proposed.astype(np.float64) - self.particles.fluid(fr.positions)
        rms = float(np.sqrt(np.mean(np.sum(diff * diff, axis=1)))) if len(diff) else 0.0
        self.stats.audits += 1
        self.stats.audit_seconds += time.perf_counter() - t0
        return rms / (self.dt_step * self.dt_step) / G, fr

    # ------------------------------------------------------------ checkpoint
    @serialised
    def state(self) -> dict[str, Any]:
        """The whole hybrid state (picklable dict): both solvers' states, the position buffer, the
        solver in charge, the rule's counters, the stats."""
        return {
            "kind": self.kind,
            "version": _STATE_VERSION,
            "mpm": self.mpm.state(),
            "neural": self.half.state(),
            "buffer": np.stack(list(self._buffer)).copy(),
            "solver_name": self.solver_name,
            "frame_solver": self._frame.solver,
            **self.rule.state(),
            "step_index": self.step_index,
            "stats": self.stats.to_dict(),
            "last_score": self.last_score,
            "n_fluid": self.n_fluid,
        }

    @serialised
    def restore(self, state: dict[str, Any]) -> None:
        """Restore a :meth:`state` of this simulator (same scene, cheap half and rule), all or
        nothing: the whole state — both solvers' states, the position buffer (its shape, finite), the
        solver names, the counters (integers within :data:`~hybridmpm.limits.MAX_FRAME_INDEX`) — is
        validated before anything changes. Raises :class:`InvalidInputError` (field ``state``…) for a
        foreign or malformed state; the simulator is then unchanged."""
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
            commit_rule = self.rule.prepare_restore(state)
            step = check_step_index("state.step_index", state["step_index"], self.r_t)
            stats = SimStats.from_dict(state["stats"])
            last_score = state["last_score"]
            if isinstance(last_score, bool) or not isinstance(last_score, (int, float)) or np.isinf(last_score):
                raise InvalidInputError("state.last_score: must be a finite number (or NaN before the first score)", "state.last_score")
            commit_mpm = self.mpm.prepare_restore(state["mpm"])
            commit_half = self.half.prepare_restore(state["neural"])
        commit_mpm()  # the one step that can fail, and it changes nothing then
        commit_half()
        commit_rule()
        self._buffer = deque([b for b in buf], maxlen=self._buffer.maxlen)
        self.solver_name = solver_name
        self.step_index = step
        self.stats = stats
        self.last_score = float(last_score)
        self._frame = Frame(
            self.step_index, self.step_index * self.r_t, self.step_index * self.dt_step, self.positions, frame_solver,
            score=self.last_score, obstacle_centers=self.mpm.frame_centers(),
        )  # fmt: skip


__all__ = ["CHEAP_HALVES", "TWIN_PARTICLES", "HybridSimulator"]
