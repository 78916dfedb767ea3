"""Sketches: arrows and ovals, as users draw them and as training makes them
(paper Sec. 3.2, App. C).

One format everywhere (CLI, Python, HTTP; docs/design.md "Sketch"): JSON
``{"kind": "arrow" | "oval", "points": [[x, y], ...], "t": [...]?, "width": [...]?}``
in domain coordinates with y up. ``t`` (optional) is the time of each point
[s] as drawn; ``width`` (optional) the stroke width at each point [m] — in 3D
it encodes depth (wider = nearer the viewer, who looks along −z).

:func:`render_sketch` is the one rasteriser: it turns a sketch into the image
the network reads, for training and for serving alike, so a sketch drawn in a
browser and a training sketch pass through the same function.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from hybridmpm.errors import InvalidInputError
from hybridmpm.files import loads_json

#: Sketch kinds.
KINDS = ("arrow", "oval")
#: Most points a sketch may have (a long pen stroke at 120 Hz for 30 s).
MAX_POINTS = 4096
#: Coordinates are accepted in [-COORD_LIMIT, 1 + COORD_LIMIT] (strokes may leave the domain).
COORD_LIMIT = 1.0
#: Default stroke width [m] of an arrow (domain units) and the 3D depth range.
WIDTH = 0.012
WIDTH_MIN, WIDTH_MAX = 0.006, 0.024
#: Image size the network reads.
IMAGE_SIZE = 64
#: Points of an oval's outline.
OVAL_POINTS = 64


@dataclass
class Sketch:
    """An arrow or an oval in domain coordinates (y up).

    ``kind`` "arrow" (from the first point to the last) or "oval" (a closed
    stroke); ``points`` float64 [P, 2] [m]; ``t`` [P] [s] or None; ``width``
    [P] [m] or None (default :data:`WIDTH`). Construction validates
    (:meth:`validate`); errors name the field (``points``, ``t``, ...).
    """

    kind: str
    points: np.ndarray
    t: np.ndarray | None = None
    width: np.ndarray | None = None
    meta: dict[str, Any] = field(default_factory=dict)
    _ellipse: tuple[np.ndarray, tuple[np.ndarray, np.ndarray, float]] | None = field(default=None, init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        self.validate()

    def validate(self) -> None:
        if self.kind not in KINDS:
            raise InvalidInputError(f"kind: must be one of {', '.join(KINDS)}, got {self.kind!r}", "kind")
        try:
            p = np.asarray(self.points, np.float64)
        except (TypeError, ValueError):
            raise InvalidInputError("points: expected [[x, y], ...] numbers", "points") from None
        if p.ndim != 2 or p.shape[1] != 2:
            raise InvalidInputError(f"points: expected [[x, y], ...], got shape {list(p.shape)}", "points")
        if not 2 <= len(p) <= MAX_POINTS:
            raise InvalidInputError(f"points: need 2 … {MAX_POINTS} points, got {len(p)}", "points")
        if not np.isfinite(p).all() or (p < -COORD_LIMIT).any() or (p > 1 + COORD_LIMIT).any():
            raise InvalidInputError(f"points: must be finite domain coordinates in [{-COORD_LIMIT:g}, {1 + COORD_LIMIT:g}]", "points")
        self.points = p
        for name in ("t", "width"):
            v = getattr(self, name)
            if v is None:
                continue
            try:
                a = np.asarray(v, np.float64)
            except (TypeError, ValueError):
                raise InvalidInputError(f"{name}: expected one number per point", name) from None
            if a.shape != (len(p),) or not np.isfinite(a).all():
                raise InvalidInputError(f"{name}: expected {len(p)} finite numbers (one per point), got shape {list(a.shape)}", name)
            if name == "t" and (np.diff(a) < 0).any():
                raise InvalidInputError("t: must not decrease along the stroke", "t")
            if name == "width" and not ((a > 0) & (a <= 0.5)).all():
                raise InvalidInputError("width: must lie in (0, 0.5] [m]", "width")
            setattr(self, name, a)
        if np.linalg.norm(p.max(0) - p.min(0)) == 0:
            raise InvalidInputError("points: all points coincide (a dot is not a sketch)", "points")

    # ------------------------------------------------------------ JSON
    @classmethod
    def from_json(cls, obj: Any) -> Sketch:
        """A sketch from its JSON object (a dict, or a JSON string). Raises
        :class:`InvalidInputError` naming the field."""
        if isinstance(obj, (str, bytes)):
            obj = loads_json(obj, "sketch")  # nesting checked before parsing
        if not isinstance(obj, dict):
            raise InvalidInputError("sketch: expected a JSON object {kind, points, t?, width?}", "sketch")
        unknown = sorted(set(obj) - {"kind", "points", "t", "width"})
        if unknown:
            raise InvalidInputError(f"{unknown[0]}: unknown sketch field (allowed: kind, points, t, width)", unknown[0])
        if "kind" not in obj or "points" not in obj:
            missing = "kind" if "kind" not in obj else "points"
            raise InvalidInputError(f"{missing}: required", missing)
        return cls(obj["kind"], obj["points"], obj.get("t"), obj.get("width"))

    def to_json(self) -> dict[str, Any]:
        d: dict[str, Any] = {"kind": self.kind, "points": self.points.tolist()}
        if self.t is not None:
            d["t"] = self.t.tolist()
        if self.width is not None:
            d["width"] = self.width.tolist()
        return d

    # ------------------------------------------------------------ geometry
    @property
    def start(self) -> np.ndarray:
        return self.points[0]

    @property
    def end(self) -> np.ndarray:
        return self.points[-1]

    @property
    def vector(self) -> np.ndarray:
        """Arrow: end − start [m] (2D, x right, y up)."""
        return self.points[-1] - self.points[0]

    def target(self, centroid: np.ndarray) -> np.ndarray:
        """The fluid centroid the sketch asks for, x–y float64 [2] [m]: an
        arrow's vector added to ``centroid``'s x–y (where the fluid is when
        the control starts), an oval's centre (:meth:`ellipse`)."""
        if self.kind == "arrow":
            return np.asarray(centroid, np.float64)[:2] + self.vector
        return self.ellipse()[0]

    def ellipse(self) -> tuple[np.ndarray, np.ndarray, float]:
        """Oval: ``(centre [2], radii [2], angle [rad])`` of the ellipse that
        best fits the stroke (direct least-squares conic fit, Fitzgibbon et al.
        1999, on coordinates centred and scaled for conditioning; if the stroke
        is no ellipse — too few or collinear points — the second moments of its
        points). Radii sorted largest first; ``angle`` is the first radius's
        direction. Fitted once per sketch (copies are returned)."""
        if self._ellipse is None or self._ellipse[0] is not self.points:
            self._ellipse = (self.points, self._fit())
        c, r, ang = self._ellipse[1]
        return c.copy(), r.copy(), ang

    def _fit(self) -> tuple[np.ndarray, np.ndarray, float]:
        p = self.points
        c0 = p.mean(0)
        scale = max(float(np.abs(p - c0).max()), 1e-12)
        q = (p - c0) / scale
        fit = _fit_ellipse(q) if len(q) >= 6 else None
        if fit is None:
            d = q - q.mean(0)
            vals, vecs = np.linalg.eigh(d.T @ d / len(d))
            order = np.argsort(vals)[::-1]
            axis = vecs[:, order[0]]
            return c0 + q.mean(0) * scale, np.sqrt(2.0 * np.maximum(vals[order], 0.0)) * scale, float(math.atan2(axis[1], axis[0]))
        c, r, ang = fit
        return c0 + c * scale, r * scale, ang

    # ------------------------------------------------------------ constructors
    @classmethod
    def arrow(cls, start: Any, end: Any, width: Any = None) -> Sketch:
        """A straight arrow; ``width`` a number or [start, end] widths [m]."""
        pts = np.array([start, end], np.float64)
        w = None if width is None else np.broadcast_to(np.asarray(width, np.float64), (2,)).copy()
        return cls("arrow", pts, None, w)

    @classmethod
    def oval(cls, center: Any, radii: Any, angle: float = 0.0, points: int = OVAL_POINTS) -> Sketch:
        """An ellipse outline: ``center`` [2], ``radii`` [2] [m], ``angle`` [rad] of the first radius."""
        c = np.asarray(center, np.float64)
        r = np.asarray(radii, np.float64)
        th = np.linspace(0.0, 2 * np.pi, points, endpoint=False)
        local = np.stack([r[0] * np.cos(th), r[1] * np.sin(th)], -1)
        rot = np.array([[math.cos(angle), -math.sin(angle)], [math.sin(angle), math.cos(angle)]])
        return cls("oval", c + local @ rot.T)


