"""Neural physics: a GNS simulator trained in PyTorch and run through onnxruntime.

- :mod:`hybridmpm.neural.runtime` — :class:`NeuralModel` (numpy + onnxruntime
  only: what simulating with a shipped model needs; the simulator is
  :class:`hybridmpm.sim.NeuralSimulator`);
- :mod:`hybridmpm.neural.model` — the GNS in PyTorch (training extra);
- :mod:`hybridmpm.neural.train` — ``hybridmpm train``;
- :mod:`hybridmpm.neural.export` — ONNX export with metadata.

Paper Sec. 2.2, 3.1.1 and App. A; GNS: Sanchez-Gonzalez et al. 2020.
"""

from hybridmpm.neural.constants import FEATURE_VERSION, KINEMATIC, METADATA_KEY, NUM_TYPES
from hybridmpm.neural.runtime import NeuralModel

__all__ = ["FEATURE_VERSION", "KINEMATIC", "METADATA_KEY", "NUM_TYPES", "NeuralModel"]
