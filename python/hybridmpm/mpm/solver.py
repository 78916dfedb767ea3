"""The MLS-MPM solver from Python (:class:`MpmSolver`, over ``hybridmpm._core``) and the grid mass of a particle set."""

from __future__ import annotations

import json
import math
import struct
from dataclasses import replace
from typing import Any

import numpy as np

from hybridmpm import _core
from hybridmpm.conventions import DT_FRAME, MATERIAL_WATER
from hybridmpm.errors import CheckpointError, InvalidInputError
from hybridmpm.errors import as_f32 as _as_f32
from hybridmpm.files import loads_json
from hybridmpm.limits import human, memory_budget
from hybridmpm.limits import memory_budget as default_budget
from hybridmpm.mpm.bodies import BODY_STATE_LEN, BodiesView, Body
from hybridmpm.mpm.params import Collider, MaterialSet, MpmParams, SampledSdf

_MAGIC = b"HMPMPY01"
#: The Rust core's checkpoint: magic, u32 D, u64 N, f64 time, u64 frame (36 bytes), then the particles.
_CORE_MAGIC = b"HMPMCKP3"
#: The core format before parameter sets (no per-particle set; still restored).
_CORE_MAGIC_V2 = b"HMPMCKP2"
#: A projection solver inside a step that spans frames: v3's records, then the frames left in the step (u32).
_CORE_MAGIC_V4 = b"HMPMCKP4"
_CORE_HEADER = 36
#: The checkpoint header's key for the colliders' poses and pending moves (absent while none has moved).
_COLLIDER_STATE = "collider_state"
#: The checkpoint header's key for the bodies' exact states (float32 [B, 13] as JSON numbers; absent without bodies).
_BODY_STATE = "body_state"
_BODY_FORCE = "body_force"


