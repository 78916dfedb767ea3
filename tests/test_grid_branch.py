"""The GNS's grid branch: p2g → U-Net → g2p added to the node latents.

Torch (training) against the exported file in onnxruntime with the Rust
transfers (run time), in 2D and 3D, fused and plain; a zero branch leaves the
GNS as it was; windows of a batch stay apart on the grid; a short training run
with the branch trains, resumes and exports a model the simulator runs.
"""

from __future__ import annotations

import json

import numpy as np
import pytest

torch = pytest.importorskip("torch", reason="the training extra (torch) is not installed")

from _datasets import split_names, write_dataset  # noqa: E402

from hybridmpm.errors import InvalidInputError  # noqa: E402
from hybridmpm.graph import radius_graph  # noqa: E402
from hybridmpm.neural import GnsRuntime  # noqa: E402


def _model(dim: int, grid: int, seed: int = 0, branch_scale: float = 0.3):
    from hybridmpm.train.gns.model import GnsConfig, GnsModel

    torch.manual_seed(seed)
    cfg = GnsConfig(
        dim=dim, radius=0.05, bounds=[[0.1, 0.9]] * dim, vel_mean=[0.0] * dim, vel_std=[0.01] * dim,
        acc_mean=[0.0] * (dim - 1) + [-1e-3], acc_std=[1e-3] * dim, latent=16, layers=2,
        grid=grid, grid_width=4, grid_levels=2, grid_types=[5, 6], grid_rest_count=3.0,
    )  # fmt: skip
    model = GnsModel(cfg).eval()
    if grid and branch_scale:
        with torch.no_grad():  # a trained-looking branch: the zero-initialised last convolution made nonzero
            for p in model.branch.net.out.parameters():
                p.normal_(0.0, branch_scale)
    return model


def _state(dim: int, n: int, seed: int = 0):
    rng = np.random.default_rng(seed)
    x = rng.uniform(0.15, 0.85, (n, dim)).astype(np.float32)
    x[:5] = 0.05  # outside the walls: the branch's stencil reads them clipped
    hist = np.stack([x + 0.004 * k * rng.normal(size=(n, dim)).astype(np.float32) for k in range(6)]).astype(np.float32)
    pt = np.where(np.arange(n) % 3 == 0, 6, 5).astype(np.int64)
    pt[:10] = 3  # obstacles
    return hist, pt


def _torch_step(model, hist, pt):
    s, r, _, _ = radius_graph(hist[-1], model.config.radius)
    with torch.no_grad():
        acc, nxt = model(torch.from_numpy(hist), torch.from_numpy(pt), torch.from_numpy(s), torch.from_numpy(r))
    return acc.numpy(), nxt.numpy()


@pytest.mark.parametrize("dim,grid,n", [(2, 16, 500), (3, 8, 400)])
def test_the_exported_branch_computes_what_torch_computes(tmp_path, dim, grid, n):
    from hybridmpm.train.gns.export import export_onnx

    model = _model(dim, grid)
    hist, pt = _state(dim, n)
    acc_t, nxt_t = _torch_step(model, hist, pt)
    plain = _model(dim, grid, branch_scale=0.0)
    plain.load_state_dict({k: v for k, v in model.state_dict().items() if not k.startswith("branch.net.out")}, strict=False)
    acc_0, _ = _torch_step(plain, hist, pt)
    # the branch changes the step well beyond the tolerance below
    assert np.abs(acc_t - acc_0).max() > 100 * 1e-6 * np.abs(acc_t).max()
    path = export_onnx(model, tmp_path / "m.onnx", {"scene": "water2d", "particle_types": [5, 6]})
    for fused in (None, False):
        rt = GnsRuntime(path, fused=fused)
        assert rt.branch is not None and rt.meta["grid_branch"]["grid"] == grid
        acc, nxt, _ = rt.predict(hist, pt)
        np.testing.assert_allclose(acc, acc_t, rtol=0, atol=1e-5 * np.abs(acc_t).max())
        np.testing.assert_allclose(nxt, nxt_t, rtol=0, atol=1e-6)


def test_a_zero_branch_leaves_the_gns_as_it_was():
    from hybridmpm.train.gns.model import GnsModel

    model = _model(2, 16, branch_scale=0.0)  # as a new branch starts: its last convolution is zero
    cfg = model.config
    plain = GnsModel(type(cfg)(**{**cfg.to_dict(), "grid": 0})).eval()
    plain.load_state_dict({k: v for k, v in model.state_dict().items() if not k.startswith("branch.")})
    hist, pt = _state(2, 300)
    np.testing.assert_array_equal(_torch_step(model, hist, pt)[0], _torch_step(plain, hist, pt)[0])


def test_the_windows_of_a_batch_stay_apart_on_the_grid():
    """Two windows in one disjoint batch get each the context it gets alone
    (the grid nodes are offset per window); read as one window they mix."""
    model = _model(2, 16)
    (h1, p1), (h2, p2) = _state(2, 200, seed=1), _state(2, 300, seed=2)
    hist = torch.from_numpy(np.concatenate([h1, h2], axis=1))
    pt = torch.from_numpy(np.concatenate([p1, p2]))
    nv = 5 * 2
    with torch.no_grad():
        nodes = model.features(hist, pt, torch.zeros(0, dtype=torch.int64), torch.zeros(0, dtype=torch.int64))[0]
        window = torch.cat([torch.zeros(200, dtype=torch.int64), torch.ones(300, dtype=torch.int64)])
        both = model.branch(hist[-1], pt, nodes[:, :nv], window, 2).numpy()
        alone = [model.branch(hist[-1][sl], pt[sl], nodes[sl, :nv]).numpy() for sl in (slice(0, 200), slice(200, 500))]
        mixed = model.branch(hist[-1], pt, nodes[:, :nv]).numpy()
    np.testing.assert_allclose(both, np.concatenate(alone), rtol=1e-5, atol=1e-6)
    assert np.abs(mixed - both).max() > 1e-3 * np.abs(both).max()


