"""Neural physics at run time: exported learned simulators run by numpy +
onnxruntime (no torch; what simulating with a shipped model needs).

- :mod:`hybridmpm.neural.base` — :class:`~hybridmpm.neural.base.Runtime`, what
  every learned kind offers at run time, and :func:`~hybridmpm.neural.base.open_model`,
  the one way to open a model file of any kind;
- :mod:`hybridmpm.neural.runtime` — :class:`GnsRuntime`, an exported GNS
  (the simulator is :class:`hybridmpm.sim.NeuralSimulator`);
- :mod:`hybridmpm.neural.fused` — the fused-kernel rewrite of its graph
  (onnxruntime custom operators in the Rust extension);
- :mod:`hybridmpm.neural.grid` — an exported grid model;
- :mod:`hybridmpm.neural.constants` — what the exporter and the runtime share.

The models are made by :mod:`hybridmpm.train` (torch, the ``train`` extra).

Paper Sec. 2.2, 3.1.1 and App. A; GNS: Sanchez-Gonzalez et al. 2020.
"""

from hybridmpm.neural.constants import FEATURE_VERSION, METADATA_KEY, NUM_TYPES
from hybridmpm.neural.runtime import GnsRuntime

__all__ = ["FEATURE_VERSION", "METADATA_KEY", "NUM_TYPES", "GnsRuntime"]
