"""Shipped neural-simulator models (small ONNX files with model cards).

``index.json`` maps each scene to the model file that serves it (one model may
serve several scenes); every model has a card ``<name>.md`` beside it (data,
config, training time, one-step and rollout errors). Simulating with a shipped
model needs only numpy and onnxruntime. ``fused/<name>`` beside a model (and
beside each variant) is the same network with the fused edge kernels
(:mod:`hybridmpm.neural.fused`), made from it by ``fused.write_fused`` and
recording its SHA-256; :class:`~hybridmpm.neural.GnsRuntime` runs it in
its place.
"""

from __future__ import annotations

import json
from importlib import resources
from pathlib import Path

from hybridmpm.errors import InvalidInputError


def shipped_models() -> dict[str, str]:
    """Scene → model file name of the shipped models."""
    text = resources.files("hybridmpm.models").joinpath("index.json").read_text()
    return dict(json.loads(text))


def shipped_model(scene: str) -> Path:
    """Path of the shipped model for ``scene``. Raises :class:`InvalidInputError`
    (field ``model``) if no shipped model serves it."""
    index = shipped_models()
    if scene not in index:
        raise InvalidInputError(
            f"model: no shipped model for scene {scene!r} (shipped: {', '.join(sorted(index)) or 'none'}); train one with hybridmpm train and pass --model",
            "model",
        )
    return Path(str(resources.files("hybridmpm.models").joinpath(index[scene])))


def shipped_switching(scene: str) -> dict:
    """The switching rule chosen for the shipped model of ``scene``
    (``switching.json``, written by ``benchmarks/release/ship_switching.py`` from
    validation rollouts; docs/hybrid.md "Switching rules"): a dict with
    ``safeguard`` and ``audit_tol`` [g], or empty where the hybrid's defaults
    were not beaten (or the file is absent)."""
    path = resources.files("hybridmpm.models").joinpath("switching.json")
    if not path.is_file():
        return {}
    entry = json.loads(path.read_text()).get(scene, {})
    return {k: entry[k] for k in ("safeguard", "audit_tol") if k in entry}


def shipped_default(scene: str) -> dict:
    """The default configuration of ``scene`` (``defaults.json``, written by
    ``benchmarks/release/ship_defaults.py`` from validation rollouts; docs/hybrid.md
    "Defaults per scene"): a dict with ``config`` (a tuned configuration:
    :data:`~hybridmpm.sim.config.CONFIG_KEYS`, a hybrid's ``rule`` and ``cheap``),
    ``label``, ``ratios_to_mpm_rp`` (time and scores against MPM at ``r_p`` on
    the validation seeds), ``cheap_share`` and the candidates it was chosen
    among; empty where none was chosen for the scene (or the file is absent).
    The file is package data, checked when it is read: raises
    :class:`InvalidInputError` (field ``defaults``, naming the file) when it is
    not a JSON object of scene entries, or the scene's entry is not an object
    whose ``config`` is an object with a ``kind`` of mpm, neural or hybrid."""
    path = resources.files("hybridmpm.models").joinpath("defaults.json")
    if not path.is_file():
        return {}

    def corrupt(why: str) -> InvalidInputError:
        return InvalidInputError(f"defaults: the package's default configurations {path} are corrupt ({why}); reinstall hybridmpm", "defaults")

    try:
        doc = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, ValueError, RecursionError) as e:
        raise corrupt(f"not readable JSON: {str(e)[:120]}") from None
    if not isinstance(doc, dict):
        raise corrupt(f"a JSON {type(doc).__name__}, not an object of scene entries")
    entry = doc.get(scene, {})
    if not isinstance(entry, dict):
        raise corrupt(f"the entry of {scene!r} is a {type(entry).__name__}, not an object")
    if entry:
        config = entry.get("config")
        if not isinstance(config, dict) or config.get("kind") not in ("mpm", "neural", "hybrid"):
            raise corrupt(f"the entry of {scene!r} has no config with a kind of mpm, neural or hybrid")
    return dict(entry)


def variant_models(scene: str) -> list[dict]:
    """The shipped variant networks of ``scene`` that ``hybridmpm bench``
    compares with the shipped model (paper Fig. 5 a-c): each a dict with
    ``name``, ``role`` ("full": r_p = r_t = 1; "spatial": r_p < 1, r_t = 1;
    "temporal": r_p = 1, r_t > 1; "size": another network size) and ``path``.
    Empty if none was trained for the scene (``variants/index.json``; cards in
    ``variants/README.md``)."""
    root = resources.files("hybridmpm.models").joinpath("variants")
    index = root.joinpath("index.json")
    if not index.is_file():
        return []
    out = []
    for v in json.loads(index.read_text()).get(scene, []):
        out.append({"name": v["name"], "role": v["role"], "path": Path(str(root.joinpath(v["file"])))})
    return out


__all__ = ["shipped_default", "shipped_model", "shipped_models", "shipped_switching", "variant_models"]
