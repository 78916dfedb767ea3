"""The GNS: features against hand computation, symmetries, ONNX-vs-torch parity
(the compiled inference graph, and graphs of torch's exporter), the runtime's
sums, threads and errors. (Needs the 'train' extra: torch, onnx, onnxscript; it
is part of the 'test' extra.) Its training: tests/test_neural_training.py."""

from __future__ import annotations

import json
import logging
import math

import numpy as np
import pytest
import torch

from hybridmpm import radius_graph
from hybridmpm.errors import InvalidInputError
from hybridmpm.neural import GnsRuntime
from hybridmpm.neural.runtime import MAX_PADDING, SMALL_TABLE, aggregation_inputs
from hybridmpm.train.gns.export import export_onnx
from hybridmpm.train.gns.model import GnsConfig, GnsModel

logging.getLogger("torch.onnx").setLevel(logging.ERROR)
R = 0.015
BOUNDS = [[0.02, 0.98], [0.02, 0.98]]


def config(dim: int = 2, latent: int = 16, layers: int = 2) -> GnsConfig:
    return GnsConfig(
        dim=dim, radius=R, bounds=[[0.02, 0.98]] * dim, vel_mean=[1e-4] * dim, vel_std=[2e-3] * dim,
        acc_mean=[-1e-5] * dim, acc_std=[2e-4] * dim, latent=latent, layers=layers, noise_std=3e-4,
    )  # fmt: skip


def random_state(n: int, dim: int = 2, seed: int = 0, lo: float = 0.3, hi: float = 0.5):
    rng = np.random.default_rng(seed)
    x = rng.uniform(lo, hi, (n, dim))
    v = rng.normal(0, 2e-3, (5, n, dim))
    hist = np.concatenate([x[None], x[None] + np.cumsum(v, axis=0)]).astype(np.float32)
    ptype = rng.choice([5, 6], n).astype(np.int64)
    return hist, ptype


def onnx_feeds(hist, ptype, graph, gather: bool) -> dict:
    """The compiled graph's inputs for a radius graph, the sum over receivers
    the ScatterND way (``gather`` false) or the gather way."""
    s, r, disp, dist = graph
    edges, degree = aggregation_inputs(r, hist.shape[1], gather)
    assert edges.shape[1] == (0 if not gather or not len(r) else np.bincount(r).max())
    return {
        "positions": hist,
        "particle_type": ptype,
        "senders": s,
        "receivers": r,
        "displacement": disp,
        "distance": dist,
        "in_edges": edges,
        "in_degree": degree,
    }


def run_torch(model, hist, ptype):
    s, r, _, _ = radius_graph(hist[-1], R)
    with torch.no_grad():
        acc, nxt = model(torch.from_numpy(hist), torch.from_numpy(ptype), torch.from_numpy(s), torch.from_numpy(r))
    return acc.numpy(), nxt.numpy()


def perturbed(model: GnsModel, seed: int = 0) -> GnsModel:
    """Every parameter and statistic moved off its default (LayerNorm gains and
    biases, the embedding, the normalisation stats), so that a weight folded
    into the wrong place in the compiled graph shows."""
    g = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for p in model.parameters():
            p.add_(0.2 * torch.randn(p.shape, generator=g))
        f = model.features
        f.vel_mean.add_(1e-4 * torch.randn(f.vel_mean.shape, generator=g))
        f.acc_mean.add_(1e-5 * torch.randn(f.acc_mean.shape, generator=g))
        f.vel_std.mul_(1 + 0.3 * torch.rand(f.vel_std.shape, generator=g))
        f.acc_std.mul_(1 + 0.3 * torch.rand(f.acc_std.shape, generator=g))
    return model.eval()


@pytest.fixture(scope="module")
def exported(tmp_path_factory):
    torch.manual_seed(0)
    model = perturbed(GnsModel(config(latent=16, layers=2)).eval())
    path = tmp_path_factory.mktemp("onnx") / "m.onnx"
    export_onnx(model, path, {"scene": "water2d", "r_p": 0.5, "r_t": 2, "particle_types": [5, 6]})
    return model, path