class MpmSolver:
    """MLS-MPM solver on the unit domain (Hu et al. 2018).

    Parameters
    ----------
    params:
        :class:`MpmParams`; defaults give 2D water on a 128² grid.

    Per-particle arrays are float32: ``positions``, ``velocities``,
    ``external_acceleration`` ``[N, D]``; ``affine`` (APIC C),
    ``deformation_gradient`` (F), ``stress`` (Kirchhoff τ, read-only)
    ``[N, D, D]``; ``volume_ratio`` (J), ``masses``, ``volumes`` ``[N]``;
    ``material`` int32 ``[N]`` (0 water, 1 sand). Setting any of them validates
    the whole array (finite, inside the domain, physical) and raises
    :class:`~hybridmpm.errors.InvalidInputError` naming the field; nothing
    changes on error.

    Memory: ``memory_budget`` (bytes; default
    :func:`hybridmpm.limits.memory_budget` at construction) bounds what the
    inputs make the solver allocate. The block index of the grid
    (``8 · ⌈(n_grid + 2)/B + 1⌉^D`` bytes, B = 8 in 2D, 4 in 3D: 8.1 GiB for
    3D ``n_grid = 4096``) is refused at construction with
    :class:`~hybridmpm.errors.InvalidInputError` naming ``n_grid``, and
    particles beyond ``memory_budget / bytes_per_particle`` (525 B in 2D,
    906 B in 3D) by :meth:`add_particles` naming ``positions``; both say the
    size they would need. Colliders thinner than 2 cells (boxes) or of radius
    below 1.5 cells (spheres) are refused (``colliders[i].half_extents`` /
    ``colliders[i].radius``): particles would fall through them.

    Threads: one solver may be used from several threads. Every call holds
    the solver's lock for its duration (taken with the GIL released), so
    calls are serialised: a thread reading ``positions`` while another is in
    :meth:`step_frame` waits for that frame to finish and then sees the state
    at a frame boundary, never a frame in progress; nothing raises because
    another thread is using the solver. The lock is not fair, and a reader
    waits at most one frame per call.
    """

    def __init__(self, params: MpmParams | None = None, *, memory_budget: int | None = None) -> None:
        self.params = params if params is not None else MpmParams()
        budget = default_budget() if memory_budget is None else memory_budget
        self._core = _core.MpmSolver(self.params.to_dict(), memory_budget=budget)

    @property
    def memory_budget(self) -> int:
        """The memory budget of this solver [bytes] (fixed at construction)."""
        budget = self._core.memory_budget
        return int(budget) if budget is not None else 2**63 - 1

    @property
    def bytes_per_particle(self) -> int:
        """Estimated bytes the solver allocates per particle (the budget's unit for ``positions``)."""
        return int(self._core.bytes_per_particle)

    def add_parameter_set(self, group: MaterialSet) -> int:
        """Append ``group`` (a material's parameters: :class:`~hybridmpm.mpm.ElasticParams`, ...) to the table of
        parameter sets, in place: the particles, the clock and every other parameter are kept, and so is each
        particle's set index. Returns the new set's index in the table (a particle's ``material_set``: the five
        defaults, then ``params.sets``; a pour adds its block's set so, docs/materials.md). Raises
        :class:`~hybridmpm.errors.InvalidInputError` naming ``sets[k]``'s key, or ``sets`` beyond the table's
        size; the solver is then unchanged."""
        params = replace(self.params, sets=[*self.params.sets, group])  # the set checked, as a scene's sets are
        index = int(self._core.add_parameter_set(params.to_dict()["sets"][-1]))
        self.params = params
        return index

    # ------------------------------------------------------------- particles
    def add_particles(
        self,
        positions: np.ndarray,
        material: int | np.ndarray = MATERIAL_WATER,
        *,
        velocities: np.ndarray | None = None,
        masses: np.ndarray | None = None,
        volumes: np.ndarray | None = None,
        material_set: int | np.ndarray | None = None,
    ) -> int:
        """Append particles; returns the new particle count.

        ``positions`` [N, D] in ``[dx, 1 − dx]`` [m]; ``material`` a code or
        int array [N]; ``material_set`` the parameter set of each (an int or
        int array [N]: an index into the table of the material defaults, by
        code, then ``params.sets``; default: the material's own default set);
        ``velocities`` [N, D] [m/s]; ``masses`` [N] [kg];
        ``volumes`` [N] [m^D] (default ``(dx/2)^D``, 2 particles per cell per
        dimension; mass defaults to density × volume). Refused with
        :class:`~hybridmpm.errors.InvalidInputError` naming ``positions``
        when the particles would need more than the memory budget (checked
        before any conversion or copy).
        """
        shape = np.shape(positions)
        if len(shape) == 2:
            n = self.num_particles + int(shape[0])
            nbytes = n * self.bytes_per_particle
            if nbytes > self.memory_budget:
                raise InvalidInputError(
                    f"positions: {n} particles ({self.bytes_per_particle} bytes each) would need {human(nbytes)} ({nbytes} bytes), "
                    f"over the memory budget of {human(self.memory_budget)} (set HYBRIDMPM_MEMORY_BUDGET or call hybridmpm.limits.set_memory_budget to change it)",
                    "positions",
                )
        return int(
            self._core.add_particles(
                _as_f32("positions", positions),
                material,
                velocities=None if velocities is None else _as_f32("velocities", velocities),
                masses=None if masses is None else _as_f32("masses", masses),
                volumes=None if volumes is None else _as_f32("volumes", volumes),
                material_set=None if material_set is None else np.asarray(material_set),
            )
        )

    def remove_particles(self, mask: np.ndarray) -> int:
        """Remove particles where the bool ``mask`` [N] is True; returns the new count."""
        return int(self._core.remove_particles(np.asarray(mask)))

    def field(self, name: str) -> np.ndarray:
        """A copy of the per-particle field ``name`` (``positions``,
        ``velocities``, ``affine``, ``deformation_gradient``, ``volume_ratio``,
        ``volume_correction``, ``masses``, ``volumes``, ``external_acceleration``,
        ``stress``, ``material``, ``material_set``): what the properties below
        read, by name, for code that moves several fields alike (state
        conversion). Raises :class:`InvalidInputError` for an unknown name."""
        return self._core.get(name)  # type: ignore[no-any-return]

    def set_field(self, name: str, value: Any) -> None:
        """Set the float per-particle field ``name`` (as :meth:`field` names it)
        to ``value`` (its shape, cast to float32). Raises
        :class:`InvalidInputError` for an unknown name or a wrong shape."""
        self._core.set(name, _as_f32(name, value))

    positions = property(lambda self: self.field("positions"), lambda self, v: self.set_field("positions", v), doc="float32 [N, D], m")
    velocities = property(lambda self: self.field("velocities"), lambda self, v: self.set_field("velocities", v), doc="float32 [N, D], m/s")
    affine = property(lambda self: self.field("affine"), lambda self, v: self.set_field("affine", v), doc="APIC C, float32 [N, D, D], 1/s")
    deformation_gradient = property(
        lambda self: self.field("deformation_gradient"), lambda self, v: self.set_field("deformation_gradient", v), doc="elastic F, float32 [N, D, D]"
    )
    volume_ratio = property(lambda self: self.field("volume_ratio"), lambda self, v: self.set_field("volume_ratio", v), doc="J, float32 [N]")
    masses = property(lambda self: self.field("masses"), lambda self, v: self.set_field("masses", v), doc="float32 [N], kg")
    volumes = property(lambda self: self.field("volumes"), lambda self, v: self.set_field("volumes", v), doc="rest volume, float32 [N], m^D")
    external_acceleration = property(
        lambda self: self.field("external_acceleration"),
        lambda self, v: self.set_field("external_acceleration", v),
        doc="added to gravity, float32 [N, D], m/s²",
    )
    stress = property(lambda self: self.field("stress"), doc="Kirchhoff stress τ, float32 [N, D, D], Pa (read-only)")

    @property
    def material(self) -> np.ndarray:
        """int32 [N]: 0 water, 1 sand, 2 elastic, 3 snow, 4 viscoplastic
        (setting it puts each particle in its material's default set)."""
        return self.field("material")

    @material.setter
    def material(self, value: Any) -> None:
        self._core.set("material", np.asarray(value))

    @property
    def material_set(self) -> np.ndarray:
        """int32 [N]: each particle's parameter set (index into the table of
        the material defaults, by code, then ``params.sets``)."""
        return self.field("material_set")

    @material_set.setter
    def material_set(self, value: Any) -> None:
        self._core.set("material_set", np.asarray(value))

    # ------------------------------------------------------------- stepping
    @staticmethod
    def _check_dt_frame(dt_frame: Any) -> float:
        if isinstance(dt_frame, bool) or not isinstance(dt_frame, (int, float, np.integer, np.floating)) or not (math.isfinite(dt_frame) and 0 < dt_frame <= 1):
            raise InvalidInputError(f"dt_frame: must be a number in (0, 1] s, got {dt_frame!r}", "dt_frame")
        return float(dt_frame)

    def step_frame(self, dt_frame: float = DT_FRAME) -> dict[str, float]:
        """Advance one frame by as many substeps as the CFL condition needs.

        Returns ``{"substeps", "dt", "max_speed", "active_blocks", "retries"}``.
        A substep that leaves a state the solver would not accept (non-finite,
        a water particle's ``J ≤ 0``, a sand particle's ``det F ≤ 0``) or breaks
        the CFL condition restarts the frame with the substep halved; if even
        ``max_substeps`` substeps fail, raises
        :class:`~hybridmpm.errors.SimulationError` (with ``.substep``). A frame
        that would need more than ``max_substeps`` substeps (particles too
        fast, e.g. velocities of 1e30 m/s) raises ``SimulationError`` naming
        the speed. In both cases the state is that of the frame's start; a
        frame that returns leaves a state :meth:`restore` accepts.
        """
        return self._core.step_frame(self._check_dt_frame(dt_frame))  # type: ignore[no-any-return]

    def substeps_for(self, dt_frame: float = DT_FRAME) -> int:
        """Substeps the next :meth:`step_frame` would take: ``ceil(dt_frame /
        dt_max)``, ``dt_max = cfl·dx / (c + |v|max)``, or the fixed
        ``substeps``. Never capped or saturated: raises
        :class:`~hybridmpm.errors.SimulationError` (naming the particles'
        speed) when more than ``max_substeps`` would be needed, as
        :meth:`step_frame` would, and :class:`InvalidInputError` naming
        ``dt_frame`` unless it is in (0, 1] s."""
        return int(self._core.substeps_for(self._check_dt_frame(dt_frame)))

    # ------------------------------------------------------------- info
    @property
    def dim(self) -> int:
        return int(self._core.dim)

    @property
    def dx(self) -> float:
        return float(self._core.dx)

    @property
    def n_grid(self) -> int:
        return int(self._core.n_grid)

    @property
    def num_particles(self) -> int:
        return int(self._core.num_particles)

    @property
    def time(self) -> float:
        """Simulated time [s]."""
        return float(self._core.time)

    @property
    def frame(self) -> int:
        return int(self._core.frame)

    @property
    def mode_runs(self) -> tuple[int, int]:
        """Frame attempts so far, ``(alone, team)``: run by the calling thread
        alone or by the pool's team of threads. The solver picks the cheaper
        way as measured and now and then probes the other (docs/engine.md, "A
        busy machine"); every attempt runs alone with ``num_threads=1``. A
        benchmark reads it to tell a slow team from frames run alone."""
        alone, team = self._core.mode_runs
        return int(alone), int(team)

    @property
    def isa(self) -> str:
        """The compiled copy of the frame loop that runs: ``"x86-64-v3"``
        (AVX2/FMA; chosen when the CPU has it) or ``"baseline"`` (portable;
        also forced by ``HYBRIDMPM_ISA=baseline`` when the solver is made).
        Both give the same bits (docs/engine.md, "Two compiled copies")."""
        return str(self._core.isa)

    def set_isa(self, name: str) -> None:
        """Run the frame loop's copy ``name`` (see :attr:`isa`) from the next
        frame on, e.g. to time one against the other. Raises
        ``InvalidInputError`` (field ``isa``) for an unknown name or one this
        CPU cannot run."""
        self._core.set_isa(name)

    @property
    def domain_bounds(self) -> tuple[float, float]:
        """Valid particle coordinates ``[lo, hi]`` (one cell inside the unit domain)."""
        lo, hi = self._core.domain_bounds
        return float(lo), float(hi)

    # ------------------------------------------------------------- moving colliders
    @property
    def collider_positions(self) -> np.ndarray:
        """Each collider's anchor now [m], float32 ``[C, D]``: a
        :class:`~hybridmpm.mpm.Box`'s or :class:`~hybridmpm.mpm.Sphere`'s
        centre, a :class:`~hybridmpm.mpm.SampledSdf`'s ``origin``. ``params``
        keeps the colliders where they were made; this is where they are."""
        return np.asarray(self._core.collider_positions, np.float32)

    @property
    def collider_moves(self) -> list[tuple[int, list[float], list[float] | None]]:
        """The pending moves for the next frame: ``(index, position, velocity)``
        (see :meth:`move_collider`; ``velocity`` None: derived)."""
        return [(int(i), list(x), None if v is None else list(v)) for i, x, v in self._core.collider_moves]

    def move_collider(self, index: int, position: Any, velocity: Any = None) -> None:
        """Move collider ``index`` over the next :meth:`step_frame`: its anchor
        (:attr:`collider_positions`) goes linearly in time from where it is to
        ``position`` [m] (``D`` numbers), reached exactly at the frame's end,
        substep by substep; its boundary condition acts on the grid velocity
        relative to ``velocity`` [m/s] (``D`` numbers; None: the distance
        over ``dt_frame``, computed in float64), so it pushes the fluid. The
        move is used once: afterwards the collider rests at ``position``. A
        velocity of zero is the static collider's boundary condition, bit for
        bit. Only translation: the shape keeps its rotation. Raises
        :class:`~hybridmpm.errors.InvalidInputError` naming ``index``,
        ``position`` or ``velocity`` (not finite, a coordinate beyond 1000 m).
        The simulators' :meth:`~hybridmpm.sim.MpmSimulator.move_obstacle` is
        the call for an obstacle of a scene."""
        self._core.move_collider(index, _as_f32("position", position), None if velocity is None else _as_f32("velocity", velocity))

    def place_collider(self, index: int, position: Any) -> None:
        """Put collider ``index``'s anchor at ``position`` [m] now, at rest
        (no push), dropping its pending move (a restore). Raises
        :class:`~hybridmpm.errors.InvalidInputError` naming ``index`` or ``position``."""
        self._core.place_collider(index, _as_f32("position", position))

    def _collider_state(self) -> dict[str, Any] | None:
        """The colliders' poses and pending moves for :meth:`checkpoint`; None
        when every collider is where ``params`` made it and none moves (the
        checkpoint is then the one of a solver without moving colliders)."""
        if not self.params.colliders:
            return None
        pos = self.collider_positions
        moves = self.collider_moves
        if not moves and np.array_equal(pos, _initial_anchors(self.params.colliders, self.dim)):
            return None
        return {"positions": [[float(v) for v in row] for row in pos], "moves": [[i, x, v] for i, x, v in moves]}

    def _check_collider_state(self, cs: Any) -> tuple[np.ndarray, list[tuple[int, np.ndarray, np.ndarray | None]]]:
        """The poses and moves of a checkpoint's ``collider_state`` (None: the
        colliders where ``params`` made them), checked; raises :class:`CheckpointError`."""
        n, d = len(self.params.colliders), self.dim
        if cs is None:
            return _initial_anchors(self.params.colliders, d), []
        try:
            pos = np.asarray(cs["positions"], np.float32)
            moves = [(int(i), np.asarray(x, np.float32), None if v is None else np.asarray(v, np.float32)) for i, x, v in cs["moves"]]
        except (KeyError, TypeError, ValueError) as e:
            raise CheckpointError(f"bad collider state: {e}") from e
        ok = pos.shape == (n, d) and np.isfinite(pos).all() and np.abs(pos).max(initial=0.0) <= 1e3
        for i, x, v in moves:
            ok = ok and 0 <= i < n and x.shape == (d,) and bool(np.isfinite(x).all()) and np.abs(x).max() <= 1e3
            ok = ok and (v is None or (v.shape == (d,) and bool(np.isfinite(v).all())))
        if not ok:
            raise CheckpointError(f"bad collider state: expected the poses of {n} colliders in {d}D and their moves")
        return pos, moves

    def _set_collider_state(self, cs: tuple[np.ndarray, list[tuple[int, np.ndarray, np.ndarray | None]]]) -> None:
        pos, moves = cs
        for i, x in enumerate(pos):
            self._core.place_collider(i, np.ascontiguousarray(x))
        for i, x, v in moves:
            self._core.move_collider(i, x, v)

    # ------------------------------------------------------------- rigid bodies
    @property
    def bodies(self) -> BodiesView:
        """The rigid bodies now (docs/bodies.md): poses, velocities, masses
        and the fluid's force on each over the last frame (:class:`~hybridmpm.mpm.bodies.BodiesView`).
        ``params.bodies`` holds each as it was given."""
        return BodiesView.from_core(self._core.bodies(), self.dim)

    def add_body(self, body: Body | dict[str, Any]) -> int:
        """Add a rigid body (a :class:`~hybridmpm.mpm.bodies.Body` or its
        dict) between frames; returns its index. Raises
        :class:`~hybridmpm.errors.InvalidInputError` naming the field
        (``bodies[i].density``, ``bodies[i].center``: outside the walls,
        ``bodies[i].half_extents``: thinner than a cell, ``bodies`` past
        :data:`~hybridmpm.mpm.bodies.MAX_BODIES`); nothing changes then."""
        b = Body.from_dict(body, f"bodies[{len(self.params.bodies)}]", self.dim)
        i = int(self._core.add_body(b.to_dict()))
        self.params = replace(self.params, bodies=[*self.params.bodies, b])
        return i

    def remove_body(self, index: int) -> None:
        """Remove body ``index`` (the later ones move down one). Raises
        :class:`~hybridmpm.errors.InvalidInputError` naming ``index``."""
        self._core.remove_body(index)
        self.params = replace(self.params, bodies=[b for k, b in enumerate(self.params.bodies) if k != int(index)])

    def _check_body_state(self, bs: Any, n: int) -> np.ndarray | None:
        """A checkpoint's body states (None: the bodies as ``params`` gives them), float32 [n, 13]; raises :class:`CheckpointError`."""
        if bs is None:
            return None
        try:
            a = np.asarray(bs, np.float64)
        except (TypeError, ValueError) as e:
            raise CheckpointError(f"bad body state: {e}") from e
        f = a.astype(np.float32)
        if a.shape != (n, BODY_STATE_LEN) or not np.isfinite(a).all() or not np.array_equal(f.astype(np.float64), a):
            raise CheckpointError(f"bad body state: expected the float32 states of {n} bodies, {BODY_STATE_LEN} numbers each")
        for i, row in enumerate(f):  # the pose inside the walls, a unit rotation, a speed a frame can simulate
            try:
                self._core.check_body_state(i, np.ascontiguousarray(row))
            except InvalidInputError as e:
                raise CheckpointError(f"bad body state: {e}") from None
        return f

    def _set_body_state(self, states: np.ndarray | None) -> None:
        for i, row in enumerate([] if states is None else states):
            self._core.set_body_state(i, np.ascontiguousarray(row))

    def _body_force_lanes(self) -> list[list[float]]:
        """The fluid's last force and torque on each body as a checkpoint keeps them: 6 lanes (force x, y, z,
        torque x, y, z; 2D: force x, y and the torque in lane 5, the others 0)."""
        b = self._core.bodies()
        lanes = []
        for f, t in zip(b["force"], b["torque"]):
            row = [0.0] * 6
            row[: self.dim] = [float(v) for v in f]
            row[6 - len(t) :] = [float(v) for v in t]
            lanes.append(row)
        return lanes

    def _check_body_force(self, bf: Any, n: int) -> np.ndarray:
        """A checkpoint's last fluid forces on the bodies, float64 [n, 6] (zeros when absent: a checkpoint written
        before they were kept); raises :class:`CheckpointError`."""
        if bf is None:
            return np.zeros((n, 6))
        try:
            a = np.asarray(bf, np.float64)
        except (TypeError, ValueError) as e:
            raise CheckpointError(f"bad body force: {e}") from e
        if a.shape != (n, 6) or not np.isfinite(a).all():
            raise CheckpointError(f"bad body force: expected the forces on {n} bodies, 6 finite numbers each")
        return a

    def _set_body_force(self, forces: np.ndarray) -> None:
        for i, row in enumerate(forces):
            self._core.set_body_force(i, [float(v) for v in row])

    # ------------------------------------------------------------- checkpoint
    def checkpoint(self) -> bytes:
        """The whole state (parameters, particles, clock, the colliders'
        poses and pending moves when any has moved, and the bodies' exact
        states) as bytes."""
        head = self.params.to_dict()
        cs = self._collider_state()
        if cs is not None:
            head[_COLLIDER_STATE] = cs
        if self.params.bodies:
            head[_BODY_STATE] = [[float(v) for v in row] for row in self._core.bodies()["state"]]
            head[_BODY_FORCE] = self._body_force_lanes()
        header = json.dumps(head).encode()
        return _MAGIC + struct.pack("<Q", len(header)) + header + self._core.checkpoint()

    @classmethod
    def from_checkpoint(cls, blob: bytes) -> MpmSolver:
        """A new solver from :meth:`checkpoint` bytes. Raises :class:`CheckpointError`."""
        params, state, cs = cls.split_checkpoint(blob)
        sim = cls(params)
        poses = sim._check_collider_state(cs)
        bodies = sim._check_body_state(_body_state(blob), len(params.bodies))
        forces = sim._check_body_force(_body_state(blob, _BODY_FORCE), len(params.bodies))
        sim._core.restore(state)
        sim._set_collider_state(poses)
        sim._set_body_state(bodies)
        sim._set_body_force(forces)
        return sim

    def restore(self, blob: bytes, *, same_particles: bool = False) -> None:
        """Restore :meth:`checkpoint` bytes into this solver (parameters must
        match). With ``same_particles`` the checkpoint must also hold this
        solver's particles: the same count, and per particle the same material
        and mass (a simulator restoring its own state). The whole checkpoint
        is validated before anything changes: raises :class:`CheckpointError`
        (positions outside the domain, non-finite values, a truncated blob,
        other parameters or particles) and the solver is then unchanged."""
        state = self.check_restore(blob, same_particles=same_particles)
        poses = self._check_collider_state(self.split_checkpoint(blob)[2])
        bodies = self._check_body_state(_body_state(blob), len(self.params.bodies))
        forces = self._check_body_force(_body_state(blob, _BODY_FORCE), len(self.params.bodies))
        self._core.restore(state)
        self._set_collider_state(poses)
        self._set_body_state(bodies)
        self._set_body_force(forces)

    def restore_particles(self, blob: bytes) -> None:
        """Restore the particles of a :meth:`checkpoint` written by a solver
        of the same particles on another grid of the same domain: positions,
        velocities, APIC affine matrices, deformation and J, time and frame
        move bit for bit; this solver keeps its own grid (``n_grid`` and the
        wall band that keeps the walls' faces). Every other parameter must
        match and the particles must be this solver's (count, materials,
        masses). The colliders stay where they are. Raises
        :class:`CheckpointError` and leaves the solver unchanged otherwise."""
        params, state, _ = self.split_checkpoint(blob)
        mine, theirs = self.params.to_dict(), params.to_dict()
        for d in (mine, theirs):
            d.pop("n_grid")
            d["walls"] = {k: v for k, v in d["walls"].items() if k != "cells"}
            d.pop("num_threads", None)
        if mine != theirs:
            diff = sorted(k for k in set(mine) | set(theirs) if mine.get(k) != theirs.get(k))
            raise CheckpointError(f"checkpoint was written with other physics ({', '.join(diff)}); only the grid may differ")
        self._check_same_particles(state)
        self._core.restore(state)

    def check_restore(self, blob: bytes, *, same_particles: bool = False) -> bytes:
        """The checks of :meth:`restore` that need no new solver (format,
        parameters, and with ``same_particles`` the particles' count,
        materials and masses), changing nothing; returns the core's part of
        the blob. Raises :class:`CheckpointError`."""
        params, state, _ = self.split_checkpoint(blob)
        if params.to_dict() != self.params.to_dict():
            raise CheckpointError("checkpoint was written with different parameters; use MpmSolver.from_checkpoint")
        if same_particles:
            self._check_same_particles(state)
        return state

    def _check_same_particles(self, state: bytes) -> None:
        """Refuse a core state (the Rust part of :meth:`checkpoint`) whose
        particles are not this solver's: count, dimension, material and mass
        per particle."""
        n = core_particle_count(state, self.dim)
        n_self = self.num_particles
        if n != n_self:
            raise CheckpointError(f"checkpoint holds {n} particles in {self.dim}D, this solver {n_self} in {self.dim}D")
        check_leading_particles(state, self.dim, np.asarray(self.material), np.asarray(self.masses, np.float32))

    @staticmethod
    def split_checkpoint(blob: bytes) -> tuple[MpmParams, bytes, Any]:
        """A checkpoint's (:meth:`checkpoint`'s bytes) parameters, core state
        and collider state (None when absent). Raises :class:`CheckpointError`
        for bytes that are not one, a truncated or malformed header."""
        if not isinstance(blob, (bytes, bytearray)) or blob[:8] != _MAGIC or len(blob) < 16:
            raise CheckpointError("not a hybridmpm MpmSolver checkpoint")
        (n,) = struct.unpack("<Q", blob[8:16])
        if 16 + n > len(blob):
            raise CheckpointError("truncated checkpoint header")
        try:
            head = loads_json(blob[16 : 16 + n], "checkpoint")  # nesting checked before parsing
            cs = head.pop(_COLLIDER_STATE, None) if isinstance(head, dict) else None
            if isinstance(head, dict):
                head.pop(_BODY_STATE, None)  # read by _body_state
                head.pop(_BODY_FORCE, None)
            params = MpmParams.from_dict(head)
        except (ValueError, TypeError) as e:
            raise CheckpointError(f"bad parameter header: {e}") from e
        return params, bytes(blob[16 + n :]), cs

    @staticmethod
    def with_header(blob: bytes, updates: dict[str, Any]) -> bytes:
        """The checkpoint ``blob`` with the keys of ``updates`` replaced in its
        parameter header (the collider state and core state kept byte for
        byte), for restoring it into a solver of other threads or further
        parameter sets. Raises :class:`CheckpointError` as :meth:`split_checkpoint`."""
        MpmSolver.split_checkpoint(blob)  # the header checked whole first
        (n,) = struct.unpack("<Q", blob[8:16])
        head = {**loads_json(blob[16 : 16 + n], "checkpoint"), **updates}
        header = json.dumps(head).encode()
        return bytes(blob[:8]) + struct.pack("<Q", len(header)) + header + bytes(blob[16 + n :])


