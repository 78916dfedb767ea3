"""hybridmpm: real-time hybrid neural / MLS-MPM fluid simulation."""

from hybridmpm import _core
from hybridmpm.errors import CheckpointError, HybridMpmError, InvalidInputError, SimulationError

__version__ = _core.__version__

__all__ = ["CheckpointError", "HybridMpmError", "InvalidInputError", "SimulationError", "__version__"]
