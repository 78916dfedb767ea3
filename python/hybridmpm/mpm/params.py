"""The MLS-MPM solver's parameters (:class:`MpmParams` and its parts: each model's parameter set
(:mod:`hybridmpm.mpm.sets`), the table of further parameter sets, walls, colliders), typed and validated in
Python; their defaults are the Rust core's (``SolverParams::default()``), defined once there."""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import asdict, dataclass, field
from typing import Any, Literal

import numpy as np

from hybridmpm import _core
from hybridmpm.conventions import MATERIALS
from hybridmpm.errors import InvalidInputError
from hybridmpm.mpm.bodies import Body
from hybridmpm.mpm.motion import Keyframe
from hybridmpm.mpm.schema import check_set
from hybridmpm.mpm.sets import (
    SET_CLASSES,
    ElasticParams,
    MaterialSet,
    SandParams,
    SnowParams,
    ViscoplasticParams,
    WaterParams,
    set_name,
)

Condition = Literal["sticky", "slip", "separate"]

#: The solver's defaults by dimension, from the Rust core
#: (:func:`hybridmpm._core.default_params`: ``SolverParams::default()``), in
#: the form of :meth:`MpmParams.to_dict`. The dataclass defaults below are
#: these values: the parameters are defined once, in Rust.
_DEFAULTS: dict[int, dict[str, Any]] = {dim: _core.default_params(dim) for dim in (2, 3)}
#: A collider's defaults (``condition``, ``friction``, ``project``), from the Rust core.
COLLIDER_DEFAULTS: dict[str, Any] = _core.default_collider()
_SOLVER = _DEFAULTS[2]  # the fields below are the same in 3D (tests/test_one_schema.py)
_WALLS = _SOLVER["walls"]

#: How the solver advances a frame (the Rust ``Integrator``), the default
#: first: ``"explicit"`` MLS-MPM substeps at the materials' wave speeds, or
#: ``"projection"``, incompressible APIC water with a pressure projection at
#: the flow's pace (docs/large-step.md).
INTEGRATORS: tuple[str, ...] = tuple(_core.INTEGRATORS)
#: The models whose scene-level table is a field of :class:`MpmParams` of their own; every other model of
#: the core has its table in :attr:`MpmParams.tables`.
FIELD_MODELS: tuple[str, ...] = ("water", "sand", "elastic", "snow", "viscoplastic")


def _further_tables() -> dict[str, Any]:
    """The default table of each model of the core without a field of :class:`MpmParams`, by name."""
    return {name: cls() for name, cls in SET_CLASSES.items() if name not in FIELD_MODELS}


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
    default to the Rust core's (``ColliderParams::default()``), as does
    ``project`` (on): a particle that ends a substep inside the box goes back
    onto its surface and loses its velocity into it (docs/obstacles.md).
    ``keyframes``: a prescribed path (:mod:`hybridmpm.mpm.motion`; the
    simulators follow it, the solver dict :meth:`to_dict` leaves it out)."""

    center: Sequence[float]
    half_extents: Sequence[float]
    angle_deg: float | None = None
    rotation: Sequence[Sequence[float]] | None = None
    condition: Condition = COLLIDER_DEFAULTS["condition"]
    friction: float = COLLIDER_DEFAULTS["friction"]
    project: bool = COLLIDER_DEFAULTS["project"]
    keyframes: tuple[Keyframe, ...] | None = None

    def to_dict(self) -> dict[str, Any]:
        d: dict[str, Any] = {
            "shape": "box",
            "center": [float(c) for c in self.center],
            "half_extents": [float(h) for h in self.half_extents],
            "condition": self.condition,
            "friction": float(self.friction),
            "project": self.project,
        }
        if self.angle_deg is not None:
            d["angle_deg"] = float(self.angle_deg)
        if self.rotation is not None:
            d["rotation"] = [[float(v) for v in row] for row in self.rotation]
        return d


@dataclass
class Sphere:
    """Static sphere (circle in 2D) collider: ``center``, ``radius`` [m].
    ``condition``, ``friction`` and ``project`` default to the Rust core's
    (``ColliderParams::default()``), as :class:`Box`'s.
    ``keyframes``: a prescribed path, as :class:`Box`'s."""

    center: Sequence[float]
    radius: float
    condition: Condition = COLLIDER_DEFAULTS["condition"]
    friction: float = COLLIDER_DEFAULTS["friction"]
    project: bool = COLLIDER_DEFAULTS["project"]
    keyframes: tuple[Keyframe, ...] | None = None

    def to_dict(self) -> dict[str, Any]:
        return {
            "shape": "sphere",
            "center": [float(c) for c in self.center],
            "radius": float(self.radius),
            "condition": self.condition,
            "friction": float(self.friction),
            "project": self.project,
        }