def test_a_file_whose_graph_and_metadata_disagree_on_the_branch_is_refused(tmp_path):
    import onnx

    from hybridmpm.neural.constants import METADATA_KEY
    from hybridmpm.train.gns.export import export_onnx

    path = export_onnx(_model(2, 16), tmp_path / "m.onnx", {"scene": "water2d", "particle_types": [5, 6]})
    proto = onnx.load(str(path))
    entry = next(p for p in proto.metadata_props if p.key == METADATA_KEY)
    meta = json.loads(entry.value)
    for spec, field in ((None, "model.grid_branch"), ({**meta["grid_branch"], "onnx": "not base64!"}, "model.grid_branch")):
        bad = dict(meta)
        if spec is None:
            bad.pop("grid_branch")
        else:
            bad["grid_branch"] = spec
        entry.value = json.dumps(bad)
        out = tmp_path / "bad.onnx"
        onnx.save(proto, str(out))
        with pytest.raises(InvalidInputError) as e:
            GnsRuntime(out)
        assert e.value.field == field


def _column_dataset(directory, n_traj=6, frames=30, seed=0):
    """Blocks of particles whose every particle accelerates by an amount set by
    its block's total particle count (a global quantity no radius graph sees)."""
    rng = np.random.default_rng(seed)
    splits: dict[str, dict] = {"train": {}, "valid": {}, "test": {}}
    for i, split in enumerate(split_names(n_traj)):
        n = int(rng.integers(30, 90))
        x = np.empty((frames + 1, n, 2))
        x[0] = rng.uniform([0.3, 0.3], [0.7, 0.5], (n, 2))
        v = np.zeros((n, 2)) + rng.normal(0, 1e-4, 2)  # each block drifts as one
        a = np.array([0.0, 2e-7 * n])
        for t in range(frames):
            v = v + a
            x[t + 1] = x[t] + v
        splits[split][f"simulation_trajectory_{i:05d}"] = (x.astype(np.float32), np.full(n, 5, np.int64))
    meta = {"bounds": [[0.02, 0.98]] * 2, "sequence_length": frames, "default_connectivity_radius": 0.03, "dim": 2, "dt": 2.5e-3}
    write_dataset(directory, splits, {**meta, "r_t": 1, "r_p": 1.0, "n_grid": 64})


def test_training_with_a_grid_branch_runs_resumes_exports_and_simulates(tmp_path):
    from hybridmpm.train.gns.train import TrainConfig, train

    data = tmp_path / "columns"
    data.mkdir()
    _column_dataset(data)
    cfg = TrainConfig(
        scene="columns", data=str(data), out=str(tmp_path / "run"), latent=8, layers=1, r_t=1, steps=20, batch=2,
        val_every=10, rollout_steps=5, threads=1, grid=16, grid_width=4, grid_levels=2, noise_std=0.0,
    )  # fmt: skip
    train(cfg, progress=False)
    train(TrainConfig(**{**cfg.__dict__, "steps": 30}), progress=False)  # resumes
    rows = (tmp_path / "run" / "log.csv").read_text().splitlines()
    assert rows[-1].startswith("30,")
    rt = GnsRuntime(tmp_path / "run" / "model.onnx")
    spec = rt.meta["grid_branch"]
    assert spec["grid"] == 16 and spec["types"] == [5] and spec["rest_count"] > 0
    # the trained branch is in use: the run time equals torch on the trained weights
    from hybridmpm.train.gns.model import GnsConfig, GnsModel

    config = torch.load(tmp_path / "run" / "checkpoint.pt", weights_only=False)["gns_config"]
    model = GnsModel(GnsConfig.from_dict(config)).eval()
    model.load_state_dict(torch.load(tmp_path / "run" / "best.pt", weights_only=False))
    hist, pt = _state(2, 80)
    pt[:] = 5
    acc_t, _ = _torch_step(model, hist, pt)
    acc, _, _ = rt.predict(hist, pt)
    np.testing.assert_allclose(acc, acc_t, rtol=0, atol=1e-5 * np.abs(acc_t).max())
    with pytest.raises(InvalidInputError) as e:
        train(TrainConfig(**{**cfg.__dict__, "grid": 32}), progress=False)
    assert e.value.field == "grid"


@pytest.mark.parametrize("field,value", [("grid", 6), ("grid", 18), ("grid", -1), ("grid_levels", 0), ("grid_width", True)])
def test_bad_grid_settings_are_refused_naming_the_field(field, value):
    from hybridmpm.train.gns.train import TrainConfig

    cfg = TrainConfig(scene="water2d", data="x", out="y", grid=16, grid_levels=3)
    setattr(cfg, field, value)
    with pytest.raises(InvalidInputError) as e:
        cfg.validate()
    assert e.value.field == field


def test_the_shipped_branch_model_steps_an_empty_cloud():
    """water_sand2d ships a GNS with a grid branch; an empty cloud (a session whose
    particles all left, or a fuzzed input) gives empty outputs, not a reshape error."""
    from hybridmpm.models import shipped_model
    from hybridmpm.neural import GnsRuntime

    model = GnsRuntime(shipped_model("water_sand2d"))
    assert model.branch is not None
    hist = np.zeros((model.t_in, 0, model.dim), np.float32)
    acc, nxt, _ = model.predict(hist, np.zeros(0, np.int64))
    assert acc.shape == (0, model.dim) and nxt.shape == (0, model.dim)
