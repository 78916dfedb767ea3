"""The fused edge kernels (``hybridmpm.neural.fused``, ``rust/gnn``,
``rust/ort-ops``) compute the compiled graph's function.

Checked against onnxruntime's own operators running the unfused graph (an
independent implementation of the same arithmetic): every shipped model on a
state of its own scene, one and two threads; the kernels' Rust unit tests
check them against the layers written out in f64 (``cargo test -p
hybridmpm-gnn``)."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import onnx
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from hybridmpm.conventions import GNS_KINEMATIC
from hybridmpm.errors import InvalidInputError
from hybridmpm.graph import radius_graph
from hybridmpm.models import shipped_model, shipped_models
from hybridmpm.neural import GnsRuntime, fused
from hybridmpm.sim import NeuralSimulator, rollout

GOLDEN = Path(__file__).parent / "golden"


def scene_state(scene: str, steps: int = 2) -> NeuralSimulator:
    sim = NeuralSimulator(scene, seed=5, mpm_threads=1)
    while sim.warming_up:
        sim.advance()
    for _ in range(steps):
        sim.advance()
    return sim


@pytest.mark.parametrize("scene", sorted(set(shipped_models())))
def test_every_shipped_model_gives_the_plain_graphs_outputs(scene: str):
    """On a state of its own scene: acceleration within 1e-5 of its largest
    value (float32 rounding of sums in another order), next position within
    1e-6 m; on two threads the fused sums are the same bits as on one."""
    sim = scene_state(scene)
    hist, ptype = sim.history, sim.particles.particle_type
    assert hist is not None
    graph = radius_graph(hist[-1], sim.model.radius)
    plain = GnsRuntime(shipped_model(scene), fused=False)
    one, two = GnsRuntime(shipped_model(scene)), GnsRuntime(shipped_model(scene), threads=2)
    assert (plain.fused, one.fused, two.fused) == (False, True, True)
    a0, x0, _ = plain.predict(hist, ptype, graph=graph)
    a1, x1, _ = one.predict(hist, ptype, graph=graph)
    a2, x2, _ = two.predict(hist, ptype, graph=graph)
    assert np.abs(a1 - a0).max() <= 1e-5 * np.abs(a0).max()
    assert np.abs(x1 - x0).max() <= 1e-6
    assert np.array_equal(a1, a2) and np.array_equal(x1, x2)


@settings(max_examples=30, deadline=None)
@given(
    scene=st.sampled_from(["water_sand2d", "water3d"]),
    n=st.integers(0, 80),
    seed=st.integers(0, 2**31 - 1),
    spread=st.floats(0.02, 1.0),
)
def test_random_clouds_give_the_plain_graphs_outputs(scene: str, n: int, seed: int, spread: float):
    """Any cloud, not only the scenes' states: random positions (clumped or
    spread over the domain, some past the walls, where the wall features
    clip), random histories, every trained type and kinematic particles
    (which the decoder holds in place): the fused graph's outputs are the
    plain graph's to float32 rounding, and kinematic particles stay put."""
    plain = GnsRuntime(shipped_model(scene), fused=False)
    fused_m = GnsRuntime(shipped_model(scene))
    assert fused_m.fused
    rng = np.random.default_rng(seed)
    lo, hi = np.asarray(plain.meta["bounds"], np.float64).T
    centre = lo + (hi - lo) * rng.uniform(0.2, 0.8, plain.dim)
    last = centre + (hi - lo) * spread * rng.uniform(-0.6, 0.6, (n, plain.dim))
    steps = rng.normal(0.0, 0.3 * plain.radius, (plain.t_in - 1, n, plain.dim)).cumsum(0)[::-1]
    hist = np.concatenate([last - steps, last[None]]).astype(np.float32)
    types = np.array([*plain.meta["particle_types"], GNS_KINEMATIC], np.int64)
    ptype = rng.choice(types, n)
    a0, x0, _ = plain.predict(hist, ptype)
    a1, x1, _ = fused_m.predict(hist, ptype)
    scale = float(np.abs(a0).max()) if n else 0.0
    assert np.abs(a1 - a0).max(initial=0.0) <= 1e-5 * scale + 1e-9
    assert np.abs(x1 - x0).max(initial=0.0) <= 1e-5 * (1.0 + scale)
    kin = ptype == GNS_KINEMATIC
    assert np.array_equal(x1[kin], hist[-1][kin])


def shipped_files() -> list[Path]:
    """Every shipped network: the models and the bench's variants."""
    root = shipped_model("water2d").parent
    return sorted(root.glob("*.onnx")) + sorted(root.glob("variants/*/*.onnx"))


def test_the_shipped_fused_files_are_the_rewrite_of_the_shipped_models(tmp_path):
    """``fused/NAME.onnx`` beside each shipped network (what serving without
    the onnx package runs) is exactly :func:`fused.write_fused` of it, made
    from it (its SHA-256 recorded); a network the kernels do not cover (latent
    32) has none."""
    files = shipped_files()
    assert len(files) >= 8
    for src in files:
        copy = tmp_path / src.parent.name / src.name
        copy.parent.mkdir(exist_ok=True)
        shutil.copy(src, copy)
        made = fused.write_fused(copy)
        sibling = fused.fused_sibling(src)
        if made is None:
            assert not sibling.exists(), f"{sibling} is stale: {src.name} no longer fuses"
            continue
        assert sibling.is_file() and made.read_bytes() == sibling.read_bytes(), f"{sibling} is stale: rerun fused.write_fused({src})"
        # every edge stage and every node update is one fused operator: an edge and a node block per message-passing step

        ops = [n.op_type for n in onnx.load(str(sibling)).graph.node if n.domain == fused.DOMAIN]
        steps = GnsRuntime(src, fused=False).meta["layers"]
        assert (ops.count("HmpmEdgeEncoder"), ops.count("HmpmEdgeBlock"), ops.count("HmpmNodeBlock")) == (1, steps, steps), (src.name, ops)
    assert not fused.fused_sibling(shipped_model("water2d").parent / "variants" / "water2d" / "size_L3x32_R15_rt2.onnx").exists()


