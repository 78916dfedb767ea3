"""An independent, deliberately plain NumPy (float64) MLS-MPM for water, after
the mpm88 example of Hu et al. 2018 / Taichi, used as a reference in tests.
It shares no code with the Rust solver."""

from __future__ import annotations

import numpy as np


def mpm88_substeps(x, v, C, J, *, n_grid, dt, steps, vol, rho=1000.0, K=4e5, gravity=-9.8, wall_cells=3):
    x = x.astype(np.float64).copy()
    v = v.astype(np.float64).copy()
    C = C.astype(np.float64).copy()
    J = J.astype(np.float64).copy()
    dim = x.shape[1]
    inv_dx = float(n_grid)
    dx = 1.0 / n_grid
    m = vol * rho
    offs = np.array(np.meshgrid(*[np.arange(3)] * dim, indexing="ij")).reshape(dim, -1).T
    shape = (n_grid + 2,) * dim
    for _ in range(steps):
        base = np.floor(x * inv_dx - 0.5).astype(int)
        fx = x * inv_dx - base
        w = [0.5 * (1.5 - fx) ** 2, 0.75 - (fx - 1) ** 2, 0.5 * (fx - 0.5) ** 2]
        stress = -dt * 4 * inv_dx**2 * vol * K * J * (J - 1)
        affine = stress[:, None, None] * np.eye(dim) + m * C
        gm = np.zeros(shape)
        gv = np.zeros(shape + (dim,))
        for o in offs:
            dpos = (o - fx) * dx
            wt = np.prod([w[o[d]][:, d] for d in range(dim)], axis=0)
            idx = tuple(base[:, d] + o[d] for d in range(dim))
            np.add.at(gm, idx, wt * m)
            np.add.at(gv, idx, wt[:, None] * (m * v + np.einsum("nij,nj->ni", affine, dpos)))
        mask = gm > 0
        gv[mask] /= gm[mask][:, None]
        gv[mask, 1] += dt * gravity
        for d in range(dim):
            idx = np.arange(n_grid + 2).reshape([-1 if k == d else 1 for k in range(dim)])
            comp = gv[..., d]
            comp[...] = np.where((idx < wall_cells) & (comp < 0), 0.0, comp)
            comp[...] = np.where((idx > n_grid - wall_cells) & (comp > 0), 0.0, comp)
        nv = np.zeros_like(v)
        nC = np.zeros_like(C)
        for o in offs:
            dpos = (o - fx) * dx
            wt = np.prod([w[o[d]][:, d] for d in range(dim)], axis=0)
            g = gv[tuple(base[:, d] + o[d] for d in range(dim))]
            nv += wt[:, None] * g
            nC += 4 * inv_dx**2 * wt[:, None, None] * np.einsum("ni,nj->nij", g, dpos)
        v, C = nv, nC
        x = x + dt * v
        J = J * (1 + dt * np.trace(C, axis1=1, axis2=2))
    return x, v, C, J
