"""Real-time mode: MPM that picks, from its scene's real-time chart, the most accurate configuration whose frame
fits real time on this machine, and changes it as the machine's pace changes (docs/realtime.md).

Its configurations, the *rungs*, and their *ladder* (most accurate first, each step down buying time) are
:mod:`hybridmpm.sim.ladder`'s.

:class:`RealtimeSimulator` is an :class:`~hybridmpm.sim.mpm.MpmSimulator` that times its own frames (an
exponential average of the median of the last :data:`MEDIAN_SAMPLES` frames' wall times, so that one slow
frame does not read as a slow machine; on a projection rung, whose step spans frames, a step's frames count as
one sample, their mean, so the frame that steps does not either) and, between
frames, moves to another rung:

* down when the frame takes longer than the budget ``dt_frame / REALTIME_MARGIN``, and has for
  :data:`DOWN_AFTER_S` seconds of wall time (a burst of slow frames while another program draws is not the
  machine's pace), or when the frames of the last :data:`DOWN_AFTER_S` took longer than real time on average:
  to the most accurate rung
  predicted to fit (the current rung's measured time scaled by the chart's time ratios, corrected by the ratios
  measured here as rungs are visited), or the fastest;
* up when a more accurate rung is predicted to fit the budget divided by :data:`HYSTERESIS`;
* at most once every :data:`DWELL_S` seconds of wall time, after :data:`MIN_SAMPLES` timed frames.

A change of grid or integrator keeps the particles: positions, velocities, APIC matrices, deformation, bodies
and obstacles move onto the new grid bit for bit (:meth:`~hybridmpm.mpm.MpmSolver.restore_particles`'s rule: only
the grid, its wall band and the integrator differ), so mass and momentum are conserved exactly; the one exception
is a particle a splash put closer to the domain's edge than one cell of a coarser grid, which moves onto that
edge (its velocity kept). A change to merged particles merges each group into one particle (mass, centre of mass
and momentum conserved, :func:`~hybridmpm.sim.convert.merge_arrays`) and remembers each particle's offset from
its group's centre; a change back splits the groups so (each particle at its group's centre plus its offset, with
the group's affine velocity: its own mass again, momentum kept, :func:`~hybridmpm.sim.convert.split_arrays`).
Blocks poured since stay whole either way, bodies and obstacles are not particles. A projection step that spans
frames is finished before a change. The simulator never catches up: a frame is a frame whatever it cost
(:func:`~hybridmpm.sim.rollout.step_realtime` drops what a host's budget did not cover). Its :meth:`state`
records the rung, so a checkpoint taken after a change restores bitwise.
"""

from __future__ import annotations

import statistics
import time
from collections import deque
from collections.abc import Callable
from dataclasses import replace
from typing import Any, NamedTuple

import numpy as np

from hybridmpm.conventions import GNS_TYPE_OF_MATERIAL, MATERIAL_WATER
from hybridmpm.errors import InvalidInputError
from hybridmpm.mpm import MpmSolver
from hybridmpm.mpm.params import INTEGRATORS, MpmParams, free_slip
from hybridmpm.scenes import make_scene
from hybridmpm.scenes.core import Clusters, Scene
from hybridmpm.sim.base import serialised
from hybridmpm.sim.convert import (
    PARTICLE_FIELDS,
    STATIC_FIELDS,
    bin_groups,
    group_firsts,
    group_mean,
    merge_arrays,
    replace_particles,
    split_arrays,
)
from hybridmpm.sim.ladder import (
    Rung,
    charted_rungs,
    make_ladder,
    realtime_chart,
    rung_key,
    rung_label,
)
from hybridmpm.sim.mpm import MpmSimulator

