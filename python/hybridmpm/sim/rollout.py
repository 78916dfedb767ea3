"""One rollout loop for every simulator, and the reference it is measured against.

:func:`rollout` advances any :class:`~hybridmpm.sim.base.Simulator` for a
number of frames and returns a :class:`Rollout` — a
:class:`~hybridmpm.trajectory.Trajectory` (positions every coarse step, fluid
then boundary particles) that also carries what each step was: its frame
number, the solver that made it, its wall time, the safeguard score, MPM
substeps, events, and why the rollout broke off, if it did.
:func:`reference` is full-resolution MPM from the same initial condition
(docs/design.md "Grid-mass error": the reference of every error).
"""

from __future__ import annotations

import math
import numbers
import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from hybridmpm.errors import InvalidInputError, SimulationError
from hybridmpm.limits import check_allocation
from hybridmpm.mpm.bodies import BodyFrame, BodyTrack
from hybridmpm.scenes.core import Scene
from hybridmpm.scenes.resolution import full_resolution
from hybridmpm.sim.base import MPM, NEURAL, Frame, NetworkFailure, Simulator, check_int
from hybridmpm.sim.mpm import MpmSimulator
from hybridmpm.trajectory import Trajectory, all_finite

#: ``stop(frame, sim)`` → None to go on, or the reason to break off.
StopRule = Callable[[Frame, Any], "str | None"]


@dataclass
class Rollout(Trajectory):
    """A :class:`~hybridmpm.trajectory.Trajectory` made by :func:`rollout`.

    Besides the trajectory's fields (``positions`` float32 [K + 1, N + B, D],
    one entry per coarse step, the first the state the rollout started from;
    ``dt_frame`` the time between entries = ``r_t·dt_frame``), per entry:
    ``frame_index`` int64 [K + 1]; ``solver`` str [K + 1] ("mpm"/"neural");
    ``seconds`` float64 [K + 1] wall time of the step (0 for the first);
    ``score`` float64 [K + 1] safeguard s(t) (nan where not computed);
    ``substeps`` int64 [K + 1]; ``controlled`` bool [K + 1]; the
    trajectory's ``obstacle_centers`` float64 [K + 1, C, D] when the
    simulator records them (a scene with obstacles); ``bodies`` the rigid
    bodies as one :class:`~hybridmpm.mpm.bodies.BodyTrack` (the bodies as
    given, ``center`` float64 [K + 1, B, D] [m], ``rotation``
    [K + 1, B, D, D], ``mass`` [B] [kg]) when every entry has the same
    bodies (:meth:`~hybridmpm.mpm.bodies.BodyTrack.stack`), else None, and
    the trajectory's ``body_center``, ``body_rotation`` and ``body_mass``
    its arrays (kept for the file and for older callers). And ``events``
    [(step, event)], ``failure`` (None, "nan", "mpm", a network failure mode
    or a stop rule's reason) and ``failure_detail`` (the error's message),
    ``stats`` (the simulator's counters),
    ``num_fluid`` N, ``r_t``. Saving keeps ``solver`` (int8, 1 = neural),
    ``score``, ``step_seconds``, ``frame_index`` and ``substeps`` as extras.
    """

    frame_index: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    solver: np.ndarray = field(default_factory=lambda: np.zeros(0, "<U6"))
    seconds: np.ndarray = field(default_factory=lambda: np.zeros(0))
    score: np.ndarray = field(default_factory=lambda: np.zeros(0))
    substeps: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    controlled: np.ndarray = field(default_factory=lambda: np.zeros(0, bool))
    events: list[tuple[int, str]] = field(default_factory=list)
    failure: str | None = None
    failure_detail: str | None = None
    stats: dict[str, Any] = field(default_factory=dict)
    num_fluid: int = 0
    r_t: int = 1
    bodies: BodyTrack | None = None

    @property
    def fluid_positions(self) -> np.ndarray:
        """float32 [K + 1, N, D]: the fluid particles only (a view)."""
        return self.positions[:, : self.num_fluid]

    @property
    def frames_done(self) -> int:
        """Frames simulated since the first entry."""
        return int(self.frame_index[-1] - self.frame_index[0])

    def frame_seconds(self, after: int = 0) -> np.ndarray:
        """Wall seconds per *frame* of the steps that end after frame ``after``
        (each step's time divided by ``r_t``, repeated ``r_t`` times): the
        per-frame latency with the first ``after`` frames left out."""
        keep = self.frame_index[1:] > after
        return np.repeat(self.seconds[1:][keep] / self.r_t, self.r_t)

    def share(self, solver: str = NEURAL) -> float:
        """Fraction of the steps made by ``solver``."""
        return float(np.mean(self.solver[1:] == solver)) if len(self.solver) > 1 else 0.0


