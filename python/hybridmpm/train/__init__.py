"""Everything that needs torch: training and export of the learned simulators.

Install with ``pip install -e '.[train]'``. Serving never imports this
package: the exported ONNX files run with numpy + onnxruntime alone
(:mod:`hybridmpm.neural`).

* :mod:`hybridmpm.train.grid` — the grid model (p2g, U-Net, g2p; a
  NeuralMPM-style learned simulator, arXiv 2408.15753) and its torch p2g/g2p;
* :mod:`hybridmpm.train.grid_train` — its training loop and ONNX export.
"""