def test_input_features_match_a_hand_computation():
    torch.manual_seed(1)
    model = GnsModel(config())
    hist = np.zeros((6, 2, 2), np.float32)
    hist[:, 0] = [[0.5 + 0.001 * k, 0.5 - 0.002 * k * k * 1e-1] for k in range(6)]
    hist[:, 1] = [[0.025, 0.97] for _ in range(6)]  # near the lower x wall and the upper y wall
    ptype = np.array([5, 3])
    s, r = np.array([0, 1, 0, 1]), np.array([0, 0, 1, 1])
    nodes, edges = model.input_features(torch.from_numpy(hist), torch.from_numpy(ptype), torch.from_numpy(s), torch.from_numpy(r))
    nodes, edges = nodes.detach().numpy(), edges.detach().numpy()
    std_eff = math.sqrt(2e-3**2 + 3e-4**2)
    v = np.diff(hist.astype(np.float64), axis=0)  # [5, N, 2]
    want_vel = ((v - 1e-4) / std_eff).transpose(1, 0, 2).reshape(2, -1)
    assert np.allclose(nodes[:, :10], want_vel, atol=1e-4)
    # walls: (x - lo)/R, (hi - x)/R clipped to [-1, 1]
    assert np.allclose(nodes[1, 10:14], [(0.025 - 0.02) / R, 1.0, 1.0, (0.98 - 0.97) / R], atol=1e-5)
    assert np.allclose(nodes[0, 10:14], 1.0)
    emb = model.features.embed.weight.detach().numpy()
    assert np.allclose(nodes[0, 14:], emb[5]) and np.allclose(nodes[1, 14:], emb[3])
    d = (hist[-1, 1] - hist[-1, 0]) / R  # edge 0 -> 1 is (senders 0, receivers 1): p_s - p_r
    assert np.allclose(edges[2, :2], -d, atol=1e-5) and np.isclose(edges[2, 2], np.linalg.norm(d), atol=1e-5)
    assert np.allclose(edges[0], 0.0)  # self-edge


def test_wall_reach_scales_the_wall_features_and_is_recorded():
    """With ``wall_reach`` k the wall features are the distances divided by
    k·R, clipped to [−1, 1] (by hand: a particle 2.5 R above the floor sees
    1 with GNS's clip and 2.5/k with k = 4); the exported model records k,
    its graph computes the same features (a model whose node encoder reads
    only the floor feature), and out-of-range reaches are refused naming
    the field."""
    from dataclasses import replace

    from hybridmpm.train.gns.onnx_graph import inference_graph

    hist = np.zeros((6, 3, 2), np.float32)
    hist[:] = [[0.5, 0.02 + 2.5 * R], [0.5, 0.02 + 0.5 * R], [0.5, 0.5]]
    ptype = np.array([5, 5, 5])
    s = r = np.arange(3)
    feats = {}
    for reach in (1.0, 4.0):
        model = GnsModel(replace(config(), wall_reach=reach))
        nodes = model.input_features(torch.from_numpy(hist), torch.from_numpy(ptype), torch.from_numpy(s), torch.from_numpy(r))[0].detach().numpy()
        feats[reach] = nodes[:, 11]  # lower y wall: after 5 velocities × 2 and the lower x wall
    assert np.allclose(feats[1.0], [1.0, 0.5, 1.0], atol=1e-5)
    assert np.allclose(feats[4.0], [2.5 / 4, 0.5 / 4, 1.0], atol=1e-5)
    # the compiled graph: zero every encoder input row but the lower-y wall's, so the output is a function of that feature only
    model = perturbed(GnsModel(replace(config(), wall_reach=4.0)))
    with torch.no_grad():
        w = model.gnn.node_encoder[0].weight
        keep = w[:, 11].clone()
        w.zero_()
        w[:, 11] = keep
    import onnxruntime as ort

    sess = ort.InferenceSession(inference_graph(model).SerializeToString(), providers=["CPUExecutionProvider"])
    graph = radius_graph(hist[-1], R)
    acc, _ = sess.run(None, onnx_feeds(hist, ptype, graph, False))
    acc_t, _ = run_torch(model, hist, ptype)
    assert np.abs(acc - acc_t).max() <= 1e-4 * np.abs(acc_t).max()
    assert np.abs(acc[0] - acc[2]).max() > 1e-3 * np.abs(acc_t).max()  # 2.5 R from the floor differs from far away
    for bad in (0.5, float("nan"), 100.0):
        with pytest.raises(InvalidInputError) as e:
            GnsModel(replace(config(), wall_reach=bad))
        assert e.value.field == "wall_reach"


