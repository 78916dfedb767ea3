"""The sketch's geometry: where a sketch asks each particle to go.

One module for the controller (PD targets), the diffusion sampler (the
geometry it is conditioned on) and the free-motion prior (the correction
that bends a path onto the sketch), so that none of the three imports
another for it.

* :func:`pd_targets` — every particle's target point under a sketch (an
  arrow: moved by it; an oval: the cloud's ±2σ ellipse mapped onto it);
* :func:`sketch_geometry` — the sketch as the Fluid ControlNet reads it
  besides its image (a global vector and per-particle offsets, over
  :data:`GEOMETRY_SCALE`);
* :func:`smoothstep` — the 0 → 1 ramp along which a plan moves onto its targets.
"""

from __future__ import annotations

import math

import numpy as np

from hybridmpm.control.sketch import Sketch

#: Length scale [m] of the sketch geometry features.
GEOMETRY_SCALE = 0.3


def sketch_geometry(sketch: Sketch | None, positions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The sketch's geometry as the model reads it, besides its image:
    ``(global float32 [11], offset float32 [N, D])``.

    ``global``: has-sketch, is-arrow, is-oval, the arrow vector, the oval's
    centre relative to the fluid's centroid, its radii (all / 0.3 m), and
    ``cos 2θ``, ``sin 2θ`` of its axis (x–y); ``offset``: per particle the
    displacement to its target point under the sketch's geometric mapping
    (:func:`pd_targets`: the arrow, or the
    cloud's ±2σ ellipse mapped onto the oval), 0 in z, / 0.3 m. A blank sketch
    (None) gives zeros. ``positions`` float [N, D] m (the fluid)."""
    x = np.asarray(positions, np.float64)
    g = np.zeros(11, np.float32)
    if sketch is None:
        return g, np.zeros_like(x, dtype=np.float32)
    g[0] = 1.0
    if sketch.kind == "arrow":
        g[1] = 1.0
        g[3:5] = sketch.vector / GEOMETRY_SCALE
    else:
        c, r, ang = sketch.ellipse()
        g[2] = 1.0
        g[5:7] = (c - x[:, :2].mean(0)) / GEOMETRY_SCALE
        g[7:9] = r / GEOMETRY_SCALE
        g[9:11] = math.cos(2 * ang), math.sin(2 * ang)
    off = (pd_targets(x, sketch) - x) / GEOMETRY_SCALE
    return g, off.astype(np.float32)


def smoothstep(frames: int) -> np.ndarray:
    """``3s² − 2s³`` at ``s = f/(frames − 1)``: float64 [frames], 0 → 1 with zero slope at both ends."""
    u = np.linspace(0.0, 1.0, frames)
    return 3 * u**2 - 2 * u**3


def pd_targets(x: np.ndarray, sketch: Sketch) -> np.ndarray:
    """Per-particle targets of the PD controller, float64 [N, D]: arrow — each
    particle moved by the arrow (x–y); oval — the cloud's ±2σ ellipse (x–y
    principal axes) mapped affinely onto the drawn ellipse by a stretch along
    the axes and the smaller of the two rotations that align the major axes
    (an ellipse is the same turned by 180°), never a reflection: a cloud
    mapped onto its own ±2σ oval stays where it is. Depth (3D z) is kept."""
    y = np.array(x, np.float64)
    if sketch.kind == "arrow":
        y[:, :2] += sketch.vector
        return y
    xy = x[:, :2]
    c0 = xy.mean(0)
    vals, vecs = np.linalg.eigh(np.cov((xy - c0).T) if len(xy) > 1 else np.eye(2) * 1e-8)
    order = np.argsort(vals)[::-1]
    r0 = 2.0 * np.sqrt(np.maximum(vals[order], 1e-10))
    c1, r1, angle = sketch.ellipse()
    r1_axes = np.array([[math.cos(angle), -math.sin(angle)], [math.sin(angle), math.cos(angle)]])
    # eigh's axes have arbitrary signs: take the major axis on the drawn one's side and the minor axis a quarter turn
    # from it, as r1_axes is built, so that the map is a rotation (det +1), never a mirror image of the cloud
    major = vecs[:, order[0]] * (1.0 if vecs[:, order[0]] @ r1_axes[:, 0] >= 0.0 else -1.0)
    r0_axes = np.array([[major[0], -major[1]], [major[1], major[0]]])
    local = (xy - c0) @ r0_axes / r0  # unit-ellipse coordinates along the cloud's axes
    y[:, :2] = c1 + (local * r1) @ r1_axes.T
    return y


__all__ = ["GEOMETRY_SCALE", "pd_targets", "sketch_geometry", "smoothstep"]
