"""The grid model: torch p2g/g2p against the engine's, the run time against torch, physics of the transfers."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from hybridmpm import _core
from hybridmpm.conventions import GNS_KINEMATIC, GNS_SAND, GNS_WATER
from hybridmpm.errors import InvalidInputError
from hybridmpm.mpm import grid_mass
from hybridmpm.neural.base import model_kind, open_model
from hybridmpm.neural.grid import GridRuntime, grid_geometry
from hybridmpm.train.grid import GridConfig, GridModel, export_grid, g2p, p2g, stencil

BOUNDS2 = [[0.015625, 0.984375], [0.015625, 0.984375]]


def _cfg(dim: int = 2, **kw) -> GridConfig:
    bounds = BOUNDS2 if dim == 2 else [[0.03, 0.97]] * 3
    base = dict(dim=dim, bounds=bounds, dt_frame=2.5e-3, gravity=[0.0, -9.8] if dim == 2 else [0.0, -9.8, 0.0], grid=16, width=4, levels=2)
    return GridConfig(**(base | kw))


def _random_model(cfg: GridConfig, seed: int = 0) -> GridModel:
    """A model whose U-Net output is not zero (the trained case), so the test sees its contribution."""
    torch.manual_seed(seed)
    m = GridModel(cfg)
    with torch.no_grad():
        m.net.out.weight.normal_(0.0, 0.05)
        m.net.out.bias.normal_(0.0, 0.05)
        m.flip_logit.fill_(0.3)
        if cfg.pressure:
            m.pressure_logit.fill_(0.5)
    return m.eval()


def test_torch_p2g_is_the_engines_grid_mass() -> None:
    rng = np.random.default_rng(1)
    x = rng.uniform(0.02, 0.95, (700, 2)).astype(np.float32)
    n = 48
    w, node = stencil(torch.from_numpy(x), torch.zeros(2), torch.full((2,), 1.0 / n), n)
    m = p2g(torch.ones(len(x), 1), w, node, n * n).reshape(n, n).numpy()
    np.testing.assert_allclose(m / m.sum(), grid_mass(x, n), atol=1e-7)


@pytest.mark.parametrize("dim", [2, 3])
def test_rust_transfers_equal_torch_and_conserve(dim: int) -> None:
    rng = np.random.default_rng(dim)
    b = np.asarray(BOUNDS2 if dim == 2 else [[0.03, 0.97]] * 3, np.float32)
    g = 12
    origin, spacing = grid_geometry(b, g)
    x = rng.uniform(b[:, 0], b[:, 1], (300, dim)).astype(np.float32)
    v = rng.normal(size=(300, 3)).astype(np.float32)
    ours = _core.grid_p2g(x, v, origin.tolist(), spacing.tolist(), g)
    w, node = stencil(torch.from_numpy(x), torch.from_numpy(origin), torch.from_numpy(spacing), g)
    theirs = p2g(torch.from_numpy(v), w, node, g**dim).numpy()
    np.testing.assert_allclose(ours, theirs, atol=1e-5)
    np.testing.assert_allclose(ours.sum(0), v.sum(0), rtol=1e-4, atol=1e-4)  # p2g conserves each channel's sum
    field = rng.normal(size=(g**dim, 2)).astype(np.float32)
    np.testing.assert_allclose(_core.grid_g2p(field, x, origin.tolist(), spacing.tolist(), g), g2p(torch.from_numpy(field), w, node).numpy(), atol=1e-5)
    # the quadratic B-spline reproduces a linear field exactly
    axes = [origin[k] + spacing[k] * np.arange(g) for k in range(dim)]
    mesh = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, dim)
    lin = (0.5 + mesh @ np.arange(1, dim + 1)).astype(np.float32)[:, None]
    np.testing.assert_allclose(_core.grid_g2p(lin, x, origin.tolist(), spacing.tolist(), g)[:, 0], 0.5 + x @ np.arange(1, dim + 1), atol=1e-5)


@pytest.mark.parametrize("dim,pressure", [(2, False), (2, True), (3, True)])
def test_exported_model_runs_as_torch_does(tmp_path, dim: int, pressure: bool) -> None:
    types = [GNS_WATER, GNS_SAND] if dim == 2 else [GNS_SAND]
    cfg = _cfg(dim, types=types, velocity_scale=0.8, rest_count=2.0, pressure=pressure)
    model = _random_model(cfg)
    path = export_grid(model, tmp_path / "g.onnx", {"scene": "test", "r_p": 0.5, "radius": 0.02})
    assert model_kind(path) == "grid"
    rt = open_model(path)
    assert isinstance(rt, GridRuntime) and rt.r_t == cfg.r_t and rt.t_in == cfg.t_in and rt.r_p == 0.5
    rng = np.random.default_rng(3)
    n = 400
    lo, hi = np.asarray(cfg.bounds, np.float32).T
    x = rng.uniform(lo + 0.1, lo + 0.4, (n, dim)).astype(np.float32)  # packed: the density correction acts
    steps = rng.normal(0, 0.004, (cfg.t_in - 1, n, dim)).astype(np.float32)
    hist = np.concatenate([x[None], x[None] + np.cumsum(steps, 0)]).astype(np.float32)
    pt = rng.choice(types + [GNS_KINEMATIC], n).astype(np.int64)
    ours = rt.frames(hist, pt)
    with torch.no_grad():
        theirs = model.frames(torch.from_numpy(hist), torch.from_numpy(pt)).numpy()
    np.testing.assert_allclose(ours, theirs, atol=2e-6)
    kin = pt == GNS_KINEMATIC
    assert np.array_equal(ours[:, kin], np.broadcast_to(hist[-1, kin], ours[:, kin].shape))  # obstacles stay
    assert ((ours >= lo) & (ours <= hi)).all()


def test_a_zero_network_moves_a_rigid_block_ballistically() -> None:
    """With no correction (the U-Net's last layer starts at zero) a block moving
    rigidly in the air falls under gravity exactly: x(t) = x0 + v t + g t²/2.
    Exactly for particles whose stencils stay on nodes the block covers (more
    than two nodes inside its edge); at the edge a particle's moved stencil
    reaches empty nodes (zero velocity), a PIC effect of a few 1e-5 m."""
    cfg = _cfg(2, grid=32, width=4, levels=2, velocity_scale=1.0, rest_count=4.0)
    model = GridModel(cfg).eval()
    dt_step = cfg.dt_frame * cfg.r_t
    v0 = np.array([0.3, 0.5])
    g = np.array(cfg.gravity)
    block = np.stack(np.meshgrid(np.linspace(0.3, 0.6, 40), np.linspace(0.4, 0.6, 30)), -1).reshape(-1, 2)
    ts = (np.arange(cfg.t_in) - (cfg.t_in - 1)) * dt_step
    hist = np.stack([block + v0 * t + 0.5 * g * t**2 for t in ts]).astype(np.float32)
    pt = np.full(len(block), GNS_WATER)
    with torch.no_grad():
        frames = model.frames(torch.from_numpy(hist), torch.from_numpy(pt)).numpy()
    t = np.arange(1, cfg.r_t + 1)[:, None, None] * cfg.dt_frame
    exact = block + v0 * t + 0.5 * g * t**2
    margin = 2.5 * (cfg.bounds[0][1] - cfg.bounds[0][0]) / (cfg.grid - 3)
    inner = ((block > [0.3 + margin, 0.4 + margin]) & (block < [0.6 - margin, 0.6 - margin])).all(1)
    assert inner.sum() > 50
    np.testing.assert_allclose(frames[:, inner], exact[:, inner], atol=1e-6)
    np.testing.assert_allclose(frames, exact, atol=5e-5)


def test_runtime_refuses_bad_input(tmp_path) -> None:
    model = _random_model(_cfg())
    path = export_grid(model, tmp_path / "g.onnx", {"scene": "test", "r_p": 0.5})
    rt = GridRuntime(path)
    with pytest.raises(InvalidInputError) as e:
        rt.frames(np.zeros((2, 10, 2), np.float32), np.full(10, GNS_WATER))
    assert e.value.field == "history"
    with pytest.raises(InvalidInputError) as e:
        _core.grid_p2g(np.full((3, 2), np.nan, np.float32), np.ones((3, 1), np.float32), [0.0, 0.0], [0.1, 0.1], 12)
    assert e.value.field == "positions"
    with pytest.raises(InvalidInputError) as e:
        _core.grid_p2g(np.zeros((3, 2), np.float32), np.ones((3, 1), np.float32), [0.0, 0.0], [0.1, 0.1], 1 << 20)
    assert e.value.field == "nodes"
    with pytest.raises(InvalidInputError) as e:
        rt.check_fits(2, np.array([GNS_SAND]))
    assert e.value.field == "model"
    with pytest.raises(InvalidInputError) as e:
        GridRuntime(tmp_path / "missing.onnx")
    assert e.value.field == "model"


def test_flip_init_sets_the_starting_beta_and_bad_values_are_refused() -> None:
    """``flip_init`` is the FLIP share β the model starts from: a particle
    whose velocity differs from its grid's by ``d`` keeps ``β·d`` in a
    zero-network call (measured on the frames, not read off the parameter);
    values outside (0, 1) are refused naming the field."""
    block = np.stack(np.meshgrid(np.linspace(0.3, 0.6, 30), np.linspace(0.4, 0.6, 20)), -1).reshape(-1, 2)
    moved = {}
    for beta in (0.5, 0.9):
        cfg = _cfg(2, grid=32, width=4, levels=2, velocity_scale=1.0, rest_count=4.0, flip_init=beta)
        model = GridModel(cfg).eval()
        assert float(torch.sigmoid(model.flip_logit.detach())) == pytest.approx(beta, abs=1e-6)
        dt_step = cfg.dt_frame * cfg.r_t
        kick = np.zeros_like(block)
        kick[len(block) // 2] = [0.2, 0.0]  # one particle moves against the block, which is at rest
        hist = np.stack([block + kick * (k - cfg.t_in + 1) * dt_step for k in range(cfg.t_in)]).astype(np.float32)
        with torch.no_grad():
            out = model.frames(torch.from_numpy(hist), torch.from_numpy(np.full(len(block), GNS_WATER))).numpy()
        moved[beta] = out[-1, len(block) // 2, 0] - hist[-1, len(block) // 2, 0]
    # the kicked particle's own share scales with beta (gravity moves it alike in both)
    assert moved[0.9] > moved[0.5] > 0
    for bad in (0.0, 1.0, -0.1, True):
        with pytest.raises(InvalidInputError) as e:
            _cfg(2, flip_init=bad).validate()
        assert e.value.field == "flip_init"
