"""The volume-fraction field of a fluid surface and the estimate of the volume
it encloses at a level: steps 1-3 of :mod:`hybridmpm.render.surface` (the p2g
of the particles' volumes, the smoothing, the closure against walls and
obstacles) and the estimate its ``iso="volume"`` level is solved on."""

from __future__ import annotations

from typing import Any

import numpy as np

from hybridmpm import _core
from hybridmpm.mpm import Sphere
from hybridmpm.scenes import collider_sdf

#: Range of the volume-matched iso level (``iso="volume"``).
ISO_MIN, ISO_MAX = 0.3, 0.7
#: Nodes of zero field around the particles' bounding box (kernel reach 1.5 +
#: smoothing 1 + a zero layer, rounded up).
_MARGIN = 3
# p2g quantisation (the determinism paragraph of hybridmpm.render.surface): weights to 2^-10, volume fractions to 2^-14
_W_SCALE = 2.0**10
_V_SCALE = 2.0**14


def _is_sampled(c: Any) -> bool:
    """A sampled-SDF collider (``origin``, ``cell``, ``values``: a scene's mesh obstacle)."""
    return all(hasattr(c, k) for k in ("origin", "cell", "values"))


def _field(
    p: np.ndarray, v: np.ndarray, lo: np.ndarray, hi: np.ndarray, h: float, smooth: int, obstacles: list[Any]
) -> tuple[np.ndarray, np.ndarray, np.ndarray, float] | None:
    """The smoothed volume fraction on the sub-grid around the particles:
    (field float64 [n_0, ..., n_{D-1}], signed distance [m] of every node to
    the nearest wall face or obstacle face (positive where fluid may be),
    origin int64 [D] the global node index of the first node (node ``i`` sits
    at ``i·h``), the volume [m^D] of the particles meshed). None if no particle
    lies within 3 nodes of the domain."""
    dim = p.shape[1]
    p_min, p_max = _bounds(p)
    if (p_min < lo - _MARGIN * h).any() or (p_max > hi + _MARGIN * h).any():
        keep = ((p >= lo - _MARGIN * h) & (p <= hi + _MARGIN * h)).all(axis=1)
        p, v = np.ascontiguousarray(p[keep]), v[keep]
        if len(p) == 0:
            return None
        p_min, p_max = _bounds(p)
    # sub-grid: the particles' bounding box (within the domain) plus the margin
    g_lo = np.floor(np.maximum(p_min, lo) / h).astype(np.int64) - _MARGIN - 1
    g_hi = np.floor(np.minimum(p_max, hi) / h).astype(np.int64) + _MARGIN + 2
    shape = [int(s) for s in g_hi - g_lo + 1]
    frac = np.rint(v * (_V_SCALE / h**dim)) / _V_SCALE  # [N]
    phi = _core.surface_p2g(np.ascontiguousarray(p), frac, h, [int(o) for o in g_lo], shape, _W_SCALE)
    for _ in range(int(smooth)):
        for ax in range(dim):
            phi = _binomial(phi, ax)
    # distance to the walls (separable box distance) and the obstacles
    coords = [(np.arange(shape[k]) + g_lo[k]) * h for k in range(dim)]
    sdf = np.full(phi.shape, np.inf)
    for k in range(dim):
        d = np.minimum(coords[k] - lo[k], hi[k] - coords[k])
        sl: list[Any] = [None] * dim
        sl[k] = slice(None)
        sdf = np.minimum(sdf, d[tuple(sl)])
    for c in obstacles:
        _obstacle_sdf(sdf, c, coords, h)
    return phi, sdf, g_lo, float(v.sum())


