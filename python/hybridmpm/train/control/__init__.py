"""The Fluid ControlNet's torch half and its data (the ``train`` extra).

* :mod:`hybridmpm.train.control.cases` — control cases by reverse simulation,
  in memory and on disk (``hybridmpm generate-control``);
* :mod:`hybridmpm.train.control.model` — the network in PyTorch;
* :mod:`hybridmpm.train.control.train` — ``hybridmpm train-control`` and the
  ONNX export that :class:`hybridmpm.control.ControlModel` runs.
"""
