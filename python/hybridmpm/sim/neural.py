"""The network alone behind the simulator interface (paper Sec. 2.2, 3.1.1, App. A).

The scene is clustered to the model's ``r_p``; MPM runs the first ``T_in − 1``
coarse steps to fill the network's position history (warm-up); from then on
each :meth:`NeuralSimulator.advance` is one network step of ``r_t`` frames:
radius graph (Rust cell list) + onnxruntime, predicted positions clipped to
the model's domain bounds, then relaxed where they are packed denser than the
initial condition.

Density relaxation (``relax`` iterations, default :data:`RELAX_ITERATIONS`;
0 = off): a learned simulator of a nearly incompressible material lets its
particles cluster step after step (on the column collapses the shipped
networks' mean number of neighbours grew from 12 to 38 in 100 frames, where
MPM's stays at 12), which no one-step loss sees. After each network step,
:func:`hybridmpm.graph.relax_density` moves the particles denser than the
rest density — the ``rest_percentile`` percentile (default 90) of the
initial condition's :func:`~hybridmpm.graph.kernel_density` over fluid
particles — apart with a unilateral Position Based Fluids constraint
(Macklin & Müller 2013), as Neural SPH (Toshev et al. 2024, Sec. 4) relaxes
its GNS rollouts; the relaxed positions become the history, so the next
velocity carries the correction. Free surfaces and splashes (less dense) and
obstacles are left alone. :attr:`NeuralSimulator.last_relaxed` counts the
particles corrected in the last step. The relaxation, the second clipping
and the next step's radius graph are one call
(:func:`hybridmpm.graph.relax_then_graph`: the same result as the three in
turn, the graph rebuilt only around the particles that moved). Where a step
is still packed above :data:`RELAX_AGAIN_DEGREE` (1.5) × the initial mean
neighbour count after that — a falling block the network drove into the
floor, clipped onto a line of the wall — the relaxation runs again, up to
:data:`RELAX_MAX_ROUNDS` more rounds, until it is not
(:attr:`NeuralSimulator.last_relax_rounds`): three iterations move a
particle at most 3R/4, short of undoing such a collapse, and the step would
otherwise fail "compressed" (sand2d seed 0 did at frame 96). Steps that
are not packed so (all others) cost nothing more.

Failure checks (:class:`~hybridmpm.sim.cheap.FailureChecks`, on by default): a step that predicts a
non-finite position ("nan"), moves a particle more than ``escape_cells``
cells beyond the model's bounds farther than its own last step carries it
("escaped": a particle on a wall that keeps its speed lands beyond the wall
by up to its last step's length before the wall clips it, which is inertia,
not a failure; water2d seeds 26, 28 and 37 stopped so at 4.1-4.5 cells with
last steps of 4.1-4.6 cells; a particle the network throws through the wall
moves farther than it did), raises the kinetic energy above
``ke_factor`` × the energy available at the start (kinetic + potential above
the floor; "energy"), or packs the particles so that their mean number of
neighbours within R exceeds ``degree_factor`` × that of the initial
condition ("compressed": sand and water are nearly incompressible, and the
graph — hence the cost — grows with the packing) is rejected:
:meth:`~NeuralSimulator.advance` raises :class:`~hybridmpm.sim.base.NetworkFailure`
and leaves the state unchanged; the hybrid uses :meth:`propose` /
:meth:`commit` to fall back to MPM instead.

Any learned kind runs here through :class:`hybridmpm.neural.base.Runtime`:
a kind whose input is a radius graph (``needs_graph``, the GNS) gets the
graph, the density relaxation and the degree check; one that moves the
particles through its own grid (the grid model) is only clipped, and its
:meth:`~hybridmpm.neural.base.Runtime.packing` is checked instead.

In the hybrid the simulator is the cheap half of the paper's hybrid
(:class:`hybridmpm.sim.cheap.CheapHalf`): :meth:`NeuralSimulator.take_over`
starts it from MPM's trajectory, :meth:`NeuralSimulator.hand_back` converts
its state for MPM (:class:`~hybridmpm.sim.convert.Conversion`).
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from hybridmpm.errors import InvalidInputError
from hybridmpm.graph import kernel_density, radius_graph, relax_then_graph
from hybridmpm.materials import refuse_untrained
from hybridmpm.mpm import MpmSolver
from hybridmpm.mpm.bodies import refuse_bodies
from hybridmpm.neural.base import Runtime, open_model
from hybridmpm.neural.runtime import Graph
from hybridmpm.scenes import make_scene
from hybridmpm.scenes.core import Clusters, Scene
from hybridmpm.scenes.resolution import at_resolution
from hybridmpm.sim.base import (
    MPM,
    NEURAL,
    Forcing,
    Frame,
    NetworkFailure,
    SimStats,
    check_int,
    check_positions,
    check_step_index,
    new_lock,
    reading_state,
    serialised,
)
from hybridmpm.sim.cheap import FailureChecks, Proposal
from hybridmpm.sim.convert import Conversion, mpm_history, neural_to_mpm
from hybridmpm.sim.mpm import MpmSimulator

_STATE_VERSION = 1

#: Default Jacobi iterations of the density relaxation after each network step (module doc).
RELAX_ITERATIONS = 3
#: Default percentile of the initial condition's kernel density taken as the rest density.
REST_PERCENTILE = 90.0
#: A step still packed above this × the initial mean neighbour count after its relaxation is relaxed again (module doc).
RELAX_AGAIN_DEGREE = 1.5
#: At most this many more rounds of ``relax`` iterations per step.
RELAX_MAX_ROUNDS = 8


class NeuralSimulator:
    """The GNS network alone (after an MPM warm-up), one model step per :meth:`advance`.

    Parameters
    ----------
    scene:
        A full-resolution :class:`~hybridmpm.scenes.Scene` (or a registered
        name / scene file built with ``seed``), or one already at the model's
        ``r_p``; clustered to the model's ``r_p`` with ``seed``.
    model:
        A run-time model of any learned kind (:class:`~hybridmpm.neural.base.Runtime`),
        an ``.onnx`` path (:func:`~hybridmpm.neural.base.open_model`), or None for
        the shipped model of the scene.
    checks, detect_failures:
        The failure checks (:class:`~hybridmpm.sim.cheap.FailureChecks`; None: the
        defaults); ``detect_failures=False`` turns them off (every prediction is taken).
    conversion:
        How :meth:`hand_back` converts the network's state for MPM
        (:class:`~hybridmpm.sim.convert.Conversion`; None: the defaults).
    clamp:
        Clip predicted positions to the model's domain bounds (the walls,
        which the network sees only through its wall-distance features).
    warmup:
        Run MPM for the first ``T_in − 1`` steps (default). False: the
        history must be given with :meth:`set_history` before :meth:`advance`
        (the hybrid does so).
    relax, rest_percentile:
        Density relaxation after each network step (module doc): Jacobi
        iterations (integer in [0, 100]; 0 = off) and the percentile in
        (0, 100] of the initial condition's kernel density taken as the rest
        density.
    max_neighbors, mpm_threads, nn_threads:
        Neighbour cap of the radius graph; MPM threads of the warm-up (0 = all
        cores); onnxruntime threads when ``model`` is a path.
    clusters:
        The :attr:`~hybridmpm.scenes.Scene.clusters` of an earlier simulator of
        the scene at the model's ``r_p``: rebuilt without the k-means.

    Raises :class:`InvalidInputError` naming the parameter, or (``model``)
    for a model that does not fit the scene.
    """

    kind = NEURAL
    #: The hybrid's ``cheap`` setting that makes this simulator its cheap half (:class:`~hybridmpm.sim.cheap.CheapHalf`).
    name = "neural"

    def __init__(
        self,
        scene: Scene | str,
        model: Runtime | str | Path | None = None,
        *,
        seed: int = 0,
        checks: FailureChecks | None = None,
        detect_failures: bool = True,
        conversion: Conversion | None = None,
        clamp: bool = True,
        warmup: bool = True,
        relax: int = RELAX_ITERATIONS,
        rest_percentile: float = REST_PERCENTILE,
        max_neighbors: int | None = None,
        mpm_threads: int = 0,
        nn_threads: int = 1,
        clusters: Clusters | None = None,
    ) -> None:
        self._lock = new_lock()
        checks = FailureChecks() if checks is None else checks
        #: The failure checks of :meth:`propose` (the hybrid passes its own).
        self.checks = checks if detect_failures else replace(checks, detect_failures=False)
        #: How :meth:`hand_back` converts the state for MPM.
        self.conversion = Conversion() if conversion is None else conversion
        if max_neighbors is not None:
            check_int("max_neighbors", max_neighbors, 1)
        check_int("relax", relax, 0)
        if relax > 100:
            raise InvalidInputError(f"relax: must be an integer in [0, 100], got {relax!r}", "relax")
        ok = isinstance(rest_percentile, (int, float)) and not isinstance(rest_percentile, bool) and math.isfinite(rest_percentile)
        if not (ok and 0 < rest_percentile <= 100):
            raise InvalidInputError(f"rest_percentile: must be a number in (0, 100], got {rest_percentile!r}", "rest_percentile")
        if isinstance(scene, str):
            scene = make_scene(scene, seed=seed)
        refuse_untrained(scene.material, "learned simulator")
        refuse_bodies(len(scene.params.bodies), "learned simulator")
        self.model: Runtime = open_model(model, scene.name, check_int("nn_threads", nn_threads, 0))
        self.scene_full = scene
        self.scene = at_resolution(scene, self.model.r_p, seed, clusters)
        self.model.check_fits(self.scene.dim, self.scene.particle_type(), scene.name)
        self.clamp = bool(clamp)
        self.max_neighbors = max_neighbors
        self.r_t = self.model.r_t
        self.t_in = self.model.t_in
        self.dt_frame = float(self.scene.dt_frame)
        self.dt_step = self.dt_frame * self.r_t
        # MPM: the warm-up, and the facts the failure checks need (masses, grid, walls)
        self._mpm_threads = mpm_threads
        mpm = MpmSimulator(self.scene, r_t=self.r_t, threads=mpm_threads)
        self.particles = mpm.particles
        self._warmup: MpmSimulator | None = mpm if warmup else None
        self._warm: list[np.ndarray] = [mpm.fluid_positions] if warmup else []
        self._dx = float(mpm.solver.dx)
        masses = np.asarray(mpm.solver.masses, np.float64)
        lo = mpm.solver.domain_bounds[0]
        g = self.scene.params.resolved_gravity()
        x0 = np.asarray(self.scene.positions, np.float64)
        v0 = np.asarray(self.scene.velocities, np.float64)
        self._masses = masses
        #: Energy available at the start [J]: kinetic + potential above the floor.
        self.energy_budget = float(0.5 * (masses * (v0**2).sum(1)).sum() + (masses * ((x0 - lo) @ -g).clip(min=0)).sum())
        b = np.asarray(self.model.meta["bounds"], np.float32)
        self._lo, self._hi = b[:, 0], b[:, 1]
        self._escape_key: tuple[int, float] | None = None
        self._escape: tuple[np.ndarray, np.ndarray] = (self._lo, self._hi)
        x0b = self.particles.pad(np.asarray(self.scene.positions, np.float32))
        self._degree0 = len(radius_graph(x0b, self.model.radius)[0]) / max(1, len(x0b))
        self._packing0 = self.model.packing(x0b, np.asarray(self.particles.fluid_mask))
        self.relax = relax
        self._movable = np.ascontiguousarray(self.particles.fluid_mask)
        rho = kernel_density(x0b, self.model.radius)[self._movable]
        #: Rest density of the relaxation (kernel units; :func:`~hybridmpm.graph.kernel_density`).
        self.rest_density = float(np.percentile(rho, rest_percentile)) if len(rho) else 1.0
        #: Particles the relaxation corrected in the last network step.
        self.last_relaxed = 0
        #: Rounds of ``relax`` iterations the last network step took (more than one after an impact; module doc).
        self.last_relax_rounds = 0
        self._history: np.ndarray | None = None
        self._next_graph: Graph | None = None
        self.step_index = 0
        self.stats = SimStats()
        self.last_edges = 0
        self.last_clamped = 0
        self._frame = Frame(0, 0, 0.0, self.particles.pad(np.asarray(self.scene.positions, np.float32)), MPM)

    # ------------------------------------------------------------ properties
    @property
    def positions(self) -> np.ndarray:
        """Current positions with boundary particles, float32 [N + B, D]."""
        return self._frame.positions

    @property
    def frame(self) -> Frame:
        return self._frame

    @property
    def velocities(self) -> np.ndarray:
        """Current fluid velocities [m/s], float32 [N, D]: the last step's
        finite difference (the warm-up MPM's velocities before the network runs)."""
        if self._history is None:
            assert self._warmup is not None
            return self._warmup.velocities
        n = self.particles.num_fluid
        return ((self._history[-1, :n].astype(np.float64) - self._history[-2, :n]) / self.dt_step).astype(np.float32)

    @property
    def history(self) -> np.ndarray | None:
        """The network's input, float32 [T_in, N + B, D] (a copy), or None during the warm-up."""
        return None if self._history is None else self._history.copy()

    @property
    def warming_up(self) -> bool:
        return self._history is None

    @property
    def detect_failures(self) -> bool:
        return self.checks.detect_failures

    @property
    def escape_cells(self) -> float:
        return self.checks.escape_cells

    @property
    def initial_degree(self) -> float:
        """Mean neighbours per particle within R of the initial condition (self-edge included)."""
        return float(self._degree0)

    @property
    def mean_degree(self) -> float:
        """Mean neighbours per particle of the graph of the next network step (nan if not built yet)."""
        if self._next_graph is None:
            return float("nan")
        return len(self._next_graph[0]) / max(1, self.particles.num_total)

    @property
    def forcing(self) -> Forcing:
        """Always None: the network cannot apply a forcing."""
        return None

    @forcing.setter
    @serialised
    def forcing(self, value: Forcing) -> None:
        if value is not None:
            raise InvalidInputError(
                "forcing: the network alone cannot apply a forcing (control runs on MPM, paper Sec. 3.2); use HybridSimulator or MpmSimulator",
                "forcing",
            )

    # ------------------------------------------------------------ network steps
    @serialised
    def set_history(self, fluid_history: np.ndarray) -> None:
        """Start the network from fluid positions float [T_in, N, D] (oldest
        first, one coarse step apart). Raises :class:`InvalidInputError`
        (field ``history``) for another shape or non-finite values."""
        h = np.asarray(fluid_history, np.float32)
        n, d = self.particles.num_fluid, self.particles.dim
        if h.shape != (self.t_in, n, d):
            raise InvalidInputError(f"history: expected shape [{self.t_in}, {n}, {d}], got {list(h.shape)}", "history")
        if not np.isfinite(h).all():
            raise InvalidInputError("history: contains NaN or inf", "history")
        self._history = self.particles.pad(h)
        self._next_graph = None
        self._warmup = None
        self._warm = []

    def failure_of(self, nxt: np.ndarray, checks: FailureChecks | None = None) -> str | None:
        """How the network's next positions ``nxt`` float32 [N, D] fail
        ``checks`` (None: :attr:`checks`) after the current history: ``"nan"``,
        ``"escaped"`` (beyond the model's bounds by more than the margin and the
        particle's own last step) or ``"energy"`` (kinetic energy over its
        budget); None when they pass. What :meth:`propose` runs on each
        prediction; needs the history (after the warm-up)."""
        assert self._history is not None
        checks = self.checks if checks is None else checks
        n = self.particles.num_fluid
        fluid = nxt[:n]
        flat = fluid.reshape(-1)  # contiguous: one long comparison, not [N, D] against [D]
        if not np.isfinite(flat).all():
            return "nan"
        lo, hi = self._escape_bounds(n, checks.escape_cells)
        if (flat < lo).any() or (flat > hi).any():
            # beyond the margin: escaped only if farther than the particle's own last step would carry it (module doc)
            last = self._history[-1, :n]
            carry = np.abs(last - self._history[-2, :n]).max(axis=1, keepdims=True) + np.float32(checks.escape_cells * self._dx)
            if ((fluid < self._lo - carry) | (fluid > self._hi + carry)).any():
                return "escaped"
        d = fluid.astype(np.float64)
        d -= self._history[-1, :n]
        ke = 0.5 * float(self._masses @ np.einsum("ij,ij->i", d, d)) / self.dt_step**2
        if ke > checks.ke_factor * self.energy_budget:
            return "energy"
        return None

    def _escape_bounds(self, n: int, escape_cells: float) -> tuple[np.ndarray, np.ndarray]:
        """The model's bounds widened by ``escape_cells`` cells, float32, each
        repeated for ``n`` particles ([n·D], the layout of a flattened [n, D]
        array); made again only when ``n`` or the margin changes."""
        margin = escape_cells * self._dx
        if self._escape_key != (n, margin):
            self._escape = (np.tile(self._lo - margin, n), np.tile(self._hi + margin, n))
            self._escape_key = (n, margin)
        return self._escape

    def _clip(self, nxt: np.ndarray) -> np.ndarray:
        if self.clamp:
            out = (nxt < self._lo) | (nxt > self._hi)
            self.last_clamped = int(out.any(axis=1).sum())
            if self.last_clamped:
                nxt = np.clip(nxt, self._lo, self._hi)
        return nxt

    @serialised
    def propose(self, checks: FailureChecks | None = None) -> Proposal:
        """Predict the next network step without taking it, under ``checks``
        (None: :attr:`checks`). Raises :class:`InvalidInputError` (field
        ``history``) during the warm-up."""
        checks = self.checks if checks is None else checks
        if self._history is None:
            raise InvalidInputError("history: the network has no position history yet (warm-up not finished; see set_history)", "history")
        acc, nxt, used = self.model.predict(self._history, self.particles.particle_type, self.max_neighbors, graph=self._next_graph)
        self.last_edges = 0 if used is None else int(len(used[0]))
        self._next_graph = None
        failure = self.failure_of(nxt, checks) if checks.detect_failures else None
        if failure is not None:
            return Proposal(acc, nxt, None, None, failure)
        if self.model.needs_graph:
            clipped, built = self._settle(nxt)
            packed = checks.detect_failures and len(built[0]) > checks.degree_factor * self._degree0 * len(clipped)
        else:
            # a kind that moves particles through its own grid clips them itself: no relaxation, no graph;
            # its packing (the grid model's: the mass-weighted mean particle count per node) is checked instead
            clipped, built = self._clip(nxt), None
            packed = checks.detect_failures and self.model.packing(clipped, self._movable) > checks.degree_factor * self._packing0
        return Proposal(acc, nxt, clipped, None, "compressed") if packed else Proposal(acc, nxt, clipped, built, None)

    def _settle(self, nxt: np.ndarray) -> tuple[np.ndarray, Graph]:
        """A graph kind's prediction clipped, relaxed (module doc) and clipped
        again, with the radius graph of the result (the next step's input)."""
        if not self.relax:
            clipped = self._clip(nxt)
            return clipped, radius_graph(clipped, self.model.radius, max_neighbors=self.max_neighbors)
        # clipped, relaxed, clipped again, and the next step's graph (one
        # Rust call: the graph reuses the relaxation's neighbour lists
        # where few particles moved)
        bounds = (self._lo, self._hi) if self.clamp else None
        clipped, self.last_relaxed, _, clamped, built = relax_then_graph(
            nxt, self._movable, self.model.radius, self.rest_density, self.relax, bounds=bounds, max_neighbors=self.max_neighbors
        )
        rounds = 1
        # an impact the network squashed into a wall: relax on until the packing is back near the initial one
        while rounds <= RELAX_MAX_ROUNDS and len(built[0]) > RELAX_AGAIN_DEGREE * self._degree0 * len(clipped):
            clipped, _, _, more, built = relax_then_graph(
                clipped, self._movable, self.model.radius, self.rest_density, self.relax, bounds=bounds, max_neighbors=self.max_neighbors
            )
            clamped += more
            rounds += 1
        self.last_relax_rounds = rounds
        if self.clamp:
            self.last_clamped = clamped
        return clipped, built

    @serialised
    def commit(self, proposal: Proposal) -> np.ndarray:
        """Take a proposed step (one without failure): append its positions to
        the history; returns them, float32 [N + B, D]. Raises
        :class:`InvalidInputError` (field ``proposal``) for a rejected one."""
        if proposal.failure is not None or proposal.positions is None or self._history is None:
            raise InvalidInputError(f"proposal: a rejected step ({proposal.failure}) cannot be committed", "proposal")
        self._history = np.concatenate([self._history[1:], proposal.positions[None].astype(np.float32)])
        self._next_graph = proposal.graph
        self.step_index += 1
        self.stats.steps[NEURAL] += 1
        return self._history[-1]

    @serialised
    def advance(self) -> Frame:
        """One coarse step: MPM during the warm-up, then the network. Raises
        :class:`~hybridmpm.sim.base.NetworkFailure` for a rejected network
        step (state unchanged), :class:`~hybridmpm.errors.SimulationError`
        if the warm-up MPM fails."""
        if self._history is None:
            return self._advance_warmup()
        t0 = time.perf_counter()
        p = self.propose()
        if p.failure is not None:
            self.stats.fallbacks[p.failure] = self.stats.fallbacks.get(p.failure, 0) + 1
            raise NetworkFailure(p.failure, self.step_index + 1)
        pos = self.commit(p).copy()
        self._frame = Frame(self.step_index, self.step_index * self.r_t, self.step_index * self.dt_step, pos, NEURAL, time.perf_counter() - t0)
        return self._frame

    def _advance_warmup(self) -> Frame:
        if self._warmup is None:
            raise InvalidInputError("history: warmup=False and no history was set (see set_history)", "history")
        fr = self._warmup.advance()
        self._warm.append(self.particles.fluid(fr.positions).copy())
        self.step_index = self._warmup.step_index
        self.stats.steps[MPM] += 1
        self.stats.mpm_retries += fr.mpm_retries
        self._frame = fr
        if len(self._warm) == self.t_in:
            self.set_history(np.stack(self._warm))
        return fr

    # ------------------------------------------------------------ the hybrid's cheap half
    def take_over(self, fine: MpmSolver, trajectory: np.ndarray) -> None:
        """Start from MPM (:class:`~hybridmpm.sim.cheap.CheapHalf`): the history
        is the last ``T_in − 1`` positions of ``trajectory`` float32 [T, N, D]
        before the current ones, which are taken from MPM's solver ``fine`` bit
        for bit (:func:`~hybridmpm.sim.convert.mpm_history`)."""
        self.set_history(mpm_history(fine.positions, trajectory[-self.t_in : -1], self.t_in))

    def hand_back(self, fine: MpmSolver, trajectory: np.ndarray) -> None:
        """Convert the state of the last network step into MPM's solver ``fine``
        (:class:`~hybridmpm.sim.cheap.CheapHalf`): from the last positions of
        ``trajectory`` float32 [T, N, D] (that step's and those before it), as
        :attr:`conversion` says, with the model's R for the ``C`` fit
        (:func:`~hybridmpm.sim.convert.neural_to_mpm`)."""
        neural_to_mpm(fine, trajectory[-3:], self.dt_step, affine_radius=self.model.radius, **self.conversion.settings())

    # ------------------------------------------------------------ checkpoint
    @serialised
    def state(self) -> dict[str, Any]:
        """The whole state (picklable dict): history (or the warm-up's MPM
        state and positions), step counter, stats."""
        return {
            "kind": self.kind,
            "version": _STATE_VERSION,
            "history": None if self._history is None else self._history.copy(),
            "warmup": None if self._warmup is None else self._warmup.state(),
            "warm": [w.copy() for w in self._warm],
            "step_index": self.step_index,
            "stats": self.stats.to_dict(),
            "frame_positions": self._frame.positions.copy(),
            "frame_solver": self._frame.solver,
        }

    @serialised
    def restore(self, state: dict[str, Any]) -> None:
        """Restore a :meth:`state` of a simulator of the same scene and model.
        The whole state is validated first (history, warm-up positions and
        frame positions of their shapes and finite, the warm-up's MPM state,
        ``step_index`` within :data:`~hybridmpm.limits.MAX_FRAME_INDEX`
        frames): raises :class:`InvalidInputError` (field ``state``…) for a
        foreign or malformed state, and this simulator is then unchanged."""
        self.prepare_restore(state)()

    def prepare_restore(self, state: dict[str, Any]) -> Callable[[], None]:
        """Validate ``state`` whole without changing anything; returns the
        commit, which cannot fail."""
        with reading_state("NeuralSimulator"):
            if not isinstance(state, dict) or state.get("kind") != self.kind or state.get("version") != _STATE_VERSION:
                raise InvalidInputError("state: not a state of a NeuralSimulator of this version", "state")
            step = check_step_index("state.step_index", state["step_index"], self.r_t)
            stats = SimStats.from_dict(state["stats"])
            n_all, d = self.particles.num_total, self.particles.dim
            hist = state["history"]
            if hist is not None:
                hist = check_positions("state.history", hist, (self.t_in, n_all, d))
            warm_in = state["warm"]
            if not isinstance(warm_in, list) or len(warm_in) > self.t_in:
                raise InvalidInputError(f"state.warm: must be a list of at most {self.t_in} position arrays", "state.warm")
            warm = [check_positions(f"state.warm[{i}]", w, (self.particles.num_fluid, d)) for i, w in enumerate(warm_in)]
            fpos = check_positions("state.frame_positions", state["frame_positions"], (n_all, d))
            solver = state["frame_solver"]
            if solver not in (MPM, NEURAL):
                raise InvalidInputError(f"state.frame_solver: must be {MPM!r} or {NEURAL!r}", "state.frame_solver")
            warmup_state = state["warmup"]
            mpm: MpmSimulator | None = None
            if warmup_state is not None:
                mpm = MpmSimulator(self.scene, r_t=self.r_t, threads=self._mpm_threads)
                mpm.restore(warmup_state)  # a new simulator: a refusal leaves this one as it is

        def commit() -> None:
            self._warmup = mpm
            self._history = hist
            self._warm = warm
            self._next_graph = None
            self.step_index = step
            self.stats = stats
            self._frame = Frame(step, step * self.r_t, step * self.dt_step, fpos, solver)

        return commit


def warmup_frames(model: Runtime) -> int:
    """MPM frames needed before the first network step: ``(T_in − 1)·r_t``."""
    return (model.t_in - 1) * model.r_t


__all__ = ["RELAX_AGAIN_DEGREE", "RELAX_ITERATIONS", "RELAX_MAX_ROUNDS", "REST_PERCENTILE", "NeuralSimulator", "Proposal", "warmup_frames"]