def test_prediction_is_translation_invariant_and_order_equivariant():
    torch.manual_seed(2)
    model = GnsModel(config(latent=16, layers=2)).eval()
    hist, ptype = random_state(300, seed=3)
    acc, nxt = run_torch(model, hist, ptype)
    shift = np.array([0.17, -0.11], np.float32)  # stays > R away from the walls
    acc2, nxt2 = run_torch(model, hist + shift, ptype)
    assert np.allclose(acc2, acc, atol=1e-7, rtol=1e-3)
    assert np.allclose(nxt2 - shift, nxt, atol=2e-6)
    perm = np.random.default_rng(4).permutation(300)
    acc3, _ = run_torch(model, hist[:, perm], ptype[perm])
    assert np.allclose(acc3, acc[perm], atol=1e-7, rtol=1e-4)
    # a particle near a wall sees it: the prediction changes when the walls move
    wall = hist - hist[-1].min(0) + 0.021
    assert not np.allclose(run_torch(model, wall, ptype)[0], acc, atol=1e-7, rtol=1e-3)


def test_every_block_updates_node_and_edge_latents():
    """Guards against an edge update that leaves edge latents unchanged (a known
    GNS bug): every block's edge and node MLP gets a gradient."""
    torch.manual_seed(3)
    model = GnsModel(config(latent=8, layers=3))
    hist, ptype = random_state(80, seed=5)
    s, r, _, _ = radius_graph(hist[-1], R)
    out = model.normalised_acceleration(torch.from_numpy(hist), torch.from_numpy(ptype), torch.from_numpy(s), torch.from_numpy(r))
    out.pow(2).sum().backward()
    for k in range(3):
        for block in (model.gnn.edge_blocks[k], model.gnn.node_blocks[k]):
            assert all(p.grad is not None and p.grad.abs().sum() > 0 for p in block.parameters())


@pytest.mark.parametrize(("n", "seed"), [(1, 0), (37, 1), (600, 2), (2300, 3)])
def test_onnx_matches_torch(exported, n, seed):
    model, path = exported
    nm = GnsRuntime(path)
    hist, ptype = random_state(n, seed=seed, lo=0.3, hi=0.3 + 0.4 * math.sqrt(n / 2300))
    acc_t, nxt_t = run_torch(model, hist, ptype)
    acc_o, nxt_o, (s, r, _, _) = nm.predict(hist, ptype)
    if n > 1:  # many receivers appear many times: the scatter must add, not overwrite
        assert np.bincount(r).max() > 5
    assert np.allclose(acc_o, acc_t, rtol=1e-4, atol=1e-9)
    assert np.allclose(nxt_o, nxt_t, rtol=0, atol=1e-6)


def test_onnx_interface_is_what_the_runtime_feeds(exported):
    """Names, dtypes and shapes of the graph's inputs and outputs and its
    metadata: what neural/runtime.py feeds and reads (and what the shipped
    models have)."""
    from hybridmpm.neural.constants import FEATURE_VERSION
    from hybridmpm.train.gns.onnx_graph import GRAPH_LAYOUT

    model, path = exported
    nm = GnsRuntime(path)
    ins = [(i.name, i.shape, i.type) for i in nm.session.get_inputs()]
    outs = [(o.name, o.shape, o.type) for o in nm.session.get_outputs()]
    assert ins == [
        ("positions", [6, "N", 2], "tensor(float)"), ("particle_type", ["N"], "tensor(int64)"),
        ("senders", ["E"], "tensor(int64)"), ("receivers", ["E"], "tensor(int64)"),
        ("displacement", ["E", 2], "tensor(float)"), ("distance", ["E"], "tensor(float)"),
        ("in_edges", ["N", "K"], "tensor(int64)"), ("in_degree", ["N", 1], "tensor(float)"),
    ]  # fmt: skip
    assert nm.meta["graph"] == GRAPH_LAYOUT
    assert outs == [("acceleration", ["N", 2], "tensor(float)"), ("next_position", ["N", 2], "tensor(float)")]
    assert nm.meta["feature_version"] == FEATURE_VERSION == 1
    assert nm.meta["parameters"] == sum(p.numel() for p in model.parameters())
    assert (nm.meta["dim"], nm.meta["t_in"], nm.meta["latent"], nm.meta["layers"], nm.meta["radius"]) == (2, 6, 16, 2, R)


