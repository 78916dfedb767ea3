"""The GNS split into parts: feature construction (train/gns/features.py), a
reusable encoder–processor–decoder and the composed simulator (train/gns/model.py).

* the pre-split model (frozen below, verbatim from commit 202ef89) and the
  composed one give bit-identical outputs from the same weights, in torch and
  through ONNX, and its state_dicts and optimiser states load;
* the processor against an independent dense, unfactored implementation;
* :class:`EncodeProcessDecode` reused standalone (other sizes, latents
  returned, zero-initialised output);
* the feature module's integration and its errors.

(Needs the 'train' extra: torch, onnx, onnxscript.)
"""

from __future__ import annotations

import io
import logging
import math
from contextlib import contextmanager

import numpy as np
import pytest
import torch
from torch import nn

from hybridmpm import radius_graph
from hybridmpm.conventions import GNS_KINEMATIC
from hybridmpm.errors import InvalidInputError
from hybridmpm.neural.constants import FEATURE_VERSION, NUM_TYPES
from hybridmpm.train.gns.features import GnsFeatures, euler_step
from hybridmpm.train.gns.model import EncodeProcessDecode, GnsConfig, GnsModel, remap_legacy_state_dict

logging.getLogger("torch.onnx").setLevel(logging.ERROR)
R = 0.015


# --- the pre-split model, frozen verbatim (202ef89:python/hybridmpm/train/gns/model.py) -------------------


def _legacy_mlp(inp: int, width: int, out: int, layer_norm: bool = True) -> nn.Sequential:
    mods: list[nn.Module] = [nn.Linear(inp, width), nn.ReLU(), nn.Linear(width, width), nn.ReLU(), nn.Linear(width, out)]
    if layer_norm:
        mods.append(nn.LayerNorm(out))
    return nn.Sequential(*mods)


class _LegacyEdgeBlock(nn.Module):
    def __init__(self, latent: int) -> None:
        super().__init__()
        self.w_e = nn.Linear(latent, latent)
        self.w_r = nn.Linear(latent, latent, bias=False)
        self.w_s = nn.Linear(latent, latent, bias=False)
        self.rest = nn.Sequential(nn.ReLU(), nn.Linear(latent, latent), nn.ReLU(), nn.Linear(latent, latent), nn.LayerNorm(latent))

    def forward(self, e, h, senders, receivers):
        first = self.w_e(e) + self.w_r(h)[receivers] + self.w_s(h)[senders]
        return self.rest(first)


class LegacyGnsModel(nn.Module):
    def __init__(self, config: GnsConfig) -> None:
        super().__init__()
        self.config = config
        d, lat = config.dim, config.latent
        self.register_buffer("vel_mean", torch.tensor(config.vel_mean, dtype=torch.float32))
        self.register_buffer("vel_std", torch.tensor([math.sqrt(s * s + config.noise_std**2) for s in config.vel_std], dtype=torch.float32))
        self.register_buffer("acc_mean", torch.tensor(config.acc_mean, dtype=torch.float32))
        self.register_buffer("acc_std", torch.tensor([math.sqrt(s * s + config.noise_std**2) for s in config.acc_std], dtype=torch.float32))
        b = torch.tensor(config.bounds, dtype=torch.float32)
        self.register_buffer("lower", b[:, 0])
        self.register_buffer("upper", b[:, 1])
        self.inv_radius = 1.0 / config.radius
        self.embed = nn.Embedding(NUM_TYPES, config.embedding)
        node_in = (config.t_in - 1) * d + 2 * d + config.embedding
        self.node_encoder = _legacy_mlp(node_in, lat, lat)
        self.edge_encoder = _legacy_mlp(d + 1, lat, lat)
        self.edge_blocks = nn.ModuleList([_LegacyEdgeBlock(lat) for _ in range(config.layers)])
        self.node_blocks = nn.ModuleList([_legacy_mlp(2 * lat, lat, lat) for _ in range(config.layers)])
        self.decoder = _legacy_mlp(lat, lat, d, layer_norm=False)

    def input_features(self, positions, particle_type, senders, receivers):
        last = positions[-1]
        vel = (positions[1:] - positions[:-1] - self.vel_mean) / self.vel_std  # [T_in-1, N, D]
        n = last.shape[0]
        vel_feat = vel.permute(1, 0, 2).reshape(n, -1)
        walls = torch.cat([(last - self.lower) * self.inv_radius, (self.upper - last) * self.inv_radius], dim=1).clamp(-1.0, 1.0)
        nodes = torch.cat([vel_feat, walls, self.embed(particle_type)], dim=1)
        disp = (last[senders] - last[receivers]) * self.inv_radius
        edges = torch.cat([disp, torch.linalg.vector_norm(disp, dim=1, keepdim=True)], dim=1)
        return nodes, edges

    def normalised_acceleration(self, positions, particle_type, senders, receivers):
        nodes, edges = self.input_features(positions, particle_type, senders, receivers)
        h = self.node_encoder(nodes)
        e = self.edge_encoder(edges)
        for edge_block, node_block in zip(self.edge_blocks, self.node_blocks):
            e = e + edge_block(e, h, senders, receivers)
            agg = torch.zeros_like(h).index_add(0, receivers, e)
            h = h + node_block(torch.cat([h, agg], dim=1))
        return self.decoder(h)

    def forward(self, positions, particle_type, senders, receivers):
        acc = self.normalised_acceleration(positions, particle_type, senders, receivers) * self.acc_std + self.acc_mean
        last = positions[-1]
        nxt = last + (last - positions[-2]) + acc
        kin = (particle_type == GNS_KINEMATIC).unsqueeze(1)
        return acc, torch.where(kin, last, nxt)


