"""The level of a material's surface, body by body: the volume matching of
:mod:`hybridmpm.render.surface` (step 4 of its module doc, ``iso="volume"``).

:func:`material_surface` builds one material's field
(:func:`~hybridmpm.render.surface_field.field`), splits it into bodies
(:func:`~hybridmpm.render.surface_field.bodies`), finds each body's level from
the field's volume estimate
(:class:`~hybridmpm.render.surface_field.VolumeEstimate`) and draws it with the
``measure`` it is given (marching cubes in 3D, contours in 2D: they stay in
:mod:`hybridmpm.render.surface`), once more where the drawn volume is off by
more than :data:`VOLUME_TOL`.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from hybridmpm.render.surface_field import ISO_BULK, ISO_MAX, ISO_MIN, Field, VolumeEstimate, bodies, closed, field

#: ``iso="volume"`` draws the surface a second time when its volume is off by more than this (relative).
VOLUME_TOL = 0.005


def material_surface(
    p: np.ndarray, v: np.ndarray, lo: np.ndarray, hi: np.ndarray, h: float, smooth: int, obs: list[Any], iso: Any, measure: Any
) -> tuple[float, Any]:
    """(level, geometry) of one material: its particles' positions ``p``
    float64 [N, D] [m] and volumes ``v`` float64 [N] [m^D] on the grid of
    spacing ``h`` [m] over the box ``lo``, ``hi`` float64 [D] [m], ``smooth``
    filter passes, the colliders ``obs``, ``iso`` ``"volume"`` or a level.
    ``measure(closed_field, level, origin, field)`` → (geometry, enclosed volume). ``iso="volume"``: each
    body (:func:`bodies`) at the level in [ISO_MIN, ISO_MAX] at which the
    field's estimated enclosed volume (:class:`VolumeEstimate`) is its
    particles' volume (the estimate covers the levels from ISO_BULK up
    first, all of them when a body needs less); a body whose surface is off
    by more than VOLUME_TOL is drawn once more, its level moved by the
    estimate's own error there. The level returned is that of the body with
    the most volume."""
    f = field(p, v, lo, hi, h, smooth, obs)
    if f is None:
        return (0.5 if iso == "volume" else float(iso)), None
    if iso != "volume":
        return float(iso), _draw(f, measure, _level32(float(iso)))[0]
    labels, n, targets = bodies(f)
    if not (targets > 0).any():
        return 0.5, None
    est = VolumeEstimate(f.phi, f.sdf, h, labels, n, low=ISO_BULK)
    c = est.levels(targets)
    if ((c == ISO_BULK) & (est.volumes(ISO_BULK) < targets)).any():  # a body thinner than bulk water: all levels
        est = VolumeEstimate(f.phi, f.sdf, h, labels, n)
        c = est.levels(targets)
    boxes = _boxes(labels) if n > 1 else [None]
    drawable = (targets > 0) & (est.volumes(ISO_MIN) > 0)  # a body whose field stays below ISO_MIN has no surface
    drawn = [_draw(f, measure, _level32(c[k]), labels, k + 1, boxes[k]) if drawable[k] else (None, 0.0) for k in range(n)]
    got = np.array([d[1] for d in drawn])
    off = (np.abs(got - targets) > VOLUME_TOL * targets) & ~((c == ISO_MIN) & (got < targets)) & ~((c == ISO_MAX) & (got > targets))
    if off.any():
        want = targets + est.volumes(c) - got  # the estimate's error at c taken as constant near it
        if est.low > ISO_MIN and (off & (est.volumes(est.low) < want)).any():
            est = VolumeEstimate(f.phi, f.sdf, h, labels, n)
        c2 = est.levels(want)
        for k in np.flatnonzero(off & (c2 != c)):
            c[k] = c2[k]
            drawn[k] = _draw(f, measure, _level32(c[k]), labels, int(k) + 1, boxes[k])
    return _level32(c[int(np.argmax(targets))]), _join([d[0] for d in drawn if d[0] is not None])


def _join(parts: list[Any]) -> Any:
    """The bodies' geometries as one: meshes ``(vertices, faces)`` concatenated,
    outlines (tuples of loops) chained; None when there are none."""
    if len(parts) <= 1:
        return parts[0] if parts else None
    if isinstance(parts[0], tuple) and len(parts[0]) == 2 and parts[0][0].shape[1:] == (3,) and parts[0][1].dtype == np.int32:
        offsets = np.cumsum([0] + [len(v) for v, _ in parts[:-1]])
        return np.concatenate([v for v, _ in parts]), np.concatenate([fs + np.int32(o) for (_, fs), o in zip(parts, offsets)])
    return tuple(loop for part in parts for loop in part)


def _boxes(labels: np.ndarray) -> list[Any]:
    """The slices of each body's bounding box (``scipy.ndimage.find_objects``)."""
    from scipy import ndimage  # here: scipy.ndimage takes half a second to import, and only volume-matched surfaces need it

    return list(ndimage.find_objects(labels))


def _level32(c: float) -> float:
    """``c`` rounded to float32: marching cubes compares the float32 field with
    the level, so a node clipped to exactly the level (on an obstacle face) is
    then outside, as a node below the level."""
    return float(np.float32(c))


def _draw(f: Field, measure: Any, c: float, labels: np.ndarray | None = None, body: int = 0, box: Any = None) -> tuple[Any, float]:
    """(geometry, enclosed volume) of the field closed at level ``c``; with
    ``box`` (a body's slices) the body ``body`` of ``labels`` alone, the
    other bodies' nodes zeroed."""
    if box is None or labels is None:
        grid, clip, origin = f.phi, f.clip, f.origin
    else:
        box = tuple(slice(max(b.start - 1, 0), b.stop + 1) for b in box)
        lab = labels[box]
        grid = np.where((lab == body) | (lab == 0), f.phi[box], 0.0)
        clip = None if f.clip is None else f.clip[box]
        origin = f.origin + np.array([b.start for b in box])
    shut = closed(grid, clip, f.h, c)
    if not shut.max() > c:
        return None, 0.0
    return measure(shut, c, origin, f)


__all__ = ["VOLUME_TOL", "material_surface"]
