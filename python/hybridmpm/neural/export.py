"""Export a trained :class:`~hybridmpm.neural.model.GnsModel` to ONNX (needs torch, onnx, onnxscript).

The graph holds the whole step of :meth:`GnsModel.forward`: feature
construction and normalisation (:mod:`hybridmpm.neural.features`), the
encoder–processor–decoder (:class:`~hybridmpm.neural.model.EncodeProcessDecode`),
denormalisation and the Euler update; particle and edge counts are dynamic.
Inputs ``positions`` float32 [t_in, N, D], ``particle_type`` int64 [N],
``senders``, ``receivers`` int64 [E]; outputs ``acceleration`` float32 [N, D]
(m/step²) and ``next_position`` float32 [N, D] (m).

The aggregation is written as ``index_add`` and exported by the dynamo
exporter (opset 18) as ``ScatterND`` with ``reduction="add"``: a real
scatter-add, not the dense adjacency product the paper timed (App. C). (The
legacy exporter turns ``index_add`` into a ``ScatterElements`` without
reduction, which silently drops duplicate receivers; the tests check parity on
graphs with many edges per receiver.)

Model metadata (scene family, dim, r_p, r_t, R, particle types, feature
version, training-data hash, architecture, errors) is stored as the ONNX
metadata property ``hybridmpm`` (a JSON object), readable by onnxruntime
without onnx installed.
"""

from __future__ import annotations

import json
import os
import warnings
from pathlib import Path
from typing import Any

import numpy as np

from hybridmpm.neural.constants import FEATURE_VERSION, METADATA_KEY
from hybridmpm.neural.model import GnsModel

INPUT_NAMES = ["positions", "particle_type", "senders", "receivers"]
OUTPUT_NAMES = ["acceleration", "next_position"]


def export_onnx(model: GnsModel, path: str | Path, metadata: dict[str, Any]) -> Path:
    """Write ``model`` to ``path`` (atomically) with ``metadata`` merged over the
    architecture facts (``feature_version``, ``dim``, ``radius``, ``t_in``,
    ``bounds``, ``latent``, ``layers``, ``parameters``). Returns the path.

    Input and output names are :data:`INPUT_NAMES` and :data:`OUTPUT_NAMES`
    (what :class:`~hybridmpm.neural.runtime.NeuralModel` feeds and reads).
    Needs torch, onnx and onnxscript (the 'train' extra); an I/O failure
    raises ``OSError`` and leaves any existing file at ``path`` untouched."""
    import onnx
    import torch

    from hybridmpm.graph import radius_graph

    model = model.eval()
    cfg = model.config
    # a small example whose graph has duplicate receivers (it always does: self-edges + neighbours)
    rng = np.random.default_rng(0)
    lo = np.array([b[0] for b in cfg.bounds]) + 2 * cfg.radius
    x = (lo + rng.uniform(0, 4 * cfg.radius, (24, cfg.dim))).astype(np.float32)
    hist = np.stack([x] * cfg.t_in)
    s, r, _, _ = radius_graph(x, cfg.radius)
    ptype = np.full(len(x), 5, np.int64)
    args = (torch.from_numpy(hist), torch.from_numpy(ptype), torch.from_numpy(s), torch.from_numpy(r))
    n, e = torch.export.Dim("N"), torch.export.Dim("E")
    dynamic = {"positions": {1: n}, "particle_type": {0: n}, "senders": {0: e}, "receivers": {0: e}}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        program = torch.onnx.export(
            model, args, dynamo=True, opset_version=18, input_names=INPUT_NAMES, output_names=OUTPUT_NAMES, dynamic_shapes=dynamic, verbose=False
        )
    assert program is not None
    proto = program.model_proto
    meta = {
        "feature_version": FEATURE_VERSION,
        "dim": cfg.dim,
        "radius": cfg.radius,
        "t_in": cfg.t_in,
        "bounds": cfg.bounds,
        "latent": cfg.latent,
        "layers": cfg.layers,
        "parameters": int(sum(p.numel() for p in model.parameters())),
        **metadata,
    }
    entry = proto.metadata_props.add()
    entry.key = METADATA_KEY
    entry.value = json.dumps(meta, sort_keys=True)
    path = Path(path)
    tmp = path.with_name(path.name + ".tmp")
    onnx.save(proto, str(tmp))
    os.replace(tmp, path)
    return path


__all__ = ["INPUT_NAMES", "METADATA_KEY", "OUTPUT_NAMES", "export_onnx"]