# --- helpers ----------------------------------------------------------------------------------------------


def config(dim: int = 2, latent: int = 16, layers: int = 2) -> GnsConfig:
    return GnsConfig(
        dim=dim, radius=R, bounds=[[0.02, 0.98]] * dim, vel_mean=[1e-4] * dim, vel_std=[2e-3] * dim,
        acc_mean=[-1e-5] * dim, acc_std=[2e-4] * dim, latent=latent, layers=layers, noise_std=3e-4,
    )  # fmt: skip


def legacy_model(cfg: GnsConfig, seed: int) -> LegacyGnsModel:
    """A pre-split model with every parameter moved off its default (LayerNorm
    gains and biases included), so that a misplaced weight shows."""
    torch.manual_seed(seed)
    model = LegacyGnsModel(cfg)
    with torch.no_grad():
        for p in model.parameters():
            p.add_(0.1 * torch.randn_like(p))
    return model.eval()


def inputs(n: int, dim: int, seed: int) -> tuple[torch.Tensor, ...]:
    """A dense random state: some particles near the walls, some kinematic."""
    rng = np.random.default_rng(seed)
    x = rng.uniform(0.3, 0.3 + 0.4 * (n / 2000) ** (1 / dim), (n, dim))
    x[: min(n, 4)] = rng.uniform(0.02, 0.03, (min(n, 4), dim))
    hist = np.concatenate([x[None], x[None] + np.cumsum(rng.normal(0, 2e-3, (5, n, dim)), axis=0)]).astype(np.float32)
    ptype = rng.choice([GNS_KINEMATIC, 5, 6], n).astype(np.int64)
    s, r, _, _ = radius_graph(hist[-1], R)
    return torch.from_numpy(hist), torch.from_numpy(ptype), torch.from_numpy(s), torch.from_numpy(r)


@contextmanager
def one_thread():
    """Parallel CPU reductions (backward of gathers, ORT's scatter) are not
    bitwise reproducible run to run; one thread is."""
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        yield
    finally:
        torch.set_num_threads(before)


# --- old vs new -----------------------------------------------------------------------------------------


@pytest.mark.parametrize(("dim", "latent", "layers"), [(2, 16, 2), (3, 8, 3)])
def test_legacy_state_dict_loads_and_gives_identical_outputs(dim, latent, layers):
    cfg = config(dim, latent, layers)
    old = legacy_model(cfg, seed=dim)
    new = GnsModel(cfg).eval()
    legacy_state = old.state_dict()
    assert "embed.weight" in legacy_state and "node_encoder.0.weight" in legacy_state  # really the old layout
    new.load_state_dict(legacy_state)  # strict: every key placed, none left over
    # the remapping is exactly the new layout, and parameter order (what optimiser states index) is unchanged
    assert list(remap_legacy_state_dict(legacy_state)) == list(new.state_dict())
    assert [p.shape for p in old.parameters()] == [p.shape for p in new.parameters()]
    assert all(torch.equal(a, b) for a, b in zip(old.parameters(), new.parameters()))
    for n, seed in [(1, 0), (40, 1), (900, 2)]:
        args = inputs(n, dim, seed)
        with torch.no_grad():
            acc_o, nxt_o = old(*args)
            acc_n, nxt_n = new(*args)
            nodes_o, edges_o = old.input_features(*args)
            nodes_n, edges_n = new.input_features(*args)
        assert torch.equal(acc_n, acc_o) and torch.equal(nxt_n, nxt_o)
        assert torch.equal(nodes_n, nodes_o) and torch.equal(edges_n, edges_o)
        assert acc_n.abs().max() > 0
    # the new layout round-trips too
    again = GnsModel(cfg)
    again.load_state_dict(new.state_dict())
    assert all(torch.equal(a, b) for a, b in zip(again.state_dict().values(), new.state_dict().values()))


