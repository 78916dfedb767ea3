"""A session's life, written once for both backends (:class:`SessionCore`).

A session is one simulator and what the service keeps around it: the lock
its work takes in turn, the recording of its recent frames, the controls it
keeps, the play loop (real time, catching up at most :data:`PLAY_LAG_S`;
a real-time session, never), the ``realtime`` event of a real-time session
whose rung changed,
its saves to the store (a snapshot at a step boundary, the record written
after), its idle clock (expiry) and the control episode; the edits of a
running session (pours, obstacle moves, rigid bodies) are its methods too,
written in :mod:`hybridmpm.service.edits` (:class:`~hybridmpm.service.edits.SessionEdits`,
its base class). The core is synchronous and thread-safe; the backends run
it in place:

- the local backend (:class:`~hybridmpm.service.sessions.SessionManager`)
  calls its methods on worker threads, each behind the session's ``asyncio``
  lock (so requests queue without holding a worker), and hands its frames
  and events to the viewers on the event loop;
- the Ray backend (:class:`~hybridmpm.service.ray_backend.actor.SessionActor`)
  calls them in the session's actor and hands frames and events to every
  front end's stream.

What the core shows goes through three hooks the backend sets:
``on_frame(frame, control_frame)``, ``on_event(msg)`` (both called from the
thread that did the work) and ``has_viewers()`` (the play loop runs while
it is true).
"""

from __future__ import annotations

import collections
import logging
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import Any

import numpy as np

from hybridmpm.scenes import scene_spec
from hybridmpm.service import checkpoint as ckpt
from hybridmpm.service.budget import MemoryBudget, RecordedBodies, RecordedFrame, Recording
from hybridmpm.service.edits import SessionEdits
from hybridmpm.service.episode import run_episode
from hybridmpm.service.facts import SessionFacts, SessionSettings, scene_geometry, session_integrator, session_realtime
from hybridmpm.service.schemas import clean
from hybridmpm.service.store import SHOWN_KEY_CHARS, SessionStore, StoredSession, rebuild, record_state
from hybridmpm.sim import Frame, RealtimeSimulator, Rollout, Simulator, make_simulator, rollout
from hybridmpm.sim.rollout import given_bodies

log = logging.getLogger("hybridmpm.service")

#: How far a playing session may fall behind real time before it stops catching up [s].
PLAY_LAG_S = 0.25
#: A playing session wakes at most once per tick [s] and steps, in that one call, the frames that are
#: due (while the call is under a tick of wall time), showing its viewers the last of them: the hand-off
#: to a worker, the timer and the frame's encoding cost once per tick instead of once per frame (water2d
#: plays 400 frames/s; a viewer's stream sends at most 60 a second, the newest).
PLAY_TICK_S = 0.01
#: How far a real-time session may fall behind before it stops catching up [s]: two ticks, so the frames that
#: fell due while the loop slept out its tick (and the timer's lateness) are stepped on waking, and no frame
#: later than that is owed. With no lag at all the loop stepped one frame a tick: water2d played 168 frames/s
#: of its 400 (``python benchmarks/bench_capacity.py --realtime``), whatever the machine had to spare.
REALTIME_LAG_S = 2 * PLAY_TICK_S
#: Controls kept per session (their trajectories can be fetched).
KEEP_CONTROLS = 8
#: Coarse steps of its recent trajectory a session keeps for download (``GET .../trajectory``).
RECORD_STEPS = 300
#: A session whose scene holds at least this many particles steps on two MPM threads where two
#: compute threads are free (:func:`session_threads`); a smaller one gains nothing from a second thread.
WIDE_SESSION_PARTICLES = 10_000


class SessionGoneError(Exception):
    """The session was deleted, expired or lost while a request used it (→ 404)."""


class BusyError(Exception):
    """A control is already running on the session (→ 409)."""