def _bounds(p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per-axis min and max of ``p`` [N, D], one column at a time (numpy's
    ``min(axis=0)`` over short rows is about ten times slower)."""
    return np.array([p[:, k].min() for k in range(p.shape[1])]), np.array([p[:, k].max() for k in range(p.shape[1])])


def _closed(phi: np.ndarray, sdf: np.ndarray, h: float, iso: float) -> np.ndarray:
    """``min(φ, iso + sdf/(2h))``: the level set ends on the wall and obstacle faces."""
    clip = iso + sdf / (2 * h)
    return np.minimum(phi, clip)


def _binomial(a: np.ndarray, ax: int) -> np.ndarray:
    """``[1, 2, 1]/4`` along axis ``ax`` (zero outside)."""
    out = 0.5 * a
    lo = [slice(None)] * a.ndim
    hi = [slice(None)] * a.ndim
    lo[ax], hi[ax] = slice(None, -1), slice(1, None)
    out[tuple(hi)] += 0.25 * a[tuple(lo)]
    out[tuple(lo)] += 0.25 * a[tuple(hi)]
    return out


def _obstacle_sdf(sdf: np.ndarray, c: Any, coords: list[np.ndarray], h: float) -> None:
    """``sdf ← min(sdf, collider_sdf)`` in place, over the nodes near obstacle ``c``."""
    dim = sdf.ndim
    if _is_sampled(c):  # the sampled box (outside it the collider's distance is positive)
        b_lo = np.asarray(c.origin, np.float64)
        b_hi = b_lo + float(c.cell) * (np.asarray(np.shape(c.values)) - 1)
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
    d = collider_sdf(c, np.stack([g.ravel() for g in grids], axis=1)).reshape(grids[0].shape)
    sdf[tuple(sl)] = np.minimum(sdf[tuple(sl)], d)


class _VolumeEstimate:
    """The volume [m^D] of ``{closed field > c}`` as a function of the level ``c``
    without drawing the surface: every cell counts the fraction of itself
    above ``c`` from the value ``φ̄`` and gradient of the field's multilinear
    interpolant at its centre, ``clip(1/2 + (φ̄ − c)/|∇φ̄|₁, 0, 1)``
    (``|∇φ̄|₁``: how much a linear field changes across the cell's extent
    along its gradient; exact for a flat face of a linear field), capped by
    the fraction of the cell inside the domain and out
    of the obstacles (the same formula on ``sdf/h`` at level 0). Piecewise
    linear and non-increasing in ``c``. Marching cubes cuts curved parts with
    flat triangles, so its volume is a little smaller: by 0.3 % for a
    16-cell block, 1-4 % for the water3d scenes' bodies (docs/mesh.md)."""

    def __init__(self, phi: np.ndarray, sdf: np.ndarray, h: float) -> None:
        # only cells with a corner above ISO_MIN/2.5 can count (φ ≥ 0, so φ̄ + |∇φ̄|₁/2 ≤ 2.5·max corner)
        cells = _cells_touching(phi > ISO_MIN / 2.5)
        val, g = _cell_centres(phi, cells)
        g = np.maximum(g, 1e-12)
        # the domain fraction is 1 where the first corner lies 4 nodes or more inside (sdf is a
        # distance, about 1-Lipschitz: the centre's value is then above half the cell's change)
        dom = np.ones(len(cells))
        near = np.flatnonzero(sdf.ravel().take(cells) < 4 * h)
        if len(near):
            s, gs = _cell_centres(sdf * (1 / h), cells[near])
            dom[near] = np.clip(0.5 + s / np.maximum(gs, 1e-12), 0.0, 1.0)
        full = val - 0.5 * g >= ISO_MAX  # cells above every level of the range: their domain fraction
        band = ~full & (val + 0.5 * g > ISO_MIN) & (dom > 0)
        self.cell = h**phi.ndim
        self.full = float(dom[full].sum())
        self.val, self.inv_g, self.dom = val[band], 1.0 / g[band], dom[band]

    def volume(self, c: float) -> float:
        frac = np.clip(0.5 + (self.val - c) * self.inv_g, 0.0, 1.0)
        return self.cell * (self.full + float(np.minimum(frac, self.dom).sum()))

    def level(self, target: float) -> float:
        """The level in [ISO_MIN, ISO_MAX] whose estimated volume is ``target``
        (a bound where none is): regula falsi (Illinois) to 1e-6 of ``target``."""
        a, b = ISO_MIN, ISO_MAX
        fa, fb = self.volume(a) - target, self.volume(b) - target
        if fa <= 0:
            return a
        if fb >= 0:
            return b
        side = 0
        for _ in range(60):
            c = (a * fb - b * fa) / (fb - fa)
            fc = self.volume(c) - target
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
