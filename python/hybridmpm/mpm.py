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
>>> from hybridmpm.mpm import MpmParams, MpmSolver, WATER
>>> sim = MpmSolver(MpmParams(dim=2))
>>> x = np.random.default_rng(0).uniform(0.3, 0.5, (500, 2)).astype(np.float32)
>>> sim.add_particles(x, WATER)
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
from hybridmpm.conventions import DEFAULT_N_GRID, DT_FRAME, MATERIAL_SAND, MATERIAL_WATER
from hybridmpm.errors import CheckpointError, InvalidInputError
from hybridmpm.errors import as_f32 as _as_f32

#: Solver material codes, short names for :data:`~hybridmpm.conventions.MATERIAL_WATER`
#: and :data:`~hybridmpm.conventions.MATERIAL_SAND` (not the GNS particle types).
WATER = MATERIAL_WATER
SAND = MATERIAL_SAND

Condition = Literal["sticky", "slip", "separate"]


@dataclass
class WaterParams:
    """Weakly compressible water. ``density`` ρ [kg/m³], ``bulk_modulus`` K [Pa]
    (sound speed ``sqrt(K/ρ)``, default 20 m/s), ``viscosity`` η [Pa·s]."""

    density: float = 1000.0
    bulk_modulus: float = 4.0e5
    viscosity: float = 0.0


@dataclass
class SandParams:
    """Drucker–Prager sand. ``youngs_modulus`` E [Pa], ``poisson_ratio`` ν,
    ``friction_angle_deg`` φ [°], ``cohesion`` c [Pa] (cone apex at mean
    stress ``c / tan φ``)."""

    density: float = 1000.0
    youngs_modulus: float = 3.5e5
    poisson_ratio: float = 0.3
    friction_angle_deg: float = 30.0
    cohesion: float = 0.0


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
    """

    cells: int = 3
    condition: Condition = "separate"
    friction: float = 0.0
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
    Must be at least 2 grid cells thick."""

    center: Sequence[float]
    half_extents: Sequence[float]
    angle_deg: float | None = None
    rotation: Sequence[Sequence[float]] | None = None
    condition: Condition = "separate"
    friction: float = 0.0

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
    """Static sphere (circle in 2D) collider: ``center``, ``radius`` [m]."""

    center: Sequence[float]
    radius: float
    condition: Condition = "separate"
    friction: float = 0.0

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
    the substep count of each frame; an int fixes it.
    """

    dim: int = 2
    n_grid: int | None = None
    gravity: Sequence[float] | None = None
    cfl: float = 0.4
    substeps: int | None = None
    max_substeps: int = 1000
    num_threads: int = 0
    water: WaterParams = field(default_factory=WaterParams)
    sand: SandParams = field(default_factory=SandParams)
    walls: WallParams = field(default_factory=WallParams)
    colliders: list[Box | Sphere] = field(default_factory=list)

    def resolved_n_grid(self) -> int:
        return int(self.n_grid) if self.n_grid is not None else DEFAULT_N_GRID.get(self.dim, DEFAULT_N_GRID[2])

    def to_dict(self) -> dict[str, Any]:
        """The plain dict the Rust binding takes (JSON-serialisable)."""
        if self.dim not in (2, 3):
            raise InvalidInputError(f"dim: must be 2 or 3, got {self.dim}", "dim")
        gravity = list(self.gravity) if self.gravity is not None else ([0.0, -9.8] if self.dim == 2 else [0.0, -9.8, 0.0])
        return {
            "dim": self.dim,
            "n_grid": self.resolved_n_grid(),
            "gravity": [float(g) for g in gravity],
            "cfl": float(self.cfl),
            "substeps": self.substeps,
            "max_substeps": int(self.max_substeps),
            "num_threads": int(self.num_threads),
            "water": asdict(self.water),
            "sand": asdict(self.sand),
            "walls": self.walls.to_dict(self.dim),
            "colliders": [c.to_dict() for c in self.colliders],
        }

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> MpmParams:
        """Inverse of :meth:`to_dict`."""
        d = dict(d)
        cols: list[Box | Sphere] = []
        for i, c in enumerate(d.pop("colliders", []) or []):
            c = dict(c)
            shape = c.pop("shape", None)
            if shape == "box":
                cols.append(Box(**c))
            elif shape in ("sphere", "circle"):
                cols.append(Sphere(**c))
            else:
                raise InvalidInputError(f"colliders[{i}].shape: must be 'box' or 'sphere', got {shape!r}", f"colliders[{i}].shape")
        return cls(
            water=WaterParams(**d.pop("water", {})),
            sand=SandParams(**d.pop("sand", {})),
            walls=WallParams.from_dict(d.pop("walls", None) or {}, dim=d.get("dim", 2)),
            colliders=cols,
            **d,
        )


_MAGIC = b"HMPMPY01"


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
    """

    def __init__(self, params: MpmParams | None = None) -> None:
        self.params = params if params is not None else MpmParams()
        self._core = _core.MpmSolver(self.params.to_dict())

    # ------------------------------------------------------------- particles
    def add_particles(
        self,
        positions: np.ndarray,
        material: int | np.ndarray = WATER,
        *,
        velocities: np.ndarray | None = None,
        masses: np.ndarray | None = None,
        volumes: np.ndarray | None = None,
    ) -> int:
        """Append particles; returns the new particle count.

        ``positions`` [N, D] in ``[dx, 1 − dx]`` [m]; ``material`` a code or
        int array [N]; ``velocities`` [N, D] [m/s]; ``masses`` [N] [kg];
        ``volumes`` [N] [m^D] (default ``(dx/2)^D``, 2 particles per cell per
        dimension; mass defaults to density × volume).
        """
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
    def step_frame(self, dt_frame: float = DT_FRAME) -> dict[str, float]:
        """Advance one frame by as many substeps as the CFL condition needs.

        Returns ``{"substeps", "dt", "max_speed", "active_blocks"}``. Raises
        :class:`~hybridmpm.errors.SimulationError` (with ``.substep``) if the
        state becomes non-finite; the state is then that of the frame's start.
        """
        if not (isinstance(dt_frame, (int, float)) and math.isfinite(dt_frame) and dt_frame > 0):
            raise InvalidInputError(f"dt_frame: must be a finite number > 0, got {dt_frame!r}", "dt_frame")
        return self._core.step_frame(float(dt_frame))  # type: ignore[no-any-return]

    def substeps_for(self, dt_frame: float = DT_FRAME) -> int:
        return int(self._core.substeps_for(float(dt_frame)))

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

    def restore(self, blob: bytes) -> None:
        """Restore :meth:`checkpoint` bytes into this solver (parameters must match)."""
        params, state = self._split(blob)
        if params.to_dict() != self.params.to_dict():
            raise CheckpointError("checkpoint was written with different parameters; use MpmSolver.from_checkpoint")
        self._core.restore(state)

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
    """Normalised grid mass (DESIGN.md "Grid-mass error"; paper Sec. 3.1.1).

    p2g of particle mass (1/N each unless ``masses`` [N] is given) with
    quadratic B-spline weights onto nodes ``i/n_grid``, ``i ∈ [0, n_grid)^D``,
    normalised to sum 1. ``positions`` [N, D] float, D ∈ {2, 3}.
    Returns float32 of shape ``[n_grid] * D``.
    """
    return _core.grid_mass(  # type: ignore[no-any-return]
        _as_f32("positions", positions), int(n_grid), None if masses is None else _as_f32("masses", masses)
    )


__all__ = [
    "DT_FRAME",
    "SAND",
    "WATER",
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