def _body_state(blob: bytes, key: str = _BODY_STATE) -> Any:
    """The bodies' states (``key`` ``body_force``: their last fluid forces) in a checkpoint's header (None when
    absent); the header checked by :meth:`MpmSolver.split_checkpoint` first."""
    (n,) = struct.unpack("<Q", blob[8:16])
    head = loads_json(blob[16 : 16 + n], "checkpoint")
    return head.get(key) if isinstance(head, dict) else None


def _core_records(state: bytes, dim: int) -> tuple[int, int, int]:
    """A core state's (the Rust part of :meth:`MpmSolver.checkpoint`: magic,
    u32 D, u64 N, f64 time, u64 frame, then fixed-size particle records)
    particle count, record size and trailing bytes per record (material, and
    set from v3; v4 ends with the frames left in a projection step), checked
    against its length. Raises :class:`CheckpointError`."""
    if len(state) < _CORE_HEADER or state[:8] not in (_CORE_MAGIC, _CORE_MAGIC_V2, _CORE_MAGIC_V4):
        raise CheckpointError("not a hybridmpm MPM checkpoint (bad magic)")
    tail = 1 if state[:8] == _CORE_MAGIC_V2 else 3
    trailer = 4 if state[:8] == _CORE_MAGIC_V4 else 0  # the frames left in a projection step
    per = 4 * (3 * dim + 3 * dim * dim + 4) + tail  # x, v, C, F, (J, vc, mass, volume), ext, τ (f32), material (u8), set (u16; not in v2)
    (dd,) = struct.unpack_from("<I", state, 8)
    (n,) = struct.unpack_from("<Q", state, 12)
    if dd != dim:
        raise CheckpointError(f"checkpoint holds particles in {dd}D, this solver is {dim}D")
    if len(state) != _CORE_HEADER + n * per + trailer:
        raise CheckpointError(f"checkpoint declares {n} particles but holds {len(state) - _CORE_HEADER - trailer} bytes of them")
    return int(n), per, tail


