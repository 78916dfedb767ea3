"""The volume-fraction field of a fluid surface, its bodies and the estimate
of the volume they enclose at a level: steps 1-3 of
:mod:`hybridmpm.render.surface` (the p2g of the particles' volumes, the
smoothing, the closure against walls and obstacles) and what its
``iso="volume"`` levels are solved on.

Its public names are the seam with :mod:`hybridmpm.render.surface` (which
draws the level sets) and :mod:`hybridmpm.render.usd` (which needs
:func:`is_sampled`): :func:`field` builds a :class:`Field`, :func:`bodies`
labels it, :class:`VolumeEstimate` finds each body's level, :func:`closed`
closes it at that level; :data:`MARGIN` sizes the sub-grid."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from hybridmpm import _core
from hybridmpm.mpm import Sphere
from hybridmpm.scenes import collider_sdf

#: Range of the volume-matched iso level of a body (``iso="volume"``): bulk
#: water lands near 0.4, bodies a few cells across lower, films thinner than
#: a cell down to 0.1 (docs/mesh.md). A body whose field stays below ISO_MIN
#: is not drawn: a particle alone in the air (its field peaks at 0.010).
ISO_MIN, ISO_MAX = 0.02, 0.7
#: The levels bulk water needs start here: the estimate covers the cells that
#: can reach them first, and all cells only when a body needs less (a film).
ISO_BULK = 0.3
#: Nodes with a volume fraction above this belong to a body (26-connected
#: components); ``ISO_MIN / 2.5``, so every cell with a part above
#: ``ISO_MIN`` has a corner above it (``φ̄ + |∇φ̄|₁/2 ≤ 2.5·max corner``).
BODY_MIN = ISO_MIN / 2.5
#: Nodes of zero field around the particles' bounding box (kernel reach 1.5 +
#: smoothing 1 + a zero layer, rounded up): an int, in nodes of spacing ``h``.
MARGIN = 3
#: Field value beyond a wall face that lies on a node layer: marching cubes
#: puts the surface on the face node, ``(φ − c)/(φ + _WALL) < 1e-14`` of a cell out.
_WALL = 1e15
# p2g quantisation (the determinism paragraph of hybridmpm.render.surface): weights to 2^-10, volume fractions to 2^-14
_W_SCALE = 2.0**10
_V_SCALE = 2.0**14


def is_sampled(c: Any) -> bool:
    """Whether collider ``c`` is a sampled SDF (it has ``origin`` float [D] [m],
    ``cell`` [m] and ``values`` float [n_0, …, n_{D-1}] [m]: a scene's mesh
    obstacle, :class:`hybridmpm.mpm.SampledSdf`) rather than a
    :class:`~hybridmpm.mpm.Box` or :class:`~hybridmpm.mpm.Sphere`."""
    return all(hasattr(c, k) for k in ("origin", "cell", "values"))


@dataclass(frozen=True)
class Field:
    """The closed field of one material on the sub-grid around its particles.

    ``phi`` float64 [n_0, …, n_{D-1}]: the smoothed volume fraction, folded
    about every wall face that lies on a node layer and ``-_WALL`` beyond it;
    ``sdf`` [m]: distance of every node to the nearest wall or obstacle face
    (positive where fluid may be); ``clip`` the same for the faces closed by
    ``min(φ, c + sdf/(2h))`` (obstacles, walls off the node layers), None
    when there are none; ``origin`` int64 [D] the global node index of
    ``phi[0, …]`` (node ``i`` sits at ``i·h``); ``faces_lo``/``faces_hi``
    float [D] the global node index of the wall faces on a node layer (±inf
    for the others), where vertices are clamped; ``p``, ``v`` the particles
    meshed and their volumes [m^D]."""

    phi: np.ndarray
    sdf: np.ndarray
    clip: np.ndarray | None
    origin: np.ndarray
    faces_lo: np.ndarray
    faces_hi: np.ndarray
    h: float
    p: np.ndarray
    v: np.ndarray


def field(p: np.ndarray, v: np.ndarray, lo: np.ndarray, hi: np.ndarray, h: float, smooth: int, obstacles: list[Any]) -> Field | None:
    """The closed field (:class:`Field`) of the particles ``p`` float64 [N, D]
    [m] with volumes ``v`` float64 [N] [m^D] in the domain ``lo``, ``hi``
    float64 [D] [m], on nodes of spacing ``h`` [m], after ``smooth`` binomial
    passes per axis and closed against the walls and ``obstacles``
    (colliders of :mod:`hybridmpm.mpm`: steps 1-3 of
    :mod:`hybridmpm.render.surface`). None if no particle lies within
    :data:`MARGIN` nodes of the domain."""
    dim = p.shape[1]
    p_min, p_max = _bounds(p)
    if (p_min < lo - MARGIN * h).any() or (p_max > hi + MARGIN * h).any():
        keep = ((p >= lo - MARGIN * h) & (p <= hi + MARGIN * h)).all(axis=1)
        p, v = np.ascontiguousarray(p[keep]), v[keep]
        if len(p) == 0:
            return None
        p_min, p_max = _bounds(p)
    # sub-grid: the particles' bounding box (within the domain) plus the margin
    g_lo = np.floor(np.maximum(p_min, lo) / h).astype(np.int64) - MARGIN - 1
    g_hi = np.floor(np.minimum(p_max, hi) / h).astype(np.int64) + MARGIN + 2
    shape = [int(s) for s in g_hi - g_lo + 1]
    frac = np.rint(v * (_V_SCALE / h**dim)) / _V_SCALE  # [N]
    phi = _core.surface_p2g(np.ascontiguousarray(p), frac, h, [int(o) for o in g_lo], shape, _W_SCALE)
    for _ in range(int(smooth)):
        for ax in range(dim):
            phi = _binomial(phi, ax)
    coords = [(np.arange(shape[k]) + g_lo[k]) * h for k in range(dim)]
    sdf: Any = np.inf
    clip: Any = None
    faces = np.stack([np.full(dim, -np.inf), np.full(dim, np.inf)])
    for k in range(dim):
        sl: list[Any] = [None] * dim
        sl[k] = slice(None)
        dist = (coords[k] - lo[k], hi[k] - coords[k])
        sdf = np.minimum(sdf, np.minimum(*dist)[tuple(sl)])
        for side, face in enumerate((lo[k], hi[k])):
            node = round(face / h)
            if abs(face / h - node) <= 1e-6:  # a face on a node layer: folded and closed there
                faces[side, k] = node
                _fold(phi, k, node - int(g_lo[k]), side)
            else:  # a face between node layers: closed by the clip
                clip = dist[side][tuple(sl)] if clip is None else np.minimum(clip, dist[side][tuple(sl)])
    sdf = np.broadcast_to(sdf, phi.shape)
    if obstacles:
        sdf = sdf.copy()
        clip = np.full(phi.shape, np.inf) if clip is None else np.broadcast_to(clip, phi.shape).copy()
        for c in obstacles:
            _obstacle_sdf((sdf, clip), c, coords, h)
    if clip is not None:
        clip = np.broadcast_to(clip, phi.shape)
    return Field(phi, sdf, clip, g_lo, faces[0], faces[1], h, p, v)


def _fold(phi: np.ndarray, ax: int, i: int, side: int) -> None:
    """In place: fold ``phi`` about its node layer ``i`` along axis ``ax``, a
    wall face (``side`` 0: the fluid is above ``i``, 1: below): the field of
    the particles' mirror images across the face is added (node ``i + j``
    gains node ``i − j``'s value, the face node doubles), so that no volume
    is lost into the wall and fluid resting on it fills the face; beyond
    the face the field is ``-_WALL``."""
    n = phi.shape[ax]
    if not 0 <= i < n:
        return
    a = np.moveaxis(phi, ax, 0)  # a view
    if side == 1:
        a = a[::-1]
        i = n - 1 - i
    m = min(i, n - 1 - i)
    if m > 0:
        a[i + 1 : i + 1 + m] += a[i - m : i][::-1]
    a[i] *= 2.0
    a[:i] = -_WALL


def _bounds(p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per-axis min and max of ``p`` [N, D], one column at a time (numpy's
    ``min(axis=0)`` over short rows is about ten times slower)."""
    return np.array([p[:, k].min() for k in range(p.shape[1])]), np.array([p[:, k].max() for k in range(p.shape[1])])