#: A frame's budget is ``dt_frame · r_t / REALTIME_MARGIN`` of wall time: a fifth of real time is kept for the
#: rest of the host's frame (serving it, drawing it).
REALTIME_MARGIN = 1.25
#: A more accurate rung is taken only when predicted to fit the budget divided by this (no flapping).
HYSTERESIS = 1.3
#: The least wall time between two changes of rung [s].
DWELL_S = 3.0
#: A rung is left for a faster one only once its average has stayed over the budget this long [s] of wall
#: time: a burst of slow frames (a browser drawing a frame beside it, a process taking the core for a moment)
#: is not the machine's pace, and a frame that ran late is not owed, so the wait costs no catch-up.
DOWN_AFTER_S = 1.0
#: Frames after a change that are not timed (caches, the first projection step).
WARMUP_FRAMES = 3
#: Timed frames a rung needs before a change is considered.
MIN_SAMPLES = 10
#: Weight of the newest sample in the exponential average of the time per frame.
EMA_ALPHA = 0.2
#: The average takes the median of the last this many samples, not the newest alone: a lone slow frame (a
#: garbage collection, the OS taking the core) moves it no more than a fast one, a slower machine within frames.
MEDIAN_SAMPLES = 5
#: How long a rung's measured time per frame stands in for its prediction [s]; older, the chart's ratio scaled
#: by the current rung's time does (the machine's load moves). A rung left for being too slow again and again,
#: each time within this long of taking it, keeps its measured time twice as long each time, up to
#: :data:`MAX_BACKOFF` doublings (no flapping back to a rung the chart's ratios keep predicting to fit); a rung
#: that held longer, or was left for a more accurate one, starts afresh.
MEASURED_TTL_S = 30.0
#: The most doublings of :data:`MEASURED_TTL_S` for a rung left for being too slow.
MAX_BACKOFF = 3


class Merge(NamedTuple):
    """The particles of a merged rung: each scene particle's group ``labels`` (int64 [N]), its ``offsets`` from
    the group's centre (float64 [N, D]), the cubes' side ``size`` [m] and the number of ``groups``; ``shown`` the
    offsets in float32 (what the shown positions add, each frame)."""

    labels: np.ndarray
    offsets: np.ndarray
    size: float
    groups: int
    shown: np.ndarray


