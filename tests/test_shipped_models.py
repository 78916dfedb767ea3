"""Shipped models: they load with onnxruntime alone, match their metadata and
cards, fit their scenes, and a 100-frame rollout on a held-out seed stays
finite and inside the domain."""

from __future__ import annotations

import numpy as np
import pytest

from hybridmpm.models import shipped_model, shipped_models
from hybridmpm.neural import NeuralModel
from hybridmpm.scenes import make_scene
from hybridmpm.sim import NeuralSimulator, rollout

INDEX = shipped_models()
HELD_OUT_SEED = 987_654_321  # trajectory seeds come from SeedSequence([S, i]); this one is not among them


def test_the_2d_water_and_sand_scenes_have_shipped_models():
    assert {"water2d", "sand2d"} <= set(INDEX)


@pytest.mark.parametrize("scene", sorted(INDEX))
def test_shipped_model_loads_fits_and_rolls_out(scene):
    path = shipped_model(scene)
    assert path.stat().st_size < 5_000_000
    card = path.with_suffix(".md").read_text()
    for word in ("Data", "Config", "Training", "rollout", "one-step"):
        assert word in card, word
    nm = NeuralModel(path)
    assert scene in nm.meta["scenes"]
    s = make_scene(scene, seed=HELD_OUT_SEED)
    assert nm.dim == s.dim
    x = rollout(NeuralSimulator(s, nm, seed=HELD_OUT_SEED, detect_failures=False, mpm_threads=1), 100).positions
    assert len(x) == 1 + 100 // nm.r_t
    assert np.isfinite(x).all()
    assert x.min() >= 0.0 and x.max() <= 1.0