def closed(phi: np.ndarray, clip: np.ndarray | None, h: float, iso: float) -> np.ndarray:
    """The field ``phi`` float64 [n_0, …, n_{D-1}] closed at level ``iso``:
    ``min(φ, iso + clip/(2h))`` (``clip`` [m] a :class:`Field`'s, or a box of
    it, the same shape; None: ``phi`` itself; ``h`` the node spacing [m]), so
    that the level set ends on the obstacle faces (and the walls off the node
    layers). A new array of ``phi``'s shape."""
    return phi if clip is None else np.minimum(phi, iso + clip * (0.5 / h))


def _binomial(a: np.ndarray, ax: int) -> np.ndarray:
    """``[1, 2, 1]/4`` along axis ``ax`` (zero outside)."""
    out = 0.5 * a
    lo = [slice(None)] * a.ndim
    hi = [slice(None)] * a.ndim
    lo[ax], hi[ax] = slice(None, -1), slice(1, None)
    out[tuple(hi)] += 0.25 * a[tuple(lo)]
    out[tuple(lo)] += 0.25 * a[tuple(hi)]
    return out


@dataclass(frozen=True)
class PosedBody:
    """A rigid body where one frame has it, for the surfaces to end on as on an
    obstacle: ``body`` (:class:`hybridmpm.mpm.bodies.Body`), its centre of
    mass ``center`` float64 [D] [m] and ``rotation`` [D, D] (a trajectory's
    ``body_center[t, i]``, ``body_rotation[t, i]``)."""

    body: Any
    center: np.ndarray
    rotation: np.ndarray

    def sdf(self, points: np.ndarray) -> np.ndarray:
        """Signed distance [m] of ``points`` [N, D] to the body there (:meth:`hybridmpm.mpm.bodies.Body.sdf`)."""
        return np.asarray(self.body.sdf(points, self.center, self.rotation))

    def reach(self) -> float:
        """The farthest point of the body from its centre of mass [m]."""
        b = self.body
        if b.shape == "box":
            return float(np.linalg.norm(b.half_extents))
        if b.shape == "capsule":
            return float(b.radius) + float(b.half_height)
        if b.shape == "mesh":
            return float(np.linalg.norm(np.asarray(b.hull()["vertices"], np.float64), axis=1).max())
        return float(b.radius)


