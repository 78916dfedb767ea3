"""Large-step water in 2D: the candidates measured against the accuracy checks before any enters the engine.

Explicit MLS-MPM with weakly compressible water takes ``dt <= cfl·dx/(c + |v|)``
with a sound speed ``c = sqrt(K/ρ)`` = 20 m/s, while a dam break's flow moves at
3 m/s at most: 18 substeps per 2.5 ms frame on 128². Two ways to step at the
flow's pace are measured here, in 2D, with the checks the engine's water meets:

- ``explicit K=...``: the engine as it is, with a softer bulk modulus ``K``
  (a lower sound speed, so fewer substeps; weak compressibility at a lower
  Mach bound). ``K=4e5`` is today's default.
- ``projection``: a prototype (numpy and scipy, this file) of incompressible
  APIC water (Jiang et al. 2015) on a MAC grid: per face component, quadratic
  B-spline p2g of mass and affine momentum, gravity, free-slip box walls (no
  normal flow; the tangential velocity inside a wall copies the fluid's), a
  Chorin pressure projection on the cells that hold particles, then g2p. The
  free surface is second order (a ghost-fluid boundary, Gibou et al. 2002 /
  Enright et al. 2003: the pressure is 0 where the particles' smoothed density
  crosses 1/2, a fraction ``theta`` of the way from a fluid cell to its air
  neighbour). A volume correction (after Kugelstadt et al. 2019) asks a cell
  denser than rest to spread by ``kappa·(ρ/ρ0 − 1)`` per step. The step is
  bounded by advection only: ``dt <= cfl·dx/(|v|max + sqrt(g·dx))``, at most a
  frame. The Poisson solve is scipy's CG with a Jacobi preconditioner
  (its iterations are reported; the engine would use a stronger one).
- ``engine``: the engine's own projection step (``integrator = "projection"``,
  ``rust/mpm/src/projection/``: the same method, in Rust, through
  :class:`~hybridmpm.sim.MpmSimulator` and :func:`~hybridmpm.sim.rollout` as
  every scene runs). Its pressure is not read out (the column at rest reports
  its volume; the Rust tests check its pressure against ρgh).

The checks (``--checks``):

- ``dam``: Martin & Moyce (1952), the n² = 2 column of ``dam_break2d`` on 128²
  and 64², scored by :func:`hybridmpm.validation.score_dam_break` (front shift-RMS
  <= 0.12, front ratio 0.90–1.32, height ratio 0.85–1.25);
- ``hydro``: a 0.5 m column filling the tank at rest for 2,000 frames: its
  volume from the particles' positions (the mean depth of the free surface
  against the lattice's) and the floor pressure against the weight of the
  water above (force balance);
- ``slosh``: the first sloshing mode of a tank of depth 0.3 m (surface
  ``0.3 + 0.01·cos(πx/L)``), its frequency against linear theory
  ``f1 = sqrt((πg/L)·tanh(πh/L))/2π`` over 1,600 frames, and how much of its
  amplitude the last half period keeps.

    python benchmarks/large_step.py --out benchmarks/results/large_step

docs/large-step.md quotes its figures. Times are whole frames on
this machine; the prototype's are numpy's, so its steps per frame and CG
iterations, not its milliseconds, are what carries over to the engine.
"""

from __future__ import annotations

import argparse
import math
import time
from typing import Any

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from hybridmpm.bench.harness import script_argv, table, write_results
from hybridmpm.conventions import DT_FRAME, MATERIAL_WATER
from hybridmpm.mpm.params import MpmParams
from hybridmpm.scenes import Scene, lattice
from hybridmpm.scenes.registry import DAM_BREAK3D_N_GRID, dam_break2d_spec, dam_break3d_spec
from hybridmpm.sim import MpmSimulator, rollout
from hybridmpm.validation import dam_break_front_height, score_dam_break

#: The bulk moduli [Pa] of the explicit rows (4e5 is the default: c = 20 m/s).
BULK_MODULI = (4e5, 1e5, 4e4)
RHO = 1000.0