@dataclass
class Control:
    """A control a session keeps: its ``id``, ``method``, trajectory
    (``positions`` float32 [steps + 1, N, D] and each step's ``solver``), the
    answer it gave (``response``) and the bytes it holds of the memory
    budget (``cost``; 0 where no ledger counts it)."""

    id: str
    method: str
    positions: np.ndarray
    solver: list[str]
    response: dict[str, Any]
    cost: int = 0


class Pacer:
    """Real-time pacing of a playing session: one coarse step (``period``
    seconds of simulated time) per ``period`` seconds of wall time;
    :meth:`delay` after each step says how long to wait before the next.
    A session that falls behind catches up at most ``lag`` seconds
    (:data:`PLAY_LAG_S`; :data:`REALTIME_LAG_S`, two play ticks, for a
    real-time session: a frame later than that is not owed, the next one is
    due a period after it)."""

    def __init__(self, period: float, lag: float = PLAY_LAG_S) -> None:
        self.period = float(period)
        self.lag = max(0.0, float(lag))
        self.next_t = time.monotonic()

    def delay(self) -> float:
        """Seconds to wait before the next step [s], ≥ 0."""
        self.next_t = max(self.next_t + self.period, time.monotonic() - self.lag)
        return max(0.0, self.next_t - time.monotonic())


def session_threads(settings: SessionSettings, most: int) -> int:
    """The MPM threads of a new session of ``settings``: 2 when ``most`` (the
    compute threads the backend grants one session) is at least 2 and its
    scene holds at least :data:`WIDE_SESSION_PARTICLES` particles, else 1.
    The engine gives the same bits on any thread count, so this changes only
    the speed. Builds the scene's initial condition to count (milliseconds);
    raises what :func:`hybridmpm.scenes.scene_spec` raises."""
    if most < 2:
        return 1
    n = scene_spec(settings.scene, seed=settings.seed, n_grid=settings.n_grid).build().num_particles
    return 2 if n >= WIDE_SESSION_PARTICLES else 1


def _nothing(*_: Any) -> None:
    return None


def _no_viewers() -> bool:
    return False