def core_particle_count(state: bytes, dim: int) -> int:
    """The particles a core state of a ``dim``-D solver holds (its format and length checked). Raises :class:`CheckpointError`."""
    return _core_records(state, dim)[0]


def check_leading_particles(state: bytes, dim: int, material: np.ndarray, masses: np.ndarray) -> None:
    """Refuse a core state whose first ``len(material)`` particles are not
    ones of this ``material`` (codes) and ``masses`` (float32), in order:
    a solver's own particles, followed by any others. Raises :class:`CheckpointError`."""
    n, per, tail = _core_records(state, dim)
    m = len(material)
    if n < m:
        raise CheckpointError(f"checkpoint holds {n} particles, fewer than the {m} expected")
    rec = np.frombuffer(state, np.uint8, m * per, _CORE_HEADER).reshape(m, per)
    mass_at = 4 * (2 * dim + 2 * dim * dim + 2)
    got = np.ascontiguousarray(rec[:, mass_at : mass_at + 4]).view("<f4")[:, 0]
    if not np.array_equal(rec[:, -tail], np.asarray(material).astype(np.uint8)):
        raise CheckpointError("checkpoint's particles are not this solver's (their materials differ)")
    if not np.array_equal(got, np.asarray(masses, np.float32)):
        raise CheckpointError("checkpoint's particles are not this solver's (their masses differ)")