def _weights(g: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Quadratic B-spline weights at ``g`` (positions in node units, [N]): the
    stencil's first node [N], weights [N, 3] and node offsets [N, 3] in cells."""
    base = np.floor(g - 0.5).astype(np.int64)
    f = g - base
    w = np.stack([0.5 * (1.5 - f) ** 2, 0.75 - (f - 1.0) ** 2, 0.5 * (f - 0.5) ** 2], axis=1)
    return base, w, np.arange(3)[None, :] - f[:, None]


class ApicProjection:
    """The prototype: incompressible APIC water on a MAC grid in the unit box, 2D
    or 3D (``n`` cells a side, the fluid resting on the walls' face
    ``(wall_cells − 1)·dx`` as the engine's does). ``x`` float [N, D] [m] at 2
    particles per cell per axis, at rest. See the module's docstring for the method."""

    def __init__(self, n: int, wall_cells: int, x: np.ndarray, *, gravity: float = -9.8, cfl: float = 1.0, kappa: float = 0.1, ghost: bool = True) -> None:
        self.n, self.dx, self.g = n, 1.0 / n, gravity
        self.dim = int(np.shape(x)[1])
        self.ws = wall_cells - 1  # solid cells per side
        self.x = np.asarray(x, np.float64).copy()
        self.v = np.zeros_like(self.x)
        self.c = np.zeros((len(self.x), self.dim, self.dim))  # c[p, a]: the affine vector of velocity component a
        self.m = RHO * (self.dx / 2) ** self.dim
        self.cfl, self.kappa, self.ghost = cfl, kappa, ghost
        i = np.arange(n)
        edge = (i < self.ws) | (i >= n - self.ws)
        self.solid = np.zeros((n,) * self.dim, bool)
        for a in range(self.dim):
            self.solid |= edge.reshape([-1 if b == a else 1 for b in range(self.dim)])
        self.p = np.zeros((n,) * self.dim)
        self.steps = 0
        self.iters: list[int] = []

    def _cut(self, arr: np.ndarray, axis: int, sl: slice) -> Any:
        """``arr`` sliced by ``sl`` along ``axis`` (a view)."""
        return arr[(slice(None),) * axis + (sl,)]

    def _stencil(self, shift: list[float], shape: tuple[int, ...]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The 3^D stencil under each particle on a grid of nodes at ``(i + shift)·dx``: flat index [N, 3^D], weight [N, 3^D], node − particle [N, 3^D, D] [m]."""
        dim, dx, k = self.dim, self.dx, len(self.x)
        idx = np.zeros((k,) + (1,) * dim, np.int64)
        w = np.ones((k,) + (1,) * dim)
        offs = []
        for a in range(dim):
            base, wa, oa = _weights(self.x[:, a] / dx - shift[a])
            ia = np.clip(base[:, None] + np.arange(3), 0, shape[a] - 1)
            view = [k] + [3 if b == a else 1 for b in range(dim)]
            idx = idx * shape[a] + ia.reshape(view)
            w = w * wa.reshape(view)
            offs.append(oa.reshape(view))
        full = (k,) + (3,) * dim
        off = np.stack([np.broadcast_to(o, full) for o in offs], -1).reshape(k, -1, dim) * dx
        return np.broadcast_to(idx, full).reshape(k, -1), np.broadcast_to(w, full).reshape(k, -1), off

    def _face(self, a: int) -> tuple[list[float], tuple[int, ...]]:
        """Component ``a``'s face grid: node shift and shape."""
        shift = [0.5] * self.dim
        shift[a] = 0.0
        return shift, tuple(self.n + (b == a) for b in range(self.dim))

    def _density(self) -> np.ndarray:
        """The particles' mass at cell centres (quadratic weights) over the rest density: float [n]*D."""
        shape = (self.n,) * self.dim
        idx, w, _ = self._stencil([0.5] * self.dim, shape)
        return np.bincount(idx.ravel(), (w * self.m).ravel(), self.n**self.dim).reshape(shape) / (self.dx**self.dim * RHO)

    @staticmethod
    def _theta(dens: np.ndarray, f: tuple[np.ndarray, ...], air: tuple[np.ndarray, ...]) -> np.ndarray:
        """Where the surface (smoothed density 1/2) lies between a fluid cell's centre and its air neighbour's, as a fraction of dx."""
        df, da = dens[f], dens[air]
        return np.clip((df - 0.5) / np.maximum(df - da, 1e-6), 0.05, 1.0)

    def _walls(self, vel: list[np.ndarray]) -> None:
        """Free slip at the box: no flow through a wall face; inside a wall the tangential components copy the fluid's."""
        n, ws, cut = self.n, self.ws, self._cut
        for a, va in enumerate(vel):
            cut(va, a, slice(0, ws + 1))[...] = 0.0
            cut(va, a, slice(n - ws, None))[...] = 0.0
            for b in range(self.dim):
                if b != a:
                    cut(va, b, slice(0, ws))[...] = cut(va, b, slice(ws, ws + 1))
                    cut(va, b, slice(n - ws, None))[...] = cut(va, b, slice(n - ws - 1, n - ws))

    def _project(self, vel: list[np.ndarray], dt: float) -> None:
        """Make the face velocities divergence-free on the fluid cells (in place)."""
        n, dx, dim, solid = self.n, self.dx, self.dim, self.solid
        self._walls(vel)
        cell = np.clip((self.x / dx).astype(np.int64), 0, n - 1)
        fluid = np.zeros((n,) * dim, bool)
        fluid[tuple(cell.T)] = True
        fluid &= ~solid
        index = -np.ones((n,) * dim, np.int64)
        fc = np.argwhere(fluid)
        index[fluid] = np.arange(len(fc))
        dens = self._density()
        div = (sum(np.diff(vel[a], axis=a) for a in range(dim)) / dx)[fluid]
        div -= self.kappa * np.maximum(dens[fluid] - 1.0, 0.0) / dt
        k = np.arange(len(fc))
        diag = np.zeros(len(fc))
        rows, cols = [k], [k]
        for a in range(dim):
            for step in (1, -1):
                nc = fc.copy()
                nc[:, a] += step
                at = tuple(nc.T)
                open_ = ~solid[at]
                nb = index[at]
                both = open_ & (nb >= 0)
                air = open_ & (nb < 0)
                diag += both
                diag[air] += 1.0 / self._theta(dens, tuple(fc[air].T), tuple(nc[air].T)) if self.ghost else 1.0
                rows.append(k[both])
                cols.append(nb[both])
        vals = [diag] + [-np.ones(len(r)) for r in rows[1:]]
        mat = sp.csr_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))), shape=(len(fc), len(fc)))
        its = [0]

        def count(_: Any) -> None:
            its[0] += 1

        p, _ = spla.cg(mat, -(RHO * dx * dx / dt) * div, x0=self.p[fluid], rtol=1e-6, maxiter=4000, M=sp.diags(1.0 / np.maximum(diag, 1.0)), callback=count)
        self.iters.append(its[0])
        self.p = np.zeros((n,) * dim)
        self.p[fluid] = p
        self._apply_gradient(vel, fluid, dens, dt)
        self._walls(vel)

    def _apply_gradient(self, vel: list[np.ndarray], fluid: np.ndarray, dens: np.ndarray, dt: float) -> None:
        """Subtract ``dt/ρ·∇p`` on every face beside a fluid cell (the ghost pressure on a face to the air)."""
        n, dx, p, solid, cut = self.n, self.dx, self.p, self.solid, self._cut
        for a, va in enumerate(vel):
            lo, hi = cut(fluid, a, slice(None, -1)), cut(fluid, a, slice(1, None))
            grad = np.diff(p, axis=a) / dx
            if self.ghost:
                for fluid_lo, mask, sign in ((True, lo & ~hi & ~cut(solid, a, slice(1, None)), -1.0), (False, hi & ~lo & ~cut(solid, a, slice(None, -1)), 1.0)):
                    at = np.nonzero(mask)
                    up = tuple(c + (b == a) for b, c in enumerate(at))
                    f, air = (at, up) if fluid_lo else (up, at)
                    grad[at] = sign * p[f] / (self._theta(dens, f, air) * dx)
            near = lo | hi
            cut(va, a, slice(1, n))[near] -= dt / RHO * grad[near]

    def step(self, dt: float) -> None:
        """One step: p2g (mass and APIC momentum per face component), gravity, the projection, g2p, then the particles move."""
        stencils = []
        vel = []
        for a in range(self.dim):
            shift, shape = self._face(a)
            idx, w, off = self._stencil(shift, shape)
            stencils.append((idx, w, off))
            size = int(np.prod(shape))
            mass = np.bincount(idx.ravel(), (self.m * w).ravel(), size).reshape(shape)
            mom = np.bincount(idx.ravel(), (self.m * w * (self.v[:, a, None] + np.einsum("pk,pjk->pj", self.c[:, a], off))).ravel(), size).reshape(shape)
            vel.append(np.where(mass > 0, mom / np.maximum(mass, 1e-30), 0.0))
        vel[1] += dt * self.g
        self._project(vel, dt)
        for a, (idx, w, off) in enumerate(stencils):
            ug = vel[a].ravel()[idx]
            self.v[:, a] = (w * ug).sum(1)
            self.c[:, a] = np.einsum("pj,pjk->pk", w * ug, off) * (4.0 / self.dx**2)
        self.x += dt * self.v
        lo = (self.ws + 1e-3) * self.dx
        np.clip(self.x, lo, 1.0 - lo, out=self.x)
        self.steps += 1

    def advance(self, dt_frame: float) -> None:
        """One frame in as few equal steps as the advective CFL allows."""
        vmax = float(np.abs(self.v).max()) if len(self.v) else 0.0
        dt = self.cfl * self.dx / (vmax + math.sqrt(abs(self.g) * self.dx))
        k = max(1, math.ceil(dt_frame / dt - 1e-9))
        for _ in range(k):
            self.step(dt_frame / k)