def test_a_stale_or_foreign_fused_file_is_not_used(tmp_path):
    """A fused file made from another model is ignored: the model runs its own
    graph (rewritten in memory here, where the onnx package is installed)."""
    src = tmp_path / "water2d.onnx"
    shutil.copy(shipped_model("water2d"), src)
    (tmp_path / "fused").mkdir()
    shutil.copy(fused.fused_sibling(shipped_model("sand2d")), fused.fused_sibling(src))
    data = fused.load_fused(src)
    assert data is not None and data != fused.fused_sibling(src).read_bytes()
    sim = scene_state("water2d", steps=1)
    hist, ptype = sim.history, sim.particles.particle_type
    a_f, _, _ = GnsRuntime(src).predict(hist, ptype)
    a_p, _, _ = GnsRuntime(src, fused=False).predict(hist, ptype)
    assert np.abs(a_f - a_p).max() <= 2e-5 * np.abs(a_p).max()


def test_graphs_of_torchs_exporter_are_left_alone():
    """A torch-exported graph (202ef89) does not match: ``fuse_graph``
    returns None and the model runs unfused; asking for the kernels on such a
    file is refused naming ``fused``."""
    import onnx

    f = GOLDEN / "models" / "water2d_202ef89.onnx"
    assert fused.fuse_graph(onnx.load(str(f))) is None
    assert GnsRuntime(f).fused is False
    with pytest.raises(InvalidInputError) as e:
        GnsRuntime(f, fused=True)
    assert e.value.field == "fused"
    with pytest.raises(InvalidInputError) as e:
        GnsRuntime(shipped_model("water2d"), fused="yes")  # type: ignore[arg-type]
    assert e.value.field == "fused"


def test_bad_indices_are_an_error_naming_them_not_a_crash():
    """The operators check what onnxruntime hands them: a receiver outside the
    nodes, or a particle type outside the type table, comes back as
    onnxruntime's error naming ``receivers`` or ``particle_type``."""
    model = GnsRuntime(shipped_model("water2d"))
    sim = scene_state("water2d", steps=1)
    hist, ptype = sim.history, sim.particles.particle_type
    s, r, d, dist = radius_graph(hist[-1], model.radius)
    r = r.copy()
    r[3] = hist.shape[1] + 5
    feeds = model.feeds(hist, ptype, (s, r, d, dist))
    with pytest.raises(Exception, match="receivers"):
        model.session.run(None, feeds)
    # a particle type outside the type table (the Python side refuses it first; the kernel too)
    feeds = model.feeds(hist, ptype, radius_graph(hist[-1], model.radius))
    feeds["particle_type"] = feeds["particle_type"].copy()
    feeds["particle_type"][0] = 99
    with pytest.raises(Exception, match="particle_type"):
        model.session.run(None, feeds)


def test_a_rollout_is_the_plain_graphs_to_rounding(monkeypatch):
    """60 frames of the dam break's network, fused and not (``HYBRIDMPM_FUSED=0``
    switches the kernels off). The network alone (no density relaxation)
    stays within 1e-5 m (measured 5e-7: float32 rounding, amplified by the
    flow). With the relaxation the bound is 1e-3 m (measured 2e-4): its
    ``ρ > ρ₀`` test is a branch, which a one-ulp difference can flip for a
    particle at the rest density, moving it by a fraction of a correction
    (the compiled graph against the torch export drifted 4.6e-4 m over 120
    frames)."""
    for relax, bound in ((0, 1e-5), (3, 1e-3)):
        runs = []
        for on in ("1", "0"):
            monkeypatch.setenv("HYBRIDMPM_FUSED", on)
            sim = NeuralSimulator("dam_break2d", seed=0, mpm_threads=1, relax=relax)
            assert sim.model.fused == (on == "1")
            runs.append(rollout(sim, 60).fluid_positions)
        assert np.abs(runs[0] - runs[1]).max() <= bound, relax


def test_a_runtime_that_cannot_load_the_kernels_runs_the_plain_graph(monkeypatch):
    """If onnxruntime refuses the custom operators (an old runtime, a library
    that does not load), the model warns and runs its plain graph; asking for
    the kernels explicitly is refused naming ``fused``."""

    def refuse(options):
        raise RuntimeError("custom op library refused")

    monkeypatch.setattr(fused, "register", refuse)
    with pytest.warns(RuntimeWarning, match="without the fused edge kernels"):
        model = GnsRuntime(shipped_model("water2d"))
    assert model.fused is False
    sim = scene_state("water2d", steps=1)
    a, _, _ = model.predict(sim.history, sim.particles.particle_type)
    assert np.isfinite(a).all()
    with pytest.raises(InvalidInputError) as e:
        GnsRuntime(shipped_model("water2d"), fused=True)
    assert e.value.field == "fused"