def test_onnx_handles_no_edges(exported):
    model, path = exported
    hist, ptype = random_state(3, seed=9)
    empty = np.zeros(0, np.int64)
    graph = (empty, empty, np.zeros((0, 2), np.float32), np.zeros(0, np.float32))
    with torch.no_grad():
        acc_t, _ = model(torch.from_numpy(hist), torch.from_numpy(ptype), torch.from_numpy(empty), torch.from_numpy(empty))
    for threads in (1, 2):
        acc, nxt, _ = GnsRuntime(path, threads=threads).predict(hist, ptype, graph=graph)
        assert acc.shape == (3, 2) and np.allclose(acc, acc_t.numpy(), rtol=1e-4, atol=1e-9)


@pytest.mark.parametrize(
    ("dim", "latent", "layers", "t_in", "embedding", "seed", "reach"),
    [
        (2, 16, 0, 6, 16, 0, 1.0),
        (2, 8, 1, 6, 16, 1, 1.0),
        (3, 16, 2, 6, 16, 2, 1.0),
        (2, 12, 3, 4, 8, 3, 1.0),
        (2, 16, 2, 6, 16, 4, 4.5),
        (3, 8, 1, 6, 16, 5, 3.0),
    ],
)
def test_compiled_graph_matches_torch(tmp_path, dim, latent, layers, t_in, embedding, seed, reach):
    """The compiled inference graph (folded normalisations and LayerNorms,
    carried biases, edge geometry as inputs) computes GnsModel.forward, on a
    perturbed model with every particle type, particles within the wall reach
    of both walls (unclipped wall features) and kinematic ones, across dims,
    depths, history lengths, embedding widths and wall reaches."""
    from dataclasses import replace

    from hybridmpm.train.gns.onnx_graph import inference_graph

    model = perturbed(GnsModel(replace(config(dim, latent, layers), t_in=t_in, embedding=embedding, wall_reach=reach)), seed)
    hist, _ = random_state(900, dim=dim, seed=seed, lo=0.3, hi=0.3 + 0.4 * math.sqrt(900 / 2300) ** (2 / dim))
    hist = np.ascontiguousarray(hist[-t_in:])
    rng = np.random.default_rng(seed)
    ptype = rng.integers(0, 9, len(hist[0])).astype(np.int64)
    ptype[::7] = 3
    near = rng.uniform(0.1 * reach * R, 0.9 * reach * R, (20, dim)).astype(np.float32)  # within the reach of a wall: features in (0, 1)
    hist[:, :10] = 0.02 + near[:10]
    hist[:, 10:20] = 0.98 - near[10:]
    acc_t, nxt_t = run_torch(model, hist, ptype)
    import onnxruntime as ort

    sess = ort.InferenceSession(inference_graph(model).SerializeToString(), providers=["CPUExecutionProvider"])
    graph = radius_graph(hist[-1], R)
    s, r = graph[:2]
    walls = model.features(*(torch.from_numpy(a) for a in (hist, ptype, s, r)))[0][:, (t_in - 1) * dim : (t_in + 1) * dim]
    assert 0.05 < float(walls[:20].abs().min()) and float(walls[:20].min()) < 0.95  # the unclipped range is exercised
    scale = np.abs(acc_t).max()
    for gather in (False, True):  # both sums over receivers
        acc, nxt = sess.run(None, onnx_feeds(hist, ptype, graph, gather))
        assert scale > 1e-5 and np.abs(acc - acc_t).max() <= 1e-4 * scale
        assert np.abs(nxt - nxt_t).max() <= 1e-6
        assert np.array_equal(nxt[ptype == 3], hist[-1, ptype == 3])


def test_compiled_graph_applies_a_vanishing_layer_norm_gain(tmp_path):
    """A LayerNorm gain with an entry below MIN_GAIN (here exactly 0) cannot be
    folded through 1/g²: the graph applies it after the division, same function."""
    from hybridmpm.train.gns.onnx_graph import MIN_GAIN, inference_graph

    model = perturbed(GnsModel(config(2, 8, 1)), 5)
    with torch.no_grad():
        model.gnn.edge_blocks[0].rest[4].weight[3] = 0.0
        model.gnn.node_encoder[5].weight[0] = MIN_GAIN / 10
    hist, ptype = random_state(300, seed=5)
    acc_t, _ = run_torch(model, hist, ptype)
    import onnxruntime as ort

    sess = ort.InferenceSession(inference_graph(model).SerializeToString(), providers=["CPUExecutionProvider"])
    acc, _ = sess.run(None, onnx_feeds(hist, ptype, radius_graph(hist[-1], R), gather=False))
    assert np.abs(acc - acc_t).max() <= 1e-4 * np.abs(acc_t).max()