def rollout(
    sim: Simulator,
    frames: int,
    *,
    progress: str | None = None,
    stop: StopRule | None = None,
    on_frame: Callable[[Frame], None] | None = None,
) -> Rollout:
    """Advance ``sim`` by ``frames`` frames (whole coarse steps:
    ``⌈frames / r_t⌉`` of them) and return the :class:`Rollout`, starting
    with the simulator's current frame.

    The rollout breaks off, keeping everything before, when a network step is
    rejected (:class:`~hybridmpm.sim.base.NetworkFailure`: ``failure`` is its
    mode), MPM cannot finish a frame ("mpm"), a step yields a non-finite fluid
    position ("nan"; that step is not kept), or ``stop(frame, sim)`` returns a
    reason (that step is kept). ``progress`` the description of a tqdm bar
    (None: no bar); ``on_frame`` is called with every kept frame. Raises
    :class:`InvalidInputError` (field ``frames``) for a negative count.
    """
    from tqdm import tqdm

    frames = check_int("frames", frames, 0)
    steps = math.ceil(frames / sim.r_t)
    p = sim.particles
    # each kept frame's positions, written into one array as the frame comes (and the frame just made)
    check_allocation("frames", (steps + 2) * p.num_total * p.dim * 4, f"keeping {steps + 1} frames of {p.num_total} particles")
    start = sim.frame
    target = start.frame_index + frames
    # one array for every kept frame, allocated once: each frame's positions are copied in and the frame's own
    # array is let go, so the next frame's reuses its memory (a fresh array per frame, stacked at the end, spent
    # more than half of a 100k-particle frame on page faults and the copy)
    kept = np.empty((steps + 1, *np.shape(start.positions)), np.float32)
    recs: list[Frame] = [keep(start, kept, 0)]
    shapes: list[Any] = [given_bodies(sim)]  # each kept frame's bodies as given (a callback may add or remove one)
    failure: str | None = None
    detail: str | None = None
    bar = tqdm(total=steps, desc=progress, unit="step", disable=progress is None)
    try:
        while sim.frame.frame_index < target:
            try:
                fr = sim.advance()
            except NetworkFailure as e:
                failure, detail = e.mode, str(e)
                break
            except SimulationError as e:
                failure, detail = "mpm", str(e)
                break
            if not all_finite(sim.particles.fluid(fr.positions)):
                failure = "nan"
                break
            fr = keep(fr, kept, len(recs))
            recs.append(fr)
            shapes.append(given_bodies(sim))
            bar.update()
            if fr.solver != MPM or not math.isnan(fr.score):
                bar.set_postfix_str(f"{fr.solver} s={fr.score:.2f}", refresh=False)
            if on_frame is not None:
                on_frame(fr)
            if stop is not None:
                reason = stop(fr, sim)
                if reason:
                    failure = str(reason)
                    break
    finally:
        bar.close()
    return _collect(sim, recs, kept[: len(recs)], shapes, failure, detail)


def keep(fr: Frame, kept: np.ndarray, k: int) -> Frame:
    """``fr`` with its positions copied into row ``k`` of ``kept`` float32 [K + 1, N + B, D], and that row in
    their place (the rollout has checked the frame's particle count: :meth:`~hybridmpm.scenes.ParticleSet.fluid`)."""
    kept[k] = fr.positions
    return replace(fr, positions=kept[k])


def given_bodies(sim: Any) -> list[Any] | None:
    """The rigid bodies ``sim`` holds now, as given (its MPM solver's ``params.bodies``: one list object until a
    body is added or removed); None for a simulator without them (the learned and hybrid ones refuse bodies)."""
    return getattr(getattr(getattr(sim, "solver", None), "params", None), "bodies", None)