def check_poured_blocks(state: bytes, dim: int, start: int, counts: list[int]) -> None:
    """Refuse a core state whose particles from ``start`` on are not
    ``counts`` blocks in order, each of one material and parameter set (a
    block poured whole: :func:`hybridmpm.sim.pour.pour_block`), with none
    left over. Raises :class:`CheckpointError`."""
    n, per, tail = _core_records(state, dim)
    if start + sum(counts) != n:
        raise CheckpointError(f"checkpoint holds {n - start} particles after its scene's {start}, its record of poured blocks {sum(counts)}")
    rec = np.frombuffer(state, np.uint8, (n - start) * per, _CORE_HEADER + start * per).reshape(n - start, per)
    kind = rec[:, per - tail :].astype(np.int64) @ (256 ** np.arange(tail, dtype=np.int64))  # material and set in one key
    at = 0
    for k, c in enumerate(counts):
        if c and not np.all(kind[at : at + c] == kind[at]):
            raise CheckpointError(f"checkpoint's poured block {k} mixes materials or parameter sets")
        at += c


def _initial_anchors(colliders: list[Collider], dim: int) -> np.ndarray:
    """Where ``params`` makes each collider: its anchor, float32 ``[C, D]``
    (a sampled shape's ``origin``, a box's or sphere's ``center``)."""
    rows = [c.origin if isinstance(c, SampledSdf) else c.center for c in colliders]
    return np.asarray([[float(v) for v in r] for r in rows], np.float32).reshape(len(colliders), dim)


