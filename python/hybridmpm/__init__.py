"""hybridmpm: real-time interactive MLS-MPM fluid simulation, with the hybrid
neural / MPM simulator of arXiv 2505.18926 reproduced beside it.

The main path (docs/design.md "Data flow")::

    scene (make_scene) ─► simulator (MpmSimulator | NeuralSimulator | HybridSimulator)
        ─► rollout ─► Rollout (a Trajectory) ─► grid_mass_error against reference()

Each registered scene's default simulator (``make_simulator(scene, "default")``,
what ``hybridmpm simulate SCENE`` runs) is the one the chart picked
(``models/defaults.json``, docs/hybrid.md "Defaults per scene"); the paper's
hybrid is :class:`HybridSimulator`:

>>> import hybridmpm as hm
>>> sim = hm.make_simulator("dam_break2d", "default")         # the chart's default
>>> sim = hm.HybridSimulator(hm.make_scene("dam_break2d"))   # the paper's hybrid: shipped model, r_c = 0.8
>>> ro = hm.rollout(sim, 300)                                # positions [K + 1, N, 2], solver per step
>>> err = hm.grid_mass_error(ro.fluid_positions, hm.reference(sim.scene_full, 300, stride=sim.r_t).fluid_positions, 128)

Subpackages: :mod:`hybridmpm.sim` (the simulator interface), :mod:`hybridmpm.scenes`
(scene specs, the paper's domains, ``r_p`` clustering), :mod:`hybridmpm.neural`
(exported learned simulators run by onnxruntime), :mod:`hybridmpm.control`
(sketch control), :mod:`hybridmpm.data` (the GNS dataset format),
:mod:`hybridmpm.metrics`, :mod:`hybridmpm.bench` (benchmarks, stress suite,
tune), :mod:`hybridmpm.render`, :mod:`hybridmpm.service` (the web service);
:mod:`hybridmpm.train` makes the models (torch, the ``train`` extra); the codes and
defaults are in :mod:`hybridmpm.conventions`. The Rust core
(``hybridmpm._core``) holds the MLS-MPM solver, the radius graph and the
grid-mass metric.
"""

from hybridmpm import _core, materials
from hybridmpm.conventions import GNS_KINEMATIC, GNS_SAND, GNS_WATER, MATERIAL_SAND, MATERIAL_WATER
from hybridmpm.errors import CheckpointError, HybridMpmError, InvalidInputError, SimulationError
from hybridmpm.graph import radius_graph
from hybridmpm.metrics import grid_mass_error
from hybridmpm.mpm import Box, MpmParams, MpmSolver, SandParams, Sphere, WallParams, WaterParams, grid_mass
from hybridmpm.neural.runtime import GnsRuntime
from hybridmpm.scenes import ParticleSet, Scene, SceneSpec, make_scene
from hybridmpm.sim import Frame, HybridSimulator, MpmSimulator, NeuralSimulator, Rollout, Simulator, make_simulator, reference, rollout
from hybridmpm.trajectory import Trajectory

__version__: str = _core.__version__

__all__ = [
    "materials",
    "GNS_KINEMATIC",
    "GNS_SAND",
    "GNS_WATER",
    "MATERIAL_SAND",
    "MATERIAL_WATER",
    "Box",
    "CheckpointError",
    "Frame",
    "HybridMpmError",
    "HybridSimulator",
    "InvalidInputError",
    "MpmParams",
    "MpmSimulator",
    "MpmSolver",
    "GnsRuntime",
    "NeuralSimulator",
    "ParticleSet",
    "Rollout",
    "SandParams",
    "Scene",
    "SceneSpec",
    "SimulationError",
    "Simulator",
    "Sphere",
    "Trajectory",
    "WallParams",
    "WaterParams",
    "__version__",
    "grid_mass",
    "grid_mass_error",
    "make_scene",
    "make_simulator",
    "radius_graph",
    "reference",
    "rollout",
]