class SessionCore(SessionEdits):
    """One session: its simulator ``sim`` (at ``settings``, from ``initial``,
    the state a reset goes back to, stepping on ``threads`` MPM threads),
    created by the client address ``client``, named ``key`` in the store;
    its recording takes from ``budget``. Build one with :meth:`build` or :meth:`load`.

    Thread-safe: the simulation work takes :attr:`lock` (a re-entrant lock,
    held for a whole step, control or restore); the recording and the kept
    controls a short lock of their own, so reading them never waits for a
    step. A closed session (:meth:`close`) refuses work with
    :class:`SessionGoneError` and stops a running control within a frame.
    """

    def __init__(
        self, key: str, settings: SessionSettings, sim: Simulator, initial: dict[str, Any], client: str, budget: MemoryBudget, threads: int = 1
    ) -> None:
        self.key = key
        self.threads = int(threads)  # the MPM threads its steps use (what a compute limiter counts)
        self.settings = settings
        self.sim = sim
        self.initial = initial
        self.client = client
        self.facts = SessionFacts.of(sim)
        self.lock = threading.RLock()  # the simulator
        self._held = threading.Lock()  # the recording, the kept controls, the control flag
        self._save_lock = threading.Lock()  # one save (snapshot then write) at a time
        self._write_lock = threading.Lock()  # a record's write or removal: a closed session's record is never written again
        self._snapshots = 0  # snapshots taken (a write of an older one than the last written is skipped)
        self._written = 0  # the snapshot the record holds
        self.recording = Recording(budget, RECORD_STEPS, int(sim.r_t))
        self.controls: collections.OrderedDict[str, Control] = collections.OrderedDict()
        self.on_frame: Callable[[Frame, int], None] = _nothing
        self.on_event: Callable[[dict[str, Any]], None] = _nothing
        self.has_viewers: Callable[[], bool] = _no_viewers
        self.playing = False
        self.controlling = False
        self.running_control: dict[str, Any] | None = None  # the control a new viewer is told of (:meth:`info`)
        self.closed = False
        self.cancel = threading.Event()  # set: the running control stops within a frame
        self.dirty = False  # changed since its last save
        self.saved_frame: int | None = None  # frame of its last save (None: no store, or not saved yet)
        self.save_failure: tuple[int | None, str] | None = None  # (errno, message) of its last failed save; None after a save
        self.restored_from_frame: int | None = None  # the frame it resumed from after a restart
        self.poured = getattr(sim, "poured_particles", 0) > 0  # particles were added (a reset then builds its simulator again)
        self.last_used = time.monotonic()
        self._realtime_seen = self._realtime_mark()  # (rung, changes) the viewers were last told of
        self._record(sim.frame)

    # ------------------------------------------------------------ building
    @classmethod
    def build(cls, key: str, settings: SessionSettings, client: str, budget: MemoryBudget, threads: int = 1) -> SessionCore:
        """A new session (:func:`hybridmpm.sim.make_simulator` with ``threads``
        MPM threads and one network thread). Blocks; raises the simulator's
        :class:`~hybridmpm.errors.InvalidInputError` for bad settings."""
        s = settings
        sim = make_simulator(s.scene, s.solver, r_c=s.r_c, seed=s.seed, threads=threads, nn_threads=1, n_grid=s.n_grid, integrator=s.integrator)
        return cls(key, settings, sim, sim.state(), client, budget, threads)

    @classmethod
    def load(cls, rec: StoredSession, budget: MemoryBudget, most_threads: int = 1) -> SessionCore:
        """The session of a store record, at its saved frame, its idle clock
        as the record says, on :func:`session_threads` MPM threads (at most
        ``most_threads``; :func:`~hybridmpm.service.store.rebuild`; raises
        what it raises). Blocks."""
        settings = SessionSettings(rec.scene, rec.seed, rec.solver, rec.r_c, rec.n_grid, rec.integrator)
        threads = session_threads(settings, most_threads)
        sim, initial = rebuild(rec, threads)
        core = cls(rec.key, settings, sim, initial, rec.client, budget, threads)
        core.saved_frame = core.restored_from_frame = core.frame_index
        core.last_used = time.monotonic() - max(0.0, time.time() - rec.last_used_at)
        return core

    # ------------------------------------------------------------ plain facts
    @property
    def frame_index(self) -> int:
        """The frame the session is at."""
        return int(self.sim.frame.frame_index)

    def touch(self) -> None:
        """Used now (its idle clock starts again)."""
        self.last_used = time.monotonic()

    def idle_s(self) -> float:
        """Seconds since it was last used."""
        return time.monotonic() - self.last_used

    def expired(self, ttl: float) -> bool:
        """Idle for more than ``ttl`` seconds and no control running."""
        return not self.controlling and self.idle_s() > ttl

    def info(self) -> dict[str, Any]:
        """Its description, less what the backend adds (``id``, ``stream``, ``viewers``, ``playing``)."""
        f = self.facts
        d = f.dim
        return {
            **self.settings.meta(),
            "dim": d,
            "num_fluid": f.num_fluid,
            "num_particles": f.num_total,
            "particle_type": [int(t) for t in f.particle_type],
            "bounds": [[0.0] * d, [1.0] * d],
            "dt_frame": f.dt_frame,
            "r_t": f.r_t,
            "frame": self.frame_index,
            "saved_frame": self.saved_frame,
            "restored_from_frame": self.restored_from_frame,
            **scene_geometry(self.sim),
            "integrator": session_integrator(self.sim),  # what runs (the settings' meta holds it only when asked)
            "realtime": self.realtime_info(),
            "obstacle_centers": np.round(np.asarray(getattr(self.sim, "obstacle_centers", np.zeros((0, d))), np.float64), 7).tolist(),
            "bodies": self.bodies_now(),
            "recorded_frames": len(self.recording),
            "control": self.control_state(),
        }

    def realtime_info(self) -> dict[str, Any] | None:
        """A real-time session's :meth:`~hybridmpm.sim.RealtimeSimulator.realtime_info` (its rung, frame time,
        real-time factor, ...; plain JSON values); None for any other session."""
        return session_realtime(self.sim)

    def _realtime_mark(self) -> tuple[str, int] | None:
        sim = self.sim
        return (sim.rung, len(sim.changes)) if isinstance(sim, RealtimeSimulator) else None

    def _realtime_news(self) -> None:
        """After steps, a restore or a reset: a real-time session whose rung changed since the viewers were last
        told (:attr:`~hybridmpm.sim.RealtimeSimulator.changes` grew, or a state moved it) emits
        ``{"type": "realtime", **realtime_info()}``."""
        mark = self._realtime_mark()
        info = session_realtime(self.sim) if mark is not None and mark != self._realtime_seen else None
        if info is not None:
            self._realtime_seen = mark
            self.on_event({"type": "realtime", **info})

    def pacer(self) -> Pacer:
        """The play loop's :class:`Pacer`: one coarse step per its simulated time, catching up at most
        :data:`PLAY_LAG_S`; a real-time session only the frames due within two play ticks (:data:`REALTIME_LAG_S`)."""
        return Pacer(float(self.sim.dt_frame) * int(self.sim.r_t), REALTIME_LAG_S if isinstance(self.sim, RealtimeSimulator) else PLAY_LAG_S)

    def control_state(self) -> dict[str, Any] | None:
        """The control running now, as a viewer that joins meanwhile needs it
        to show what the others see: ``{"status": "running", "id", "method",
        "frames", "start_frame", "sketch" (the sketch's JSON or None),
        "plan" (the plan's summary once made, else None)}``; None when no
        control runs. Set before the ``running`` event is emitted and cleared
        before the control returns, so a stream opened at any moment learns of
        a running control from its opening message, its events, or both."""
        with self._held:
            c = self.running_control
            return None if c is None else {**c}

    # ------------------------------------------------------------ what it shows
    def _record(self, fr: Frame) -> None:
        bodies = self._recorded_bodies(fr.body_center, fr.body_rotation, fr.body_mass)
        self._record_values(int(fr.frame_index), fr.positions, str(fr.solver), bool(fr.controlled), fr.obstacle_centers, bodies)

    def _recorded_bodies(self, center: np.ndarray | None, rotation: np.ndarray | None, mass: np.ndarray | None) -> RecordedBodies | None:
        """A frame's bodies as the recording keeps them: with the solver's list of the bodies as given (one object
        until a body is added or removed, so a download knows which frames share their bodies); None without."""
        given = given_bodies(self.sim)
        if not given or center is None or rotation is None or mass is None:
            return None
        return given, center, rotation, mass

    def _record_values(
        self, frame_index: int, positions: np.ndarray, solver: str, controlled: bool, centers: np.ndarray | None, bodies: RecordedBodies | None = None
    ) -> None:
        with self._held:
            if not self.closed:
                self.recording.add(frame_index, positions, solver, controlled, centers, bodies)

    def _show(self, fr: Frame, control_frame: int = 0) -> None:
        """Record ``fr`` and hand it to the viewers."""
        self._record(fr)
        self.on_frame(fr, control_frame)

    def republish(self) -> None:
        """Hand the current frame to the viewers again (after a control that stopped early)."""
        self.on_frame(self.sim.frame, 0)

    def recorded(self, count: int) -> list[RecordedFrame]:
        """The latest ``count`` frames of its recent trajectory, oldest first."""
        self.touch()
        with self._held:
            return self.recording.last(count)

    def _changed(self) -> None:
        self.dirty = True
        self.touch()

    def _open(self) -> None:
        if self.closed:
            raise SessionGoneError()

    # ------------------------------------------------------------ the work
    def rollout(self, frames: int) -> Rollout:
        """Advance ``frames`` frames (:func:`hybridmpm.sim.rollout`): every
        coarse step is recorded, the last one shown."""
        with self.lock:
            self._open()
            ro = rollout(self.sim, frames)
            self._changed()
            for k in range(1, len(ro.frame_index)):
                centers = None if ro.obstacle_centers is None else ro.obstacle_centers[k]
                track = ro.bodies  # the rollout's bodies when its frames share them
                poses = (None, None, None) if track is None else (track.center[k], track.rotation[k], track.mass)
                self._record_values(int(ro.frame_index[k]), ro.positions[k], str(ro.solver[k]), False, centers, self._recorded_bodies(*poses))
            if len(ro.frame_index) > 1:
                self.on_frame(self.sim.frame, 0)
            self._realtime_news()
        return ro

    def play(self) -> Iterator[float]:
        """The play loop: while it plays, is open and has viewers, it steps
        the coarse steps that are due (:class:`Pacer`: real time) in calls
        of at most about :data:`PLAY_TICK_S` of wall time, yielding after
        each call the seconds to wait before the next (at least the rest of
        the tick). Every step is recorded; the viewers are shown the last
        step of a call (the step before a pause or a failure included). A
        step that fails stops it, with an ``error`` event. The backend waits
        between the calls (a thread's sleep, or the event loop's with each
        call on a worker). :attr:`lock` is taken per step; the local
        backend queues a session's requests behind a whole call (about a
        tick)."""
        pacer = self.pacer()
        while self.playing and not self.closed and self.has_viewers():
            start, delay = time.monotonic(), 0.0
            last: Frame | None = None  # the call's latest step: the viewers get it when the call ends
            failure: Exception | None = None
            while True:
                with self.lock:
                    going = self.playing and not self.closed
                    if going:
                        try:
                            last = self.sim.advance()
                        except Exception as e:  # noqa: BLE001 - a failed step pauses the stream with a message
                            self.playing, going, failure = False, False, e
                        else:
                            self._changed()
                            self._record(last)
                            self._realtime_news()
                            delay = pacer.delay()
                    ends = not going or delay > 0 or time.monotonic() - start >= PLAY_TICK_S or not (self.playing and self.has_viewers())
                    if ends and last is not None:
                        self.on_frame(last, 0)  # under the lock: a request's frame after it is never overtaken
                    if failure is not None:
                        self.on_event({"type": "error", "message": f"simulation stopped: {failure}"})
                if not going:
                    return
                if ends:
                    break
            yield max(delay, start + PLAY_TICK_S - time.monotonic())

    def control(
        self,
        method: str,
        frames: int,
        sketch: Any,
        cid: str,
        left: Callable[[], bool] | None = None,
        store: SessionStore | None = None,
        share: Callable[[], None] | None = None,
    ) -> tuple[Rollout, dict[str, Any], dict[str, Any] | None, float | None]:
        """Plan and run control ``cid`` with ``method`` for ``frames`` frames
        of ``sketch`` (a :class:`~hybridmpm.control.Sketch` or None; the
        scene's :class:`~hybridmpm.control.Controller`;
        :func:`~hybridmpm.service.episode.run_episode`): the viewers get a
        ``control running`` event once it starts, its plan and every
        controlled frame. The save policy around a control, for both
        backends: with ``store`` the session is saved before it is announced
        (the steps answered before it are durable; a periodic saver skips a
        session in a control) and again once it ends, before it is answered
        (a control that answered is durable). It stops
        within a frame when ``left()`` turns true (its client left), when
        :attr:`cancel` is set, or when the session closes, and so does a plan
        in progress (between its model rollouts' frames); ``share()`` (the
        backend's hand-over of the compute this call holds to other work that
        waits for it) is called between the same units of work. Returns
        ``(rollout, metrics, plan summary or None, time.perf_counter() of
        the first controlled frame or None)``. Raises :class:`BusyError`
        when a control is running and :class:`SessionGoneError` when the
        session closed before or during it."""
        from hybridmpm.control import Controller  # import time: the controllers load only when a control runs

        with self._held:  # a close sets `closed` then the cancel flag under this lock: a control never clears a close's cancel
            if self.controlling:
                raise BusyError()
            self._open()
            self.controlling = True
            self.cancel.clear()
        try:
            controller = Controller.for_scene(self.facts.scene_name, method, frames=frames)
            if store is not None:
                self.save(store)
            with self.lock:
                self._open()
                running = {
                    "status": "running",
                    "id": cid,
                    "method": method,
                    "frames": int(frames),
                    "start_frame": self.frame_index,
                    "sketch": clean(sketch.to_json()) if sketch is not None else None,
                }
                with self._held:  # the state first, then the event: a viewer attached in between hears of it twice, never not
                    self.running_control = {**running, "plan": None}
                self.on_event({"type": "control", **running})

                def stop() -> bool:
                    return self.cancel.is_set() or self.closed or (left is not None and left())

                def on_event(msg: dict[str, Any]) -> None:
                    if msg.get("type") == "plan":
                        with self._held:
                            if self.running_control is not None:
                                self.running_control["plan"] = {k: v for k, v in msg.items() if k not in ("type", "id")}
                    self.on_event(msg)

                try:
                    out = run_episode(self.sim, sketch, controller, cid, self._show, on_event, stop, share)
                finally:
                    self._realtime_news()  # a control's frames may have moved a real-time session's rung
                self._changed()
            self._open()
            if store is not None:
                self.save(store)
            return out
        finally:
            with self._held:
                self.running_control = None
            self.controlling = False

    def keep_control(self, c: Control) -> list[Control]:
        """Keep ``c``; returns the oldest ones dropped beyond :data:`KEEP_CONTROLS`."""
        with self._held:
            self.controls[c.id] = c
            dropped = []
            while len(self.controls) > KEEP_CONTROLS:
                dropped.append(self.controls.popitem(last=False)[1])
        return dropped

    def get_control(self, cid: str) -> Control | None:
        """The kept control ``cid``, or None."""
        self.touch()
        with self._held:
            return self.controls.get(cid)

    def state(self) -> dict[str, Any]:
        """Its whole state (:meth:`~hybridmpm.sim.Simulator.state`), between steps."""
        with self.lock:
            self._open()
            return self.sim.state()

    def checkpoint(self) -> bytes:
        """Its whole state as a checkpoint (:func:`hybridmpm.service.checkpoint.dumps`)."""
        state = self.state()
        self.touch()
        return ckpt.dumps(state, self.settings.meta())

    def restore(self, state: dict[str, Any]) -> None:
        """Restore ``state``, all or nothing: the simulator's refusal
        (:class:`~hybridmpm.errors.InvalidInputError`,
        :class:`~hybridmpm.errors.CheckpointError`, or a ``KeyError``/``TypeError``/...
        of a malformed tree) leaves it as it was. The recent trajectory starts
        again. A state taken before or after a pour brings its own particles
        back (:meth:`hybridmpm.sim.MpmSimulator.restore`): the facts follow and
        the viewers get a ``particles`` event when they changed."""
        with self.lock:
            self._open()
            bodies = self.bodies_given()
            self.sim.restore(state)
            facts = SessionFacts.of(self.sim)
            moved = not np.array_equal(facts.particle_type, self.facts.particle_type)
            self.facts, self.poured = facts, getattr(self.sim, "poured_particles", 0) > 0
            self._changed()
            with self._held:
                self.recording.clear()
            self._show(self.sim.frame)
            frame = self.frame_index
            if self.bodies_given() != bodies:  # a state taken before or after a body was added or removed
                self._bodies_event(frame)
            self._realtime_news()  # a real-time state brings its rung back
        if moved:
            self.on_event({"type": "particles", "frame": frame, "added": 0, "num_particles": facts.num_total, "num_fluid": facts.num_fluid,
                           "particle_type": [int(t) for t in facts.particle_type]})  # fmt: skip

    def reset(self) -> None:
        """Back to the initial condition; the viewers get the frame and a ``reset`` event
        (after a pour, a new simulator of the session's settings, and a ``particles`` event first)."""
        with self.lock:
            bodies = self.bodies_given()
            if self.poured:
                s = self.settings
                self.sim = make_simulator(
                    s.scene, s.solver, r_c=s.r_c, seed=s.seed, threads=self.threads, nn_threads=1, n_grid=s.n_grid, integrator=s.integrator
                )
                self.facts, self.poured = SessionFacts.of(self.sim), False
                f = self.facts
                self.on_event({"type": "particles", "frame": 0, "added": 0, "num_particles": f.num_total, "num_fluid": f.num_fluid,
                               "particle_type": [int(t) for t in f.particle_type]})  # fmt: skip
            self.sim.restore(self.initial)
            self._changed()
            with self._held:
                self.recording.clear()
            self._show(self.sim.frame)
            if self.bodies_given() != bodies:  # the scene's own bodies again
                self._bodies_event(self.frame_index)
            self._realtime_news()
            self.on_event({"type": "reset", "frame": self.frame_index})

    # ------------------------------------------------------------ saves
    def snapshot(self) -> tuple[dict[str, Any], int, int] | None:
        """The state a save writes (:func:`~hybridmpm.service.store.record_state`),
        its frame and its number (snapshots are numbered in the order taken),
        taken between steps; None when it is closed or has not changed since
        its last save. Clears its changed mark."""
        with self.lock:
            if self.closed or not self.dirty:
                return None
            self.dirty = False
            self._snapshots += 1
            return record_state(self.sim), self.frame_index, self._snapshots

    def write(self, store: SessionStore, state: dict[str, Any], frame: int, number: int = 0) -> bool:
        """Write :meth:`snapshot` number ``number`` to ``store`` (its record:
        the state, the settings that rebuild it, its idle clock as wall time,
        its client); False when it could not (logged; it is marked changed
        again, so the next save tries again). A snapshot older than the one
        the record holds (two saves that crossed: the periodic saver's and a
        control's), or one of a closed session, is not written (True)."""
        t0 = time.perf_counter()
        meta = {
            **self.settings.meta(),
            "last_used_at": time.time() - (time.monotonic() - self.last_used),
            "client": self.client[: ckpt.MAX_META_CHARS],
        }
        with self._write_lock:
            if self.closed or (number and number < self._written):
                return True
            try:
                data = ckpt.dumps(state, meta)
                store.write(self.key, data)
            except Exception as e:  # noqa: BLE001 - a failed save must not fail the session
                self.dirty = True
                self.save_failure = (getattr(e, "errno", None), f"{type(e).__name__}: {getattr(e, 'strerror', None) or e}")
                log.warning("store: saving session %s… failed: %s", self.key[:SHOWN_KEY_CHARS], e)
                return False
            self._written = max(self._written, number)
        self.saved_frame = frame
        self.save_failure = None
        log.debug("store: session %s… saved at frame %d: %d bytes in %.1f ms", self.key[:SHOWN_KEY_CHARS], frame, len(data), (time.perf_counter() - t0) * 1e3)
        return True

    def save(self, store: SessionStore) -> bool:
        """:meth:`snapshot` then :meth:`write`, one save at a time; True when
        there was nothing to save."""
        with self._save_lock:
            snap = self.snapshot()
            if snap is None:
                return True
            return self.write(store, *snap)

    def close(self, store: SessionStore | None = None) -> None:
        """Close it: it refuses further work, a running control stops within
        a frame, its recording's memory goes back to the budget, its hooks
        show nothing more; with
        ``store`` its record is removed (after a write under way; none comes
        after: no record outlives its session). Idempotent: a backend closes
        it at once, then removes its record off the event loop."""
        with self._held:
            self.closed = True
            self.playing = False
            self.cancel.set()
            self.recording.release()
        # a closed session shows nothing more; and its hooks (closures over the backend's objects) go, so that
        # its simulator is freed with the last reference to it rather than by the cycle collector
        self.on_frame, self.on_event, self.has_viewers = _nothing, _nothing, _no_viewers
        if store is not None:
            with self._write_lock:
                store.delete(self.key)


__all__ = [
    "KEEP_CONTROLS",
    "PLAY_LAG_S",
    "PLAY_TICK_S",
    "REALTIME_LAG_S",
    "RECORD_STEPS",
    "BusyError",
    "Control",
    "Pacer",
    "SessionCore",
    "SessionGoneError",
]
