"""Rigid bodies that the fluid moves and that push it back (docs/bodies.md).

A :class:`Body` is what a scene file's ``[[bodies]]`` table and
:meth:`~hybridmpm.sim.MpmSimulator.add_body` take: the Rust core's
``BodyParams`` (``shape`` ``"box"``, ``"sphere"`` / ``"circle"``,
``"capsule"`` or, in 3D, ``"mesh"``; ``center``, ``half_extents``,
``radius`` and ``half_height``, or a mesh's ``path`` and ``scale`` (read as
mesh obstacles are, kept as its convex hull's ``vertices``); ``rotation``
or, in 2D, ``angle_deg``, ``density`` or ``mass``, ``velocity``,
``angular_velocity``, ``friction``), checked there, every error naming the
field (``bodies[0].density``). :class:`BodiesView` is the bodies' state between
frames (:attr:`~hybridmpm.mpm.MpmSolver.bodies`).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, fields
from typing import Any

import numpy as np

from hybridmpm import _core
from hybridmpm.errors import InvalidInputError
from hybridmpm.limits import F32_MAX, F32_TINY, check_float32

#: Most bodies a solver takes (the Rust core's ``MAX_BODIES``).
MAX_BODIES: int = int(_core.MAX_BODIES)
#: Shapes a body may have (``circle`` is ``sphere``; ``mesh`` is 3D only).
SHAPES = ("box", "sphere", "circle", "capsule", "mesh")
#: Most points a mesh body's hull is built from (the Rust core's ``MAX_HULL_POINTS``).
MAX_HULL_POINTS: int = int(_core.MAX_HULL_POINTS)
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


def _float32_numbers(field: str, v: Any) -> None:
    """Refuse (naming ``field`` and the value given) a finite number, or one in a nested list, that float32 (the
    core's precision) holds as infinity or as a subnormal: ``density = 1e-300`` would be 0 there. Anything else is
    left to the core's checks."""
    try:
        a = np.asarray(v, np.float64)
    except (TypeError, ValueError):
        return
    if a.dtype != np.float64 or a.size == 0:
        return
    finite = a[np.isfinite(a)]
    bad = finite[(np.abs(finite) > F32_MAX) | ((finite != 0) & (np.abs(finite) < F32_TINY))]
    if bad.size:
        check_float32(field, float(bad[0]))


@dataclass(frozen=True)
class Body:
    """A rigid body as given: its shape, pose, velocity, density (kg/m³) or
    mass (kg; per unit depth in 2D, as the particles' masses) and Coulomb
    ``friction`` against the fluid (default 0). ``center`` [m] is the centre
    of mass (a mesh's: where the mesh's origin goes; the centre of mass is
    its hull's); ``rotation`` a ``D``×``D`` rotation (columns: the body's
    axes) or, in 2D, ``angle_deg`` counter-clockwise; ``velocity`` [m/s];
    ``angular_velocity`` [rad/s], one number in 2D, three in 3D. A capsule
    is the points within ``radius`` of the segment from ``-half_height`` to
    ``half_height`` [m] along the body's y axis. A mesh (3D) is the convex
    hull of ``vertices`` [V, 3] [m] in the mesh's frame, read from ``path``
    times ``scale`` (:func:`hybridmpm.scenes.body_mesh.resolve_mesh_body`,
    which simplifies a hull of more than
    :data:`~hybridmpm.scenes.body_mesh.MAX_HULL_FACES` triangles;
    ``path`` stays as the label its errors name). A body lies inside the walls and is at least 1
    grid cell in every half extent, radius and half height (a hull: half its
    thinnest width); a solver takes at most :data:`MAX_BODIES`."""

    shape: str
    center: Sequence[float]
    half_extents: Sequence[float] | None = None
    radius: float | None = None
    half_height: float | None = None
    path: str | None = None
    scale: float | None = None
    vertices: Sequence[Sequence[float]] | None = None
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
            d[f.name] = v if f.name in ("shape", "path") else _vec(v)
        return d

    @classmethod
    def from_dict(cls, d: Any, field: str = "bodies[0]", dim: int | None = None) -> Body:
        """A body from a dict (a scene file's table), refusing unknown keys
        and a missing ``shape`` or ``center`` with
        :class:`InvalidInputError` naming ``field.key``, a mesh in 2D
        (``dim``) naming ``field.shape`` and a mesh whose ``path`` was not
        read into ``vertices`` yet naming ``field.path``
        (:func:`hybridmpm.scenes.body_mesh.resolve_mesh_body` reads it). The
        values are checked by :func:`check_bodies`."""
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
                what = f" (one of {', '.join(SHAPES)})" if key == "shape" else ""
                raise InvalidInputError(f"{field}.{key}: missing{what}", f"{field}.{key}")
        if d.get("shape") == "mesh" and dim == 2:
            raise InvalidInputError(f"{field}.shape: 'mesh' bodies are 3D only (dim = 3); this scene has dim = 2", f"{field}.shape")
        if d.get("shape") == "mesh" and d.get("vertices") is None and d.get("path") is not None:
            raise InvalidInputError(
                f"{field}.path: not read yet: a scene file or MpmSimulator.add_body reads it (hybridmpm.scenes.body_mesh.resolve_mesh_body)", f"{field}.path"
            )
        for key, v in d.items():
            if key not in ("shape", "path", "angle_deg"):  # the core reads angle_deg in float64
                _float32_numbers(f"{field}.{key}", v)
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

    def hull(self) -> dict[str, np.ndarray]:
        """A mesh body's convex hull (:func:`hybridmpm._core.body_hull`):
        ``vertices`` float32 [V, 3] in the body's frame (centre of mass at 0)
        [m], ``faces`` uint32 [F, 3] (outward), ``offset`` float32 [3] (the
        centre of mass in the mesh's frame) and ``volume`` [m³]; computed
        once. Raises :class:`InvalidInputError` naming ``vertices``."""
        if self.shape != "mesh":
            raise InvalidInputError(f"shape: only a mesh body has a hull, this is a {self.shape}", "shape")
        cached = self.__dict__.get("_hull")
        if cached is None:
            cached = _core.body_hull(_vec(self.vertices), "path" if self.path is not None else "vertices")
            object.__setattr__(self, "_hull", cached)  # frozen: the hull is derived, not a field
        return cached

    def center_of_mass(self, dim: int) -> np.ndarray:
        """Where the body's centre of mass starts, float64 [D] [m]: ``center``,
        or for a mesh ``center`` plus its rotated hull offset."""
        c = np.asarray(self.center, np.float64)
        if self.shape == "mesh":
            c = c + self.rotation_matrix(dim) @ np.asarray(self.hull()["offset"], np.float64)
        return c

    def sdf(self, points: np.ndarray, center: Any = None, rotation: Any = None) -> np.ndarray:
        """Signed distance [m] of ``points`` [N, D] to the body (negative
        inside), float64 [N], where it is given or with its centre of mass
        at ``center`` [D] and ``rotation`` [D, D] (its pose now:
        :attr:`BodiesView.center`): what keeps a scene's blocks and a pour
        from seeding particles inside it. The solver's own distance, from
        the Rust core (:func:`hybridmpm._core.body_sdf`, float32 inside):
        a hull's is the largest of its face planes' (exact inside, a lower
        bound outside). Memory: the ``N`` distances, whatever the face
        count. Raises :class:`InvalidInputError` naming ``points``,
        ``center`` or ``rotation``."""
        p = np.ascontiguousarray(points, np.float64)
        if p.ndim != 2:
            raise InvalidInputError(f"points: expected [N, 2] or [N, 3], got shape {p.shape}", "points")
        c = None if center is None else np.asarray(center, np.float64).ravel().tolist()
        r = None if rotation is None else np.asarray(rotation, np.float64).tolist()
        return np.asarray(_core.body_sdf(self.to_dict(), p, c, r))


#: One frame's rigid bodies as :meth:`BodyTrack.stack` takes them: the bodies as given (a solver's ``params.bodies``),
#: their centres of mass float [B, D] [m], rotations [B, D, D] (columns: the body's axes) and masses [B] [kg; per unit
#: depth in 2D] (or None). A frame without bodies is None.
BodyFrame = tuple[Sequence[Any], Any, Any, Any]


def _real(field: str, v: Any) -> np.ndarray:
    """``v`` as a float64 array, or :class:`InvalidInputError` naming ``field`` when it holds no real numbers."""
    try:
        a = np.asarray(v)
    except (TypeError, ValueError) as e:  # ragged nested lists
        raise InvalidInputError(f"{field}: expected an array of real numbers ({e})", field) from e
    if a.dtype.kind not in "biuf":
        raise InvalidInputError(f"{field}: expected real numbers, got dtype {a.dtype}", field)
    out = np.array(a, np.float64)  # a copy: the track's arrays are its own, read-only
    out.flags.writeable = False
    return out


@dataclass(frozen=True, eq=False, repr=False)
class BodyTrack:
    """The rigid bodies of a run over its stored frames, as one checked value:
    what a rollout, a trajectory file and a session's recording hand to the
    pictures and exports (the GIF, the mesh sequences, the surfaces that end on
    the bodies, USD).

    ``shapes`` the ``B`` bodies as given (:class:`Body`, a scene's
    ``params.bodies``), a tuple; ``center`` float64 [T, B, D] [m] each body's
    centre of mass in each of the ``T`` frames (D 2 or 3); ``rotation``
    float64 [T, B, D, D] its rotation there (columns: the body's axes, ``x =
    center + rotation @ local``); ``mass`` float64 [B] [kg; per unit depth in
    2D], or None where the poses came without masses (a picture's arguments).
    The arrays are the track's own copies, read-only and finite.

    Constructing one (:meth:`make`, :meth:`stack` or the class itself) checks
    it once; its users check nothing again. Raises :class:`InvalidInputError`
    naming ``bodies`` (not a list), ``body_center`` (not real numbers, not [T, B, D] for the ``B``
    shapes with D 2 or 3, not finite), ``body_rotation`` (not real numbers,
    not [T, B, D, D], not finite) or ``body_mass`` (not [B], not finite and
    > 0). The rotations' orthonormality is not checked (the solver keeps
    them so; a picture draws what it is given)."""

    shapes: Sequence[Any]  # kept as a tuple
    center: np.ndarray
    rotation: np.ndarray
    mass: np.ndarray | None = None

    def __post_init__(self) -> None:
        if isinstance(self.shapes, (str, bytes, dict)) or not isinstance(self.shapes, (Sequence, np.ndarray)):
            raise InvalidInputError(f"bodies: expected the bodies as given (a list), got {type(self.shapes).__name__}", "bodies")
        b = len(self.shapes)
        c = _real("body_center", self.center)
        if c.ndim != 3 or c.shape[1] != b or c.shape[2] not in (2, 3) or not np.isfinite(c).all():
            raise InvalidInputError(f"body_center: expected finite [T, {b}, D] for the scene's {b} bodies, got {list(c.shape)}", "body_center")
        r = _real("body_rotation", self.rotation)
        if r.shape != c.shape + (c.shape[2],) or not np.isfinite(r).all():
            raise InvalidInputError(f"body_rotation: expected finite {list(c.shape + (c.shape[2],))}, got {list(r.shape)}", "body_rotation")
        m = None if self.mass is None else _real("body_mass", self.mass)
        if m is not None and (m.shape != (b,) or not np.isfinite(m).all() or not (m > 0).all()):
            raise InvalidInputError(f"body_mass: expected [{b}] finite masses > 0 [kg], got {list(m.shape)}", "body_mass")
        object.__setattr__(self, "shapes", tuple(self.shapes))
        object.__setattr__(self, "center", c)
        object.__setattr__(self, "rotation", r)
        object.__setattr__(self, "mass", m)

    @classmethod
    def make(cls, shapes: Sequence[Any], center: Any, rotation: Any, mass: Any = None, t_count: int | None = None) -> BodyTrack:
        """The track of ``shapes`` (B bodies as given) at ``center`` [T, B, D] [m] and ``rotation`` [T, B, D, D],
        with ``mass`` [B] [kg] or None, checked (the class's errors); with ``t_count``, ``T`` must be it (else
        :class:`InvalidInputError` naming ``body_center``)."""
        track = cls(shapes, center, rotation, mass)
        if t_count is not None and track.num_frames != t_count:
            b = len(track.shapes)
            raise InvalidInputError(
                f"body_center: expected finite [{t_count}, {b}, D] for the scene's {b} bodies in {t_count} frames, got {list(track.center.shape)}",
                "body_center",
            )
        return track

    @classmethod
    def stack(cls, frames: Sequence[BodyFrame | None]) -> BodyTrack | None:
        """The one rule that makes a track of per-frame records (:data:`BodyFrame`, oldest first): their poses
        stacked, float64 [T, B, D] and [T, B, D, D], with the first frame's shapes and masses, when every frame has
        the same bodies; None when there is no frame, a frame has no bodies (None, or no shapes), or the frames
        disagree on them (a body added or removed: another count, another body at an index — not the same object
        nor an equal :class:`Body` — or other masses). What a rollout (:func:`hybridmpm.sim.rollout`) and a
        session's recent trajectory keep. Raises :class:`InvalidInputError` as :meth:`make` for bad poses."""
        recs = [f for f in frames if f is not None and f[0] is not None and len(f[0])]
        if not recs or len(recs) != len(frames):
            return None
        first = recs[0]
        if not all(_same_shapes(f[0], first[0]) and _same_masses(f[3], first[3]) for f in recs[1:]):
            return None
        try:
            center, rotation = np.stack([np.asarray(f[1]) for f in recs]), np.stack([np.asarray(f[2]) for f in recs])
        except ValueError as e:
            raise InvalidInputError(f"body_center: the frames' poses do not stack ({e})", "body_center") from e
        return cls.make(first[0], center, rotation, first[3])

    @property
    def num_frames(self) -> int:
        """T."""
        return int(self.center.shape[0])

    @property
    def dim(self) -> int:
        """D, 2 or 3."""
        return int(self.center.shape[2])

    def __repr__(self) -> str:
        kinds = ", ".join(str(getattr(b, "shape", type(b).__name__)) for b in self.shapes)
        mass = "with masses" if self.mass is not None else "no masses"
        return f"BodyTrack([{kinds}], {self.num_frames} frames, {self.dim}D, {mass})"


def _same_shapes(a: Sequence[Any], b: Sequence[Any]) -> bool:
    """Whether two frames' bodies as given are the same: as many, each the same object or an equal :class:`Body`."""
    if len(a) != len(b):
        return False
    return all(x is y or (isinstance(x, Body) and isinstance(y, Body) and x.to_dict() == y.to_dict()) for x, y in zip(a, b))


def _same_masses(a: Any, b: Any) -> bool:
    """Whether two frames' masses are equal (both None, or the same numbers)."""
    if a is None or b is None:
        return a is None and b is None
    return bool(np.array_equal(np.asarray(a, np.float64), np.asarray(b, np.float64)))


def as_body_track(bodies: Any, center: Any = None, rotation: Any = None, *, mass: Any = None, t_count: int | None = None) -> BodyTrack | None:
    """What a public entry point was given of the bodies, as one :class:`BodyTrack` made once at its top:
    ``bodies`` a track already (then ``center`` and ``rotation`` stay None), or the bodies as given with their
    loose arrays ``center`` [T, B, D] [m] and ``rotation`` [T, B, D, D] (and ``mass`` [B] [kg]: :meth:`BodyTrack.make`).
    None (no bodies drawn or written) when ``bodies`` is None or empty or ``center`` is None. ``t_count``: the
    frames the track must have. Raises :class:`InvalidInputError` naming ``body_center`` (also for a track given
    with arrays beside it, or of another frame count), ``body_rotation`` or ``body_mass``."""
    if isinstance(bodies, BodyTrack):
        if center is not None or rotation is not None:
            raise InvalidInputError("body_center: give the poses either in the BodyTrack or as arrays, not both", "body_center")
        if t_count is not None and bodies.num_frames != t_count:
            b = len(bodies.shapes)
            raise InvalidInputError(f"body_center: expected [{t_count}, {b}, D] (a pose per frame), got {list(bodies.center.shape)}", "body_center")
        return bodies
    if bodies is None or not len(bodies) or center is None:
        return None
    return BodyTrack.make(bodies, center, rotation, mass, t_count)


def check_poses(bodies: Sequence[Any], center: Any, rotation: Any, t_count: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    """``center`` [T, B, D] [m] and ``rotation`` [T, B, D, D] for ``bodies`` (B of them; ``t_count`` frames when
    given), checked as :meth:`BodyTrack.make` checks them, as read-only float64 arrays: the track's poses for a
    caller that wants the arrays alone. Raises :class:`InvalidInputError` naming ``body_center`` or
    ``body_rotation``."""
    track = BodyTrack.make(bodies, center, rotation, t_count=t_count)
    return track.center, track.rotation


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


__all__ = [
    "BODY_STATE_LEN",
    "MAX_BODIES",
    "MAX_HULL_POINTS",
    "SHAPES",
    "BodiesView",
    "Body",
    "BodyFrame",
    "BodyTrack",
    "as_body_track",
    "check_bodies",
    "check_poses",
    "refuse_bodies",
]