def test_graphs_of_torchs_exporter_still_run_and_upgrade(tmp_path):
    """A model exported by torch's ONNX exporter before the compiled layout (four
    inputs): the runtime feeds it what it asks for, on one thread whatever
    ``threads`` asks (its ScatterND sum loses updates on more: a warning says
    so), and upgrade_onnx rewrites it as the compiled graph of the same weights
    (same outputs, metadata kept)."""
    import json

    from hybridmpm.neural.constants import FEATURE_VERSION, METADATA_KEY
    from hybridmpm.train.gns.export import upgrade_onnx

    model = perturbed(GnsModel(config(2, 8, 2)), 7)
    hist, ptype = random_state(400, seed=7)
    s, r, _, _ = radius_graph(hist[-1], R)
    args = tuple(torch.from_numpy(a) for a in (hist, ptype, s, r))
    n, e = torch.export.Dim("N"), torch.export.Dim("E")
    dyn = {"positions": {1: n}, "particle_type": {0: n}, "senders": {0: e}, "receivers": {0: e}}
    prog = torch.onnx.export(model, args, dynamo=True, opset_version=18, input_names=["positions", "particle_type", "senders", "receivers"],
                             output_names=["acceleration", "next_position"], dynamic_shapes=dyn, verbose=False)  # fmt: skip
    proto = prog.model_proto
    entry = proto.metadata_props.add()
    meta = {"feature_version": FEATURE_VERSION, "dim": 2, "radius": R, "t_in": 6, "bounds": BOUNDS, "latent": 8, "layers": 2, "scene": "water2d", "r_t": 2}
    entry.key, entry.value = METADATA_KEY, json.dumps(meta)
    old = tmp_path / "old.onnx"
    old.write_bytes(proto.SerializeToString())
    acc_t, nxt_t = run_torch(model, hist, ptype)
    legacy = GnsRuntime(old)
    assert legacy.input_names == ["positions", "particle_type", "senders", "receivers"]
    acc_l, _, _ = legacy.predict(hist, ptype)
    assert np.abs(acc_l - acc_t).max() <= 1e-4 * np.abs(acc_t).max()
    with pytest.warns(UserWarning, match="threads: old.onnx has no in_edges input"):
        two = GnsRuntime(old, threads=2)
    assert (two.threads, two.spinning) == (1, False)
    assert np.array_equal(two.predict(hist, ptype)[0], acc_l)
    assert upgrade_onnx(old, tmp_path / "new.onnx") and not upgrade_onnx(tmp_path / "new.onnx")
    new = GnsRuntime(tmp_path / "new.onnx")
    acc_n, nxt_n, _ = new.predict(hist, ptype)
    assert np.abs(acc_n - acc_t).max() <= 1e-4 * np.abs(acc_t).max() and np.abs(nxt_n - nxt_t).max() <= 1e-6
    # an upgraded torch-exported graph predates the wall reach: it records GNS's clip at R
    assert {k: v for k, v in new.meta.items() if k != "graph"} == {**legacy.meta, "parameters": new.meta["parameters"], "wall_reach": 1.0}


def test_kinematic_particles_do_not_move(exported):
    _, path = exported
    hist, ptype = random_state(200, seed=6)
    ptype[:20] = 3
    nm = GnsRuntime(path)
    x = hist
    for _ in range(3):
        _, nxt, _ = nm.predict(x, ptype)
        x = np.concatenate([x[1:], nxt[None]])
    assert np.array_equal(x[-1, :20], hist[-1, :20]) and not np.array_equal(x[-1, 20:], hist[-1, 20:])


def test_runtime_errors_name_the_field(exported, tmp_path):
    _, path = exported
    hist, ptype = random_state(10, seed=7)
    with pytest.raises(InvalidInputError) as e:
        GnsRuntime(tmp_path / "missing.onnx")
    assert e.value.field == "model"
    (tmp_path / "junk.onnx").write_bytes(b"not onnx")
    with pytest.raises(InvalidInputError) as e:
        GnsRuntime(tmp_path / "junk.onnx")
    assert e.value.field == "model"
    nm = GnsRuntime(path)  # the history checks are the simulator's: tests/test_sim.py
    with pytest.raises(InvalidInputError, match="3D") as e:
        nm.check_fits(3, np.full(4, 5))
    assert e.value.field == "model"
    with pytest.raises(InvalidInputError, match="particle types"):
        nm.check_fits(2, np.full(10, 7))
    with pytest.raises(InvalidInputError, match="sand3d"):
        nm.check_fits(2, ptype, "sand3d")


