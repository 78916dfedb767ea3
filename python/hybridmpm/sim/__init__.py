"""The simulator interface (docs/design.md "Data flow"): one protocol, three simulators, one rollout.

* :class:`MpmSimulator` — the Rust MLS-MPM solver (at ``r_p``, ``r_t`` frames a step);
* :class:`NeuralSimulator` — the GNS network alone, after an MPM warm-up
  (paper Sec. 2.2, 3.1.1);
* :class:`HybridSimulator` — the paper's method: its cheap half steps, MPM
  while the safeguard ``s(t) < r_c`` or a forcing is set (paper Sec. 3.1.2,
  3.2); the cheap half is any :class:`CheapHalf` (the network, or MPM on a
  coarser grid), its switching rule a :class:`SwitchingRule`
  (:mod:`hybridmpm.sim.switching`);
* :func:`make_simulator` — a simulator by kind; ``"default"`` is the scene's
  default configuration, chosen by the chart (``models/defaults.json``,
  docs/hybrid.md "Defaults per scene"); ``"realtime"`` a
  :class:`RealtimeSimulator`, the most accurate configuration of its real-time
  chart that fits real time on this machine (docs/realtime.md);
* :func:`rollout` — the one frame loop (:func:`step_realtime`, a host loop's tick, runs its frames through it); :func:`reference` — full-resolution
  MPM, the reference of every error.

>>> from hybridmpm.sim import HybridSimulator, rollout
>>> sim = HybridSimulator("dam_break2d")           # shipped model, r_c = 0.8
>>> ro = rollout(sim, 300)                          # ro.positions [K + 1, N + B, D], ro.solver
>>> sim.forcing = accelerations                     # [N, D] m/s²: MPM applies it
>>> fr = sim.advance()                              # one more coarse step
"""

from hybridmpm.sim.base import MPM, NEURAL, Forcing, ForcingFunction, Frame, NetworkFailure, SimStats, Simulator
from hybridmpm.sim.cheap import CheapHalf, FailureChecks, Proposal
from hybridmpm.sim.config import SOLVERS, default_settings, load_tuned, make_simulator, tuned_settings
from hybridmpm.sim.hybrid import HybridSimulator
from hybridmpm.sim.mpm import MpmSimulator
from hybridmpm.sim.neural import NeuralSimulator, warmup_frames
from hybridmpm.sim.realtime import RealtimeSimulator
from hybridmpm.sim.rollout import RealtimeTick, Rollout, reference, rollout, step_realtime
from hybridmpm.sim.safeguard import ACCEL_FLOOR, complexity_score
from hybridmpm.sim.switching import DWELL, AuditRule, ErrorRule, PaperRule, SwitchingRule, make_rule

__all__ = [
    "ACCEL_FLOOR",
    "DWELL",
    "MPM",
    "NEURAL",
    "SOLVERS",
    "AuditRule",
    "CheapHalf",
    "ErrorRule",
    "FailureChecks",
    "Forcing",
    "ForcingFunction",
    "Frame",
    "HybridSimulator",
    "MpmSimulator",
    "NetworkFailure",
    "NeuralSimulator",
    "PaperRule",
    "Proposal",
    "RealtimeSimulator",
    "RealtimeTick",
    "Rollout",
    "SimStats",
    "Simulator",
    "SwitchingRule",
    "complexity_score",
    "default_settings",
    "load_tuned",
    "make_rule",
    "make_simulator",
    "reference",
    "rollout",
    "step_realtime",
    "tuned_settings",
    "warmup_frames",
]
