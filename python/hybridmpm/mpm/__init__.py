"""Typed Python API over the Rust MLS-MPM solver.

The solver is MLS-MPM (Hu et al. 2018, "A moving least squares material point
method ...", APIC transfers, quadratic B-splines) on the unit domain
``[0, 1]^D`` with ``n_grid`` cells per dimension. Materials: weakly
compressible water (Kirchhoff stress ``τ = K·J·(J−1)·I``) and Drucker–Prager
sand (Klár et al. 2016, Hencky strain, SVD return mapping; in 2D the cone is
matched to plane-strain Mohr–Coulomb, ``α = sin φ / √2``); elastic solids
(fixed-corotated, Stomakhin et al. 2012, or neo-Hookean), snow (Stomakhin et
al. 2013) and viscoplastic solids (von Mises on the Hencky strain with viscous
relaxation); docs/materials.md. Units are SI.

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
from hybridmpm.mpm.params import (
    INTEGRATORS,
    WALL_FACES,
    Box,
    Collider,
    Condition,
    ElasticParams,
    MaterialSet,
    MpmParams,
    SampledSdf,
    SandParams,
    SnowParams,
    Sphere,
    ViscoplasticParams,
    WallFace,
    WallParams,
    WaterParams,
)
from hybridmpm.mpm.solver import MpmSolver, grid_mass

__all__ = [
    "DT_FRAME",
    "INTEGRATORS",
    "Box",
    "Collider",
    "Condition",
    "ElasticParams",
    "MaterialSet",
    "MpmParams",
    "MpmSolver",
    "SampledSdf",
    "SandParams",
    "SnowParams",
    "Sphere",
    "ViscoplasticParams",
    "WALL_FACES",
    "WallFace",
    "WallParams",
    "WaterParams",
    "grid_mass",
]
