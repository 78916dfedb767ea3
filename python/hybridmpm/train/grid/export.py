"""The grid model's file: its ONNX export and its snapshots (needs torch and onnx).

:func:`export_grid` writes the U-Net of a :class:`~hybridmpm.train.grid.model.GridModel`
as the ``.onnx`` file :class:`hybridmpm.neural.grid.GridRuntime` runs;
:func:`load_snapshot` reads a model back from a training run's ``best.pt`` or
``checkpoint.pt`` (:mod:`hybridmpm.train.grid.train`).
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

import torch

from hybridmpm.neural.constants import METADATA_KEY
from hybridmpm.neural.grid import GRID_INPUT, GRID_KIND, GRID_OUTPUT
from hybridmpm.train.grid.model import GridConfig, GridModel


def export_grid(model: GridModel, path: str | Path, metadata: dict[str, Any]) -> Path:
    """Write ``model``'s U-Net to ``path`` (atomically) as the file
    :class:`hybridmpm.neural.grid.GridRuntime` runs: input ``grid`` float32
    [1, C, G^D], output ``dv`` float32 [1, r_t·D, G^D], standard ONNX
    operators (opset 18); the metadata property ``hybridmpm`` holds
    ``metadata`` (the run's facts, :func:`~hybridmpm.train.scaffold.export_metadata`)
    merged over ``kind``, ``grid_config``, ``beta``, ``pressure_strength``,
    ``dim``, ``r_t``, ``t_in``, ``bounds``, ``particle_types``,
    ``parameters``; ``kind`` is always ``"grid"``. Needs torch and onnx."""
    import warnings

    import onnx

    cfg = model.config
    meta = {
        "kind": GRID_KIND,
        "grid_config": cfg.to_dict(),
        "beta": float(torch.sigmoid(model.flip_logit.detach())),
        "pressure_strength": float(torch.nn.functional.softplus(model.pressure_logit.detach())) if cfg.pressure else None,
        "dim": cfg.dim,
        "r_t": cfg.r_t,
        "t_in": cfg.t_in,
        "bounds": cfg.bounds,
        "particle_types": cfg.types,
        "parameters": int(sum(p.numel() for p in model.parameters())),
        **metadata,
    }
    meta["kind"] = GRID_KIND
    path = Path(path)
    tmp = path.with_name(path.name + ".tmp")
    example = torch.zeros(1, cfg.in_channels, *[cfg.grid] * cfg.dim)
    net = model.net.eval()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        torch.onnx.export(net, (example,), str(tmp), input_names=[GRID_INPUT], output_names=[GRID_OUTPUT], opset_version=18, dynamo=False)
    proto = onnx.load(str(tmp))
    entry = proto.metadata_props.add()
    entry.key, entry.value = METADATA_KEY, json.dumps(meta, sort_keys=True)
    onnx.save(proto, str(tmp))
    os.replace(tmp, path)
    return path


def load_snapshot(path: str | Path) -> GridModel:
    """A :class:`GridModel` (in eval mode) from a ``best.pt`` / ``checkpoint.pt``
    of :func:`~hybridmpm.train.grid.train.train_grid` (``model``: its state
    dict, ``config``: its :class:`GridConfig` as a dict)."""
    state = torch.load(path, weights_only=False)
    model = GridModel(GridConfig(**state["config"]))
    model.load_state_dict(state["model"])
    return model.eval()


__all__ = ["export_grid", "load_snapshot"]