#: Largest sketch image accepted [pixels] (a 2048² canvas).
MAX_IMAGE_PIXELS = 2048 * 2048
#: Largest sketch file read [bytes] (a PNG or a JSON sketch).
MAX_SKETCH_FILE_BYTES = 16 * 2**20
#: Longest side a sketch image is read at [pixels]: a larger one is read as its ink mask, max-pooled down to this.
READ_SIZE = 512
#: A pixel is ink when its colour is this far (in levels of 255) from the background's.
INK_LEVEL = 64


def sketch_from_png(data: bytes) -> Sketch:
    """A sketch from a PNG of the drawing (any size up to :data:`MAX_IMAGE_PIXELS`,
    the image spanning the domain ``[0, 1]²`` with y up, ink darker or
    lighter than the background): :func:`sketch_from_image` of its pixels,
    decoded at 8 bits per channel. An image larger than :data:`READ_SIZE`
    is read as its ink mask, computed in bands of rows and max-pooled down
    to that size (a few bytes per pixel, never a float copy of the whole
    image). Raises :class:`InvalidInputError` (field ``sketch``) for a file
    that is not a PNG, too large, or holds no readable stroke."""
    import io

    from PIL import Image

    if not isinstance(data, (bytes, bytearray)) or data[:8] != b"\x89PNG\r\n\x1a\n":
        raise InvalidInputError("sketch: not a PNG image", "sketch")
    try:
        with Image.open(io.BytesIO(data), formats=["PNG"]) as im:
            if im.width * im.height > MAX_IMAGE_PIXELS:
                raise InvalidInputError(f"sketch: {im.width}×{im.height} pixels, more than {MAX_IMAGE_PIXELS}", "sketch")
            rgb = im.convert("RGB")
    except InvalidInputError:
        raise
    except Exception as e:  # noqa: BLE001 - Pillow raises many types for broken files
        raise InvalidInputError(f"sketch: unreadable PNG ({type(e).__name__})", "sketch") from e
    if max(rgb.size) <= READ_SIZE:
        return sketch_from_image(np.asarray(rgb))
    if min(rgb.size) < 8:
        raise InvalidInputError(f"sketch: expected an image of at least 8×8 pixels, got {list(rgb.size)}", "sketch")
    return _sketch_from_ink(_pooled_ink(np.asarray(rgb)))