def test_legacy_optimiser_state_resumes_identically():
    """An Adam state saved with the pre-split model (indexed by parameter
    position) continues the same optimisation in the new model."""
    cfg = config(2, 8, 2)
    args = inputs(200, 2, seed=5)
    target = torch.randn(200, 2, generator=torch.Generator().manual_seed(0))
    with one_thread():
        old = legacy_model(cfg, seed=0).train()
        opt_old = torch.optim.Adam(old.parameters(), lr=1e-3)

        def step(model: LegacyGnsModel | GnsModel, opt: torch.optim.Optimizer) -> None:
            opt.zero_grad()
            ((model.normalised_acceleration(*args) - target) ** 2).mean().backward()
            opt.step()

        step(old, opt_old)
        saved = io.BytesIO()  # the checkpoint after one step, as train.py writes it
        torch.save({"model": old.state_dict(), "optimizer": opt_old.state_dict()}, saved)
        saved.seek(0)
        state = torch.load(saved, weights_only=True)
        new = GnsModel(cfg).train()
        new.load_state_dict(state["model"])
        opt_new = torch.optim.Adam(new.parameters(), lr=1e-3)
        opt_new.load_state_dict(state["optimizer"])
        for _ in range(3):
            step(old, opt_old)
            step(new, opt_new)
        assert all(torch.equal(a, b) for a, b in zip(old.parameters(), new.parameters()))


def test_legacy_loads_inside_a_larger_module():
    """The remapping respects the prefix of a GnsModel nested in another module."""
    cfg = config(2, 8, 1)
    old = legacy_model(cfg, seed=3)
    outer = nn.Module()
    outer.sim = GnsModel(cfg)
    outer.load_state_dict({f"sim.{k}": v for k, v in old.state_dict().items()})
    args = inputs(50, 2, seed=1)
    with torch.no_grad():
        assert torch.equal(outer.sim(*args)[0], old(*args)[0])


def test_onnx_export_of_legacy_and_new_models_agree(tmp_path):
    import onnxruntime as ort

    from hybridmpm.neural.constants import CONTEXT_INPUT
    from hybridmpm.neural.runtime import aggregation_inputs
    from hybridmpm.train.gns.export import INPUT_NAMES, OUTPUT_NAMES, export_onnx

    cfg = config(2, 16, 2)
    old = legacy_model(cfg, seed=11)
    new = GnsModel(cfg).eval()
    new.load_state_dict(old.state_dict())
    meta = {"scene": "water2d", "r_p": 1.0, "r_t": 2, "particle_types": [5, 6]}
    export_onnx(old, tmp_path / "old.onnx", meta)  # type: ignore[arg-type]  # the exporter only reads .config and runs forward
    export_onnx(new, tmp_path / "new.onnx", meta)
    so = ort.SessionOptions()
    so.intra_op_num_threads = 1
    s_old, s_new = (ort.InferenceSession(str(tmp_path / f), so) for f in ("old.onnx", "new.onnx"))
    plain_inputs = [n for n in INPUT_NAMES if n != CONTEXT_INPUT]  # grid_context: only a GNS with a grid branch takes it
    for s in (s_old, s_new):
        assert [i.name for i in s.get_inputs()] == plain_inputs and [o.name for o in s.get_outputs()] == list(OUTPUT_NAMES)
    assert [(i.shape, i.type) for i in s_new.get_inputs()] == [(i.shape, i.type) for i in s_old.get_inputs()]
    assert [(o.shape, o.type) for o in s_new.get_outputs()] == [(o.shape, o.type) for o in s_old.get_outputs()]
    assert s_new.get_modelmeta().custom_metadata_map == s_old.get_modelmeta().custom_metadata_map
    for n, seed in [(1, 0), (700, 1)]:
        hist, ptype, _, _ = (a.numpy() for a in inputs(n, 2, seed))
        s, r, disp, dist = radius_graph(hist[-1], R)
        feeds = {"positions": hist, "particle_type": ptype, "senders": s, "receivers": r, "displacement": disp, "distance": dist}
        for gather in (False, True):
            edges, degree = aggregation_inputs(r, len(ptype), gather)
            both = {**feeds, "in_edges": edges, "in_degree": degree}
            for a, b in zip(s_old.run(None, both), s_new.run(None, both)):
                assert np.array_equal(a, b)


