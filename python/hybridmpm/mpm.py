"""Typed Python API over the Rust MLS-MPM solver.

The solver is MLS-MPM (Hu et al. 2018, "A moving least squares material point
method ...", APIC transfers, quadratic B-splines) on the unit domain
``[0, 1]^D`` with ``n_grid`` cells per dimension. Materials: weakly
compressible water (Kirchhoff stress ``τ = K·J·(J−1)·I``) and Drucker–Prager
sand (Klár et al. 2016, Hencky strain, SVD return mapping; in 2D the cone is
matched to plane-strain Mohr–Coulomb, ``α = sin φ / √2``). Units are SI.

Example
-------
>>> import numpy as np
>>> from hybridmpm.conventions import MATERIAL_WATER
>>> from hybridmpm.mpm import MpmParams, MpmSolver
>>> sim = MpmSolver(MpmParams(dim=2))
>>> x = np.random.default_rng(0).uniform(0.3, 0.5, (500, 2)).astype(np.float32)
>>> sim.add_particles(x, MATERIAL_WATER)
500

Frames are advanced by the simulators of :mod:`hybridmpm.sim`
(:class:`~hybridmpm.sim.MpmSimulator` wraps this solver; ``rollout`` is the
one frame loop), which call :meth:`MpmSolver.step_frame`.
"""

from __future__ import annotations

import json
import math
import struct
from collections.abc import Sequence
from dataclasses import asdict, dataclass, field
from typing import Any, Literal

import numpy as np

from hybridmpm import _core
from hybridmpm.conventions import DT_FRAME, MATERIAL_WATER
from hybridmpm.errors import CheckpointError, InvalidInputError
from hybridmpm.errors import as_f32 as _as_f32
from hybridmpm.limits import human, memory_budget
from hybridmpm.limits import memory_budget as default_budget

Condition = Literal["sticky", "slip", "separate"]

#: The solver's defaults by dimension, from the Rust core
#: (:func:`hybridmpm._core.default_params`: ``SolverParams::default()``), in
#: the form of :meth:`MpmParams.to_dict`. The dataclass defaults below are
#: these values: the parameters are defined once, in Rust.
_DEFAULTS: dict[int, dict[str, Any]] = {dim: _core.default_params(dim) for dim in (2, 3)}
#: A collider's defaults (``condition``, ``friction``), from the Rust core.
_COLLIDER_DEFAULTS: dict[str, Any] = _core.default_collider()
_SOLVER = _DEFAULTS[2]  # the fields below are the same in 3D (tests/test_one_schema.py)
_WATER, _SAND, _WALLS = _SOLVER["water"], _SOLVER["sand"], _SOLVER["walls"]


@dataclass
class WaterParams:
    """Weakly compressible water. ``density`` ρ [kg/m³], ``bulk_modulus`` K [Pa]
    (sound speed ``sqrt(K/ρ)``, default 20 m/s), ``viscosity`` η [Pa·s].
    Defaults are the Rust core's (``WaterParams::default()``)."""

    density: float = _WATER["density"]
    bulk_modulus: float = _WATER["bulk_modulus"]
    viscosity: float = _WATER["viscosity"]


@dataclass
class SandParams:
    """Drucker–Prager sand. ``youngs_modulus`` E [Pa], ``poisson_ratio`` ν,
    ``friction_angle_deg`` φ [°], ``cohesion`` c [Pa] (cone apex at mean
    stress ``c / tan φ``), ``density`` ρ [kg/m³]. Defaults are the Rust
    core's (``SandParams::default()``)."""

    density: float = _SAND["density"]
    youngs_modulus: float = _SAND["youngs_modulus"]
    poisson_ratio: float = _SAND["poisson_ratio"]
    friction_angle_deg: float = _SAND["friction_angle_deg"]
    cohesion: float = _SAND["cohesion"]