def body_frame(frame: Frame, shapes: Any) -> BodyFrame | None:
    """A frame's bodies as :meth:`~hybridmpm.mpm.bodies.BodyTrack.stack` takes them: ``shapes`` (the bodies as
    given when it was made) with its ``body_center``, ``body_rotation`` and ``body_mass``; None without."""
    if not shapes or frame.body_center is None or frame.body_rotation is None or frame.body_mass is None:
        return None
    return shapes, frame.body_center, frame.body_rotation, frame.body_mass


def _collect(sim: Simulator, recs: list[Frame], positions: np.ndarray, shapes: list[Any], failure: str | None, detail: str | None) -> Rollout:
    p = sim.particles
    solver = np.array([r.solver for r in recs])
    seconds = np.array([0.0] + [r.seconds for r in recs[1:]])
    score = np.array([r.score for r in recs], np.float64)
    substeps = np.array([r.substeps for r in recs], np.int64)
    frame_index = np.array([r.frame_index for r in recs], np.int64)
    centers = [r.obstacle_centers for r in recs if r.obstacle_centers is not None]
    # the bodies when every kept frame has the same ones (none added or removed during the rollout)
    track = BodyTrack.stack([body_frame(r, g) for r, g in zip(recs, shapes)])
    extras = {
        "solver": (solver != MPM).astype(np.int8),  # 1: the cheap half (the network, or the coarse grid of the classical twin)
        "score": score,
        "step_seconds": seconds,
        "frame_index": frame_index,
        "substeps": substeps,
    }
    return Rollout(
        positions=positions,
        obstacle_centers=np.stack(centers) if centers and len(centers) == len(recs) else None,
        body_center=None if track is None else track.center,
        body_rotation=None if track is None else track.rotation,
        body_mass=None if track is None else track.mass,
        bodies=track,
        particle_type=p.particle_type,
        dt_frame=sim.dt_frame * sim.r_t,
        n_grid=sim.scene.params.resolved_n_grid(),
        masses=p.full_masses(),
        material=p.full_material(),
        extras=extras,
        frame_index=frame_index,
        solver=solver,
        seconds=seconds,
        score=score,
        substeps=substeps,
        controlled=np.array([r.controlled for r in recs], bool),
        events=[(r.step, r.event) for r in recs if r.event],
        failure=failure,
        failure_detail=detail,
        stats=sim.stats.to_dict(),
        num_fluid=p.num_fluid,
        r_t=sim.r_t,
    )


def reference(scene: Scene, frames: int, *, stride: int = 1, threads: int = 0, progress: str | None = None) -> Rollout:
    """Full-resolution MPM from ``scene``'s initial condition, every ``stride``
    frames for ``⌈frames/stride⌉·stride`` frames (whole strides, like the
    network's coarse steps): the reference of the grid-mass error. A scene
    clustered to ``r_p < 1`` or moved to another grid is rebuilt from its spec
    on the grid it was made for (:func:`~hybridmpm.scenes.resolution.full_resolution`).
    Raises :class:`InvalidInputError` (field ``scene``) if such a scene has no spec,
    :class:`~hybridmpm.errors.SimulationError` if MPM fails."""

    scene = full_resolution(scene)
    ro = rollout(MpmSimulator(scene, r_t=stride, threads=threads), frames, progress=progress)
    if ro.failure is not None:
        raise SimulationError(f"reference: full-resolution MPM failed after {ro.frames_done} frames: {ro.failure_detail or ro.failure}")
    return ro


#: The longest wall interval one :func:`step_realtime` call takes [s]: a host that paused longer (a hidden browser
#: tab, a debugger) gets one ordinary tick, not a burst.
MAX_WALL_DT = 1.0