@dataclass(eq=False)
class SampledSdf:
    """Static collider given by its signed distance [m] sampled on a regular
    grid (negative inside; a scene's mesh obstacle, made by
    :mod:`hybridmpm.scenes.obstacle_mesh`): ``origin`` [m] (``dim`` numbers,
    the position of sample ``[0, ..., 0]``), ``cell`` [m] (the spacing),
    ``values`` float32 ``[n_0, ..., n_{dim-1}]`` (sample ``i`` at
    ``origin + cell·i``); ``normals`` optional float32 ``[n_0, ...,
    n_{dim-1}, dim]``, the outward unit normal at each sample (without them
    the solver takes central differences of the distance). The solver
    interpolates both multilinearly (Rust ``Shape::Sampled``);
    :func:`hybridmpm.scenes.collider_sdf` interpolates ``values`` the same way.
    ``source`` is the scene-file obstacle it was sampled from (``shape =
    "mesh"``, ...), kept by :class:`~hybridmpm.scenes.SceneSpec` for saving
    and regridding; it is not sent to the solver. ``condition``,
    ``friction`` and ``project`` default to the Rust core's
    (``ColliderParams::default()``), as :class:`Box`'s.
    ``keyframes``: a prescribed path of the mesh's ``center`` (``source``),
    as :class:`Box`'s; not sent to the solver either."""

    origin: Sequence[float]
    cell: float
    values: np.ndarray
    normals: np.ndarray | None = None
    condition: Condition = COLLIDER_DEFAULTS["condition"]
    friction: float = COLLIDER_DEFAULTS["friction"]
    project: bool = COLLIDER_DEFAULTS["project"]
    source: dict[str, Any] | None = None
    keyframes: tuple[Keyframe, ...] | None = None

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, SampledSdf):
            return NotImplemented
        return (
            [float(v) for v in self.origin] == [float(v) for v in other.origin]
            and float(self.cell) == float(other.cell)
            and np.array_equal(np.asarray(self.values), np.asarray(other.values))
            and (self.normals is None) == (other.normals is None)
            and (self.normals is None or np.array_equal(np.asarray(self.normals), np.asarray(other.normals)))
            and (self.condition, float(self.friction), self.project) == (other.condition, float(other.friction), other.project)
        )

    def to_dict(self) -> dict[str, Any]:
        values = np.asarray(self.values, np.float32)
        d: dict[str, Any] = {
            "shape": "sampled",
            "origin": [float(c) for c in self.origin],
            "cell": float(self.cell),
            "dims": [int(n) for n in values.shape],
            "values": values.ravel().tolist(),
            "condition": self.condition,
            "friction": float(self.friction),
            "project": self.project,
        }
        if self.normals is not None:
            d["normals"] = np.asarray(self.normals, np.float32).ravel().tolist()
        return d

    @classmethod
    def from_dict(cls, name: str, d: dict[str, Any]) -> SampledSdf:
        """Inverse of :meth:`to_dict` (without ``shape``); errors name ``{name}.<key>``."""
        unknown = sorted(set(d) - {"origin", "cell", "dims", "values", "normals", "condition", "friction", "project"}, key=str)
        if unknown:
            raise InvalidInputError(
                f"{name}.{unknown[0]}: unknown parameter (allowed: cell, condition, dims, friction, normals, origin, project, values)", f"{name}.{unknown[0]}"
            )
        for key in ("origin", "cell", "dims", "values"):
            if key not in d:
                raise InvalidInputError(f"{name}.{key}: missing", f"{name}.{key}")
        dims = d["dims"]
        if not isinstance(dims, (list, tuple)) or not all(isinstance(n, (int, np.integer)) and not isinstance(n, bool) and n >= 2 for n in dims):
            raise InvalidInputError(f"{name}.dims: expected a list of integers >= 2, got {dims!r}", f"{name}.dims")
        try:
            values = np.asarray(d["values"], np.float32)
        except (TypeError, ValueError) as e:
            raise InvalidInputError(f"{name}.values: expected a list of numbers", f"{name}.values") from e
        if values.ndim != 1 or values.size != math.prod(int(n) for n in dims):
            raise InvalidInputError(f"{name}.values: expected {math.prod(int(n) for n in dims)} numbers (dims {list(dims)})", f"{name}.values")
        normals = None
        if d.get("normals") is not None:
            try:
                normals = np.asarray(d["normals"], np.float32)
            except (TypeError, ValueError) as e:
                raise InvalidInputError(f"{name}.normals: expected a list of numbers", f"{name}.normals") from e
            if normals.ndim != 1 or normals.size != len(dims) * values.size:
                raise InvalidInputError(f"{name}.normals: expected {len(dims) * values.size} numbers ({len(dims)} per sample)", f"{name}.normals")
            normals = normals.reshape([*(int(n) for n in dims), len(dims)])
        return cls(
            origin=d["origin"],
            cell=d["cell"],
            values=values.reshape([int(n) for n in dims]),
            normals=normals,
            condition=d.get("condition", COLLIDER_DEFAULTS["condition"]),
            friction=d.get("friction", COLLIDER_DEFAULTS["friction"]),
            project=d.get("project", COLLIDER_DEFAULTS["project"]),
        )