#: Wall faces by axis and side: ``x-`` is x = 0, ``x+`` x = 1, ``y-`` the floor
#: (y is up), ``y+`` the ceiling, ``z-`` / ``z+`` (3D only).
WALL_FACES = ("x-", "x+", "y-", "y+", "z-", "z+")
_CONDITIONS = ("sticky", "slip", "separate")


@dataclass
class WallFace:
    """Override for one wall face: its boundary ``condition`` and/or Coulomb
    ``friction`` μ; a field left ``None`` keeps the all-walls value."""

    condition: Condition | None = None
    friction: float | None = None

    def to_dict(self) -> dict[str, Any]:
        d: dict[str, Any] = {}
        if self.condition is not None:
            d["condition"] = self.condition
        if self.friction is not None:
            d["friction"] = float(self.friction)
        return d


@dataclass
class WallParams:
    """Domain walls: a band of ``cells`` grid cells inside every face of the
    unit domain, with a boundary ``condition`` (``"sticky"``: no slip,
    ``"slip"``: no normal motion, ``"separate"``: may leave the wall, with
    Coulomb friction) and friction μ (used by ``separate``), for all faces.

    ``faces`` overrides them per face: ``{"y-": WallFace(friction=0.6)}``
    (a dict ``{"friction": 0.6}`` works too). Face names are
    :data:`WALL_FACES`; ``y-`` is the floor (y is up), ``z-``/``z+`` exist
    in 3D only. A rough floor with slipping side walls, the usual
    granular-collapse setup::

        WallParams(condition="slip", faces={"y-": WallFace("separate", 0.6)})

    Defaults are the Rust core's (``WallParams::default()``).
    """

    cells: int = _WALLS["cells"]
    condition: Condition = _WALLS["condition"]
    friction: float = _WALLS["friction"]
    faces: dict[str, WallFace] = field(default_factory=dict)

    def face(self, name: str) -> tuple[str, float]:
        """The ``(condition, friction)`` in force on face ``name``."""
        f = _wall_face(f"walls.faces.{name}", self.faces.get(name, WallFace()))
        return (f.condition or self.condition, float(self.friction if f.friction is None else f.friction))

    def validate(self, dim: int | None = None) -> None:
        """Check every field; raises :class:`InvalidInputError` naming it
        (e.g. ``walls.faces.y-.friction``). ``dim`` also rejects z faces in 2D."""
        if isinstance(self.cells, bool) or not isinstance(self.cells, (int, np.integer)) or self.cells < 2:
            raise InvalidInputError(f"walls.cells: must be an integer >= 2, got {self.cells!r}", "walls.cells")
        _check_condition("walls.condition", self.condition)
        _check_friction("walls.friction", self.friction)
        if not isinstance(self.faces, dict):
            raise InvalidInputError("walls.faces: expected a mapping of face name to {condition, friction}", "walls.faces")
        names = WALL_FACES[: 2 * dim] if dim in (2, 3) else WALL_FACES
        for name, face in self.faces.items():
            if name not in names:
                where = f" in {dim}D" if dim in (2, 3) else ""
                raise InvalidInputError(
                    f"walls.faces.{name}: unknown wall face{where} (allowed: {', '.join(names)}; y- is the floor)",
                    f"walls.faces.{name}",
                )
            _wall_face(f"walls.faces.{name}", face)

    def to_dict(self, dim: int | None = None) -> dict[str, Any]:
        """Plain dict (validated): ``faces`` only when some face is overridden,
        in the order of :data:`WALL_FACES`."""
        self.validate(dim)
        d: dict[str, Any] = {"cells": int(self.cells), "condition": self.condition, "friction": float(self.friction)}
        if self.faces:
            d["faces"] = {n: _wall_face(f"walls.faces.{n}", self.faces[n]).to_dict() for n in WALL_FACES if n in self.faces}
        return d

    @classmethod
    def from_dict(cls, d: dict[str, Any], dim: int | None = None) -> WallParams:
        """Inverse of :meth:`to_dict`; validates (errors name the field)."""
        if not isinstance(d, dict):
            raise InvalidInputError("walls: expected a table/object", "walls")
        unknown = sorted(set(d) - {"cells", "condition", "friction", "faces"})
        if unknown:
            raise InvalidInputError(f"walls.{unknown[0]}: unknown wall parameter (allowed: cells, condition, friction, faces)", f"walls.{unknown[0]}")
        faces_raw = d.get("faces") or {}
        if not isinstance(faces_raw, dict):
            raise InvalidInputError("walls.faces: expected a mapping of face name to {condition, friction}", "walls.faces")
        default = cls()
        walls = cls(
            cells=d.get("cells", default.cells),
            condition=d.get("condition", default.condition),
            friction=d.get("friction", default.friction),
            faces={str(k): _wall_face(f"walls.faces.{k}", v) for k, v in faces_raw.items()},
        )
        walls.validate(dim)
        return walls