@dataclass(frozen=True)
class RealtimeTick:
    """What one :func:`step_realtime` call did. ``frames`` advanced (whole coarse steps of ``r_t``);
    ``simulated_s`` the simulated time they cover [s]; ``wall_s`` the wall time spent stepping [s]; ``dropped_s``
    simulated time the budget could not cover and that is not owed to the next tick [s]; ``owed_s`` the
    remainder under one coarse step carried to the next tick [s]; ``realtime_factor`` ``simulated_s / wall_dt``
    (1.0: real time; NaN for ``wall_dt`` 0); ``rollout`` the frames themselves (its ``failure`` says why a
    tick broke off: as :func:`rollout`)."""

    frames: int
    simulated_s: float
    wall_s: float
    dropped_s: float
    owed_s: float
    realtime_factor: float
    rollout: Rollout


def step_realtime(sim: Simulator, wall_dt: float, *, owed_s: float = 0.0, budget_s: float | None = None) -> RealtimeTick:
    """Advance ``sim`` by the frames ``wall_dt`` seconds of wall time cover, within a budget: the host loop's
    tick (a game's update, the page's play loop) for an embedded simulator. Like :func:`rollout` it is a
    function of the simulator, not a method: the simulators stay below the loop that drives them.

    ``owed_s`` is the last tick's ``owed_s`` (the simulated time under one coarse step it could not take; 0 at
    the start): the host passes it back, so the call holds no state. With ``wall_dt`` added, this call advances
    the whole coarse steps (``r_t · dt_frame`` each) that time holds, through :func:`rollout` (the one frame loop),
    stopping once it has spent ``budget_s`` of wall time (default ``wall_dt``: never more stepping than the
    tick covers; at least one step is taken when one is due). What the budget did not cover is dropped, not
    owed: a frame that ran late is not made up later, so a slow machine runs in slow motion instead of falling
    ever further behind (the "spiral of death" of fixed-step game loops). ``wall_dt`` [s] is finite in
    [0, :data:`MAX_WALL_DT`] (longer is taken as that); ``owed_s`` [s] finite in [0, one coarse step];
    ``budget_s`` [s] finite > 0. Raises :class:`InvalidInputError` naming ``wall_dt``, ``owed_s`` or
    ``budget_s``."""

    def seconds(name: str, v: Any, positive: bool) -> float:
        if isinstance(v, bool) or not isinstance(v, numbers.Real) or not math.isfinite(v) or v < 0 or (positive and v == 0):
            raise InvalidInputError(f"{name}: must be a finite number of seconds {'>' if positive else '>='} 0, got {v!r}", name)
        return float(v)

    wall_dt = min(seconds("wall_dt", wall_dt, False), MAX_WALL_DT)
    budget = wall_dt if budget_s is None else seconds("budget_s", budget_s, True)
    step_s = sim.dt_frame * sim.r_t
    owed = seconds("owed_s", owed_s, False)
    if owed > step_s * (1 + 1e-9):
        raise InvalidInputError(f"owed_s: at most one coarse step ({step_s} s), the last tick's owed_s; got {owed_s!r}", "owed_s")
    owed += wall_dt
    due = math.floor(owed / step_s + 1e-9)  # 0.0075 s of 2.5 ms frames is 3 of them, not 2.9999999999999996
    t0 = time.perf_counter()

    def deadline(frame: Frame, _sim: Any) -> str | None:
        return "budget" if time.perf_counter() - t0 >= budget else None

    ro = rollout(sim, due * sim.r_t, stop=deadline)
    wall = time.perf_counter() - t0
    done = ro.frames_done // sim.r_t
    remainder = max(0.0, owed - due * step_s)  # under one step: owed to the next tick
    if done == due:
        dropped = 0.0
    elif ro.failure == "budget":
        dropped = (due - done) * step_s  # not owed: the next tick starts afresh
    else:  # the simulator could not step (its rollout's failure says why): nothing is owed
        dropped, remainder = (due - done) * step_s + remainder, 0.0
    simulated = ro.frames_done * sim.dt_frame
    return RealtimeTick(
        frames=ro.frames_done,
        simulated_s=simulated,
        wall_s=wall,
        dropped_s=dropped,
        owed_s=remainder,
        realtime_factor=simulated / wall_dt if wall_dt > 0 else math.nan,
        rollout=ro,
    )


__all__ = ["MAX_WALL_DT", "RealtimeTick", "Rollout", "StopRule", "body_frame", "given_bodies", "reference", "rollout", "step_realtime"]