class Explicit:
    """The engine (through :class:`~hybridmpm.sim.MpmSimulator` and
    :func:`~hybridmpm.sim.rollout`) with ``params`` but water of bulk modulus ``k``
    [Pa], on the particles ``x`` [N, D] at hydrostatic rest below ``surface`` [N] [m]:
    explicit MLS-MPM, or with ``integrator="projection"`` the engine's projection step
    (incompressible: the particles start at rest uncompressed, ``k`` unused)."""

    def __init__(self, params: MpmParams, x: np.ndarray, surface: np.ndarray, k: float, integrator: str = "explicit") -> None:
        self.k = k if integrator == "explicit" else math.nan
        d = params.to_dict()
        compressed = np.clip(1.0 - RHO * 9.8 * np.clip(surface - x[:, 1], 0.0, None) / k, 0.5, 1.0)
        scene = Scene(
            "large_step",
            MpmParams.from_dict({**d, "water": {**d["water"], "bulk_modulus": k}, "integrator": integrator}),
            x.astype(np.float32),
            np.full(len(x), MATERIAL_WATER, np.int32),
            np.zeros(x.shape, np.float32),
            volume_ratio=(compressed if integrator == "explicit" else np.ones(len(x))).astype(np.float32),
        )
        self.sim = MpmSimulator(scene)
        self.solver = self.sim.solver
        self.steps = 0

    @property
    def x(self) -> np.ndarray:
        return np.asarray(self.solver.positions, np.float64)

    def advance(self, dt_frame: float) -> None:
        self.steps += self.solver.substeps_for(dt_frame)
        rollout(self.sim, 1)

    def pressure(self, particles: np.ndarray) -> float:
        """The mean Cauchy pressure ``K(1 − J)`` of the given particles [Pa]."""
        return float((self.k * (1.0 - np.asarray(self.solver.volume_ratio, np.float64)[particles])).mean())