def _check_condition(name: str, c: Any) -> None:
    if c not in _CONDITIONS:
        raise InvalidInputError(f"{name}: must be one of 'sticky', 'slip', 'separate', got {c!r}", name)


def _check_friction(name: str, mu: Any) -> None:
    if isinstance(mu, bool) or not isinstance(mu, (int, float, np.integer, np.floating)) or not math.isfinite(mu):
        raise InvalidInputError(f"{name}: must be a finite number, got {mu!r}", name)
    if mu < 0:
        raise InvalidInputError(f"{name}: must be >= 0, got {mu!r}", name)


def _wall_face(name: str, v: Any) -> WallFace:
    """A validated :class:`WallFace` from a ``WallFace`` or a dict."""
    if isinstance(v, dict):
        extra = sorted(set(v) - {"condition", "friction"})
        if extra:
            raise InvalidInputError(f"{name}.{extra[0]}: unknown wall-face parameter (allowed: condition, friction)", f"{name}.{extra[0]}")
        v = WallFace(condition=v.get("condition"), friction=v.get("friction"))
    if not isinstance(v, WallFace):
        raise InvalidInputError(f"{name}: expected a table/object with 'condition' and/or 'friction', got {v!r}", name)
    if v.condition is not None:
        _check_condition(f"{name}.condition", v.condition)
    if v.friction is not None:
        _check_friction(f"{name}.friction", v.friction)
    return v


@dataclass
class Box:
    """Static box collider: ``center``, ``half_extents`` [m]; rotated by
    ``angle_deg`` (2D) or a 3×3 ``rotation`` matrix (3D) — a rotated box is a ramp.
    Must be at least 2 grid cells thick. ``condition`` and ``friction``
    default to the Rust core's (``ColliderParams::default()``)."""

    center: Sequence[float]
    half_extents: Sequence[float]
    angle_deg: float | None = None
    rotation: Sequence[Sequence[float]] | None = None
    condition: Condition = _COLLIDER_DEFAULTS["condition"]
    friction: float = _COLLIDER_DEFAULTS["friction"]

    def to_dict(self) -> dict[str, Any]:
        d: dict[str, Any] = {
            "shape": "box",
            "center": [float(c) for c in self.center],
            "half_extents": [float(h) for h in self.half_extents],
            "condition": self.condition,
            "friction": float(self.friction),
        }
        if self.angle_deg is not None:
            d["angle_deg"] = float(self.angle_deg)
        if self.rotation is not None:
            d["rotation"] = [[float(v) for v in row] for row in self.rotation]
        return d


@dataclass
class Sphere:
    """Static sphere (circle in 2D) collider: ``center``, ``radius`` [m].
    ``condition`` and ``friction`` default to the Rust core's (``ColliderParams::default()``)."""

    center: Sequence[float]
    radius: float
    condition: Condition = _COLLIDER_DEFAULTS["condition"]
    friction: float = _COLLIDER_DEFAULTS["friction"]

    def to_dict(self) -> dict[str, Any]:
        return {
            "shape": "sphere",
            "center": [float(c) for c in self.center],
            "radius": float(self.radius),
            "condition": self.condition,
            "friction": float(self.friction),
        }


