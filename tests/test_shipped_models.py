"""Shipped models: they load with onnxruntime alone, match their metadata and
cards, fit their scenes, a 100-frame rollout on a held-out seed stays finite,
and each meets an accuracy bound against MPM at its r_p on a held-out state
that a broken model (zero acceleration, or weights perturbed by 10 %) does
not meet."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from hybridmpm.bench import TEST_SEED0
from hybridmpm.metrics import grid_mass_error
from hybridmpm.models import shipped_model, shipped_models
from hybridmpm.neural import GnsRuntime
from hybridmpm.scenes import make_scene
from hybridmpm.sim import MpmSimulator, NeuralSimulator, rollout

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
    nm = GnsRuntime(path)
    assert scene in nm.meta["scenes"]
    s = make_scene(scene, seed=HELD_OUT_SEED)
    assert nm.dim == s.dim
    x = rollout(NeuralSimulator(s, nm, seed=HELD_OUT_SEED, detect_failures=False, mpm_threads=1), 100).positions
    assert len(x) == 1 + 100 // nm.r_t
    assert np.isfinite(x).all()
    # (no "inside the domain" check: NeuralSimulator clips every prediction to the domain, so it
    # could not fail; test_the_shipped_model_meets_its_accuracy_bound checks where the fluid goes)


def test_every_shipped_gns_file_is_of_the_current_layout():
    """Every GNS graph shipped (the models, their variants, the fused
    siblings of both) records the compiled layout the runtime runs: a file
    of an earlier layout would be refused on load (tests/test_neural.py)."""
    import json

    import onnx

    from hybridmpm.neural.constants import GRAPH_LAYOUT, METADATA_KEY

    root = shipped_model("water2d").parent
    files = sorted(p for p in root.rglob("*.onnx") if "control" not in p.relative_to(root).parts)
    layouts = {}
    for f in files:
        meta = {p.key: p.value for p in onnx.load(str(f), load_external_data=False).metadata_props}
        layouts[str(f.relative_to(root))] = json.loads(meta[METADATA_KEY]).get("graph")
    assert len(layouts) >= 2 * len(set(INDEX.values())), layouts  # the models and their fused siblings at least
    assert set(layouts.values()) == {GRAPH_LAYOUT}, layouts


#: Network steps of the accuracy check (after MPM's T_in − 1 warm-up steps).
HORIZON = 5
#: Bound on each shipped model's mean grid-mass error (128 cells) against MPM at its r_p over
#: HORIZON network steps from MPM's history at the first test seed, raw output (no density
#: relaxation: it moves particles away from MPM's state on purpose, and would blur the contrast).
#: About 1.5 × the error measured at 4979fba (in brackets), and below the error of the same model
#: with its weights perturbed by 10 % (``perturbed``) and of a zero-acceleration model (all
#: measured at 1.3-10 × the bound): a retrained model must meet the same bound.
ACCURACY_BOUND = {
    "dam_break2d": 0.09,  # (0.058; perturbed 0.18, zero acceleration 0.16)
    "sand2d": 0.045,  # (0.029; 0.12, 0.18)
    "sand3d": 0.13,  # (0.084; 0.33, 0.36)
    "sand_ramps2d": 0.05,  # (0.031; 0.082, 0.25)
    "water2d": 0.09,  # (0.059; 0.21, 0.22)
    "water3d": 0.04,  # (0.025; 0.43, 0.29)
    "water_ramps2d": 0.065,  # (0.041; 0.29, 0.23)
    "water_sand2d": 0.031,  # the GNS with a grid branch (0.0247; perturbed 0.035: closer to the model than a GNS's, the U-Net is not perturbed)
}


class ZeroAcceleration(GnsRuntime):
    """A broken model: the shipped one's metadata, no acceleration (each particle keeps its last velocity)."""

    def predict(self, history, particle_type, max_neighbors=None, graph=None):
        acc, _, used = super().predict(history, particle_type, max_neighbors, graph)
        h = history.astype(np.float64)
        return np.zeros_like(acc), (2 * h[-1] - h[-2]).astype(np.float32), used


def perturbed(path: Path, out: Path, rel: float = 0.1) -> Path:
    """A broken model: the weight matrices of ``path`` times ``1 + rel·N(0, 1)`` (seeded), saved to ``out``."""
    import onnx
    from onnx import numpy_helper

    m = onnx.load(str(path))
    rng = np.random.default_rng(0)
    changed = 0
    for init in m.graph.initializer:
        if init.name.startswith("W") and len(init.dims) == 2:
            w = numpy_helper.to_array(init)
            init.CopyFrom(numpy_helper.from_array((w * (1 + rel * rng.standard_normal(w.shape))).astype(w.dtype), init.name))
            changed += 1
    assert changed >= 10, changed  # the MLPs' weights, whatever the graph's layout names them
    onnx.save(m, str(out))
    return out


def test_every_shipped_model_has_an_accuracy_bound():
    assert set(ACCURACY_BOUND) == set(INDEX)


@pytest.mark.parametrize("scene", sorted(INDEX))
def test_the_shipped_model_meets_its_accuracy_bound(scene, tmp_path):
    nm = GnsRuntime(shipped_model(scene))
    s = make_scene(scene, seed=TEST_SEED0)  # a test seed: held out from training and validation
    frames = (nm.t_in - 1 + HORIZON) * nm.r_t
    mpm = rollout(MpmSimulator(s, r_p=nm.r_p, r_t=nm.r_t, threads=1, seed=TEST_SEED0), frames).fluid_positions

    def error(model: GnsRuntime) -> float:
        ro = rollout(NeuralSimulator(s, model, seed=TEST_SEED0, detect_failures=False, relax=0, mpm_threads=1), frames)
        assert np.array_equal(ro.fluid_positions[: nm.t_in], mpm[: nm.t_in])  # the same MPM warm-up: the network starts from MPM's history
        return float(grid_mass_error(ro.fluid_positions, mpm, 128)[nm.t_in :].mean())

    bound = ACCURACY_BOUND[scene]
    err = error(nm)
    print(f"{scene}: error {err:.4f} (bound {bound})")
    assert err <= bound
    assert error(ZeroAcceleration(shipped_model(scene))) > bound
    assert error(GnsRuntime(perturbed(shipped_model(scene), tmp_path / "perturbed.onnx"))) > bound
