"""The hybrid simulator (issue 5; paper Sec. 3.1.2): neural physics by default,
MPM while the fluid-complexity score ``s(t)`` is below ``r_c``.

>>> from hybridmpm.hybrid import HybridSimulator
>>> sim = HybridSimulator("dam_break2d")              # shipped model, r_c = 0.8
>>> for frame in sim.step(frames=300): ...            # frame.positions, frame.solver
"""

from hybridmpm.hybrid.convert import estimate_volume_ratio, fit_affine, mpm_history, neural_to_mpm
from hybridmpm.hybrid.safeguard import ACCEL_FLOOR, DELTA, R_C, complexity_score
from hybridmpm.hybrid.simulator import DWELL, MPM, NEURAL, Frame, HybridSimulator, HybridStats

__all__ = [
    "ACCEL_FLOOR",
    "DELTA",
    "DWELL",
    "MPM",
    "NEURAL",
    "R_C",
    "Frame",
    "HybridSimulator",
    "HybridStats",
    "complexity_score",
    "estimate_volume_ratio",
    "fit_affine",
    "mpm_history",
    "neural_to_mpm",
]