@dataclass
class MpmParams:
    """All solver parameters (see the Rust ``SolverParams`` for the ranges).

    ``substeps=None`` lets the CFL condition ``dt ≤ cfl·dx/(c + |v|max)`` pick
    the substep count of each frame; an int fixes it. Defaults are the Rust
    core's (``SolverParams::default()``, as a dict
    ``hybridmpm._core.default_params(dim)``): ``n_grid=None`` and
    ``gravity=None`` [m/s², ``dim`` numbers] take those of ``dim``.
    """

    dim: int = 2
    n_grid: int | None = None
    gravity: Sequence[float] | None = None
    cfl: float = _SOLVER["cfl"]
    substeps: int | None = _SOLVER["substeps"]
    max_substeps: int = _SOLVER["max_substeps"]
    num_threads: int = _SOLVER["num_threads"]
    water: WaterParams = field(default_factory=WaterParams)
    sand: SandParams = field(default_factory=SandParams)
    walls: WallParams = field(default_factory=WallParams)
    colliders: list[Box | Sphere] = field(default_factory=list)

    def resolved_n_grid(self) -> int:
        self._check_int("n_grid", self.n_grid, optional=True)
        return int(self.n_grid) if self.n_grid is not None else int(_DEFAULTS.get(self.dim, _DEFAULTS[2])["n_grid"])

    def resolved_gravity(self) -> np.ndarray:
        """Gravity [m/s²], float64 ``[dim]``: ``gravity``, or the engine's
        default for ``dim`` when it is None (what the solver applies)."""
        return np.asarray(self.to_dict()["gravity"], np.float64)

    @staticmethod
    def _check_int(name: str, v: Any, *, optional: bool = False) -> None:
        """An integer (``int`` or numpy integer; not a bool, a float such as
        ``64.5`` or ``64.0``, or a string such as ``"64"``), else
        :class:`InvalidInputError` naming ``name``."""
        if v is None and optional:
            return
        if isinstance(v, bool) or not isinstance(v, (int, np.integer)):
            what = "an integer or None" if optional else "an integer"
            raise InvalidInputError(f"{name}: must be {what}, got {v!r}", name)

    @staticmethod
    def _check_number(name: str, v: Any) -> None:
        """A real number (not a bool or a string); the range is the solver's to check."""
        if isinstance(v, bool) or not isinstance(v, (int, float, np.integer, np.floating)):
            raise InvalidInputError(f"{name}: must be a number, got {v!r}", name)

    def validate(self) -> None:
        """Check the type of every field: integer parameters (``dim``,
        ``n_grid``, ``substeps``, ``max_substeps``, ``num_threads``,
        ``walls.cells``) must be integers — ``64.5``, ``64.0``, ``"64"`` and
        ``True`` are refused, not coerced — and real parameters numbers.
        Raises :class:`InvalidInputError` naming the field. Ranges (``n_grid``
        in [16, 4096], ``cfl`` in (0, 1], ...) are checked by the solver,
        which names the field too."""
        if isinstance(self.dim, bool) or not isinstance(self.dim, (int, np.integer)) or self.dim not in (2, 3):
            raise InvalidInputError(f"dim: must be 2 or 3, got {self.dim!r}", "dim")
        self._check_int("n_grid", self.n_grid, optional=True)
        self._check_int("substeps", self.substeps, optional=True)
        self._check_int("max_substeps", self.max_substeps)
        self._check_int("num_threads", self.num_threads)
        self._check_number("cfl", self.cfl)
        if self.gravity is not None:
            if isinstance(self.gravity, (str, bytes, dict)) or not isinstance(self.gravity, (Sequence, np.ndarray)) or len(self.gravity) != self.dim:
                raise InvalidInputError(f"gravity: must be a list of {self.dim} numbers, got {self.gravity!r}", "gravity")
            for i, g in enumerate(self.gravity):
                self._check_number(f"gravity[{i}]", g)
        for name, group, cls in (("water", self.water, WaterParams), ("sand", self.sand, SandParams)):
            if not isinstance(group, cls):
                raise InvalidInputError(f"{name}: must be a {cls.__name__}, got {group!r}", name)
            for key, value in asdict(group).items():
                self._check_number(f"{name}.{key}", value)
        if not isinstance(self.walls, WallParams):
            raise InvalidInputError(f"walls: must be a WallParams, got {self.walls!r}", "walls")
        self.walls.validate(self.dim)
        if not isinstance(self.colliders, (list, tuple)):
            raise InvalidInputError(f"colliders: must be a list of Box / Sphere, got {self.colliders!r}", "colliders")
        for i, c in enumerate(self.colliders):
            if not isinstance(c, (Box, Sphere)):
                raise InvalidInputError(f"colliders[{i}]: must be a Box or a Sphere, got {c!r}", f"colliders[{i}]")

    def to_dict(self) -> dict[str, Any]:
        """The plain dict the Rust binding takes (JSON-serialisable); validated
        first (:meth:`validate`)."""
        self.validate()
        gravity = list(self.gravity) if self.gravity is not None else _DEFAULTS[self.dim]["gravity"]
        return {
            "dim": int(self.dim),
            "n_grid": self.resolved_n_grid(),
            "gravity": [float(g) for g in gravity],
            "cfl": float(self.cfl),
            "substeps": None if self.substeps is None else int(self.substeps),
            "max_substeps": int(self.max_substeps),
            "num_threads": int(self.num_threads),
            "water": asdict(self.water),
            "sand": asdict(self.sand),
            "walls": self.walls.to_dict(self.dim),
            "colliders": [c.to_dict() for c in self.colliders],
        }

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> MpmParams:
        """Inverse of :meth:`to_dict`; validates (errors name the field)."""
        if not isinstance(d, dict):
            raise InvalidInputError(f"params: expected a dict, got {d!r}", "params")
        d = dict(d)

        def build(name: str, factory: Any, kwargs: Any) -> Any:
            if not isinstance(kwargs, dict):
                raise InvalidInputError(f"{name}: expected a dict, got {kwargs!r}", name)
            allowed = set(factory.__dataclass_fields__)
            unknown = sorted(set(kwargs) - allowed, key=str)
            if unknown:
                raise InvalidInputError(f"{name}.{unknown[0]}: unknown parameter (allowed: {', '.join(sorted(allowed))})", f"{name}.{unknown[0]}")
            return factory(**kwargs)

        raw_cols = d.pop("colliders", []) or []
        if not isinstance(raw_cols, (list, tuple)):
            raise InvalidInputError(f"colliders: expected a list, got {raw_cols!r}", "colliders")
        cols: list[Box | Sphere] = []
        for i, c in enumerate(raw_cols):
            if not isinstance(c, dict):
                raise InvalidInputError(f"colliders[{i}]: expected a dict, got {c!r}", f"colliders[{i}]")
            c = dict(c)
            shape = c.pop("shape", None)
            if shape == "box":
                cols.append(build(f"colliders[{i}]", Box, c))
            elif shape in ("sphere", "circle"):
                cols.append(build(f"colliders[{i}]", Sphere, c))
            else:
                raise InvalidInputError(f"colliders[{i}].shape: must be 'box' or 'sphere', got {shape!r}", f"colliders[{i}].shape")
        water = build("water", WaterParams, d.pop("water", {}))
        sand = build("sand", SandParams, d.pop("sand", {}))
        walls = WallParams.from_dict(d.pop("walls", None) or {}, dim=d.get("dim", 2))
        top = set(cls.__dataclass_fields__) - {"water", "sand", "walls", "colliders"}
        unknown = sorted(set(d) - top, key=str)
        if unknown:
            raise InvalidInputError(f"{unknown[0]}: unknown parameter (allowed: {', '.join(sorted(top))})", str(unknown[0]))
        params = cls(water=water, sand=sand, walls=walls, colliders=cols, **d)
        params.validate()
        return params


