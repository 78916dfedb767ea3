"""A learned correction of coarse MPM (experimental; docs/neural.md, "A learned
correction of coarse MPM").

MPM on a coarser grid keeps walls, obstacles, plasticity and conservation; a
small per-particle network adds, as a force inside the solver, what one frame
on the scene's grid would have done differently (:mod:`.teacher`), trained
DAgger-style without gradients through the solver
(:mod:`hybridmpm.train.correction`). Its go/no-go against the plain coarse grid
and MPM at ``r_p`` is measured by ``benchmarks/correction_go_no_go.py``: on
water2d and sand2d it does not pay, and the bounds in that report say why, so
no simulator runs it by default.
"""

from hybridmpm.sim.correction.features import num_features, particle_features
from hybridmpm.sim.correction.forcing import CorrectionForcing, LabelledForcing, OracleForcing, coarse_simulator
from hybridmpm.sim.correction.model import Correction
from hybridmpm.sim.correction.teacher import split_state, teacher_frame

__all__ = [
    "Correction",
    "CorrectionForcing",
    "LabelledForcing",
    "OracleForcing",
    "coarse_simulator",
    "num_features",
    "particle_features",
    "split_state",
    "teacher_frame",
]