def _obstacle_sdf(out: tuple[np.ndarray, ...], c: Any, coords: list[np.ndarray], h: float) -> None:
    """``a ← min(a, collider_sdf)`` in place for every ``a`` of ``out``, over the nodes near obstacle ``c`` (a
    collider or a :class:`PosedBody`)."""
    dim = len(coords)
    if is_sampled(c):  # the sampled box (outside it the collider's distance is positive)
        b_lo = np.asarray(c.origin, np.float64)
        b_hi = b_lo + float(c.cell) * (np.asarray(np.shape(c.values)) - 1)
    elif isinstance(c, PosedBody):
        b_lo, b_hi = c.center - c.reach(), c.center + c.reach()
    else:
        center = np.asarray(c.center, np.float64)
        r = float(c.radius) if isinstance(c, Sphere) else float(np.linalg.norm(c.half_extents))
        b_lo, b_hi = center - r, center + r
    sl = []
    for k in range(dim):
        i0 = int(np.searchsorted(coords[k], b_lo[k] - 3 * h))
        i1 = int(np.searchsorted(coords[k], b_hi[k] + 3 * h, side="right"))
        if i1 <= i0:
            return
        sl.append(slice(i0, i1))
    grids = np.meshgrid(*[coords[k][sl[k]] for k in range(dim)], indexing="ij")
    points = np.stack([g.ravel() for g in grids], axis=1)
    d = (c.sdf(points) if isinstance(c, PosedBody) else collider_sdf(c, points)).reshape(grids[0].shape)
    for a in out:
        a[tuple(sl)] = np.minimum(a[tuple(sl)], d)