_MAGIC = b"HMPMPY01"
#: The Rust core's checkpoint: magic, u32 D, u64 N, f64 time, u64 frame (36 bytes), then the particles.
_CORE_MAGIC = b"HMPMCKP2"
_CORE_HEADER = 36


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

    # ------------------------------------------------------------- particles
    def add_particles(
        self,
        positions: np.ndarray,
        material: int | np.ndarray = MATERIAL_WATER,
        *,
        velocities: np.ndarray | None = None,
        masses: np.ndarray | None = None,
        volumes: np.ndarray | None = None,
    ) -> int:
        """Append particles; returns the new particle count.

        ``positions`` [N, D] in ``[dx, 1 − dx]`` [m]; ``material`` a code or
        int array [N]; ``velocities`` [N, D] [m/s]; ``masses`` [N] [kg];
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
            )
        )

    def remove_particles(self, mask: np.ndarray) -> int:
        """Remove particles where the bool ``mask`` [N] is True; returns the new count."""
        return int(self._core.remove_particles(np.asarray(mask)))

    def _get(self, name: str) -> np.ndarray:
        return self._core.get(name)  # type: ignore[no-any-return]

    def _set(self, name: str, value: Any) -> None:
        self._core.set(name, _as_f32(name, value))

    positions = property(lambda self: self._get("positions"), lambda self, v: self._set("positions", v), doc="float32 [N, D], m")
    velocities = property(lambda self: self._get("velocities"), lambda self, v: self._set("velocities", v), doc="float32 [N, D], m/s")
    affine = property(lambda self: self._get("affine"), lambda self, v: self._set("affine", v), doc="APIC C, float32 [N, D, D], 1/s")
    deformation_gradient = property(
        lambda self: self._get("deformation_gradient"), lambda self, v: self._set("deformation_gradient", v), doc="elastic F, float32 [N, D, D]"
    )
    volume_ratio = property(lambda self: self._get("volume_ratio"), lambda self, v: self._set("volume_ratio", v), doc="J, float32 [N]")
    masses = property(lambda self: self._get("masses"), lambda self, v: self._set("masses", v), doc="float32 [N], kg")
    volumes = property(lambda self: self._get("volumes"), lambda self, v: self._set("volumes", v), doc="rest volume, float32 [N], m^D")
    external_acceleration = property(
        lambda self: self._get("external_acceleration"),
        lambda self, v: self._set("external_acceleration", v),
        doc="added to gravity, float32 [N, D], m/s²",
    )
    stress = property(lambda self: self._get("stress"), doc="Kirchhoff stress τ, float32 [N, D, D], Pa (read-only)")

    @property
    def material(self) -> np.ndarray:
        """int32 [N]: 0 water, 1 sand."""
        return self._get("material")

    @material.setter
    def material(self, value: Any) -> None:
        self._core.set("material", np.asarray(value))

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

    # ------------------------------------------------------------- checkpoint
    def checkpoint(self) -> bytes:
        """The whole state (parameters, particles, clock) as bytes."""
        header = json.dumps(self.params.to_dict()).encode()
        return _MAGIC + struct.pack("<Q", len(header)) + header + self._core.checkpoint()

    @classmethod
    def from_checkpoint(cls, blob: bytes) -> MpmSolver:
        """A new solver from :meth:`checkpoint` bytes. Raises :class:`CheckpointError`."""
        params, state = cls._split(blob)
        sim = cls(params)
        sim._core.restore(state)
        return sim

    def restore(self, blob: bytes, *, same_particles: bool = False) -> None:
        """Restore :meth:`checkpoint` bytes into this solver (parameters must
        match). With ``same_particles`` the checkpoint must also hold this
        solver's particles: the same count, and per particle the same material
        and mass (a simulator restoring its own state). The whole checkpoint
        is validated before anything changes: raises :class:`CheckpointError`
        (positions outside the domain, non-finite values, a truncated blob,
        other parameters or particles) and the solver is then unchanged."""
        self._core.restore(self.check_restore(blob, same_particles=same_particles))

    def restore_particles(self, blob: bytes) -> None:
        """Restore the particles of a :meth:`checkpoint` written by a solver
        of the same particles on another grid of the same domain: positions,
        velocities, APIC affine matrices, deformation and J, time and frame
        move bit for bit; this solver keeps its own grid (``n_grid`` and the
        wall band that keeps the walls' faces). Every other parameter must
        match and the particles must be this solver's (count, materials,
        masses). Raises :class:`CheckpointError` and leaves the solver
        unchanged otherwise."""
        params, state = self._split(blob)
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
        params, state = self._split(blob)
        if params.to_dict() != self.params.to_dict():
            raise CheckpointError("checkpoint was written with different parameters; use MpmSolver.from_checkpoint")
        if same_particles:
            self._check_same_particles(state)
        return state

    def _check_same_particles(self, state: bytes) -> None:
        """Refuse a core state (the Rust part of :meth:`checkpoint`: magic,
        u32 D, u64 N, f64 time, u64 frame, then fixed-size particle records)
        whose particles are not this solver's: count, dimension, material and
        mass per particle."""
        d = self.dim
        per = 4 * (3 * d + 3 * d * d + 4) + 1  # x, v, C, F, (J, vc, mass, volume), ext, τ (f32), material (u8)
        if len(state) < _CORE_HEADER or state[:8] != _CORE_MAGIC:
            raise CheckpointError("not a hybridmpm MPM checkpoint (bad magic)")
        (dd,) = struct.unpack_from("<I", state, 8)
        (n,) = struct.unpack_from("<Q", state, 12)
        n_self = self.num_particles
        if dd != d or n != n_self:
            raise CheckpointError(f"checkpoint holds {n} particles in {dd}D, this solver {n_self} in {d}D")
        if len(state) != _CORE_HEADER + n * per:
            raise CheckpointError(f"checkpoint declares {n} particles but holds {len(state) - _CORE_HEADER} bytes of them")
        rec = np.frombuffer(state, np.uint8, n * per, _CORE_HEADER).reshape(n, per)
        mass_at = 4 * (2 * d + 2 * d * d + 2)
        masses = np.ascontiguousarray(rec[:, mass_at : mass_at + 4]).view("<f4")[:, 0]
        if not np.array_equal(rec[:, -1], np.asarray(self.material).astype(np.uint8)):
            raise CheckpointError("checkpoint's particles are not this solver's (their materials differ)")
        if not np.array_equal(masses, np.asarray(self.masses, np.float32)):
            raise CheckpointError("checkpoint's particles are not this solver's (their masses differ)")

    @staticmethod
    def _split(blob: bytes) -> tuple[MpmParams, bytes]:
        if not isinstance(blob, (bytes, bytearray)) or blob[:8] != _MAGIC or len(blob) < 16:
            raise CheckpointError("not a hybridmpm MpmSolver checkpoint")
        (n,) = struct.unpack("<Q", blob[8:16])
        if 16 + n > len(blob):
            raise CheckpointError("truncated checkpoint header")
        try:
            params = MpmParams.from_dict(json.loads(blob[16 : 16 + n]))
        except (ValueError, TypeError) as e:
            raise CheckpointError(f"bad parameter header: {e}") from e
        return params, bytes(blob[16 + n :])


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


__all__ = [
    "DT_FRAME",
    "Box",
    "MpmParams",
    "MpmSolver",
    "SandParams",
    "Sphere",
    "WALL_FACES",
    "WallFace",
    "WallParams",
    "WaterParams",
    "grid_mass",
]