def _make(method: str, params: MpmParams, x: np.ndarray, surface: np.ndarray) -> Any:
    """The method on the grid and walls of ``params``: ``explicit K=...``, ``projection`` with optional
    ``cfl=``, ``kappa=`` and ``ghost=0`` (a first-order free surface: p = 0 at the air cell's centre), or
    ``engine`` (the engine's projection step)."""
    name, *options = method.split()
    keys = dict(o.split("=", 1) for o in options)
    if name == "engine":
        return Explicit(params, x, surface, params.water.bulk_modulus, integrator="projection")
    if name == "projection":
        return ApicProjection(
            params.resolved_n_grid(),
            params.walls.cells,
            x,
            cfl=float(keys.get("cfl", 1.0)),
            kappa=float(keys.get("kappa", 0.1)),
            ghost=keys.get("ghost", "1") == "1",
        )
    return Explicit(params, x, surface, float(keys["K"]))


def _run(sim: Any, frames: int, each: Any = None) -> float:
    """Advance ``frames`` frames (calling ``each(sim)`` before each and after the last); returns ms per frame."""
    t0 = time.perf_counter()
    for _ in range(frames):
        if each is not None:
            each(sim)
        sim.advance(DT_FRAME)
    if each is not None:
        each(sim)
    return 1e3 * (time.perf_counter() - t0) / frames


def _cost(sim: Any, frames: int, ms: float) -> dict[str, Any]:
    out = {"steps_per_frame": sim.steps / frames, "ms_per_frame": ms}
    if isinstance(sim, ApicProjection):
        out["cg_iterations"] = float(np.mean(sim.iters))
    return out