def test_simulate_neural_writes_the_mpm_outputs(exported, tmp_path):
    from hybridmpm.cli import main
    from hybridmpm.trajectory import Trajectory

    _, path = exported
    out = tmp_path / "nn"
    assert main(["simulate", "water2d", "--solver", "neural", "--model", str(path), "--frames", "14", "--out", str(out), "--quiet"]) == 0
    traj = Trajectory.load(out / "trajectory.npz")
    assert traj.num_frames == 1 + 14 // 2 and traj.dt_frame == pytest.approx(5e-3)  # one stored frame per model step (r_t = 2)
    assert np.isfinite(traj.positions).all()
    summary = json.loads((out / "summary.json").read_text())
    assert summary["solver"] == "neural" and summary["r_t"] == 2 and summary["warmup_mpm_frames"] == 10 and summary["neural_steps"] == 2
    assert summary["wall_ms_per_frame"]["median"] > 0 and (out / "render.gif").exists()
    # the model was trained for water2d: another scene family is refused, naming the model
    assert main(["simulate", "sand2d", "--solver", "neural", "--model", str(path), "--frames", "14", "--out", str(tmp_path / "x"), "--quiet"]) == 2


@pytest.mark.parametrize("fused", [False, None])
def test_threads_and_spinning(exported, fused):
    """Two onnxruntime threads spin by default (they pay only so), one does
    not; the prediction is the same function either way, with the fused edge
    kernels (their serial sums) or the plain graph (its gather way); bad
    thread counts are refused naming the field (``threads`` here,
    ``nn_threads`` on a simulator)."""
    from hybridmpm.sim import NeuralSimulator

    _, path = exported
    one, two = GnsRuntime(path, fused=fused), GnsRuntime(path, threads=2, fused=fused)
    assert one.fused == two.fused == (fused is None)
    assert (one.spinning, two.spinning, GnsRuntime(path, threads=2, spinning=False).spinning) == (False, True, False)
    hist, ptype = random_state(1500, seed=8, lo=0.3, hi=0.6)
    a1, x1, graph = one.predict(hist, ptype)
    # edges in a random order: onnxruntime's ScatterND on 2 threads loses updates on nearly every run so
    # (module doc of hybridmpm.train.gns.onnx_graph); the gather way that 2 threads take must not, run after run
    perm = np.random.default_rng(1).permutation(len(graph[1]))
    shuffled = tuple(a[perm] for a in graph)
    for g in [graph] * 5 + [shuffled] * 20:
        a2, x2, _ = two.predict(hist, ptype, graph=g)
        assert np.abs(a2 - a1).max() <= 1e-5 * np.abs(a1).max() and np.abs(x2 - x1).max() <= 1e-6
    for bad in (-1, 257, True, 1.5):
        with pytest.raises(InvalidInputError) as e:
            GnsRuntime(path, threads=bad)
        assert e.value.field == "threads"
        with pytest.raises(InvalidInputError) as e:
            NeuralSimulator("water2d", nn_threads=bad)
        assert e.value.field == "nn_threads"


def test_predict_refuses_foreign_types_and_graphs(exported):
    """A negative type code would be wrapped by onnxruntime's Gather (torch
    raises): refused naming particle_type; a graph that is not the four arrays
    of radius_graph (the pre-compiled (senders, receivers) pair) naming graph."""
    _, path = exported
    nm = GnsRuntime(path)
    hist, ptype = random_state(50, seed=10)
    for bad in (-1, 9):
        p = ptype.copy()
        p[7] = bad
        with pytest.raises(InvalidInputError) as e:
            nm.predict(hist, p)
        assert e.value.field == "particle_type"
    s, r, _, _ = radius_graph(hist[-1], R)
    with pytest.raises(InvalidInputError) as e:
        nm.predict(hist, ptype, graph=(s, r))  # type: ignore[arg-type]
    assert e.value.field == "graph"


