"""What a trained model says about the run that made it: the one function
that writes the run's facts into an exported model's metadata (the GNS's and
the grid model's ONNX property ``hybridmpm``, the controller's
``control.json``), beside the architecture facts each family's exporter adds.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import torch


def data_sha256(metadata: dict[str, Any]) -> str | None:
    """The SHA-256 of a GNS dataset's training split as its ``metadata.json``
    records it (``sha256.train``; :func:`hybridmpm.data.gns.file_sha256`), or None."""
    sha = metadata.get("sha256")
    return sha.get("train") if isinstance(sha, dict) else None


def export_metadata(
    model: torch.nn.Module, *, scene: str, steps: int, data: dict[str, Any] | Sequence[dict[str, Any]] | None = None, **facts: Any
) -> dict[str, Any]:
    """The run facts an exported model carries: ``scene`` (the scene family it
    is for), ``steps`` (optimiser steps of the weights exported), ``parameters``
    (their count in ``model``); when trained on GNS datasets (``data``: the
    dataset's ``metadata.json``, or the pooled datasets' in order)
    ``data_sha256`` (:func:`data_sha256`; a list for pooled datasets) and
    ``r_p`` (the data's spatial resolution, 1 when unstated); then ``facts``
    (the family's: seconds [s], scores, settings that change the model's use),
    which win over the above."""
    meta: dict[str, Any] = {"scene": scene, "steps": int(steps), "parameters": int(sum(p.numel() for p in model.parameters()))}
    if data is not None:
        metas = [data] if isinstance(data, dict) else list(data)
        shas = [data_sha256(m) for m in metas]
        meta["data_sha256"] = shas[0] if isinstance(data, dict) else shas
        meta["r_p"] = float(metas[0].get("r_p", 1.0))
    meta.update(facts)
    return meta


__all__ = ["data_sha256", "export_metadata"]