def dam(method: str, n: int, dim: int = 2) -> dict[str, Any]:
    """Martin & Moyce on ``dam_break2d`` at ``n``², or on ``dam_break3d`` (34³) read
    in its middle third across z, until T = t·sqrt(2g/a) reaches 3.5."""
    if dim == 2:
        spec = dam_break2d_spec()
        scene = (spec if n == 128 else spec.on_grid(n)).build()
    else:
        scene = dam_break3d_spec(n_grid=n).build()
    x = np.asarray(scene.positions, np.float64)
    info = scene.info
    sim = _make(method, scene.params, x, np.full(len(x), info["y_floor"] + 2 * info["a"]))
    frames, pos = math.ceil(3.5 / math.sqrt(2 * 9.8 / info["a"]) / DT_FRAME), []
    slab = slice(None) if dim == 2 else np.abs(x[:, 2] - 0.5) < (0.5 - info["x_wall"]) / 3
    ms = _run(sim, frames, lambda s: pos.append(s.x[slab, :2].copy()))
    z, h = dam_break_front_height(np.array(pos), info["a"], info["x_wall"], info["y_floor"], info["spacing"])
    s = score_dam_break(np.arange(frames + 1) * DT_FRAME, z, h, info["a"])
    return {
        **_cost(sim, frames, ms),
        "front_rms": s.rms_front_shifted,
        "front_ratio": [s.ratio_min, s.ratio_max],
        "height_ratio": [s.height_ratio_min, s.height_ratio_max],
        "passes": s.passes(),
    }


class Tank:
    """A tank filling the 128² box between its walls, water below ``depth + amp·cos(πx/L)`` [m]."""

    n = 128

    def __init__(self, depth: float, amp: float = 0.0) -> None:
        self.dx = 1.0 / self.n
        self.sp = self.dx / 2
        self.wall = (MpmParams(dim=2, n_grid=self.n).walls.cells - 1) * self.dx
        self.length = 1.0 - 2 * self.wall
        self.columns = round(self.length / self.dx)
        x = lattice([self.wall, self.wall], [1 - self.wall, self.wall + depth + amp + self.sp], self.sp).astype(np.float64)
        surface = self.wall + depth + amp * np.cos(math.pi * (x[:, 0] - self.wall) / self.length)
        keep = x[:, 1] < surface
        self.x, self.surface = x[keep], surface[keep]

    def depths(self, x: np.ndarray) -> np.ndarray:
        """The free surface's depth over the floor per column of cells [m]: the highest particle plus half a spacing."""
        col = np.clip(((x[:, 0] - self.wall) / self.dx).astype(np.int64), 0, self.columns - 1)
        top = np.full(self.columns, -np.inf)
        np.maximum.at(top, col, x[:, 1])
        return top + self.sp / 2 - self.wall

    def weight_above(self, x: np.ndarray, y: float) -> float:
        """The weight per unit width of the water above height ``y`` away from the side walls [Pa] (force balance's floor pressure)."""
        inner = (x[:, 0] > self.wall + 0.1) & (x[:, 0] < 1 - self.wall - 0.1)
        return 9.8 * RHO * self.sp**2 * np.count_nonzero(inner & (x[:, 1] > y)) / (self.length - 0.2)


def _pressure(sim: Any, tank: Tank, cells: int) -> tuple[float, float]:
    """The mean pressure [Pa] of the row of cells (projection) or particles (explicit: ``K(1 − J)``) ``cells`` cells above
    the bottom fluid cell, away from the side walls, and that row's height [m]. Within the wall band the explicit
    engine's boundary nodes carry part of the weight, so its floor row does not read the water's pressure; 8 cells
    up it does."""
    lo, hi = tank.wall + 0.1, 1 - tank.wall - 0.1
    y0 = tank.wall + (cells + 0.5) * tank.dx
    if isinstance(sim, ApicProjection):
        i0, i1 = int(lo / tank.dx) + 1, int(hi / tank.dx) - 1
        return y0, float(sim.p[i0:i1, sim.ws + cells].mean())
    x = sim.x
    row = (x[:, 0] > lo) & (x[:, 0] < hi) & (np.abs(x[:, 1] - y0) < tank.sp / 2)
    return float(x[row, 1].mean()), sim.pressure(row)