#: A collider of :class:`MpmParams`.
Collider = Box | Sphere | SampledSdf


def free_slip(collider: Box | Sphere | SampledSdf) -> bool:
    """Whether ``collider`` is free slip (not ``sticky``, no friction): the obstacles the projection
    integrator steps round (docs/large-step.md)."""
    return collider.condition != "sticky" and float(collider.friction) == 0.0


@dataclass
class MpmParams:
    """All solver parameters (see the Rust ``SolverParams`` for the ranges).

    ``substeps=None`` lets the CFL condition ``dt ≤ cfl·dx/(c + |v|max)`` pick
    the substep count of each frame; an int fixes it. Defaults are the Rust
    core's (``SolverParams::default()``, as a dict
    ``hybridmpm._core.default_params(dim)``): ``n_grid=None`` and
    ``gravity=None`` [m/s², ``dim`` numbers] take those of ``dim``.

    ``water`` ... ``viscoplastic`` are each material's default parameter set
    (entries 0 to 4 of the table particles index, by material code);
    ``tables`` holds the default set of every further model of the core (one
    without a field here: :data:`FIELD_MODELS`), by its name, each at its
    code (:meth:`table` reads any model's); ``sets`` holds further sets
    (entries ``len(MATERIALS)``, ... after the defaults), e.g. a second jelly of
    another stiffness: a particle's ``material_set`` names its entry.

    ``integrator`` is one of :data:`INTEGRATORS`: ``"explicit"`` (MLS-MPM
    substeps at the CFL bound of the materials' wave speeds) or
    ``"projection"`` (incompressible APIC water, one step per two cells the
    flow crosses; water in the box walls and around free-slip colliders, at
    rest or moving: a solver with bodies, sand or solids refuses its frames
    naming ``integrator``, a collider with friction or a sticky one is
    refused naming ``colliders[i].friction`` / ``.condition``).
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
    elastic: ElasticParams = field(default_factory=ElasticParams)
    snow: SnowParams = field(default_factory=SnowParams)
    viscoplastic: ViscoplasticParams = field(default_factory=ViscoplasticParams)
    tables: dict[str, Any] = field(default_factory=_further_tables)
    sets: list[MaterialSet] = field(default_factory=list)
    walls: WallParams = field(default_factory=WallParams)
    colliders: list[Collider] = field(default_factory=list)
    bodies: list[Body] = field(default_factory=list)
    integrator: str = INTEGRATORS[0]

    def table(self, name: str) -> Any:
        """The scene-level table (default parameter set) of model ``name``: its field (``self.water``, ...)
        or its entry of :attr:`tables` (the model's defaults where that lacks it). Raises ``KeyError`` for
        a name that is not a model of the core (:data:`~hybridmpm.conventions.MATERIALS`)."""
        if name in FIELD_MODELS:
            return getattr(self, name)
        return self.tables[name] if name in self.tables else SET_CLASSES[name]()

    def set_index(self, group: MaterialSet, sets: Sequence[MaterialSet] | None = None) -> int | None:
        """The index in the table of parameter sets (what a particle's ``material_set`` names) of a particle with
        ``group``'s parameters: its material's code where ``group`` is that material's default set (``self.water``,
        ...), ``len(MATERIALS) + k`` where it is ``sets[k]`` (``sets``: ``self.sets`` unless given: a table being
        built), None where the table lacks it (appended, it is ``len(MATERIALS) + len(sets)``). The one rule for
        scenes' blocks and pours (docs/materials.md). Raises ``KeyError`` when ``group`` is not a parameter set
        of a model (:data:`~hybridmpm.mpm.sets.SET_CLASSES`)."""
        name = set_name(type(group))
        if name is None:
            raise KeyError(f"not a parameter set of a model of the core: {group!r}")
        if group == self.table(name):
            return MATERIALS[name]
        table = self.sets if sets is None else sets
        return len(MATERIALS) + list(table).index(group) if group in table else None

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
        The materials' parameters are checked against the core's ranges
        (:mod:`hybridmpm.mpm.schema`) as given, in float64, and in float32.
        Raises :class:`InvalidInputError` naming the field. The other ranges
        (``n_grid`` in [16, 4096], ``cfl`` in (0, 1], ...) are checked by the
        solver, which names the field too."""
        if isinstance(self.dim, bool) or not isinstance(self.dim, (int, np.integer)) or self.dim not in (2, 3):
            raise InvalidInputError(f"dim: must be 2 or 3, got {self.dim!r}", "dim")
        self._check_int("n_grid", self.n_grid, optional=True)
        self._check_int("substeps", self.substeps, optional=True)
        self._check_int("max_substeps", self.max_substeps)
        self._check_int("num_threads", self.num_threads)
        self._check_number("cfl", self.cfl)
        if not isinstance(self.integrator, str) or self.integrator not in INTEGRATORS:
            raise InvalidInputError(f"integrator: must be one of {', '.join(map(repr, INTEGRATORS))}, got {self.integrator!r}", "integrator")
        if self.gravity is not None:
            if isinstance(self.gravity, (str, bytes, dict)) or not isinstance(self.gravity, (Sequence, np.ndarray)) or len(self.gravity) != self.dim:
                raise InvalidInputError(f"gravity: must be a list of {self.dim} numbers, got {self.gravity!r}", "gravity")
            for i, g in enumerate(self.gravity):
                self._check_number(f"gravity[{i}]", g)
        if not isinstance(self.tables, dict) or any(k in FIELD_MODELS or k not in SET_CLASSES for k in self.tables):
            raise InvalidInputError(
                f"tables: must map models without a field of their own ({', '.join(k for k in SET_CLASSES if k not in FIELD_MODELS) or 'none'}) "
                f"to their parameter sets, got {self.tables!r}",
                "tables",
            )
        groups: list[tuple[str, Any, type]] = [(name, self.table(name), cls) for name, cls in SET_CLASSES.items()]
        if not isinstance(self.sets, (list, tuple)):
            raise InvalidInputError(f"sets: must be a list of parameter sets, got {self.sets!r}", "sets")
        for i, group in enumerate(self.sets):
            if set_name(type(group)) is None:
                raise InvalidInputError(f"sets[{i}]: must be one of {', '.join(c.__name__ for c in SET_CLASSES.values())}, got {group!r}", f"sets[{i}]")
            groups.append((f"sets[{i}].{set_name(type(group))}", group, type(group)))
        for name, group, cls in groups:
            if not isinstance(group, cls):
                raise InvalidInputError(f"{name}: must be a {cls.__name__}, got {group!r}", name)
            check_set(f"{name}.", str(set_name(cls)), asdict(group), by_key=False)
        if not isinstance(self.walls, WallParams):
            raise InvalidInputError(f"walls: must be a WallParams, got {self.walls!r}", "walls")
        self.walls.validate(self.dim)
        if not isinstance(self.colliders, (list, tuple)):
            raise InvalidInputError(f"colliders: must be a list of Box / Sphere / SampledSdf, got {self.colliders!r}", "colliders")
        for i, c in enumerate(self.colliders):
            if not isinstance(c, (Box, Sphere, SampledSdf)):
                raise InvalidInputError(f"colliders[{i}]: must be a Box, a Sphere or a SampledSdf, got {c!r}", f"colliders[{i}]")
        if not isinstance(self.bodies, (list, tuple)) or not all(isinstance(b, Body) for b in self.bodies):
            raise InvalidInputError(f"bodies: must be a list of Body, got {self.bodies!r}", "bodies")
        if self.integrator != INTEGRATORS[0]:
            for i, c in enumerate(self.colliders):  # the projection's obstacles are free slip (docs/large-step.md)
                if not free_slip(c):
                    field_ = f"colliders[{i}].{'condition' if c.condition == 'sticky' else 'friction'}"
                    raise InvalidInputError(
                        f"{field_}: the {self.integrator} integrator has free-slip obstacles, and this one is {c.condition!r} with friction "
                        f"{c.friction!r} (use 'slip' or 'separate' without friction, or integrator 'explicit')",
                        field_,
                    )

    def to_dict(self) -> dict[str, Any]:
        """The plain dict the Rust binding takes (JSON-serialisable); validated
        first (:meth:`validate`)."""
        self.validate()
        gravity = list(self.gravity) if self.gravity is not None else _DEFAULTS[self.dim]["gravity"]
        out: dict[str, Any] = {
            "dim": int(self.dim),
            "n_grid": self.resolved_n_grid(),
            "gravity": [float(g) for g in gravity],
            "cfl": float(self.cfl),
            "substeps": None if self.substeps is None else int(self.substeps),
            "max_substeps": int(self.max_substeps),
            "num_threads": int(self.num_threads),
            **{name: asdict(self.table(name)) for name in SET_CLASSES},  # every model's table, in code order
            "sets": [{set_name(type(g)): asdict(g)} for g in self.sets],
            "walls": self.walls.to_dict(self.dim),
            "colliders": [c.to_dict() for c in self.colliders],
        }
        if self.integrator != INTEGRATORS[0]:  # absent when explicit, as the Rust dict leaves it out: headers unchanged
            out["integrator"] = self.integrator
        if self.bodies:  # absent without bodies: the dict (and a checkpoint's header) of a scene without them is unchanged
            out["bodies"] = [b.to_dict() for b in self.bodies]
        return out

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
        cols: list[Collider] = []
        for i, c in enumerate(raw_cols):
            if not isinstance(c, dict):
                raise InvalidInputError(f"colliders[{i}]: expected a dict, got {c!r}", f"colliders[{i}]")
            c = dict(c)
            shape = c.pop("shape", None)
            if shape == "box":
                cols.append(build(f"colliders[{i}]", Box, c))
            elif shape in ("sphere", "circle"):
                cols.append(build(f"colliders[{i}]", Sphere, c))
            elif shape == "sampled":
                cols.append(SampledSdf.from_dict(f"colliders[{i}]", c))
            else:
                raise InvalidInputError(f"colliders[{i}].shape: must be 'box', 'sphere' or 'sampled', got {shape!r}", f"colliders[{i}].shape")
        raw_bodies = d.pop("bodies", []) or []
        if not isinstance(raw_bodies, (list, tuple)):
            raise InvalidInputError(f"bodies: expected a list, got {raw_bodies!r}", "bodies")
        bodies = [Body.from_dict(b, f"bodies[{i}]", d.get("dim", 2)) for i, b in enumerate(raw_bodies)]
        groups = {name: build(name, c, d.pop(name, {})) for name, c in SET_CLASSES.items()}
        tables = {name: groups.pop(name) for name in SET_CLASSES if name not in FIELD_MODELS}
        raw_sets = d.pop("sets", []) or []
        if not isinstance(raw_sets, (list, tuple)):
            raise InvalidInputError(f"sets: expected a list, got {raw_sets!r}", "sets")
        sets: list[MaterialSet] = []
        for i, entry in enumerate(raw_sets):
            if not (isinstance(entry, dict) and len(entry) == 1 and next(iter(entry)) in SET_CLASSES):
                raise InvalidInputError(f"sets[{i}]: expected one of {{{', '.join(SET_CLASSES)}: {{...}}}}, got {entry!r}", f"sets[{i}]")
            ((name, kwargs),) = entry.items()
            sets.append(build(f"sets[{i}].{name}", SET_CLASSES[name], kwargs))
        walls = WallParams.from_dict(d.pop("walls", None) or {}, dim=d.get("dim", 2))
        top = set(cls.__dataclass_fields__) - {*SET_CLASSES, "tables", "sets", "walls", "colliders", "bodies"}
        unknown = sorted(set(d) - top, key=str)
        if unknown:
            raise InvalidInputError(f"{unknown[0]}: unknown parameter (allowed: {', '.join(sorted(top))})", str(unknown[0]))
        params = cls(**groups, tables=tables, sets=sets, walls=walls, colliders=cols, bodies=bodies, **d)
        params.validate()
        return params


#: The constitutive parameters a calibrated coarse material may set (dotted
#: paths into :meth:`MpmParams.to_dict`), with the physical bounds its fit
#: searches within (benchmarks/coarse_ladder.py; docs/correction.md "Rung 1"):
#: sand's friction angle φ [°], Young's modulus E [Pa] and cohesion c [Pa],
#: the floor's Coulomb friction μ (face ``y-``), water's bulk modulus K [Pa]
#: (sound speed 10–28 m/s) and viscosity η [Pa·s].
CALIBRATION_BOUNDS: dict[str, tuple[float, float]] = {
    "sand.friction_angle_deg": (15.0, 45.0),
    "sand.youngs_modulus": (1.0e5, 1.0e6),
    "sand.cohesion": (0.0, 200.0),
    "walls.faces.y-.friction": (0.0, 1.2),
    "water.bulk_modulus": (1.0e5, 8.0e5),
    "water.viscosity": (0.0, 0.5),
}


def with_calibration(params: MpmParams, values: dict[str, float]) -> MpmParams:
    """A copy of ``params`` with the constitutive parameters of ``values`` set
    (keys of :data:`CALIBRATION_BOUNDS`, e.g. ``{"sand.friction_angle_deg":
    27.5, "walls.faces.y-.friction": 0.5}``; a wall face's other settings are
    kept). Raises :class:`InvalidInputError` naming ``calibrated.<key>`` for an
    unknown key, a value that is not a finite number, or one outside its bounds."""
    d = params.to_dict()
    for key, value in values.items():
        if key not in CALIBRATION_BOUNDS:
            raise InvalidInputError(f"calibrated.{key}: not a calibrated parameter (allowed: {', '.join(CALIBRATION_BOUNDS)})", f"calibrated.{key}")
        lo, hi = CALIBRATION_BOUNDS[key]
        if isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)) or not lo <= float(value) <= hi:
            raise InvalidInputError(f"calibrated.{key}: must be a number in [{lo:g}, {hi:g}], got {value!r}", f"calibrated.{key}")
        *path, leaf = key.split(".")
        node = d
        for part in path:
            node = node.setdefault(part, {})
        node[leaf] = float(value)
    return MpmParams.from_dict(d)
