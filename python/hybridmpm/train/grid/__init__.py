"""The grid model (needs torch): a learned simulator that sees the whole
fluid through a grid (p2g, a U-Net, g2p; NeuralMPM-style, arXiv 2408.15753),
its training and its file.

* :mod:`~hybridmpm.train.grid.model` — :class:`GridConfig`, :class:`GridModel`,
  :class:`UNet`, the torch p2g/g2p (:func:`stencil`, :func:`p2g`, :func:`g2p`,
  :func:`grid_geometry`), :func:`pressure_shift`, :func:`rest_count`;
* :mod:`~hybridmpm.train.grid.train` — :class:`GridTrainConfig`,
  :func:`train_grid` (``hybridmpm train-grid``) on the training scaffold
  (:mod:`hybridmpm.train.scaffold`), :func:`rollout`, :func:`validation_error`;
* :mod:`~hybridmpm.train.grid.export` — :func:`export_grid` (the ``.onnx``
  file :class:`hybridmpm.neural.grid.GridRuntime` runs), :func:`load_snapshot`.
"""

from hybridmpm.train.grid.export import export_grid, load_snapshot
from hybridmpm.train.grid.model import GridConfig, GridModel, UNet, g2p, grid_geometry, p2g, pressure_shift, rest_count, stencil
from hybridmpm.train.grid.train import GridTrainConfig, rollout, train_grid, validation_error, velocity_scale

__all__ = [
    "GridConfig",
    "GridModel",
    "GridTrainConfig",
    "UNet",
    "export_grid",
    "g2p",
    "grid_geometry",
    "load_snapshot",
    "p2g",
    "pressure_shift",
    "rest_count",
    "rollout",
    "stencil",
    "train_grid",
    "validation_error",
    "velocity_scale",
]
