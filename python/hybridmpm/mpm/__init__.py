"""Typed Python API over the Rust MLS-MPM solver.

The solver is MLS-MPM (Hu et al. 2018, "A moving least squares material point
method ...", APIC transfers, quadratic B-splines) on the unit domain
``[0, 1]^D`` with ``n_grid`` cells per dimension. Materials: weakly
compressible water (Kirchhoff stress ``τ = K·J·(J−1)·I``) and Drucker–Prager
sand (Klár et al. 2016, Hencky strain, SVD return mapping; in 2D the cone is
matched to plane-strain Mohr–Coulomb, ``α = sin φ / √2``). Units are SI.

Example
-------
>>> import numpy as np
>>> from hybridmpm.conventions import MATERIAL_WATER
>>> from hybridmpm.mpm import MpmParams, MpmSolver
>>> sim = MpmSolver(MpmParams(dim=2))
>>> x = np.random.default_rng(0).uniform(0.3, 0.5, (500, 2)).astype(np.float32)
>>> sim.add_particles(x, MATERIAL_WATER)
500

Frames are advanced by the simulators of :mod:`hybridmpm.sim`
(:class:`~hybridmpm.sim.MpmSimulator` wraps this solver; ``rollout`` is the
one frame loop), which call :meth:`MpmSolver.step_frame`.
"""

from hybridmpm.conventions import DT_FRAME
from hybridmpm.mpm.params import WALL_FACES, Box, Collider, Condition, MpmParams, SampledSdf, SandParams, Sphere, WallFace, WallParams, WaterParams
from hybridmpm.mpm.solver import MpmSolver, grid_mass

__all__ = [
    "DT_FRAME",
    "Box",
    "Collider",
    "Condition",
    "MpmParams",
    "MpmSolver",
    "SampledSdf",
    "SandParams",
    "Sphere",
    "WALL_FACES",
    "WallFace",
    "WallParams",
    "WaterParams",
    "grid_mass",
]