def hydro(method: str, frames: int = 2000) -> dict[str, Any]:
    """A 0.5 m column at rest for ``frames`` frames: volume and pressure against the weight above."""
    tank = Tank(0.5)
    sim = _make(method, MpmParams(dim=2, n_grid=tank.n), tank.x, tank.surface)
    start = tank.depths(tank.x)[4:-4].mean()
    ms = _run(sim, frames)
    x = sim.x
    depth = tank.depths(x)[4:-4]
    pressure = {cells: _pressure(sim, tank, cells) for cells in (0, 8)}
    speed = float(np.abs(sim.v).max()) if isinstance(sim, ApicProjection) else float(np.abs(np.asarray(sim.solver.velocities)).max())
    return {
        **_cost(sim, frames, ms),
        "volume": float(depth.mean() / start),
        "surface_spread_cells": float(depth.max() - depth.min()) / tank.dx,
        "floor_pressure": pressure[0][1],
        "floor_ratio": pressure[0][1] / tank.weight_above(x, pressure[0][0]),
        "ratio_8_cells_up": pressure[8][1] / tank.weight_above(x, pressure[8][0]),
        "max_speed": speed,
    }


def slosh(method: str, frames: int = 1600, depth: float = 0.3, amp: float = 0.01) -> dict[str, Any]:
    """The first sloshing mode: its frequency against linear theory, and the amplitude it keeps."""
    tank = Tank(depth, amp)
    sim = _make(method, MpmParams(dim=2, n_grid=tank.n), tank.x, tank.surface)
    basis = np.cos(math.pi * (np.arange(tank.columns) + 0.5) * tank.dx / tank.length)
    mode: list[float] = []
    ms = _run(sim, frames, lambda s: mode.append(2.0 * float(np.mean(tank.depths(s.x) * basis))))
    a = np.array(mode) - np.mean(mode)
    t = np.arange(len(a)) * DT_FRAME
    crossings = [t[i] - a[i] * DT_FRAME / (a[i + 1] - a[i]) for i in range(len(a) - 1) if a[i] * a[i + 1] < 0]
    f1 = math.sqrt(math.pi * 9.8 / tank.length * math.tanh(math.pi * depth / tank.length)) / (2 * math.pi)
    f = 1.0 / (2.0 * float(np.mean(np.diff(crossings))))
    peaks = [float(np.abs(a[(t >= crossings[i]) & (t < crossings[i + 1])]).max()) for i in range(len(crossings) - 1)]
    return {
        **_cost(sim, frames, ms),
        "frequency": f,
        "theory": f1,
        "frequency_error": f / f1 - 1.0,
        "amplitude_kept": peaks[-1] / amp,
        "half_periods": len(peaks),
    }


#: Each check's runs: (its function of the method and the grid, the grids it runs on).
CHECKS: dict[str, tuple[Any, tuple[int, ...]]] = {
    "dam": (dam, (128, 64)),
    "dam3d": (lambda method, n: dam(method, n, dim=3), (DAM_BREAK3D_N_GRID,)),
    "hydro": (lambda method, n: hydro(method), (Tank.n,)),
    "slosh": (lambda method, n: slosh(method), (Tank.n,)),
}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--checks", default=",".join(CHECKS), help="comma-separated, of " + ", ".join(CHECKS))
    ap.add_argument(
        "--methods",
        default=",".join([f"explicit K={k:g}" for k in BULK_MODULI] + ["projection"]),
        help="comma-separated: explicit K=PA, projection [cfl=C] [kappa=K] [ghost=0], or engine",
    )
    ap.add_argument("--out", required=True, help="output folder")
    args = ap.parse_args(argv)
    methods = [m.strip() for m in args.methods.split(",") if m.strip()]
    rows: list[dict[str, Any]] = []
    for check in [c.strip() for c in args.checks.split(",") if c.strip()]:
        if check not in CHECKS:
            ap.error(f"--checks: unknown check {check!r}; choose from {', '.join(CHECKS)}")
        run, grids = CHECKS[check]
        for method in methods:
            for n in grids:
                r = run(method, n)
                rows.append({"check": check, "method": method, "n_grid": n, **r})
                print(rows[-1], flush=True)
    lines = ["# Large-step water in 2D: candidates against the checks"]

    def fmt(v: Any) -> str:
        if isinstance(v, list):
            return "–".join(f"{x:.3f}" for x in v)
        return f"{v:.4g}" if isinstance(v, float) else str(v)

    for check in dict.fromkeys(r["check"] for r in rows):
        sel = [r for r in rows if r["check"] == check]
        keys = [k for k in dict.fromkeys(k for r in sel for k in r) if k != "check"]
        lines.append(f"## {check}\n\n" + "\n".join(table(keys, [[fmt(r.get(k, "")) for k in keys] for r in sel])))
    write_results(args.out, "large_step", doc={"rows": rows}, markdown=lines, argv=script_argv("large_step.py", argv))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