class RealtimeSimulator(MpmSimulator):
    """MPM in real-time mode (module docstring; docs/realtime.md): the scene's default particles (its chart's
    ``r_p``) on the ladder's rungs, the most accurate that fits real time here.

    ``scene``, ``r_p``, ``seed``, ``threads``, ``clusters`` as :class:`~hybridmpm.sim.mpm.MpmSimulator` (one frame
    a step). ``rung`` the key to start on (None: the ladder's most accurate); ``adaptive`` False keeps it there
    (timed and reported, never changed: a host's fixed choice, the chart's runs). ``clock`` the wall clock
    [s] the frames are timed with (a test's fake one; default :func:`time.perf_counter`). Raises
    :class:`InvalidInputError` naming ``rung`` for a key not on the ladder, or as ``MpmSimulator``."""

    def __init__(
        self,
        scene: Scene | str,
        *,
        r_p: float = 1.0,
        seed: int = 0,
        threads: int = 0,
        clusters: Clusters | None = None,
        rung: str | None = None,
        adaptive: bool = True,
        clock: Callable[[], float] = time.perf_counter,
    ) -> None:
        if isinstance(scene, str):
            scene = make_scene(scene, seed=seed)
        #: on a merged rung: each scene particle's group (int64 [N]), its offset from the group's centre (float64
        #: [N, D]) and the groups' lattice spacing [m]; None on the scene's particles
        self._merge: Merge | None = None
        super().__init__(scene, r_p=r_p, seed=seed, threads=threads, clusters=clusters)
        self.ladder = make_ladder(self.scene)
        #: the ladder of the explicit rungs: what the mode moves on while the projection cannot step what the
        #: simulator holds (another material poured into the water)
        self._explicit_ladder = make_ladder(self.scene, (INTEGRATORS[0],))
        #: the scene's shipped real-time chart (:func:`realtime_chart`; None: a scene of your own)
        self.chart = realtime_chart(self.scene)
        self._clock = clock
        self.adaptive = bool(adaptive)
        #: rung key -> the scene's own solver parameters on that rung (the particles' parameter sets kept)
        #: every rung it can run (the ladder's, and the explicit ones a body or another material falls back on)
        rungs = charted_rungs(self.scene)
        self._n_scene_grid = self.scene.params.resolved_n_grid()
        self._rungs = {r.key: r for r in rungs}
        self._rung_params = {r.key: self._params_on(r) for r in rungs}
        #: the scene's own particles (a merged rung's base is its groups, :meth:`_merged_base`), and their masses,
        #: rest volumes, materials and sets: what a split gives back
        self._fine_particles = self._scene_particles
        self._members = {f: np.asarray(self.solver.field(f)) for f in STATIC_FIELDS}
        self._chart_ratios = {r.key: r.time_ratio for r in rungs}
        #: rung key -> (its measured wall time per frame [s], when): this machine's times of the rungs visited
        self._measured: dict[str, tuple[float, float]] = {}
        #: rung key -> how often in a row it was left for being too slow (:data:`MEASURED_TTL_S`)
        self._strikes: dict[str, int] = {}
        here = rung_key(self.solver.params.resolved_n_grid(), self.solver.params.integrator)
        self._rung = here
        self._ema: float | None = None
        self._samples = 0
        #: the last :data:`MEDIAN_SAMPLES` samples [s a frame] on the current rung
        self._recent: deque[float] = deque(maxlen=MEDIAN_SAMPLES)
        self._since_change = 0
        #: the wall time [s] and the frames of the step under way (a projection step spans frames)
        self._cycle = (0.0, 0)
        self._last_change = clock()
        #: when the average last went over the budget and has stayed there since [s, the clock's]; None: within it
        self._over_since: float | None = None
        #: the frames timed since the window's start: (its start [s], their wall time [s], their count), and whether
        #: the last window of DOWN_AFTER_S was slower than real time on average (its mean frame over ``dt_frame``)
        self._window = (clock(), 0.0, 0)
        self._slow_window = False
        #: the share of its threads' time this simulator may spend (:meth:`set_share`; 1: alone)
        self._share = 1.0
        self.changes: list[dict[str, Any]] = []
        if rung is None and here not in {r.key for r in self.ladder}:  # the scene's own configuration is off the ladder
            self._switch(self.ladder[0].key)
        if rung is not None:
            if rung not in self._rung_params:
                raise InvalidInputError(f"rung: must be one of {', '.join(self._rung_params)}, got {rung!r}", "rung")
            self._switch(rung)

    # ------------------------------------------------------------ rungs
    def _params_on(self, rung: Rung) -> MpmParams:
        """The scene's own solver parameters (its parameter sets and bodies) with ``rung``'s grid, wall band,
        obstacles and integrator."""
        spec = self.scene_full.spec
        if spec is None:
            raise InvalidInputError("scene: real-time mode moves a scene between grids; it needs a scene built from a spec", "scene")
        grid = spec.on_grid(rung.n_grid).params  # the obstacles' sampled distances on the new grid
        return replace(self._scene_params, n_grid=grid.n_grid, walls=grid.walls, colliders=grid.colliders, integrator=rung.integrator)

    def _own_base(self) -> bool:
        """On merged particles a state is always checked against its own groups (:meth:`restore`)."""
        return self._merge is None

    def _bin_size(self, rung: Rung) -> float:
        """The side [m] of the cubes a merged ``rung`` groups the particles in: ``f / (n_grid · particles_per_cell)``,
        the lattice spacing of the scene's density on the rung's grid times ``f = (r_p at that density / r_p)^(1/D)``
        (1 on a coarser grid at the scene's density, 2 at half of it per axis, 4 at a quarter)."""
        spec = self.scene_full.spec
        ppc = spec.particles_per_cell if spec is not None else 2
        at_density = min(1.0, rung.n_grid / self._n_scene_grid) ** self.particles.dim
        f = round((at_density / rung.r_p) ** (1.0 / self.particles.dim))
        return f / (rung.n_grid * ppc)

    def _merged_base(self, labels: np.ndarray, k: int) -> Any:
        """The particle set of the scene merged into the groups ``labels``: ``k`` particles, each of its group's
        material and summed mass (float32 of the float64 sum, as :func:`~hybridmpm.sim.convert.merge_arrays` sums)."""
        fine, lab = self._fine_particles, np.asarray(labels, np.int64)
        first = group_firsts(lab, k)
        material = np.asarray(self._members["material"], np.int32)[first]
        types = np.array([GNS_TYPE_OF_MATERIAL[int(c)] for c in material], np.int64)
        masses = np.bincount(lab, np.asarray(self._members["masses"], np.float64), minlength=k).astype(np.float32)
        return replace(
            fine, num_fluid=k, particle_type=np.concatenate([types, np.asarray(fine.particle_type)[fine.num_fluid :]]), material=material, masses=masses
        )

    def _resample(self, rung: Rung) -> None:
        """Make the particles those of ``rung``: split a merge that ``rung`` does not keep, then merge into
        ``rung``'s groups (module docstring). Poured blocks stay whole after the scene's particles."""
        size = self._bin_size(rung) if rung.r_p < 1.0 else None
        if (self._merge is None and size is None) or (self._merge is not None and self._merge.size == size):
            return
        fields = {f: np.asarray(self.solver.field(f)) for f in PARTICLE_FIELDS}
        head = self._scene_particles.num_fluid
        scene = {f: a[:head] for f, a in fields.items()}
        if self._merge is not None:
            scene = split_arrays(scene, self._merge.labels, self._merge.offsets, self._members, self.solver.domain_bounds)
        merge = None
        if size is not None:
            labels, k = bin_groups(scene["positions"], scene["material_set"], size)
            scene, offsets = merge_arrays(scene, labels, k)
            merge = Merge(labels, offsets, size, k, offsets.astype(np.float32))
        replace_particles(self.solver, {f: np.concatenate([scene[f], a[head:]]) for f, a in fields.items()})
        self._merge = merge
        self._scene_particles = self._fine_particles if merge is None else self._merged_base(merge.labels, merge.groups)
        self.adopt(self.solver, self._pours)

    # ------------------------------------------------------------ the particles shown
    # On merged particles the simulator still shows the scene's own (each at its group's centre plus its
    # offset): frames, rollouts, recordings, forcings and a session's facts keep the scene's particle count.
    def _particle_set(self, solver: MpmSolver, old: Any) -> Any:
        own = super()._particle_set(solver, old)
        if self._merge is None:
            return own
        fine, k = self._fine_particles, self._scene_particles.num_fluid
        n = fine.num_fluid
        return replace(
            own,
            num_fluid=n + own.num_fluid - k,
            particle_type=np.concatenate([np.asarray(fine.particle_type)[:n], np.asarray(own.particle_type)[k:]]),
            material=np.concatenate([np.asarray(fine.material), np.asarray(own.material)[k:]]),
            masses=np.concatenate([np.asarray(fine.masses, np.float32), np.asarray(own.masses)[k:]]),
        )

    def _presented(self, n_solver: int) -> int:
        return n_solver if self._merge is None else n_solver - self._merge.groups + len(self._merge.labels)

    @property
    def fluid_positions(self) -> np.ndarray:
        """The particles' positions, float32 [N, D] (a copy): on merged particles each of the scene's at its
        group's centre plus its offset (inside the domain), the poured ones as they are."""
        x = np.asarray(self.solver.positions, np.float32)
        if self._merge is None:
            return x.copy()
        labels, k, shown = self._merge.labels, self._merge.groups, self._merge.shown
        lo, hi = self.solver.domain_bounds
        own = np.take(x, labels, axis=0)  # labels < k: the groups; take is several times faster than indexing
        own += shown
        np.clip(own, lo, hi, out=own)
        return np.concatenate([own, x[k:]])

    @property
    def velocities(self) -> np.ndarray:
        """The particles' velocities [m/s], float32 [N, D]: on merged particles each of the scene's its group's
        affine velocity ``v + C·offset``."""
        v = np.asarray(self.solver.velocities, np.float32)
        if self._merge is None:
            return v.copy()
        labels, offsets, _, k, _ = self._merge
        own = np.asarray(v[:k], np.float64)[labels] + np.einsum("nij,nj->ni", np.asarray(self.solver.affine[:k], np.float64)[labels], offsets)
        return np.concatenate([own.astype(np.float32), v[k:]])

    def _apply_acceleration(self, acc: np.ndarray) -> None:
        """On merged particles a group takes its members' mass-weighted mean acceleration (their force)."""
        if self._merge is None:
            super()._apply_acceleration(acc)
            return
        labels, k = self._merge.labels, self._merge.groups
        own = group_mean(acc[: len(labels)], labels, np.asarray(self._members["masses"], np.float64), k)
        self.solver.external_acceleration = np.concatenate([own.astype(np.float32), acc[len(labels) :]])

    @property
    def rung(self) -> str:
        """The key of the rung in use (:func:`rung_key`)."""
        return self._rung

    def projection_ok(self) -> bool:
        """Whether the projection steps what the simulator holds now: water only (poured blocks included) and
        free-slip obstacles only (bodies it steps, docs/large-step.md)."""
        p = self.solver.params
        return all(map(free_slip, p.colliders)) and bool(np.all(np.asarray(self.solver.material) == MATERIAL_WATER))

    def _available(self, key: str) -> bool:
        return self._rung_params[key].integrator == INTEGRATORS[0] or self.projection_ok()

    def _switch(self, key: str) -> bool:
        """Move the particles onto rung ``key`` (between frames); False (and nothing changed) while a projection
        step still spans frames."""
        if self.solver.params.integrator != INTEGRATORS[0] and self.solver.substeps_for(self.dt_frame) == 0:
            return False  # mid-step: the step's frames are finished on its own grid first
        target = self._rung_params[key]
        self._inside(target.resolved_n_grid())
        updates = {k: v for k, v in target.to_dict().items() if k in ("n_grid", "walls", "colliders")}
        updates["integrator"] = target.integrator
        blob = MpmSolver.with_header(self.solver.checkpoint(), updates)
        self.adopt(MpmSolver.from_checkpoint(blob), self._pours)
        self._resample(self._rungs[key])
        self._scene_params = target
        self._rung = key
        self._restart_timing()
        return True

    def _restart_timing(self) -> None:
        """Time the rung afresh after a change (a move, a restore): no samples, no step under way, the dwell and
        the overrun's clocks from now."""
        self._since_change = self._samples = 0
        self._recent.clear()
        self._cycle = (0.0, 0)
        self._last_change = self._clock()
        self._over_since = None
        self._window, self._slow_window = (self._last_change, 0.0, 0), False

    def _inside(self, n_grid: int) -> None:
        """Move the particles that a splash put deeper into the wall band than one cell of ``n_grid`` from the
        domain's edge (where a coarser grid's stencil cannot reach) onto that edge: positions only, so mass and
        momentum stay as they are. Usually none."""
        x = np.asarray(self.solver.positions, np.float32)
        lo = np.nextafter(np.float32(1.0 / n_grid), np.float32(1.0))
        hi = np.nextafter(np.float32(1.0) - np.float32(1.0 / n_grid), np.float32(0.0))
        if (x < lo).any() or (x > hi).any():
            self.solver.set_field("positions", np.clip(x, lo, hi))

    def set_rung(self, key: str) -> None:
        """Move to rung ``key`` now (a host's or a test's choice; the timing restarts). Raises
        :class:`InvalidInputError` naming ``rung`` for a key not on the ladder, or while a projection step
        spans frames (advance a frame and ask again)."""
        if key not in self._rung_params:
            raise InvalidInputError(f"rung: must be one of {', '.join(self._rung_params)}, got {key!r}", "rung")
        if not self._available(key):
            raise InvalidInputError(f"rung: {key} steps water only, and this simulator holds another material", "rung")
        if key != self._rung and not self._switch(key):
            raise InvalidInputError("rung: a projection step spans this frame; advance a frame and ask again", "rung")

    def predicted_s(self, key: str) -> float | None:
        """The predicted wall time of a frame on rung ``key`` [s]: its own measured average where it was timed in
        the last :data:`MEASURED_TTL_S` seconds, longer after repeated failures (the current rung's is its running
        average), else the current rung's average scaled by the chart's time ratios; None before the current rung
        has been timed."""
        if self._ema is None or self._samples < 1:
            return None
        if key == self._rung:
            return self._ema
        seen = self._measured.get(key)
        ttl = MEASURED_TTL_S * 2 ** min(max(self._strikes.get(key, 0) - 1, 0), MAX_BACKOFF)
        if seen is not None and self._clock() - seen[1] <= ttl:
            return seen[0]
        return self._ema * self._chart_ratios[key] / self._chart_ratios[self._rung]

    def budget_s(self) -> float:
        """A frame's wall-time budget [s]: ``dt_frame · r_t /`` :data:`REALTIME_MARGIN`, times its share
        (:meth:`set_share`)."""
        return self.dt_step / REALTIME_MARGIN * self._share

    def set_share(self, share: float) -> None:
        """The share of its threads' time this simulator may spend, in (0, 1] (1, the default: all of it).
        A server whose playing real-time sessions need more than its cores gives each a share
        (:func:`hybridmpm.service.capacity.realtime_share`): a frame's budget shrinks with it, so the mode
        steps down to a rung that fits, where its own frame times (each frame runs alone on its threads)
        would not see the others. Raises :class:`InvalidInputError` (field ``share``) outside (0, 1]."""
        if isinstance(share, bool) or not isinstance(share, (int, float)) or not (0.0 < float(share) <= 1.0):
            raise InvalidInputError(f"share: must be a number in (0, 1], got {share!r}", "share")
        self._share = float(share)

    def _choose(self) -> str | None:
        """The rung to move to now, or None to stay (module docstring)."""
        if self._ema is None:
            return None
        budget, ratio, now = self.budget_s(), self._chart_ratios[self._rung], self._clock()
        if self._ema <= budget:
            self._over_since = None
        elif self._over_since is None:
            self._over_since = now
        if not self.adaptive or self._samples < MIN_SAMPLES or now - self._last_change < DWELL_S:
            return None
        projection = self.projection_ok()  # once a decision, not once a rung
        ladder = self.ladder if projection else self._explicit_ladder
        over_long = self._over_since is not None and now - self._over_since >= DOWN_AFTER_S
        if over_long or self._slow_window:
            faster = [r for r in ladder if r.time_ratio < ratio]
            for r in faster:
                p = self.predicted_s(r.key)
                if p is not None and p <= budget:
                    return r.key
            return faster[-1].key if faster else None
        if self._over_since is not None:
            return None  # over the budget, not yet for long enough
        for r in ladder:  # most accurate first
            if r.time_ratio <= ratio:
                break
            p = self.predicted_s(r.key)
            if p is not None and p <= budget / HYSTERESIS:
                return r.key
        return None

    def _to_explicit(self) -> None:
        """From a projection rung to the explicit rung on the same grid and particles, at once (a step spanning
        frames ends where it is); nothing on an explicit rung."""
        if self._rung_params[self._rung].integrator == INTEGRATORS[0]:
            return
        if self.solver.substeps_for(self.dt_frame) == 0:  # mid-step: a particle edit ends it (docs/large-step.md)
            self.solver.set_field("positions", np.asarray(self.solver.positions, np.float32))
        n_grid, r_p = self._rungs[self._rung].n_grid, self._rungs[self._rung].r_p
        key = rung_key(n_grid, INTEGRATORS[0], r_p)  # the same particles, merged or not, where that rung exists
        before, key = self._rung, key if key in self._rung_params else rung_key(n_grid, INTEGRATORS[0])
        self._switch(key)
        self.changes.append({"frame": self.frame.frame_index, "from": before, "to": key, "frame_ms": None})

    # ------------------------------------------------------------ stepping
    def advance(self) -> Any:
        """One frame on the current rung (:meth:`MpmSimulator.advance`), timed; then a change of rung when the
        measured times ask for one (module docstring)."""
        t0 = self._clock()
        try:
            frame = super().advance()
        except InvalidInputError as e:
            # the projection refuses a frame of what it does not step (another material poured), leaving the
            # state as it was: that frame runs on the explicit step of the same grid (the solver checks what it
            # holds each step, so nothing is read here on the frames that step)
            if e.field != "integrator" or self._rung_params[self._rung].integrator == INTEGRATORS[0]:
                raise
            self._to_explicit()
            frame = super().advance()
        wall = self._clock() - t0
        self._since_change += 1
        if self._since_change > WARMUP_FRAMES:
            self._time(wall, stepped=frame.substeps > 0)
            start, total, frames = self._window
            self._window = (start, total + wall, frames + 1)
            if t0 + wall - start >= DOWN_AFTER_S:  # a window's mean slower than real time itself
                self._slow_window = (total + wall) / (frames + 1) > self.dt_step * self._share
                self._window = (t0 + wall, 0.0, 0)
        before = self._rung
        target = self._choose()
        if target is not None and target != before:
            ema, entered = self._ema, self._last_change
            if self._switch(target):
                self.changes.append({"frame": frame.frame_index, "from": before, "to": target, "frame_ms": None if ema is None else ema * 1e3})
                if ema is not None:
                    self._measured[before] = (ema, self._clock())
                # left for a faster rung soon after it was taken (a bounce): one more strike; after a long
                # stay the failure is the machine's new pace, a first strike
                bounce = self._clock() - entered < MEASURED_TTL_S
                down = self._chart_ratios[target] < self._chart_ratios[before]
                self._strikes[before] = (self._strikes.get(before, 0) + 1 if bounce else 1) if down else 0
        return frame

    def _time(self, wall: float, stepped: bool) -> None:
        """Fold a timed frame of ``wall`` seconds into the average. On the explicit step each frame is a sample.
        On the projection a step's frames are one (their mean, weighted as that many frames): the sample ends
        where the next step begins (``stepped``: the frame took a step)."""
        explicit = self._rung_params[self._rung].integrator == INTEGRATORS[0]
        total, frames = self._cycle
        if not explicit and not (stepped and frames):
            self._cycle = (total + wall, frames + 1)
            return
        if explicit:
            per, k = wall, 1
        else:  # this frame begins the next step: the last step's frames are the sample
            per, k = total / frames, frames
            self._cycle = (wall, 1)
        self._recent.append(per)
        per = statistics.median(self._recent)  # a lone slow frame is not the machine's pace (MEDIAN_SAMPLES)
        if self._ema is None or self._samples == 0:
            self._ema = per
        else:
            keep = (1 - EMA_ALPHA) ** k
            self._ema = keep * self._ema + (1 - keep) * per
        self._samples += k

    def realtime_info(self) -> dict[str, Any]:
        """What real-time mode is doing (plain JSON values): ``rung`` and ``label`` of the configuration in use,
        ``frame_ms`` its measured wall time per frame (the running average; None before it was timed),
        ``budget_ms`` a frame's budget, ``realtime_factor`` the simulated time a wall second of stepping covers on
        this rung (``dt_frame · r_t / frame``: 1.0 is real time; None before it was timed), ``changes`` the
        number of changes of rung so far, the ``ladder``'s keys, most accurate first, ``share`` the share of
        its threads' time it may spend (:meth:`set_share`, in (0, 1]; 1: alone), and ``particles`` the particles
        it steps (fewer than it shows on a merged rung)."""
        return {
            "rung": self._rung,
            "label": rung_label(self._rung, self.particles.dim),
            "frame_ms": None if self._ema is None else round(self._ema * 1e3, 3),
            "budget_ms": round(self.budget_s() * 1e3, 3),
            "realtime_factor": None if not self._ema else round(self.dt_step / self._ema, 3),
            "changes": len(self.changes),
            "ladder": [r.key for r in self.ladder],
            "share": round(self._share, 4),
            "particles": int(self.solver.num_particles),
        }

    # ------------------------------------------------------------ checkpoint
    @serialised
    def state(self) -> dict[str, Any]:
        """:meth:`MpmSimulator.state` with the ``rung`` it was taken on and, on merged particles, ``merge``: each
        scene particle's group ``labels`` (int32 [N]) and its ``offsets`` from the group's centre (float64 [N, D]),
        what a later split puts back."""
        merge = None if self._merge is None else {"labels": self._merge.labels.astype(np.int32), "offsets": self._merge.offsets.copy()}
        return {**super().state(), "rung": self._rung, "merge": merge}

    def _check_merge(self, raw: Any, rung: Rung) -> Merge | None:
        """A state's ``merge`` for ``rung``, checked: None on the scene's particles; on merged ones the labels
        of the scene's N particles (integers, every group from 0 up non-empty and of one parameter set) and
        their offsets (finite, [N, D], at most the domain's size). Raises :class:`InvalidInputError` naming
        ``state.merge``."""
        field = "state.merge"
        if rung.r_p >= 1.0:
            if raw is not None:
                raise InvalidInputError(f"{field}: rung {rung.key} holds the scene's own particles; expected none", field)
            return None
        if not isinstance(raw, dict) or not isinstance(raw.get("labels"), np.ndarray) or not isinstance(raw.get("offsets"), np.ndarray):
            raise InvalidInputError(f"{field}: rung {rung.key} merges particles; expected its labels and offsets arrays", field)
        n, d = len(self._members["masses"]), self.particles.dim
        labels, offsets = raw["labels"], raw["offsets"]
        if labels.shape != (n,) or labels.dtype.kind not in "iu" or offsets.shape != (n, d) or offsets.dtype.kind != "f":
            raise InvalidInputError(f"{field}: expected labels int [{n}] and offsets float [{n}, {d}]", field)
        lab = labels.astype(np.int64)
        if n and (lab.min() < 0 or lab.max() >= n):
            raise InvalidInputError(f"{field}.labels: must lie in [0, {n})", f"{field}.labels")
        k = int(lab.max()) + 1 if n else 0
        sets = np.unique(np.stack([lab, np.asarray(self._members["material_set"], np.int64)], 1), axis=0)
        if np.any(np.bincount(lab, minlength=k) == 0) or len(sets) != k:
            raise InvalidInputError(f"{field}.labels: every group from 0 up must hold particles of one parameter set", f"{field}.labels")
        off = offsets.astype(np.float64)
        if not np.isfinite(off).all() or np.abs(off).max(initial=0.0) > 1.0:
            raise InvalidInputError(f"{field}.offsets: must be finite and within the domain's size", f"{field}.offsets")
        return Merge(lab, off, self._bin_size(rung), k, off.astype(np.float32))

    @serialised
    def restore(self, state: dict[str, Any]) -> None:
        """Restore a :meth:`state`: move to its rung first (its particles and grid), then restore as
        :meth:`MpmSimulator.restore`; a state of a plain ``MpmSimulator`` of the scene restores onto the
        scene's own grid and integrator. Raises :class:`InvalidInputError` naming ``state.rung`` for a rung
        not on this ladder, or as ``MpmSimulator.restore``; on an error the simulator keeps its rung and state."""
        if not isinstance(state, dict):
            raise InvalidInputError("state: not a state of an MpmSimulator of this version", "state")
        key = state.get("rung", self.ladder[0].key)
        if not isinstance(key, str) or key not in self._rung_params:
            raise InvalidInputError(f"state.rung: must be one of {', '.join(self._rung_params)}, got {key!r}", "state.rung")
        merge = self._check_merge(state.get("merge"), self._rungs[key])
        plain = {k: v for k, v in state.items() if k not in ("rung", "merge")}
        keep_solver, keep_params, keep_rung, keep_scene = self.solver, self._scene_params, self._rung, self.scene
        keep_merge, keep_base = self._merge, self._scene_particles
        try:
            # the state's particles are checked against its own base: the scene's, or its groups
            self._scene_particles = self._fine_particles if merge is None else self._merged_base(merge.labels, merge.groups)
            self._merge = merge
            if key != self._rung:
                target = self._rung_params[key]
                self.solver = MpmSolver(replace(target, num_threads=keep_solver.params.num_threads), memory_budget=keep_solver.memory_budget)
                self._scene_params = target
                self.scene = replace(self.scene, params=target)
                self._rung = key
            super().restore(plain)
        except BaseException:
            self.solver, self._scene_params, self._rung, self.scene = keep_solver, keep_params, keep_rung, keep_scene
            self._merge, self._scene_particles = keep_merge, keep_base
            raise
        if key == keep_rung and merge is None and keep_merge is None:
            return
        self._restart_timing()


__all__ = [
    "DOWN_AFTER_S",
    "DWELL_S",
    "HYSTERESIS",
    "MAX_BACKOFF",
    "MEASURED_TTL_S",
    "MEDIAN_SAMPLES",
    "REALTIME_MARGIN",
    "Merge",
    "RealtimeSimulator",
]
