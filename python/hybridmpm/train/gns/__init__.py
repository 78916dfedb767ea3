"""The GNS in PyTorch: what makes a shipped model (the ``train`` extra).

* :mod:`hybridmpm.train.gns.features` — the GNS input features (velocity
  history, wall distances, edge geometry) as torch modules;
* :mod:`hybridmpm.train.gns.model` — :class:`~hybridmpm.train.gns.model.GnsModel`,
  the encoder–processor–decoder and its configuration;
* :mod:`hybridmpm.train.gns.train` — ``hybridmpm train``;
* :mod:`hybridmpm.train.gns.export` — ONNX export with metadata;
* :mod:`hybridmpm.train.gns.onnx_graph` — the inference graph written
  straight from the weights (the layout the runtime and the fused kernels read).

The exported file runs without torch: :class:`hybridmpm.neural.GnsRuntime`.
"""