def test_aggregation_inputs_sum_each_nodes_in_edges():
    """The gather way's table (aggregation_inputs) against a brute-force
    scatter-add (np.add.at), for receivers in any order, nodes without in-edges
    and repeated edges; a table that would outgrow MAX_PADDING times the edges
    is not built (width 0: the ScatterND way)."""
    rng = np.random.default_rng(12)
    n = 50
    r = rng.integers(0, n - 5, 400)  # the last 5 nodes have no in-edges
    for receivers in (np.sort(r), r):
        edges, degree = aggregation_inputs(receivers, n, gather=True)
        assert edges.dtype == np.int64 and degree.dtype == np.float32 and degree.shape == (n, 1)
        assert np.array_equal(degree[:, 0], np.bincount(receivers, minlength=n))
        assert edges.shape == (n, np.bincount(receivers).max())
        x = rng.normal(size=(len(receivers), 3))
        want = np.zeros((n, 3))
        np.add.at(want, receivers, x)
        got = np.concatenate([x, np.zeros((1, 3))])[edges].sum(axis=1)  # what the graph computes: a zero row at index E
        assert np.allclose(got, want, atol=1e-12)
        real = np.arange(edges.shape[1])[None, :] < degree  # the slots that are not padding: every edge once
        assert np.array_equal(np.sort(edges[real]), np.arange(len(receivers))) and (receivers[edges[real]] == np.nonzero(real)[0]).all()
        assert (edges[~real] == len(receivers)).all()
        assert aggregation_inputs(receivers, n, gather=False)[0].shape == (n, 0)
    for n in (50, 400):  # node 0 receives 4n + 1 of 5n edges: a table of n·(4n + 1) entries
        crowded = np.concatenate([np.arange(n), np.zeros(4 * n, np.int64)])
        small = n * (4 * n + 1) <= SMALL_TABLE
        assert n * (4 * n + 1) > MAX_PADDING * len(crowded) and aggregation_inputs(crowded, n, gather=True)[0].shape == (n, 4 * n + 1 if small else 0)


def test_the_gather_sum_is_as_precise_as_scatter_next_to_a_crowded_node(exported):
    """One node with hundreds of in-edges among nodes of few (a table within
    the limits, so the gather way runs): every node's acceleration matches the
    ScatterND way's to float32 rounding of its own size: 1e-7 relative
    (padding with a real edge and subtracting it again was 4.6e-5 off here)."""
    _, path = exported
    hist, ptype = random_state(300, seed=15, lo=0.05, hi=0.95)
    s, r, disp, dist = radius_graph(hist[-1], R)
    extra = np.random.default_rng(15).integers(1, 300, 200)  # 200 more edges into node 0, geometry of real neighbours
    s2, r2 = np.concatenate([s, extra]), np.concatenate([r, np.zeros(200, np.int64)])
    d2 = np.concatenate([disp, np.repeat(np.float32([[0.3 * R, 0.4 * R]]), 200, 0)])
    dist2 = np.concatenate([dist, np.full(200, 0.5 * R, np.float32)])
    order = np.argsort(r2, kind="stable")
    graph = (s2[order], r2[order], d2[order], dist2[order])
    one, two = GnsRuntime(path, fused=False), GnsRuntime(path, threads=2, fused=False)  # the plain graph's two ways
    assert two.feeds(hist, ptype, graph)["in_edges"].shape[1] == 201
    a1, _, _ = one.predict(hist, ptype, graph=graph)
    a2, _, _ = two.predict(hist, ptype, graph=graph)
    scale = np.abs(a1).max(axis=1) + 1e-3 * np.abs(a1).max()
    assert (np.abs(a2 - a1).max(axis=1) <= 1e-5 * scale).all()


def test_a_crowded_graph_runs_on_one_thread(exported):
    """A graph whose padded in-edge table would be too large (a few crowded
    particles) is summed the ScatterND way on a one-thread session, same
    prediction; other graphs run on the model's own session."""
    _, path = exported
    hist, ptype = random_state(3000, seed=13, lo=0.05, hi=0.95)
    hist[:, :400] = hist[:, :1] + np.float32(1e-5) * np.arange(400, dtype=np.float32)[None, :, None]  # 400 particles on one spot
    one, two = GnsRuntime(path, fused=False), GnsRuntime(path, threads=2, fused=False)  # the plain graph's fallback
    a1, _, graph = one.predict(hist, ptype)
    feeds = two.feeds(hist, ptype, graph)
    assert feeds["in_edges"].shape[1] == 0 and two.session_for(feeds) is not two.session
    a2, _, _ = two.predict(hist, ptype, graph=graph)
    assert np.abs(a2 - a1).max() <= 1e-5 * np.abs(a1).max()
    calm = random_state(3000, seed=13, lo=0.3, hi=0.6)
    feeds = two.feeds(calm[0], calm[1], radius_graph(calm[0][-1], R))
    assert feeds["in_edges"].shape[1] > 0 and two.session_for(feeds) is two.session


