"""Rigid bodies that the fluid moves and that push it back (docs/bodies.md).

A :class:`Body` is what a scene file's ``[[bodies]]`` table and
:meth:`~hybridmpm.sim.MpmSimulator.add_body` take: the Rust core's
``BodyParams`` (``shape`` ``"box"`` or ``"sphere"`` / ``"circle"``,
``center``, ``half_extents`` or ``radius``, ``rotation`` or, in 2D,
``angle_deg``, ``density`` or ``mass``, ``velocity``, ``angular_velocity``,
``friction``), checked there, every error naming the field
(``bodies[0].density``). :class:`BodiesView` is the bodies' state between
frames (:attr:`~hybridmpm.mpm.MpmSolver.bodies`).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, fields
from typing import Any

import numpy as np

from hybridmpm import _core
from hybridmpm.errors import InvalidInputError

#: Most bodies a solver takes (the Rust core's ``MAX_BODIES``).
MAX_BODIES: int = int(_core.MAX_BODIES)
#: Numbers in a body's exact state (centre 3, rotation 4, velocity 3, angular velocity 3; float32).
BODY_STATE_LEN: int = int(_core.BODY_STATE_LEN)


def _num(v: Any) -> Any:
    """A real number as a float; anything else as given (the core names it)."""
    if isinstance(v, (int, float, np.integer, np.floating)) and not isinstance(v, bool):
        return float(v)
    return v


def _vec(v: Any) -> Any:
    if isinstance(v, (str, bytes, dict)) or not isinstance(v, (Sequence, np.ndarray)):
        return _num(v)
    return [_vec(x) for x in v]


@dataclass(frozen=True)
class Body:
    """A rigid body as given: its shape, pose, velocity, density (kg/m³) or
    mass (kg; per unit depth in 2D, as the particles' masses) and Coulomb
    ``friction`` against the fluid (default 0). ``center`` [m] is the centre
    of mass; ``rotation`` a ``D``×``D`` rotation (columns: the body's axes)
    or, in 2D, ``angle_deg`` counter-clockwise; ``velocity`` [m/s];
    ``angular_velocity`` [rad/s], one number in 2D, three in 3D. A body
    lies inside the walls and is at least 1 grid cell in every half extent
    or radius; a solver takes at most :data:`MAX_BODIES`."""

    shape: str
    center: Sequence[float]
    half_extents: Sequence[float] | None = None
    radius: float | None = None
    angle_deg: float | None = None
    rotation: Sequence[Sequence[float]] | None = None
    density: float | None = None
    mass: float | None = None
    velocity: Sequence[float] | None = None
    angular_velocity: float | Sequence[float] | None = None
    friction: float | None = None

    def to_dict(self) -> dict[str, Any]:
        """The dict the Rust core reads (keys left out where None)."""
        d: dict[str, Any] = {}
        for f in fields(self):
            v = getattr(self, f.name)
            if v is None:
                continue
            if f.name == "angular_velocity" and not isinstance(v, (Sequence, np.ndarray)):
                v = [v]
            d[f.name] = v if f.name == "shape" else _vec(v)
        return d

    @classmethod
    def from_dict(cls, d: Any, field: str = "bodies[0]") -> Body:
        """A body from a dict (a scene file's table), refusing unknown keys
        and a missing ``shape`` or ``center`` with
        :class:`InvalidInputError` naming ``field.key``; the values are checked by :func:`check_bodies`."""
        if isinstance(d, Body):
            return d
        if not isinstance(d, dict):
            raise InvalidInputError(f"{field}: expected a table/object, got {d!r}", field)
        allowed = [f.name for f in fields(cls)]
        unknown = sorted((k for k in d if k not in allowed), key=str)
        if unknown:
            raise InvalidInputError(f"{field}.{unknown[0]}: unknown body field (allowed: {', '.join(allowed)})", f"{field}.{unknown[0]}")
        for key in ("shape", "center"):
            if d.get(key) is None:
                what = " ('box' or 'sphere')" if key == "shape" else ""
                raise InvalidInputError(f"{field}.{key}: missing{what}", f"{field}.{key}")
        return cls(**d)

    def rotation_matrix(self, dim: int) -> np.ndarray:
        """The body's rotation as given, float64 [D, D]."""
        if self.rotation is not None:
            return np.asarray(self.rotation, np.float64).reshape(dim, dim)
        r = np.eye(dim)
        if self.angle_deg is not None and dim == 2:
            a = np.radians(float(self.angle_deg))
            r = np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
        return r

    def sdf(self, points: np.ndarray, center: Any = None, rotation: Any = None) -> np.ndarray:
        """Signed distance [m] of ``points`` [N, D] to the body (negative
        inside), float64 [N], where it is given or at ``center`` [D] and
        ``rotation`` [D, D] (its pose now: :attr:`BodiesView.center`): what
        keeps a scene's blocks and a pour from seeding particles inside it."""
        p = np.asarray(points, np.float64)
        rel = p - np.asarray(self.center if center is None else center, np.float64)
        if self.shape != "box":
            return np.linalg.norm(rel, axis=1) - float(self.radius or 0.0)
        r = self.rotation_matrix(p.shape[1]) if rotation is None else np.asarray(rotation, np.float64)
        q = np.abs(rel @ r) - np.asarray(self.half_extents, np.float64)
        return np.linalg.norm(np.maximum(q, 0.0), axis=1) + np.minimum(q.max(axis=1), 0.0)


def check_bodies(bodies: Sequence[Body], dim: int, n_grid: int, wall_cells: int, start: int = 0) -> list[float]:
    """Check ``bodies`` as a ``dim``-D solver of ``n_grid`` cells and walls
    ``wall_cells`` thick would when they are added as bodies ``start``,
    ``start + 1``, … (shape, size, density or mass, rotation, inside the
    walls, at most :data:`MAX_BODIES`); returns their masses [kg; per unit
    depth in 2D]. Raises :class:`InvalidInputError` naming the field
    (``bodies[1].density``)."""
    if start + len(bodies) > MAX_BODIES:
        raise InvalidInputError(f"bodies: at most {MAX_BODIES} bodies, got {start + len(bodies)}", "bodies")
    return [float(_core.check_body(b.to_dict(), dim, n_grid, wall_cells, start + i)) for i, b in enumerate(bodies)]


def refuse_bodies(count: int, who: str) -> None:
    """Raise :class:`InvalidInputError` (field ``bodies``) when a scene holds
    ``count`` > 0 rigid bodies that ``who`` (a learned simulator, the
    diffusion controller) cannot run: it never saw one. MPM runs them."""
    if count:
        raise InvalidInputError(
            f"bodies: the {who} was not trained with rigid bodies, and this scene holds {count}; run it with the mpm solver (and PD control)", "bodies"
        )


@dataclass(frozen=True)
class BodiesView:
    """The bodies at a frame's end, in order, read-only float64 arrays:
    ``center`` [B, D] [m], ``rotation`` [B, D, D] (columns: the body's
    axes), ``velocity`` [B, D] [m/s], ``angular_velocity`` [B] in 2D (about
    z, counter-clockwise) or [B, 3] [rad/s], ``mass`` [B] [kg; per unit
    depth in 2D], and the fluid's mean ``force`` [B, D] [N] and ``torque``
    [B] or [B, 3] [N·m] on each over the last frame (gravity and contacts
    not included; zero before the first frame and after a restore)."""

    center: np.ndarray
    rotation: np.ndarray
    velocity: np.ndarray
    angular_velocity: np.ndarray
    mass: np.ndarray
    force: np.ndarray
    torque: np.ndarray

    def __len__(self) -> int:
        return int(self.mass.shape[0])

    @classmethod
    def from_core(cls, raw: dict[str, np.ndarray], dim: int) -> BodiesView:
        def ro(a: np.ndarray) -> np.ndarray:
            a = np.array(a, np.float64)
            a.flags.writeable = False
            return a

        w = (lambda a: a[:, 0]) if dim == 2 else (lambda a: a)
        return cls(
            center=ro(raw["center"]),
            rotation=ro(raw["rotation"]),
            velocity=ro(raw["velocity"]),
            angular_velocity=ro(w(raw["angular_velocity"])),
            mass=ro(raw["mass"]),
            force=ro(raw["force"]),
            torque=ro(w(raw["torque"])),
        )


__all__ = ["BODY_STATE_LEN", "MAX_BODIES", "BodiesView", "Body", "check_bodies", "refuse_bodies"]