def bodies(f: Field) -> tuple[np.ndarray, int, np.ndarray]:
    """The bodies of the field: int32 labels of the nodes (26-connected
    components of ``φ > BODY_MIN``, 1 … n; 0 elsewhere), n, and the volume
    [m^D] of each body's particles, float64 [n] (a particle belongs to the
    body of its nearest node in the domain; a particle whose node has
    ``φ ≤ BODY_MIN``, spray on its own, to none)."""
    from scipy import ndimage  # here: scipy.ndimage takes half a second to import, and only volume-matched surfaces need it

    labels, n = ndimage.label(f.phi > BODY_MIN, structure=np.ones((3,) * f.phi.ndim, bool))
    x = f.p * (1 / f.h)
    x += 0.5
    np.floor(x, out=x)  # the nearest node (global index)
    lo_node, hi_node = _bounds(x)
    for k in np.flatnonzero((lo_node < f.faces_lo) | (hi_node > f.faces_hi)):  # clamped into the domain
        np.clip(x[:, k], f.faces_lo[k], f.faces_hi[k], out=x[:, k])
    strides = np.cumprod((f.phi.shape[1:] + (1,))[::-1])[::-1].astype(np.float64)
    body = labels.ravel().take((x @ strides).astype(np.intp) - int(f.origin @ strides))
    if n == 1:
        out = body == 0
        return labels, 1, np.array([float(f.v.sum() - (f.v[out].sum() if out.any() else 0.0))])
    targets = np.bincount(body, weights=f.v, minlength=n + 1)[1:]
    return labels, int(n), targets


class VolumeEstimate:
    """The volume [m^D] of each body's part of ``{closed field > c}`` as a
    function of its level ``c``, without drawing the surface: every cell
    counts the fraction of itself above ``c`` from the value ``φ̄`` and
    gradient of the field's multilinear interpolant at its centre,
    ``clip(1/2 + (φ̄ − c)/|∇φ̄|₁, 0, 1)`` (``|∇φ̄|₁``: how much a linear field
    changes across the cell's extent along its gradient; exact for a flat
    face of a linear field), capped by the fraction of the cell inside the
    domain and out of the obstacles (the same formula on ``sdf/h`` at level
    0). A cell belongs to the body of its corners (``labels``, n bodies; all
    to one when n is 1). Piecewise linear and non-increasing in ``c``; built
    for the levels from ``low`` up (the fewer cells, the faster). Marching
    cubes cuts curved parts with flat triangles, so its volume is a little
    smaller: by 0.1-0.3 % for blocks of 8-16 cells, 1-4 % for the water3d
    scenes' bodies (docs/mesh.md)."""

    def __init__(self, phi: np.ndarray, sdf: np.ndarray, h: float, labels: np.ndarray | None = None, n: int = 1, low: float = ISO_MIN) -> None:
        # levels from ``low`` up: only cells with a corner above low/2.5 can count
        self.low = low
        cells = _cells_touching(phi > low / 2.5)
        val, g = _cell_centres(phi, cells)
        g = np.maximum(g, 1e-12)
        # the domain fraction is 1 where the first corner lies 4 nodes or more inside (sdf is a
        # distance, about 1-Lipschitz: the centre's value is then above half the cell's change)
        dom = np.ones(len(cells))
        near = np.flatnonzero(sdf.ravel().take(cells) < 4 * h)
        if len(near):
            s, gs = _cell_centres(sdf * (1 / h), cells[near])
            dom[near] = np.clip(0.5 + s / np.maximum(gs, 1e-12), 0.0, 1.0)
        full = np.flatnonzero(val - 0.5 * g >= ISO_MAX)  # cells above every level of the range: their domain fraction
        band = np.flatnonzero((val - 0.5 * g < ISO_MAX) & (val + 0.5 * g > low) & (dom > 0))
        self.n, self.cell = (n if labels is not None else 1), h**phi.ndim
        if self.n > 1 and labels is not None:  # a cell's corners above BODY_MIN are of one body (26-connected)
            self.full = np.bincount(_corner_max(labels, cells[full]) - 1, weights=dom[full], minlength=n)
            lab = _corner_max(labels, cells[band]) - 1
            order = np.argsort(lab, kind="stable")
            band = band[order]
            self.start = np.searchsorted(lab[order], np.arange(n + 1))
        else:
            self.full = np.array([dom[full].sum()])
            self.start = np.array([0, len(band)])
        self.val, self.inv_g, self.dom = val[band], 1.0 / g[band], dom[band]

    def volume(self, body: int, c: float) -> float:
        """The estimated volume [m^D] of body ``body`` (0 … n − 1) at level ``c``."""
        sl = slice(self.start[body], self.start[body + 1])
        frac = np.clip(0.5 + (self.val[sl] - c) * self.inv_g[sl], 0.0, 1.0)
        return self.cell * (float(self.full[body]) + float(np.minimum(frac, self.dom[sl]).sum()))

    def volumes(self, c: Any) -> np.ndarray:
        """The estimated volume of each body [n] at its level ``c`` [n]."""
        return np.array([self.volume(k, float(ck)) for k, ck in enumerate(np.broadcast_to(c, (self.n,)))])

    def levels(self, targets: Any) -> np.ndarray:
        """The level of each body whose estimated volume is its ``targets`` [n]: :meth:`level`."""
        return np.array([self.level(k, float(t)) for k, t in enumerate(np.broadcast_to(targets, (self.n,)))])

    def level(self, body: int, target: float) -> float:
        """The level in [low, ISO_MAX] whose estimated volume of body
        ``body`` is ``target`` (a bound where none is): regula falsi
        (Illinois) to 1e-6 of ``target``."""
        a, b = self.low, ISO_MAX
        fa, fb = self.volume(body, a) - target, self.volume(body, b) - target
        if fa <= 0:
            return a
        if fb >= 0:
            return b
        side, c = 0, a
        for _ in range(60):
            c = (a * fb - b * fa) / (fb - fa)
            fc = self.volume(body, c) - target
            if abs(fc) <= 1e-6 * target or b - a < 1e-9:
                return c
            if fc > 0:
                a, fa = c, fc
                fb = fb / 2 if side == 1 else fb
                side = 1
            else:
                b, fb = c, fc
                fa = fa / 2 if side == -1 else fa
                side = -1
        return c