def test_a_compiled_graph_of_an_earlier_layout_is_refused_naming_the_file(exported, tmp_path):
    """A compiled graph of a layout other than the current one (the real
    compiled-2 file tests/golden/gns_compiled2_tiny.onnx, which has the
    current graph's inputs; a current export relabelled compiled-1) is
    refused on load, whatever the threads or fused kernels asked, with an
    error naming the file and its layout and saying to re-export; upgrade_onnx
    refuses it too and leaves the file alone."""
    from pathlib import Path

    import onnx

    from hybridmpm.neural.constants import GRAPH_LAYOUT, METADATA_KEY
    from hybridmpm.train.gns.export import upgrade_onnx

    old2 = Path(__file__).parent / "golden" / "gns_compiled2_tiny.onnx"
    proto = onnx.load(str(exported[1]))
    entry = next(p for p in proto.metadata_props if p.key == METADATA_KEY)
    assert json.loads(entry.value)["graph"] == GRAPH_LAYOUT
    entry.value = json.dumps({**json.loads(entry.value), "graph": "compiled-1"})
    old1 = tmp_path / "relabelled.onnx"
    old1.write_bytes(proto.SerializeToString())
    for old, layout in ((old2, "compiled-2"), (old1, "compiled-1")):
        for kwargs in ({}, {"threads": 2}, {"fused": True}, {"fused": False}):
            with pytest.raises(InvalidInputError) as e:
                GnsRuntime(old, **kwargs)  # type: ignore[arg-type]
            assert e.value.field == "model", kwargs
            assert str(old) in str(e.value) and repr(layout) in str(e.value) and "re-export" in str(e.value), str(e.value)
        before = old.read_bytes()
        with pytest.raises(ValueError, match="re-export"):
            upgrade_onnx(old, tmp_path / "never.onnx")
        assert old.read_bytes() == before and not (tmp_path / "never.onnx").exists()


def test_every_layer_norm_takes_its_square_root_on_one_column(exported):
    """The folded LayerNorm of the compiled graph (train/gns/onnx_graph.py):
    each Sqrt reads a Gemm of one output column (the variance, ε its C input)
    and only a MatMul with a row of ones reads it back, widening it for the
    division; the weights of that column are 1/(g²L) of the LayerNorm's gain
    g, read from the torch model (the encoders' and every layer's edge and node
    LayerNorms)."""
    import onnx
    from onnx import numpy_helper

    model, path = exported
    g = onnx.load(str(path)).graph
    consts = {i.name: numpy_helper.to_array(i) for i in g.initializer}
    producer = {o: n for n in g.node for o in n.output}
    readers: dict[str, list] = {}
    for n in g.node:
        for name in n.input:
            readers.setdefault(name, []).append(n)
    net = model.gnn
    norms = [net.node_encoder[5], net.edge_encoder[5]]
    for k in range(model.config.layers):
        norms += [net.edge_blocks[k].rest[4], net.node_blocks[k][5]]
    expected = sorted((1.0 / (ln.weight.detach().double().numpy() ** 2 * len(ln.weight)) for ln in norms), key=lambda k: k[0])
    found = []
    for n in (n for n in g.node if n.op_type == "Sqrt"):
        var = producer[n.input[0]]
        assert var.op_type == "Gemm" and consts[var.input[1]].shape == (16, 1) and consts[var.input[2]].size == 1, n.name
        (widen,) = readers[n.output[0]]
        assert widen.op_type == "MatMul" and np.array_equal(consts[widen.input[1]], np.ones((1, 16), np.float32)), n.name
        assert {r.op_type for r in readers[widen.output[0]]} == {"Div"}, n.name
        found.append(consts[var.input[1]][:, 0].astype(np.float64))
    assert len(found) == len(expected) == 2 + 2 * model.config.layers
    assert np.allclose(sorted(found, key=lambda k: k[0]), expected, rtol=1e-6, atol=0)