# --- the encoder–processor–decoder on its own -----------------------------------------------------------


def random_graph(n: int, e: int, seed: int) -> tuple[torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    return torch.randint(0, n, (e,), generator=g), torch.randint(0, n, (e,), generator=g)


def test_processor_matches_a_dense_unfactored_reference():
    """Independent reference in float64: the edge MLP applied to the
    concatenation ``[e; h_r; h_s]`` (one weight matrix, not the factored
    per-node projections) and the sum over receivers as a dense incidence
    product, on a graph with repeated receivers and an isolated node."""
    torch.manual_seed(0)
    net = EncodeProcessDecode(node_in=5, edge_in=2, node_out=3, latent=6, layers=3).double()
    with torch.no_grad():
        for p in net.parameters():
            p.add_(0.1 * torch.randn_like(p))
    n, ne = 9, 40
    senders, receivers = random_graph(n - 1, ne, seed=1)  # node n-1 receives nothing
    assert torch.bincount(receivers).max() > 3
    h = torch.randn(n, 6, dtype=torch.float64)
    e = torch.randn(ne, 6, dtype=torch.float64)
    incidence = torch.zeros(n, ne, dtype=torch.float64)
    incidence[receivers, torch.arange(ne)] = 1.0
    hr, er = h, e
    for eb, nb in zip(net.edge_blocks, net.node_blocks):
        w = torch.cat([eb.w_e.weight, eb.w_r.weight, eb.w_s.weight], dim=1)
        er = er + eb.rest(torch.cat([er, hr[receivers], hr[senders]], dim=1) @ w.T + eb.w_e.bias)
        hr = hr + nb(torch.cat([hr, incidence @ er], dim=1))
    with torch.no_grad():
        hp, ep = net.process(h, e, senders, receivers)
    assert torch.allclose(hp, hr, rtol=1e-12, atol=1e-12) and torch.allclose(ep, er, rtol=1e-12, atol=1e-12)
    # the isolated node was updated by its node MLP alone (aggregate 0)
    assert not torch.equal(hp[-1], h[-1])


def test_encode_process_decode_reused_standalone():
    """Other input and output sizes (a per-particle field in, a field out),
    latents returned, the processor run on latents from elsewhere."""
    torch.manual_seed(1)
    net = EncodeProcessDecode(node_in=11, edge_in=4, node_out=5, latent=12, layers=2)
    n, ne = 30, 120
    s, r = random_graph(n, ne, seed=2)
    nodes, edges = torch.randn(n, 11), torch.randn(ne, 4)
    out = net(nodes, edges, s, r)
    assert out.shape == (n, 5) and out.dtype == torch.float32
    out2, h, e = net(nodes, edges, s, r, return_latents=True)
    assert torch.equal(out2, out) and h.shape == (n, 12) and e.shape == (ne, 12)
    # the stages compose to forward
    h0, e0 = net.encode(nodes, edges)
    assert torch.equal(net.decode(net.process(h0, e0, s, r)[0]), out)
    # the processor on arbitrary latents (e.g. a denoiser's) and on a graph with no edges
    h1, e1 = net.process(torch.randn(n, 12), torch.randn(ne, 12), s, r)
    assert h1.shape == (n, 12) and e1.shape == (ne, 12)
    empty = torch.zeros(0, dtype=torch.int64)
    assert net(nodes, torch.zeros(0, 4), empty, empty).shape == (n, 5)
    # every parameter learns
    out.pow(2).sum().backward()
    assert all(p.grad is not None and p.grad.abs().sum() > 0 for p in net.parameters())
    # wrong input width: torch's error, not a silent broadcast
    with pytest.raises(RuntimeError):
        net(torch.randn(n, 10), edges, s, r)


def test_zero_initialised_output_is_exactly_zero_and_then_learns():
    torch.manual_seed(2)
    net = EncodeProcessDecode(node_in=7, edge_in=3, node_out=2, latent=8, layers=2, zero_init_output=True)
    n, ne = 25, 90
    s, r = random_graph(n, ne, seed=3)
    nodes, edges = 10 * torch.randn(n, 7), torch.randn(ne, 3)
    out, h, _ = net(nodes, edges, s, r, return_latents=True)
    assert out.shape == (n, 2) and torch.count_nonzero(out) == 0
    assert torch.count_nonzero(h) > 0  # only the head is zero: the latents carry information
    default = EncodeProcessDecode(node_in=7, edge_in=3, node_out=2, latent=8, layers=2)
    assert torch.count_nonzero(default(nodes, edges, s, r)) > 0
    opt = torch.optim.SGD(net.parameters(), lr=0.1)
    (net(nodes, edges, s, r) - 1.0).pow(2).sum().backward()
    opt.step()
    assert torch.count_nonzero(net(nodes, edges, s, r)) > 0


@pytest.mark.parametrize(
    ("kwargs", "field"),
    [({"node_in": 0}, "node_in"), ({"edge_in": -1}, "edge_in"), ({"node_out": 0}, "node_out"), ({"latent": 0}, "latent"), ({"layers": -1}, "layers")],
)
def test_encode_process_decode_rejects_bad_sizes(kwargs, field):
    args = {"node_in": 4, "edge_in": 3, "node_out": 2, "latent": 8, "layers": 1, **kwargs}
    with pytest.raises(InvalidInputError) as e:
        EncodeProcessDecode(**args)
    assert e.value.field == field


# --- features and integration ---------------------------------------------------------------------------


def test_gns_model_is_features_then_network_then_integration():
    torch.manual_seed(4)
    model = GnsModel(config(3, 8, 2)).eval()
    assert model.features.node_size == 5 * 3 + 2 * 3 + 16 == 37 and model.features.edge_size == 4  # paper App. A: D = 37 in 3D
    assert model.gnn.node_in == 37 and model.gnn.edge_in == 4 and model.gnn.node_out == 3
    args = inputs(300, 3, seed=2)
    with torch.no_grad():
        acc, nxt = model(*args)
        nodes, edges = model.features(*args)
        acc2, nxt2 = model.features.integrate(args[0], args[1], model.gnn(nodes, edges, args[2], args[3]))
    assert torch.equal(acc, acc2) and torch.equal(nxt, nxt2)


def test_euler_step_and_normalisation_by_hand():
    hist = torch.tensor(np.random.default_rng(0).uniform(0.2, 0.8, (6, 4, 2)), dtype=torch.float32)
    acc = torch.tensor([[1e-3, -2e-3]] * 4)
    ptype = torch.tensor([5, GNS_KINEMATIC, 6, 5])
    nxt = euler_step(hist, acc, ptype).numpy().astype(np.float64)
    h = hist.numpy().astype(np.float64)
    want = 2 * h[-1] - h[-2] + acc.numpy()  # v' = v + a, p' = p + v' with dt = 1 step
    want[1] = h[-1, 1]  # kinematic particles stay
    assert np.allclose(nxt, want, rtol=0, atol=1e-6) and np.array_equal(nxt[1], h[-1, 1])
    f = GnsFeatures(
        dim=2, radius=R, bounds=[[0, 1]] * 2, vel_mean=[0, 0], vel_std=[1e-3, 2e-3], acc_mean=[1e-5, -3e-5], acc_std=[4e-4, 1e-4],
        noise_std=3e-4,
    )  # fmt: skip
    std = np.sqrt(np.array([4e-4, 1e-4]) ** 2 + 3e-4**2)  # noise variance folded in (GNS)
    norm = f.normalise_acceleration(acc).numpy()
    assert np.allclose(norm, (acc.numpy() - [1e-5, -3e-5]) / std, rtol=1e-6)
    assert torch.allclose(f.denormalise_acceleration(f.normalise_acceleration(acc)), acc, rtol=1e-6, atol=0)
    assert FEATURE_VERSION == 1  # the numbers did not change with the split (see the legacy tests above)


@pytest.mark.parametrize(
    ("kwargs", "field"),
    [
        ({"dim": 4}, "dim"),
        ({"radius": 0.0}, "radius"),
        ({"bounds": [[0, 1]]}, "bounds"),
        ({"bounds": [[0, 1], [1, 0]]}, "bounds"),
        ({"vel_mean": [0.0]}, "vel_mean"),
        ({"acc_std": [1e-3, math.nan]}, "acc_std"),
        ({"noise_std": -1.0}, "noise_std"),
        ({"t_in": 1}, "t_in"),
    ],
)
def test_features_reject_bad_settings(kwargs, field):
    args = {
        "dim": 2, "radius": R, "bounds": [[0, 1]] * 2, "vel_mean": [0, 0], "vel_std": [1e-3] * 2, "acc_mean": [0, 0],
        "acc_std": [1e-3] * 2, **kwargs,
    }  # fmt: skip
    with pytest.raises(InvalidInputError) as e:
        GnsFeatures(**args)
    assert e.value.field == field


def test_features_reject_a_history_of_the_wrong_shape():
    model = GnsModel(config(2, 8, 1))
    hist, ptype, s, r = inputs(20, 2, seed=0)
    for bad in (hist[1:], hist[..., :1], hist[-1]):
        with pytest.raises(InvalidInputError) as e:
            model(bad, ptype, s, r)
        assert e.value.field == "positions"


def test_a_legacy_training_checkpoint_resumes(tmp_path):
    """``hybridmpm train`` rerun on an out directory holding a pre-split
    ``checkpoint.pt`` and ``best.pt`` resumes (model, Adam state, step) and
    exports the legacy best weights unchanged."""
    import csv
    import json
    from dataclasses import asdict

    from _datasets import drag_dataset

    from hybridmpm.neural import GnsRuntime
    from hybridmpm.train.gns.train import TrainConfig, train

    data, out = tmp_path / "drag", tmp_path / "model"
    data.mkdir()
    out.mkdir()
    drag_dataset(data, n_traj=4, frames=16, n=30)
    cfg = TrainConfig(
        scene="drag", data=str(data), out=str(out), latent=8, layers=1, r_t=1, steps=4, batch=1, lr=1e-3, lr_final=1e-4,
        noise_std=1e-5, val_every=2, val_windows=2, rollout_steps=3, threads=1,
    )  # fmt: skip
    gcfg = GnsConfig(
        dim=2, radius=0.02, bounds=[[0.02, 0.98]] * 2, vel_mean=[0.0, -1e-4], vel_std=[3e-3] * 2, acc_mean=[0.0, -2e-5],
        acc_std=[5e-4] * 2, latent=8, layers=1, noise_std=1e-5,
    )  # fmt: skip
    old = legacy_model(gcfg, seed=7).train()
    opt = torch.optim.Adam(old.parameters(), lr=1e-3)
    args = inputs(30, 2, seed=3)
    opt.zero_grad()
    old.normalised_acceleration(*args).pow(2).mean().backward()
    opt.step()
    old.eval()
    (out / "train_config.json").write_text(json.dumps(asdict(cfg)))
    torch.save(old.state_dict(), out / "best.pt")
    state = {
        "model": old.state_dict(), "optimizer": opt.state_dict(), "step": 2, "best": 0.0, "elapsed": 1.0,
        "rng": np.random.default_rng(0).bit_generator.state, "torch_rng": torch.get_rng_state(), "gns_config": gcfg.to_dict(),
    }  # fmt: skip
    torch.save(state, out / "checkpoint.pt")
    summary = train(cfg, progress=False)
    assert summary["steps"] == 4
    with open(out / "log.csv", newline="") as f:
        assert [row["step"] for row in csv.DictReader(f)] == ["4"]  # resumed: no step-0 baseline
    resumed = torch.load(out / "checkpoint.pt", weights_only=False)
    assert resumed["step"] == 4 and next(iter(resumed["model"])).startswith("features.")
    assert all(v["step"] == 3 for v in resumed["optimizer"]["state"].values())  # 1 saved Adam step + 2 resumed
    # best.pt was never beaten (best = 0): the export holds the legacy weights
    nm = GnsRuntime(out / "model.onnx")
    hist, ptype, _, _ = inputs(200, 2, seed=4)
    acc_o, nxt_o, _ = nm.predict(hist.numpy(), ptype.numpy())
    ss, rr, _, _ = radius_graph(hist[-1].numpy(), 0.02)
    with torch.no_grad():
        acc_t, nxt_t = old(hist, ptype, torch.from_numpy(ss), torch.from_numpy(rr))
    assert np.allclose(acc_o, acc_t.numpy(), rtol=1e-4, atol=1e-9) and np.allclose(nxt_o, nxt_t.numpy(), rtol=0, atol=1e-6)