def _pooled_ink(a: np.ndarray) -> np.ndarray:
    """The ink mask of a large uint8 [H, W, 3] image, max-pooled by the
    smallest integer factor that brings its longer side to at most
    :data:`READ_SIZE`, computed a band of rows at a time in float32."""
    h, w = a.shape[:2]
    k = -(-max(h, w) // READ_SIZE)
    bg = np.median(a[::k, ::k].reshape(-1, 3), axis=0).astype(np.float32)  # the background: the median colour
    hp, wp = -(-h // k), -(-w // k)
    out = np.zeros((hp, wp), bool)
    band = 16 * k
    for r0 in range(0, h, band):
        block = a[r0 : r0 + band].astype(np.float32) - bg
        ink = np.einsum("ijc,ijc->ij", block, block) > INK_LEVEL**2
        rows = -(-ink.shape[0] // k)
        padded = np.zeros((rows * k, wp * k), bool)
        padded[: ink.shape[0], :w] = ink
        out[r0 // k : r0 // k + rows] = padded.reshape(rows, k, wp, k).any(axis=(1, 3))
    return out


def sketch_from_image(img: np.ndarray) -> Sketch:
    """Read an arrow or an oval back from a picture of it.

    ``img`` uint8 [H, W] (grey) or [H, W, 3] spanning ``[0, 1]²`` with y up
    (row 0 is y = 1). The ink is what differs from the background (the median
    tone or colour) by more than 64 levels. An oval leaves its centre empty and its ink ring fits an ellipse
    (least squares); otherwise it is an arrow along the ink's principal axis,
    pointing to the end whose ink is wider (the head). Raises
    :class:`InvalidInputError` (field ``sketch``) when too little ink is found."""
    a = np.asarray(img, np.float64)
    if a.ndim == 3:  # colour: the distance of each pixel's colour from the background's (the median colour)
        a = np.linalg.norm(a[..., :3] - np.median(a[..., :3].reshape(-1, 3), axis=0), axis=-1)
    elif a.ndim == 2:
        a = np.abs(a - float(np.median(a)))
    if a.ndim != 2 or min(a.shape) < 8:
        raise InvalidInputError(f"sketch: expected an image of at least 8×8 pixels, got {list(np.shape(img))}", "sketch")
    return _sketch_from_ink(a > INK_LEVEL)


def _sketch_from_ink(ink: np.ndarray) -> Sketch:
    """:func:`sketch_from_image` from the ink mask bool [H, W]."""
    h, w = ink.shape
    if ink.sum() < 8 or ink.mean() > 0.5:
        raise InvalidInputError("sketch: no stroke found in the image", "sketch")
    rows, cols = np.nonzero(ink)
    pts = np.stack([(cols + 0.5) / w, 1.0 - (rows + 0.5) / h], -1)
    c = pts.mean(0)
    d = pts - c
    vals, vecs = np.linalg.eigh(d.T @ d / len(d))
    major, minor = vecs[:, 1], vecs[:, 0]
    u = d @ major
    v = d @ minor
    extent = float(u.max() - u.min())
    width = float(v.max() - v.min())
    # an oval: a closed ring leaves its middle empty
    near = np.linalg.norm(d, axis=1) < 0.25 * min(extent, max(width, 1e-9))
    if width > 0.25 * extent and near.mean() < 0.02:
        fit = _fit_ellipse((pts - c) / max(extent, 1e-9))
        if fit is not None:
            ec, er, ang = fit
            return Sketch.oval(c + ec * max(extent, 1e-9), er * max(extent, 1e-9), ang)
    lo, hi = u.min(), u.max()
    band = 0.2 * (hi - lo)
    spread_lo = float(np.ptp(v[u < lo + band])) if (u < lo + band).any() else 0.0
    spread_hi = float(np.ptp(v[u > hi - band])) if (u > hi - band).any() else 0.0
    tail, head = (c + lo * major, c + hi * major) if spread_hi >= spread_lo else (c + hi * major, c + lo * major)
    return Sketch.arrow(tail, head)


def _fit_ellipse(q: np.ndarray) -> tuple[np.ndarray, np.ndarray, float] | None:
    """Centre, radii (largest first) and angle of the least-squares ellipse
    through points ``q`` [P, 2], or None if the best conic is no ellipse."""
    x, y = q[:, 0], q[:, 1]
    d1 = np.stack([x * x, x * y, y * y], 1)
    d2 = np.stack([x, y, np.ones_like(x)], 1)
    s1, s2, s3 = d1.T @ d1, d1.T @ d2, d2.T @ d2
    try:
        t = -np.linalg.solve(s3, s2.T)
        m = s1 + s2 @ t
        m = np.array([m[2] / 2, -m[1], m[0] / 2])
        vals, vecs = np.linalg.eig(m)
    except np.linalg.LinAlgError:
        return None
    vecs = np.real(vecs)
    cond = 4 * vecs[0] * vecs[2] - vecs[1] ** 2
    ok = np.nonzero(cond > 0)[0]
    if len(ok) == 0:
        return None
    a1 = vecs[:, ok[0]]
    a, b, c = a1
    dd, e, f = t @ a1
    den = b * b - 4 * a * c
    if den >= 0:
        return None
    cx = (2 * c * dd - b * e) / den
    cy = (2 * a * e - b * dd) / den
    # the quadratic form at the centre: [x y] M [x y]^T = k
    mm = np.array([[a, b / 2], [b / 2, c]])
    k = -(a * cx * cx + b * cx * cy + c * cy * cy + dd * cx + e * cy + f)
    ev, evec = np.linalg.eigh(mm / k if k != 0 else mm)
    if not (ev > 0).all():
        return None
    radii = 1.0 / np.sqrt(ev)  # eigh sorts ascending: the smallest eigenvalue is the largest radius
    axis = evec[:, 0]
    return np.array([cx, cy]), radii, float(math.atan2(axis[1], axis[0]))


def sketch_from_trajectory(start: np.ndarray, end: np.ndarray, kind: str) -> Sketch:
    """The sketch training pairs with a controlled run (paper App. C).

    ``start``, ``end`` float [N, D]: fluid positions at the first and the last
    frame of the *controlled* run. Arrow: from the centroid of ``start`` to
    that of ``end`` (in 3D projected on x–y, the viewer looking along −z;
    widths from :data:`WIDTH_MIN` to :data:`WIDTH_MAX` by the depth z of each
    segment, constant when z does not change). Oval: the ellipse centred on
    ``end``'s centroid with radii ±2σ along its principal axes (x–y)."""
    a, b = np.asarray(start, np.float64), np.asarray(end, np.float64)
    if kind == "arrow":
        c0, c1 = a.mean(0), b.mean(0)
        if a.shape[1] == 3:
            z0, z1 = c0[2], c1[2]
            if abs(z1 - z0) < 1e-9:
                w = np.full(2, 0.5 * (WIDTH_MIN + WIDTH_MAX))
            else:  # nearer (larger z) is wider; the depth range of this arrow spans the width range
                w = np.array([WIDTH_MIN, WIDTH_MAX]) if z1 > z0 else np.array([WIDTH_MAX, WIDTH_MIN])
            return Sketch.arrow(c0[:2], c1[:2], w)
        return Sketch.arrow(c0, c1)
    if kind == "oval":
        xy = b[:, :2]
        c = xy.mean(0)
        vals, vecs = np.linalg.eigh(np.cov((xy - c).T) if len(xy) > 1 else np.eye(2) * 1e-8)
        order = np.argsort(vals)[::-1]
        radii = 2.0 * np.sqrt(np.maximum(vals[order], 1e-10))
        ax = vecs[:, order[0]]
        return Sketch.oval(c, np.maximum(radii, 1e-3), math.atan2(ax[1], ax[0]))
    raise InvalidInputError(f"kind: must be one of {', '.join(KINDS)}, got {kind!r}", "kind")


def render_sketch(sketch: Sketch | None, size: int = IMAGE_SIZE, supersample: int = 4) -> np.ndarray:
    """Rasterise a sketch: uint8 [size, size, 3], white ink on black, the
    domain ``[0, 1]²`` filling the image with y up (row 0 is y = 1). Arrows:
    the stroke (per-point widths) and a head at the end, in channel 0 and 1
    (channel 1 holds the head only: where the arrow points); ovals in channel
    2. ``None`` (no sketch) renders blank — the classifier-free guidance
    null. Drawn ``supersample``× larger with Pillow and downsampled (anti-aliased)."""
    from PIL import Image, ImageDraw

    if not 8 <= int(size) <= 1024:
        raise InvalidInputError(f"size: must be in [8, 1024], got {size!r}", "size")
    big = int(size) * int(supersample)
    layers = [Image.new("L", (big, big), 0) for _ in range(3)]
    if sketch is not None:

        def px(p: np.ndarray) -> tuple[float, float]:
            return (float(p[0]) * big, float(1.0 - p[1]) * big)  # y up → rows down, once

        pts = sketch.points
        widths = sketch.width if sketch.width is not None else np.full(len(pts), WIDTH)
        if sketch.kind == "arrow":
            stroke = ImageDraw.Draw(layers[0])
            for i in range(len(pts) - 1):
                w = max(1, round(0.5 * (widths[i] + widths[i + 1]) * big))
                stroke.line([px(pts[i]), px(pts[i + 1])], fill=255, width=w)
            v = sketch.vector
            length = float(np.linalg.norm(v))
            if length > 0:
                u = v / length
                n = np.array([-u[1], u[0]])
                head = min(0.35 * length, 0.06) + 2 * widths[-1]
                tip = pts[-1]
                tri = [px(tip), px(tip - head * u + 0.5 * head * n), px(tip - head * u - 0.5 * head * n)]
                ImageDraw.Draw(layers[1]).polygon(tri, fill=255)
                ImageDraw.Draw(layers[0]).polygon(tri, fill=255)
        else:
            w = max(1, round(float(np.mean(widths)) * big))
            ring = [px(p) for p in np.concatenate([pts, pts[:1]])]
            ImageDraw.Draw(layers[2]).line(ring, fill=255, width=w, joint="curve")
    img = np.stack([np.asarray(layer.resize((int(size), int(size)), Image.Resampling.BOX)) for layer in layers], -1)
    return img.astype(np.uint8)


__all__ = [
    "IMAGE_SIZE",
    "KINDS",
    "MAX_IMAGE_PIXELS",
    "MAX_POINTS",
    "WIDTH",
    "Sketch",
    "render_sketch",
    "sketch_from_image",
    "sketch_from_png",
    "sketch_from_trajectory",
]
