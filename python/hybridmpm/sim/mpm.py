"""MPM alone behind the simulator interface (the Rust MLS-MPM solver).

One coarse step is ``r_t`` frames (default 1); each frame is as many CFL
substeps as the solver needs (it halves the substep and retries a frame that
goes non-finite). A ``forcing`` is written into the solver's per-particle
external acceleration before each frame (paper Sec. 3.2: the controller's
accelerations are applied by MPM).

Moving obstacles (docs/obstacles.md, "Moving obstacles"): before each frame
the simulator moves every obstacle that follows a keyframed path
(:mod:`hybridmpm.mpm.motion`) to the path's centre at the frame's end, and
every obstacle given a :meth:`MpmSimulator.move_obstacle` for this step a
share of the way to its target; the solver sweeps it there substep by
substep and its boundary condition pushes the fluid with its velocity
(:meth:`~hybridmpm.mpm.MpmSolver.move_collider`). A frame's time is
``frame · dt_frame`` in float64. Each obstacle's boundary particles in the
frames move with it (:attr:`MpmSimulator.obstacle_offsets`).
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import replace
from typing import Any

import numpy as np

from hybridmpm.conventions import GNS_TYPE_OF_MATERIAL
from hybridmpm.errors import CheckpointError, InvalidInputError, SimulationError
from hybridmpm.mpm import MpmSolver, SampledSdf
from hybridmpm.mpm.bodies import BodiesView, Body
from hybridmpm.mpm.motion import MAX_OBSTACLE_SPEED, Keyframe, check_center, check_velocity, path_center
from hybridmpm.mpm.params import Collider
from hybridmpm.mpm.solver import check_leading_particles, check_poured_blocks, core_particle_count
from hybridmpm.scenes import make_scene
from hybridmpm.scenes.body_mesh import bounding_radius, resolve_mesh_body
from hybridmpm.scenes.core import Clusters, Scene
from hybridmpm.scenes.obstacles import obstacle_center
from hybridmpm.scenes.particles import ParticleSet
from hybridmpm.scenes.resolution import at_resolution, check_r_t, on_grid, with_integrator
from hybridmpm.sim.base import (
    MPM,
    Forcing,
    Frame,
    SimStats,
    check_forcing,
    check_int,
    check_step_index,
    new_lock,
    reading_state,
    resolve_forcing,
    serialised,
)
from hybridmpm.sim.convert import neural_to_mpm

_STATE_VERSION = 1


def probe_frame(solver: MpmSolver, dt_frame: float) -> dict[str, float]:
    """One frame (``dt_frame`` [s]) of a bare :class:`~hybridmpm.mpm.MpmSolver` that no
    simulator holds: a state built for a one-frame question (a coarse state
    split onto the scene's grid, a solver put back to a checkpoint
    afterwards), as the experiments of docs/correction.md ask it. Returns the
    solver's frame statistics (``substeps``, ``dt``, ``max_speed``,
    ``active_blocks``, ``retries``: :meth:`~hybridmpm.mpm.MpmSolver.step_frame`). Raises
    :class:`~hybridmpm.errors.SimulationError` if the frame cannot be
    finished. Rollouts go through :func:`hybridmpm.sim.rollout`, never here."""
    return solver.step_frame(dt_frame)


class MpmSimulator:
    """MLS-MPM on a scene, one coarse step (``r_t`` frames) per :meth:`advance`.

    Parameters
    ----------
    scene:
        A :class:`~hybridmpm.scenes.Scene` (or a registered scene name / scene
        file, built with ``seed``).
    r_p:
        Spatial downsampling in (0, 1]: the scene is clustered to ``r_p·N``
        particles (k-means seeded by ``seed``, paper Sec. 3.1.1) first.
    r_t:
        Frames per coarse step (≥ 1).
    threads:
        Solver threads (0 = all cores).
    clusters:
        The :attr:`~hybridmpm.scenes.Scene.clusters` of an earlier simulator of
        the same scene at the same ``r_p`` (a restored session): the
        downsampled scene is rebuilt from them without the k-means.
    n_grid, particles_per_cell, keep_particles:
        Run on another grid of the same domain
        (:func:`~hybridmpm.scenes.resolution.on_grid`: the same blocks,
        obstacles and wall faces, reseeded at ``particles_per_cell`` per axis,
        or with ``keep_particles`` the scene's own particles); None: the
        scene's grid. Applied before ``r_p``.
    calibrated:
        Run the calibrated coarse material of the scene on ``n_grid``
        (:func:`~hybridmpm.scenes.resolution.calibrate`; docs/correction.md);
        refused (field ``calibrated``) where no fit exists.
    integrator:
        ``"explicit"`` or ``"projection"`` (:data:`hybridmpm.mpm.INTEGRATORS`;
        :func:`~hybridmpm.scenes.resolution.with_integrator`); None: the
        scene's. The projection steps water only, round free-slip obstacles
        and rigid bodies (field ``integrator`` otherwise; docs/large-step.md).

    ``solver`` is the underlying :class:`~hybridmpm.mpm.MpmSolver`. Raises
    :class:`InvalidInputError` naming the bad parameter.
    """

    kind = MPM

    def __init__(
        self,
        scene: Scene | str,
        *,
        r_p: float = 1.0,
        r_t: int = 1,
        seed: int = 0,
        threads: int = 0,
        clusters: Clusters | None = None,
        n_grid: int | None = None,
        particles_per_cell: int | None = None,
        keep_particles: bool = False,
        calibrated: bool = False,
        integrator: str | None = None,
    ) -> None:
        self._lock = new_lock()
        if isinstance(scene, str):
            scene = make_scene(scene, seed=seed)
        self.r_t = check_r_t(r_t)
        threads = check_int("threads", threads, 0)
        self.scene_full = scene
        scene_on_grid = on_grid(scene, n_grid, particles_per_cell, keep_particles=keep_particles, calibrated=calibrated)
        self.scene = at_resolution(with_integrator(scene_on_grid, integrator), r_p, seed, clusters)
        self.solver: MpmSolver = self.scene.make_solver(num_threads=threads)
        self.particles = self.scene.particles(self.solver.masses)
        #: the scene's own solver parameters and particles: a state with blocks poured after them restores (:meth:`restore`)
        self._scene_params, self._scene_particles = self.solver.params, self.particles
        #: the particle count of each block poured into it, in order (:func:`hybridmpm.sim.pour.pour_block`)
        self._pours: list[int] = []
        self.dt_frame = float(self.scene.dt_frame)
        self.dt_step = self.dt_frame * self.r_t
        self.step_index = 0
        self.stats = SimStats()
        self._forcing: Forcing = None
        self._applied = False
        self._colliders: list[Collider] = list(self.scene.params.colliders)
        #: (index, keyframes) of the obstacles that follow a path
        self._paths: list[tuple[int, tuple[Keyframe, ...]]] = [(i, c.keyframes) for i, c in enumerate(self._colliders) if c.keyframes]
        #: obstacle index -> (target centre float64 [D], boundary velocity float64 [D] or None) for the next step
        self._moves: dict[int, tuple[np.ndarray, np.ndarray | None]] = {}
        self._anchors0 = self.solver.collider_positions.copy()
        self._frame = Frame(0, 0, 0.0, self.particles.pad(self.fluid_positions), MPM, obstacle_centers=self.frame_centers(), **self.frame_bodies())

    # ------------------------------------------------------------ state
    @property
    def fluid_positions(self) -> np.ndarray:
        """The solver's particle positions, float32 [N, D] (a copy: the solver's field reads copy them out)."""
        return np.asarray(self.solver.positions, np.float32)

    @property
    def positions(self) -> np.ndarray:
        """Current positions with boundary particles, float32 [N + B, D] (each
        obstacle's at its current pose: :attr:`obstacle_offsets`)."""
        return self.particles.pad(self.fluid_positions, self.obstacle_offsets)

    @property
    def velocities(self) -> np.ndarray:
        """Current fluid velocities [m/s], float32 [N, D] (the solver's)."""
        return np.asarray(self.solver.velocities, np.float32).copy()

    @property
    def frame(self) -> Frame:
        """The last :class:`Frame` (the initial condition before the first step)."""
        return self._frame

    @property
    def forcing(self) -> Forcing:
        """External acceleration [m/s²] of the fluid particles: float32 [N, D],
        a callable ``(frame, positions, velocities) -> [N, D] | None``, or None
        (see :mod:`hybridmpm.sim.base`)."""
        return self._forcing

    @forcing.setter
    @serialised
    def forcing(self, value: Forcing) -> None:
        self._forcing = check_forcing(value, self.particles.num_fluid, self.particles.dim)
        if self._forcing is None and self._applied:
            self._clear_forcing()

    def _fluid_state(self) -> tuple[np.ndarray, np.ndarray]:
        """What a forcing function is handed: fluid positions and velocities, float32 [N, D] (copies)."""
        return self.fluid_positions, self.velocities

    def _clear_forcing(self) -> None:
        self.solver.external_acceleration = np.zeros((self.solver.num_particles, self.particles.dim), np.float32)
        self._applied = False

    def _apply_acceleration(self, acc: np.ndarray) -> None:
        """Write a resolved forcing, float32 [N, D] of the particles :attr:`particles` counts, into the solver."""
        self.solver.external_acceleration = acc

    # ------------------------------------------------------------ obstacles
    @property
    def obstacle_centers(self) -> np.ndarray:
        """Each obstacle's centre now [m], float64 ``[C, D]``: a box's or
        sphere's centre (the solver's float32 value), a mesh's ``center``
        (its sampled origin's displacement added to the scene's centre)."""
        pos = self.solver.collider_positions.astype(np.float64)
        out = pos.copy()
        for i, c in enumerate(self._colliders):
            if isinstance(c, SampledSdf):
                out[i] = obstacle_center(c) + (pos[i] - self._anchors0[i].astype(np.float64))
        return out.reshape(len(self._colliders), self.particles.dim)

    def frame_centers(self) -> np.ndarray | None:
        """What a :class:`Frame` records as ``obstacle_centers``: :attr:`obstacle_centers`, or None in a scene without obstacles."""
        return self.obstacle_centers if self._colliders else None

    @property
    def obstacle_offsets(self) -> np.ndarray | None:
        """Each obstacle's displacement from where the scene put it [m],
        float64 ``[C, D]`` (the solver's float32 anchors' difference: exactly
        0 for an obstacle that stands there), or None while none is away. A
        frame's boundary particles of obstacle ``i`` are the scene's moved by
        row ``i`` (:meth:`~hybridmpm.scenes.ParticleSet.pad`); obstacles
        translate only, so this is the whole pose change."""
        if not self._colliders:
            return None
        pos = self.solver.collider_positions
        if np.array_equal(pos, self._anchors0):
            return None
        return pos.astype(np.float64) - self._anchors0.astype(np.float64)

    @property
    def obstacles_displaced(self) -> bool:
        """Whether an obstacle is away from where the scene put it (the
        network's boundary particles stand there: the hybrid runs MPM then)."""
        return self.obstacle_offsets is not None

    @property
    def obstacles_moving(self) -> bool:
        """Whether an obstacle moves in the next step: a pending
        :meth:`move_obstacle`, or a path whose centre changes over the step."""
        if self._moves:
            return True
        f0 = self.step_index * self.r_t
        for _, keys in self._paths:
            centres = [path_center(keys, (f0 + k) * self.dt_frame) for k in range(self.r_t + 1)]
            if any(not np.array_equal(a, b) for a, b in zip(centres, centres[1:])):
                return True
        return False

    @serialised
    def move_obstacle(self, index: int, center: Any, velocity: Any = None) -> None:
        """Move obstacle ``index`` (its place in the scene's ``obstacles``)
        during the next :meth:`advance`: its centre goes linearly in time
        from where it is to ``center`` [m] (``dim`` numbers inside the
        domain ``[0, 1]``), reached exactly at the step's end; its boundary
        condition pushes the fluid with ``velocity`` [m/s] (``dim`` numbers;
        None: the distance over the step's duration ``r_t · dt_frame``).
        Called again before the step, the last call wins; without a call the
        obstacle stays where it is. The one entry of an obstacle's motion
        from outside (the session's drag); a path of the scene file moves
        its obstacle itself. Translation only.

        Raises :class:`~hybridmpm.errors.InvalidInputError` naming ``index``
        (not an obstacle, or one that follows a keyframed path), ``center``
        or ``velocity``."""
        n = len(self._colliders)
        if n == 0:
            raise InvalidInputError("index: this scene has no obstacles", "index")
        i = check_int("index", index, 0, n - 1)
        if self._colliders[i].keyframes:
            raise InvalidInputError(f"index: obstacle {i} follows the keyframed path of its scene", "index")
        c = check_center("center", center, self.particles.dim)
        v = None if velocity is None else check_velocity("velocity", velocity, self.particles.dim)
        step_s = self.r_t * self.dt_frame
        dist = float(np.linalg.norm(c - self.obstacle_centers[i]))
        speed = dist / step_s
        # judged on the distance, within float32's rounding of the two centres (the unit box: 2·eps32 at most), so
        # a move at exactly the cap from the centre the solver reports is not refused for its last bit
        if dist > MAX_OBSTACLE_SPEED * step_s + 2.0 * float(np.finfo(np.float32).eps):
            raise InvalidInputError(
                f"center: {speed:.4g} m/s to get there in one step ({step_s * 1e3:.3g} ms); at most {MAX_OBSTACLE_SPEED:g} m/s (move it in smaller steps)",
                "center",
            )
        self._moves[i] = (c, v)

    def _anchor(self, i: int, center: np.ndarray) -> np.ndarray:
        """The solver's anchor of obstacle ``i`` with its centre at ``center``, float32 [D]."""
        c = self._colliders[i]
        if isinstance(c, SampledSdf):
            return (self._anchors0[i].astype(np.float64) + (center - obstacle_center(c))).astype(np.float32)
        return np.asarray(center, np.float32)

    def _move_for_frame(self, k: int, frame: int, start: np.ndarray) -> None:
        """Hand the solver the obstacles' moves for frame ``k`` (of ``r_t``)
        of this step, frame number ``frame``; ``start`` the solver's anchors at the step's start."""
        dt = self.dt_frame
        for i, keys in self._paths:
            c0, c1 = path_center(keys, frame * dt), path_center(keys, (frame + 1) * dt)
            end = self._anchor(i, c1)
            if np.array_equal(c0, c1) and np.array_equal(end, self.solver.collider_positions[i]):
                continue  # still: the static boundary condition
            self.solver.move_collider(i, end, ((c1 - c0) / dt).astype(np.float32))
        for i, (target, v) in self._moves.items():  # in the solver's float32 anchors: a move to where it is has velocity 0
            a, b = start[i].astype(np.float64), self._anchor(i, target).astype(np.float64)
            end = b if k == self.r_t - 1 else a + (b - a) * ((k + 1) / self.r_t)
            vel = (b - a) / self.dt_step if v is None else v
            self.solver.move_collider(i, end.astype(np.float32), vel.astype(np.float32))

    # ------------------------------------------------------------ rigid bodies
    @property
    def bodies(self) -> BodiesView:
        """The rigid bodies at the last frame's end (docs/bodies.md): centre,
        rotation, velocity, angular velocity, mass and the fluid's force and
        torque on each over the last frame (read-only arrays)."""
        return self.solver.bodies

    @serialised
    def add_body(self, body: Body | dict[str, Any]) -> int:
        """Add a rigid body (a :class:`~hybridmpm.mpm.bodies.Body` or its
        dict, as a scene file's ``[[bodies]]`` table) between steps; returns
        its index. Raises :class:`InvalidInputError` naming the field
        (``bodies[i].density``, ``bodies`` past the cap); nothing changes then.
        A mesh body's ``path`` is read relative to the working directory."""
        if isinstance(body, dict):
            body = resolve_mesh_body(body, f"bodies[{len(self.solver.params.bodies)}]", self.solver.dim, n_grid=self.solver.params.resolved_n_grid())
        steppable = self._steppable()
        i = self.solver.add_body(body)
        if steppable and not self._steppable():  # the body alone makes a frame need more than max_substeps
            b = self.solver.bodies
            speed = float(np.linalg.norm(b.velocity[i]))
            spin = float(np.linalg.norm(b.angular_velocity[i])) * bounding_radius(self.solver.params.bodies[i], self.solver.dim)
            key = f"bodies[{i}].{'velocity' if speed >= spin else 'angular_velocity'}"
            try:
                self.solver.substeps_for(self.dt_frame)
            except SimulationError as e:
                reason = str(e)
            self.solver.remove_body(i)
            raise InvalidInputError(f"{key}: the body is too fast for a frame on this grid: {reason}", key)
        self._frame = replace(self._frame, **self.frame_bodies())
        return i

    def _steppable(self) -> bool:
        """Whether the next frame needs at most ``max_substeps`` substeps (the CFL condition at the state now)."""
        try:
            self.solver.substeps_for(self.dt_frame)
        except SimulationError:
            return False
        return True

    @serialised
    def remove_body(self, index: int) -> None:
        """Remove body ``index`` between steps (the later ones move down one).
        Raises :class:`InvalidInputError` naming ``index``."""
        self.solver.remove_body(index)
        self._frame = replace(self._frame, **self.frame_bodies())

    def frame_bodies(self) -> dict[str, Any]:
        """What a :class:`Frame` records of the bodies (``body_center``,
        ``body_rotation``, ``body_mass``, float64), or nothing without bodies."""
        if not self.solver.params.bodies:
            return {}
        b = self.solver.bodies
        return {"body_center": np.array(b.center), "body_rotation": np.array(b.rotation), "body_mass": np.array(b.mass)}

    # ------------------------------------------------------------ stepping
    @serialised
    def advance(self) -> Frame:
        """Advance ``r_t`` frames; returns their :class:`Frame`. Raises
        :class:`~hybridmpm.errors.SimulationError` if a frame cannot be
        finished even with the smallest substep (the state is then that of
        the failing frame's start)."""
        t0 = time.perf_counter()
        retries = replans = substeps = 0
        controlled = False
        n, d = self.particles.num_fluid, self.particles.dim
        start = self.solver.collider_positions
        for k in range(self.r_t):
            if self._paths or self._moves:
                self._move_for_frame(k, self.step_index * self.r_t + k, start)
            if self._forcing is not None:
                acc = resolve_forcing(self._forcing, self.step_index * self.r_t + k, n, d, self._fluid_state)
                if acc is not None:
                    self._apply_acceleration(acc)
                    self._applied = controlled = True
                elif self._applied:
                    self._clear_forcing()
            st = self.solver.step_frame(self.dt_frame)
            retries += int(st.get("retries", 0))
            replans += int(st.get("replans", 0))
            substeps += int(st["substeps"])
        pos = self.fluid_positions
        self._moves.clear()
        self.step_index += 1
        self.stats.steps[MPM] += 1
        self.stats.mpm_retries += retries
        self.stats.mpm_replans += replans
        self._frame = Frame(
            self.step_index,
            self.step_index * self.r_t,
            self.step_index * self.dt_step,
            self.particles.pad(pos, self.obstacle_offsets),
            MPM,
            time.perf_counter() - t0,
            mpm_retries=retries,
            substeps=substeps,
            controlled=controlled,
            obstacle_centers=self.frame_centers(),
            **self.frame_bodies(),
        )
        return self._frame

    @serialised
    def load_history(self, history: np.ndarray, dt_step: float, **conversion: Any) -> dict[str, Any]:
        """Take over from the network: write the state of a fluid position
        history float32 [T ≥ 2, N, D] (one ``dt_step`` apart) into the solver
        (:func:`~hybridmpm.sim.convert.neural_to_mpm`, keyword arguments
        ``affine``, ``affine_radius``, ``volume_ratio``, ``velocity``); returns what was set."""
        return neural_to_mpm(self.solver, history, dt_step, **conversion)

    # ------------------------------------------------------------ checkpoint
    @serialised
    def state(self) -> dict[str, Any]:
        """The whole state (picklable dict): solver checkpoint (with the
        obstacles' poses), step counter, stats, an array forcing (a callable
        forcing is not saved) and the obstacle moves pending for the next step
        (``obstacle_moves``: a list of records ``{"index": int, "center":
        [D floats], "velocity": [D floats] or None}``, in the order they were
        given; plain JSON values, so the state survives a JSON round trip —
        the service's checkpoint — unchanged)."""
        return {
            "kind": self.kind,
            "version": _STATE_VERSION,
            "solver": self.solver.checkpoint(),
            "step_index": self.step_index,
            "stats": self.stats.to_dict(),
            "forcing": self._forcing.copy() if isinstance(self._forcing, np.ndarray) else None,
            "applied": self._applied,
            "obstacle_moves": [{"index": i, "center": c.tolist(), "velocity": None if v is None else v.tolist()} for i, (c, v) in self._moves.items()],
            "poured": list(self._pours),
        }

    @serialised
    def restore(self, state: dict[str, Any]) -> None:
        """Restore a :meth:`state` of a simulator of the same scene, taken
        before or after blocks were poured into it
        (:func:`hybridmpm.sim.pour.pour_block`): the simulator then holds the
        state's particles, the scene's own followed by the poured ones, and
        their parameter sets. The whole state is validated first (kind,
        version, the solver's particles — the scene's own by count, material
        and mass, at most :data:`~hybridmpm.sim.pour.MAX_POURED_TOTAL` in all,
        finite values inside the domain, parameter sets — ``step_index``
        within :data:`~hybridmpm.limits.MAX_FRAME_INDEX` frames, the
        forcing): raises :class:`InvalidInputError` (field ``state``…) or
        :class:`~hybridmpm.errors.CheckpointError` for a foreign or malformed
        state, and this simulator is then unchanged."""
        self.prepare_restore(state, poured=True)()

    def prepare_restore(self, state: dict[str, Any], poured: bool = False) -> Callable[[], None]:
        """Validate ``state`` whole without changing anything; returns the
        commit. With ``poured`` a state whose particles are the scene's plus
        poured blocks (or the scene's alone, after a pour) is accepted: a new
        solver is made and restored here; without it (a simulator inside
        another one) the particles must be the solver's own. The commit's only
        step that can fail is the solver's restore, which itself changes
        nothing unless it succeeds (so a commit that raises has changed nothing)."""
        with reading_state("MpmSimulator"):
            if not isinstance(state, dict) or state.get("kind") != self.kind or state.get("version") != _STATE_VERSION:
                raise InvalidInputError("state: not a state of an MpmSimulator of this version", "state")
            step = check_step_index("state.step_index", state["step_index"], self.r_t)
            stats = SimStats.from_dict(state["stats"])
            applied = state.get("applied", False)
            if not isinstance(applied, bool):
                raise InvalidInputError("state.applied: must be true or false", "state.applied")
            blob = state["solver"]
            if not isinstance(blob, (bytes, bytearray)):
                raise InvalidInputError("state.solver: must be the solver's checkpoint bytes", "state.solver")
            blob = bytes(blob)
            pours = self._check_pours(state.get("poured", []))  # absent from states saved before blocks were poured
            grown = self._poured_solver(blob, pours) if poured else None
            if grown is None:
                self.solver.check_restore(blob, same_particles=True)
                if pours != self._pours:
                    raise CheckpointError(f"state.poured: records blocks of {pours} particles, this simulator holds {self._pours}")
            n_fluid = self.particles.num_fluid if grown is None else self._presented(int(grown.num_particles))
            forcing = check_forcing(state["forcing"], n_fluid, self.particles.dim)
            moves = self._check_moves(state.get("obstacle_moves", {}))  # absent from states saved before obstacles moved

        def commit() -> None:
            if grown is None:
                self.solver.restore(blob, same_particles=True)
            else:
                self.adopt(grown, pours)
            self._moves = moves
            self.step_index = step
            self.stats = stats
            self._forcing = forcing
            self._applied = applied
            self._frame = Frame(step, step * self.r_t, step * self.dt_step, self.positions, MPM, obstacle_centers=self.frame_centers(), **self.frame_bodies())

        return commit

    def _check_pours(self, raw: Any) -> list[int]:
        """A state's ``poured`` (the particle count of each block poured, in
        order), checked: a list of at most :data:`~hybridmpm.sim.pour.MAX_POURED_TOTAL` ints,
        each in [1, :data:`~hybridmpm.sim.pour.MAX_POUR_PARTICLES`]. Raises
        :class:`InvalidInputError` naming ``state.poured``."""
        from hybridmpm.sim.pour import MAX_POUR_PARTICLES, MAX_POURED_TOTAL  # at call time: a test lowers the bounds

        field = "state.poured"
        if not isinstance(raw, (list, tuple)) or len(raw) > MAX_POURED_TOTAL:
            raise InvalidInputError(f"{field}: must be a list of the particle counts of the blocks poured", field)
        return [check_int(f"{field}[{k}]", c, 1, MAX_POUR_PARTICLES) for k, c in enumerate(raw)]

    def _poured_solver(self, blob: bytes, pours: list[int]) -> MpmSolver | None:
        """None when ``blob`` holds this solver's particles and parameters
        (the plain restore); else a new solver restored from it when it is a
        state of this scene with the blocks ``pours`` (their particle counts)
        poured after its particles, each of one material and set, or of this
        scene alone while this simulator holds poured blocks: the scene's
        solver parameters with the scene's parameter sets followed by any
        others, the scene's particles first (count, materials, masses), at
        most :data:`~hybridmpm.sim.pour.MAX_POURED_TOTAL` particles (the
        scene's own count where larger) within the solver's memory budget.
        Raises :class:`~hybridmpm.errors.CheckpointError` otherwise."""
        params, core, _ = MpmSolver.split_checkpoint(blob)
        n = core_particle_count(core, self.particles.dim)
        if n == self.solver.num_particles and params.to_dict() == self.solver.params.to_dict() and pours == self._pours and self._own_base():
            return None
        return self._grown_solver(blob, pours)

    def _presented(self, n_solver: int) -> int:
        """The particles :attr:`particles` counts for a solver of ``n_solver`` particles (the same, here)."""
        return n_solver

    def _own_base(self) -> bool:
        """Whether a state of this solver's particle count and parameters holds its particles, so that the plain
        restore checks it against them (a real-time simulator on merged particles says no: a state's groups are
        checked against the state's own base)."""
        return True

    def _grown_solver(self, blob: bytes, pours: list[int]) -> MpmSolver:
        """A new solver restored from ``blob`` after the checks of :meth:`_poured_solver` (the scene's
        parameters and particles, ``pours`` after them). Raises :class:`~hybridmpm.errors.CheckpointError`."""
        from hybridmpm.sim.pour import MAX_POURED_TOTAL  # at call time: a test lowers the bound

        params, core, _ = MpmSolver.split_checkpoint(blob)
        d = self.particles.dim
        n = core_particle_count(core, d)
        base = self._scene_params.to_dict()
        theirs = params.to_dict()
        sets0, sets = base.pop("sets", []), theirs.pop("sets", [])
        for key in ("num_threads", "bodies"):  # bodies added or removed since the scene's: the checkpoint's
            base.pop(key, None)
            theirs.pop(key, None)
        if base != theirs or sets[: len(sets0)] != sets0:
            diff = sorted(k for k in set(base) | set(theirs) if base.get(k) != theirs.get(k)) or ["sets"]
            raise CheckpointError(f"checkpoint was written with other solver parameters ({', '.join(diff)})")
        scene = self._scene_particles
        most = max(MAX_POURED_TOTAL, scene.num_fluid)
        if n > most:
            raise CheckpointError(f"checkpoint holds {n} particles, more than the {most} a simulator of this scene holds with poured blocks")
        check_leading_particles(core, d, np.asarray(scene.material), np.asarray(scene.masses, np.float32))
        check_poured_blocks(core, d, int(scene.num_fluid), pours)
        threads = int(self.solver.params.num_threads)
        if params.num_threads != threads:  # this simulator's threads (the same bits on any count): the header says so too
            blob = MpmSolver.with_header(blob, {"num_threads": threads})
            params = MpmSolver.split_checkpoint(blob)[0]
        out = MpmSolver(params, memory_budget=self.solver.memory_budget)
        out.restore(blob)
        return out

    @property
    def pours(self) -> list[int]:
        """The particle count of each block poured into it, in order."""
        return list(self._pours)

    @property
    def poured_particles(self) -> int:
        """The particles it holds beyond its scene's own (blocks poured into it)."""
        return int(self.solver.num_particles) - int(self._scene_particles.num_fluid)

    def adopt(self, solver: MpmSolver, pours: list[int]) -> None:
        """Run on ``solver`` from now on: this scene's particles followed by
        the blocks poured, ``pours`` particles each (:func:`hybridmpm.sim.pour.pour_block`,
        :meth:`restore`), in its parameter sets; the particle set, the scene's
        parameters and the current frame follow. Between steps."""
        self._pours = list(pours)
        self.solver = solver
        self.particles = self._particle_set(solver, self.particles)
        self.scene = replace(self.scene, params=solver.params)
        f = self._frame
        self._frame = Frame(f.step, f.frame_index, f.time, self.positions, f.solver, obstacle_centers=f.obstacle_centers, **self.frame_bodies())

    def _particle_set(self, solver: MpmSolver, old: ParticleSet) -> ParticleSet:
        """The particle set of ``solver``'s particles, with ``old``'s boundary particles."""
        material = np.asarray(solver.material, np.int32)
        fluid_types = np.array([GNS_TYPE_OF_MATERIAL[int(c)] for c in material], np.int64)
        return ParticleSet(
            int(solver.num_particles),
            old.boundary,
            np.concatenate([fluid_types, np.asarray(old.particle_type)[old.num_fluid :]]),
            material,
            np.asarray(solver.masses, np.float32),
            old.boundary_obstacle,
        )

    def _check_moves(self, raw: Any) -> dict[int, tuple[np.ndarray, np.ndarray | None]]:
        """A state's pending obstacle moves (its ``obstacle_moves``, absent
        from states saved before obstacles moved), checked as
        :meth:`move_obstacle` checks them: the list of records :meth:`state`
        writes, or the form states held before it — a mapping of obstacle
        index (an int, or its decimal string after a JSON round trip) to
        ``(center, velocity)``. Raises :class:`InvalidInputError` naming
        ``state.obstacle_moves…``."""
        field = "state.obstacle_moves"
        if isinstance(raw, dict):  # states written before the moves were a list
            records = []
            for key, value in raw.items():
                if isinstance(key, str) and key.isascii() and key.isdigit() and len(key) <= 6:
                    key = int(key)
                if not isinstance(value, (list, tuple)) or len(value) != 2:
                    raise InvalidInputError(f"{field}: bad move of obstacle {key!r} (expected [center, velocity])", field)
                records.append({"index": key, "center": value[0], "velocity": value[1]})
            raw = records
        if not isinstance(raw, (list, tuple)):
            raise InvalidInputError(f"{field}: must be a list of {{index, center, velocity}} records", field)
        out: dict[int, tuple[np.ndarray, np.ndarray | None]] = {}
        d = self.particles.dim
        for k, rec in enumerate(raw):
            if not isinstance(rec, dict) or set(rec) != {"index", "center", "velocity"}:
                raise InvalidInputError(f"{field}[{k}]: must be a record with exactly index, center and velocity", field)
            if not self._colliders:
                raise InvalidInputError(f"{field}[{k}]: this scene has no obstacles", field)
            i = check_int(f"{field}[{k}].index", rec["index"], 0, len(self._colliders) - 1)
            if self._colliders[i].keyframes:
                raise InvalidInputError(f"{field}[{k}].index: obstacle {i} follows the keyframed path of its scene", field)
            if i in out:
                raise InvalidInputError(f"{field}[{k}].index: obstacle {i} moved twice", field)
            c = check_center(f"{field}[{k}].center", rec["center"], d)
            v = None if rec["velocity"] is None else check_velocity(f"{field}[{k}].velocity", rec["velocity"], d)
            out[i] = (c, v)
        return out


__all__ = ["MpmSimulator", "probe_frame"]
