"""hybridmpm: real-time hybrid neural / MLS-MPM fluid simulation.

The Rust core (``hybridmpm._core``) holds the MLS-MPM solver, the radius
graph and the grid-mass metric; this package gives them a typed API.
Subpackages: :mod:`hybridmpm.scenes` (scene specs and the paper's domains),
:mod:`hybridmpm.data` (GNS-layout datasets, ``r_p``/``r_t`` downsampling,
generation), :mod:`hybridmpm.metrics` (grid-mass error and friends).
"""

from hybridmpm import _core
from hybridmpm.errors import CheckpointError, HybridMpmError, InvalidInputError, SimulationError
from hybridmpm.graph import radius_graph
from hybridmpm.mpm import SAND, WATER, Box, MpmParams, MpmSolver, SandParams, Sphere, WallParams, WaterParams, grid_mass
from hybridmpm.trajectory import Trajectory

__version__: str = _core.__version__

__all__ = [
    "SAND",
    "WATER",
    "Box",
    "CheckpointError",
    "HybridMpmError",
    "InvalidInputError",
    "MpmParams",
    "MpmSolver",
    "SandParams",
    "SimulationError",
    "Sphere",
    "Trajectory",
    "WallParams",
    "WaterParams",
    "__version__",
    "grid_mass",
    "radius_graph",
]