def _corner_max(a: np.ndarray, cells: np.ndarray) -> np.ndarray:
    """The largest value of ``a`` at the corners of ``cells`` (flat indices of their first corners)."""
    d = a.ndim
    flat = a.ravel()
    strides = [int(np.prod(a.shape[k + 1 :])) for k in range(d)]
    out = flat.take(cells)
    for bits in range(1, 2**d):
        np.maximum(out, flat.take(cells + sum(b * s for b, s in zip(_bits(bits, d), strides))), out=out)
    return out


def _cells_touching(mask: np.ndarray) -> np.ndarray:
    """Flat node indices (into ``mask``'s shape) of the first corner of every
    cell with a corner where ``mask`` holds."""
    any_corner = mask
    for ax in range(mask.ndim):
        lo: list[Any] = [slice(None)] * mask.ndim
        hi: list[Any] = [slice(None)] * mask.ndim
        lo[ax], hi[ax] = slice(None, -1), slice(1, None)
        any_corner = any_corner[tuple(lo)] | any_corner[tuple(hi)]
    cell = np.zeros(mask.shape, bool)
    cell[tuple(slice(0, n - 1) for n in mask.shape)] = any_corner
    return np.flatnonzero(cell)


def _bits(bits: int, d: int) -> list[int]:
    """The corner offsets (0 or 1 per axis, first axis first) numbered ``bits``."""
    return [(bits >> (d - 1 - k)) & 1 for k in range(d)]


def _cell_centres(a: np.ndarray, cells: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Value and ``|gradient|₁`` [1/node] of the multilinear interpolant of the
    node values ``a`` at the centres of ``cells`` (flat indices of their first
    corners): two arrays [len(cells)]."""
    d = a.ndim
    flat = a.ravel()
    strides = [int(np.prod(a.shape[k + 1 :])) for k in range(d)]
    corners = [flat.take(cells + sum(b * s for b, s in zip(_bits(bits, d), strides))) for bits in range(2**d)]
    total = corners[0].copy()
    for c in corners[1:]:
        total += c
    l1 = np.zeros(len(cells))
    for k in range(d):
        upper = [c for bits, c in enumerate(corners) if _bits(bits, d)[k]]
        face = upper[0] + upper[1]
        for c in upper[2:]:
            face += c
        face *= 2
        face -= total  # Σ upper face − Σ lower face
        l1 += np.abs(face)
    return total * 0.5**d, l1 * 0.5 ** (d - 1)