def grid_mass(positions: np.ndarray, n_grid: int, masses: np.ndarray | None = None) -> np.ndarray:
    """Normalised grid mass (docs/design.md "Grid-mass error"; paper Sec. 3.1.1).

    p2g of particle mass (1/N each unless ``masses`` [N] is given) with
    quadratic B-spline weights onto nodes ``i/n_grid``, ``i ∈ [0, n_grid)^D``,
    normalised to sum 1. ``positions`` [N, D] float, D ∈ {2, 3}.
    Returns float32 of shape ``[n_grid] * D``.

    ``n_grid`` must be an integer in [3, 4096] (``64.5``, ``"64"`` and
    ``True`` are refused) whose grid, 12 bytes per node (``12 · n_grid^D``:
    192 MiB for 2D 4096, 12 GiB for 3D 1024), fits the memory budget
    (:func:`hybridmpm.limits.memory_budget`); otherwise
    :class:`~hybridmpm.errors.InvalidInputError` naming ``n_grid`` and the
    size it would need, before anything is allocated.
    """

    if isinstance(n_grid, bool) or not isinstance(n_grid, (int, np.integer)):
        raise InvalidInputError(f"n_grid: must be an integer in [3, 4096], got {n_grid!r}", "n_grid")
    return _core.grid_mass(  # type: ignore[no-any-return]
        _as_f32("positions", positions), int(n_grid), None if masses is None else _as_f32("masses", masses), memory_budget=memory_budget()
    )
