"""Export a trained :class:`~hybridmpm.train.gns.model.GnsModel` to ONNX (needs torch and onnx).

The file holds the whole step of :meth:`GnsModel.forward` — feature
construction and normalisation (:mod:`hybridmpm.train.gns.features`), the
encoder–processor–decoder (:class:`~hybridmpm.train.gns.model.EncodeProcessDecode`),
denormalisation and the Euler update — as the inference graph of
:func:`hybridmpm.train.gns.onnx_graph.inference_graph`: written op by op from the
weights for onnxruntime's CPU kernels (normalisations and LayerNorms folded
into the Linear layers, edge geometry taken from the radius-graph pass,
Gather and a sum over receivers that is exact on any number of threads).
Particle and edge counts are dynamic. Inputs :data:`INPUT_NAMES`:
``positions`` float32 [t_in, N, D], ``particle_type`` int64 [N],
``senders``, ``receivers`` int64 [E], ``displacement`` float32 [E, D] and
``distance`` float32 [E] (of :func:`hybridmpm.graph.radius_graph` on
``positions[-1]``), ``in_edges`` int64 [N, K] and ``in_degree`` float32 [N, 1]
(:func:`hybridmpm.neural.runtime.aggregation_inputs`); outputs
:data:`OUTPUT_NAMES`: ``acceleration`` float32 [N, D] (m/step²) and
``next_position`` float32 [N, D] (m). The tests check the graph against torch
on graphs with many edges per receiver.

Model metadata (scene family, dim, r_p, r_t, R, particle types, feature
version, graph layout, training-data hash, architecture, errors) is stored as
the ONNX metadata property ``hybridmpm`` (a JSON object), readable by
onnxruntime without onnx installed.
"""

from __future__ import annotations

import base64
import copy
import json
import os
from pathlib import Path
from typing import Any

from hybridmpm.neural.constants import BRANCH_KEY, FEATURE_VERSION, METADATA_KEY
from hybridmpm.neural.grid_branch import BRANCH_INPUT, BRANCH_OUTPUT, branch_channels
from hybridmpm.train.gns.model import GnsConfig, GnsModel
from hybridmpm.train.gns.onnx_graph import GRAPH_LAYOUT, INPUT_NAMES, OUTPUT_NAMES, inference_graph, state_dict_from_onnx


def export_onnx(model: GnsModel, path: str | Path, metadata: dict[str, Any]) -> Path:
    """Write ``model`` to ``path`` (atomically) with ``metadata`` merged over the
    architecture facts (``feature_version``, ``dim``, ``radius``, ``t_in``,
    ``bounds``, ``latent``, ``layers``, ``wall_reach``, ``parameters``); ``graph`` is always
    :data:`~hybridmpm.train.gns.onnx_graph.GRAPH_LAYOUT` (what the file holds). Returns the path.

    Input and output names are :data:`INPUT_NAMES` and :data:`OUTPUT_NAMES`
    (what :class:`~hybridmpm.neural.runtime.GnsRuntime` feeds and reads).
    Needs torch and onnx (the 'train' extra); an I/O failure raises
    ``OSError`` and leaves any existing file at ``path`` untouched."""
    cfg = model.config
    meta = {
        "feature_version": FEATURE_VERSION,
        "graph": GRAPH_LAYOUT,
        "dim": cfg.dim,
        "radius": cfg.radius,
        "t_in": cfg.t_in,
        "bounds": cfg.bounds,
        "latent": cfg.latent,
        "layers": cfg.layers,
        "wall_reach": cfg.wall_reach,
        "parameters": int(sum(p.numel() for p in model.parameters())),
        **metadata,
    }
    meta["graph"] = GRAPH_LAYOUT
    if getattr(model, "branch", None) is not None:  # a model class from before the grid branch has no such attribute
        meta[BRANCH_KEY] = branch_metadata(model)
    else:
        meta.pop(BRANCH_KEY, None)
    proto = inference_graph(model, json.dumps(meta, sort_keys=True))
    path = Path(path)
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_bytes(proto.SerializeToString())
    os.replace(tmp, path)
    return path


def branch_metadata(model: GnsModel) -> dict[str, Any]:
    """The ``grid_branch`` metadata of a GNS with a grid branch
    (:mod:`hybridmpm.neural.grid_branch`): its constants and its U-Net as an
    ONNX graph (torch's exporter, opset 18, standard operators), base64."""
    import io
    import warnings

    import torch

    branch = model.branch
    assert branch is not None
    cfg = model.config
    example = torch.zeros(1, branch_channels(cfg.dim, len(branch.types), cfg.t_in), *[branch.grid] * cfg.dim)
    buf = io.BytesIO()
    net = copy.deepcopy(branch.net).eval()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        torch.onnx.export(net, (example,), buf, input_names=[BRANCH_INPUT], output_names=[BRANCH_OUTPUT], opset_version=18, dynamo=False)  # type: ignore[arg-type]
    feats = model.features
    return {
        "grid": branch.grid,
        "width": cfg.grid_width,
        "levels": cfg.grid_levels,
        "types": list(branch.types),
        "rest_count": branch.rest_count,
        "latent": cfg.latent,
        "vel_mean": [float(v) for v in feats.vel_mean],
        "vel_std": [float(v) for v in feats.vel_std],
        "onnx": base64.b64encode(buf.getvalue()).decode("ascii"),
    }


def upgrade_onnx(path: str | Path, out: str | Path | None = None) -> bool:
    """Rewrite a GNS exported by torch's ONNX exporter (no ``graph`` in its
    metadata) as the compiled inference graph of the same weights
    (:data:`~hybridmpm.train.gns.onnx_graph.GRAPH_LAYOUT`), keeping its
    metadata; to ``out`` (default: in place, atomically). Returns False,
    writing nothing, if ``path`` is already of the current layout. Same
    function: the tests check the graphs against each other. Raises
    ``ValueError`` for a compiled graph of another layout (its weights are
    folded: only its training run can export it again). Needs torch and onnx
    (the 'train' extra)."""
    import onnx

    proto = onnx.load(str(path))
    layout = json.loads({p.key: p.value for p in proto.metadata_props}[METADATA_KEY]).get("graph")
    if layout == GRAPH_LAYOUT:
        return False
    sd, meta = state_dict_from_onnx(path)
    stats: dict[str, Any] = {k: [float(x) for x in sd[f"features.{k}"]] for k in ("vel_mean", "vel_std", "acc_mean", "acc_std")}
    # the stored stds already include the training noise (they are the effective stds): noise_std=0 keeps them
    cfg = GnsConfig(
        dim=meta["dim"], radius=meta["radius"], bounds=meta["bounds"], latent=meta["latent"], layers=meta["layers"],
        t_in=meta.get("t_in", 6), noise_std=0.0, embedding=int(sd["features.embed.weight"].shape[1]), **stats,
    )  # fmt: skip
    import torch

    model = GnsModel(cfg).eval()
    model.load_state_dict({k: torch.from_numpy(v.copy()) for k, v in sd.items()})
    export_onnx(model, out if out is not None else path, meta)
    return True


__all__ = ["INPUT_NAMES", "METADATA_KEY", "OUTPUT_NAMES", "branch_metadata", "export_onnx", "upgrade_onnx"]
