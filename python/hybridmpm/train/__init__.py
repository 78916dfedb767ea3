"""Everything that needs torch, and everything that makes data for it: the
*make* side of hybridmpm (install with ``pip install -e '.[train]'``).

Serving never imports this package: the exported ONNX files run with numpy +
onnxruntime alone (:mod:`hybridmpm.neural`, :mod:`hybridmpm.control`), and
``tests/test_architecture.py`` keeps it so.

* :mod:`hybridmpm.train.datasets` — GNS-layout datasets from MPM rollouts
  (``hybridmpm generate``; the format is :mod:`hybridmpm.data`);
* :mod:`hybridmpm.train.gns` — the GNS in PyTorch: features, model, training
  (``hybridmpm train``), ONNX export and the inference graph;
* :mod:`hybridmpm.train.control` — control cases by reverse simulation
  (``hybridmpm generate-control``) and the Fluid ControlNet's training
  (``hybridmpm train-control``);
* :mod:`hybridmpm.train.grid` — the grid model (p2g, U-Net, g2p; a
  NeuralMPM-style learned simulator, arXiv 2408.15753): the model and its
  torch p2g/g2p, its training (``hybridmpm train-grid``) and ONNX export;
* :mod:`hybridmpm.train.scaffold` — what the three families' trainings share:
  the settings' base, the loop with progress and resumable checkpoints, the
  validation curve and the export metadata;
* :mod:`hybridmpm.train.distributed` — data-parallel ranks.
"""
