"""Moving obstacles: keyframed paths and the checks of a pose.

An obstacle (a collider of :class:`~hybridmpm.mpm.MpmParams`) may follow a
prescribed path: keyframes ``(t, center)``, ``t`` in seconds of simulated
time from the scene's start, ``center`` [m]. The path is piecewise linear
between keyframes (:func:`path_center`, :func:`numpy.interp` per axis, in
float64); before the first key the obstacle sits at the first key's centre,
after the last at the last's. Translation only: the obstacle keeps its
rotation. The simulators move the obstacles frame by frame
(:meth:`~hybridmpm.sim.MpmSimulator.move_obstacle`); docs/obstacles.md,
"Moving obstacles".
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from hybridmpm.errors import InvalidInputError

#: Fastest an obstacle may move [m/s]: a given velocity, a move asked of one step, a path's leg (a faster
#: one would ask the CFL rule for more substeps than a frame may take).
MAX_OBSTACLE_SPEED = 50.0
#: Most keyframes one obstacle's path may have.
MAX_KEYFRAMES = 4096
#: Latest keyframe time [s] (a day of simulated time; far beyond any rollout).
MAX_KEYFRAME_TIME = 86400.0


@dataclass(frozen=True)
class Keyframe:
    """One key of an obstacle's path: time ``t`` [s] and ``center`` [m] (``dim`` numbers)."""

    t: float
    center: tuple[float, ...]

    def to_dict(self) -> dict[str, Any]:
        return {"t": float(self.t), "center": [float(c) for c in self.center]}


def _number(v: Any) -> bool:
    return isinstance(v, (int, float, np.integer, np.floating)) and not isinstance(v, bool) and math.isfinite(float(v))


def check_center(name: str, value: Any, dim: int) -> np.ndarray:
    """An obstacle centre: ``dim`` finite numbers inside the unit domain
    ``[0, 1]``, as float64 ``[dim]``; else :class:`InvalidInputError` naming ``name``."""
    if isinstance(value, (str, bytes, dict)) or not isinstance(value, (Sequence, np.ndarray)):
        raise InvalidInputError(f"{name}: expected {dim} numbers [m], got {value!r}", name)
    if len(value) != dim or not all(_number(v) for v in value):
        raise InvalidInputError(f"{name}: expected {dim} finite numbers [m], got {list(value)!r}", name)
    c = np.asarray([float(v) for v in value], np.float64)
    if np.any(c < 0.0) or np.any(c > 1.0):
        raise InvalidInputError(f"{name}: must lie inside the domain [0, 1] on every axis, got {c.tolist()}", name)
    return c


def check_velocity(name: str, value: Any, dim: int) -> np.ndarray:
    """A velocity [m/s]: ``dim`` finite numbers, float64 ``[dim]``; else :class:`InvalidInputError` naming ``name``."""
    if isinstance(value, (str, bytes, dict)) or not isinstance(value, (Sequence, np.ndarray)):
        raise InvalidInputError(f"{name}: expected {dim} numbers [m/s], got {value!r}", name)
    if len(value) != dim or not all(_number(v) for v in value):
        raise InvalidInputError(f"{name}: expected {dim} finite numbers [m/s], got {list(value)!r}", name)
    v = np.asarray([float(v) for v in value], np.float64)
    if float(np.linalg.norm(v)) > MAX_OBSTACLE_SPEED:
        raise InvalidInputError(f"{name}: at most {MAX_OBSTACLE_SPEED:g} m/s, got {float(np.linalg.norm(v)):.4g}", name)
    return v


def check_keyframes(name: str, raw: Any, dim: int) -> tuple[Keyframe, ...]:
    """A path as a scene file gives it: a list of 1 to :data:`MAX_KEYFRAMES`
    tables ``{t, center}`` (:class:`Keyframe` objects too), times finite, in
    ``[0, MAX_KEYFRAME_TIME]`` s and strictly increasing, centres inside the
    domain, no leg faster than :data:`MAX_OBSTACLE_SPEED`. Raises :class:`InvalidInputError` naming the entry, e.g.
    ``obstacles[1].keyframes[2].t``."""
    if isinstance(raw, (str, bytes, dict)) or not isinstance(raw, (list, tuple)):
        raise InvalidInputError(f"{name}: expected a list of {{t, center}} keyframes, got {type(raw).__name__}", name)
    if not 1 <= len(raw) <= MAX_KEYFRAMES:
        raise InvalidInputError(f"{name}: {len(raw)} keyframes; a path has 1 to {MAX_KEYFRAMES}", name)
    keys: list[Keyframe] = []
    for k, entry in enumerate(raw):
        f = f"{name}[{k}]"
        if isinstance(entry, Keyframe):
            entry = entry.to_dict()
        if not isinstance(entry, dict):
            raise InvalidInputError(f"{f}: expected a table {{t, center}}, got {entry!r}", f)
        extra = sorted(set(entry) - {"t", "center"}, key=str)
        if extra:
            raise InvalidInputError(f"{f}.{extra[0]}: unknown keyframe key (allowed: t, center)", f"{f}.{extra[0]}")
        for key in ("t", "center"):
            if key not in entry:
                raise InvalidInputError(f"{f}.{key}: missing", f"{f}.{key}")
        t = entry["t"]
        if not _number(t) or not 0.0 <= float(t) <= MAX_KEYFRAME_TIME:
            raise InvalidInputError(f"{f}.t: must be a finite time in [0, {MAX_KEYFRAME_TIME:g}] s, got {t!r}", f"{f}.t")
        if keys and not float(t) > keys[-1].t:
            raise InvalidInputError(f"{f}.t: keyframe times must increase, got {float(t)!r} after {keys[-1].t!r}", f"{f}.t")
        c = check_center(f"{f}.center", entry["center"], dim)
        if keys:
            speed = float(np.linalg.norm(c - np.asarray(keys[-1].center))) / (float(t) - keys[-1].t)
            if speed > MAX_OBSTACLE_SPEED:
                raise InvalidInputError(f"{f}.center: reached at {speed:.4g} m/s from the key before; at most {MAX_OBSTACLE_SPEED:g} m/s", f"{f}.center")
        keys.append(Keyframe(float(t), tuple(float(v) for v in c)))
    return tuple(keys)


def path_center(keys: Sequence[Keyframe], t: float) -> np.ndarray:
    """The path's centre [m] at time ``t`` [s]: float64 ``[dim]``,
    :func:`numpy.interp` per axis (piecewise linear; the first key's centre
    before it, the last's after it)."""
    ts = np.asarray([k.t for k in keys], np.float64)
    cs = np.asarray([k.center for k in keys], np.float64)
    return np.asarray([np.interp(float(t), ts, cs[:, d]) for d in range(cs.shape[1])], np.float64)


__all__ = ["MAX_OBSTACLE_SPEED", "MAX_KEYFRAMES", "MAX_KEYFRAME_TIME", "Keyframe", "check_center", "check_keyframes", "check_velocity", "path_center"]
