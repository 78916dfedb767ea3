"""The GNS's training (hybridmpm.train.gns.train) on a small drag-and-gravity
dataset: a real learning check, the pushforward and unrolled (BPTT) windows
against independent computations, wall reach, pooled datasets and the weight
average (EMA), each with its resume and its refusals. (Needs the 'train'
extra: torch, onnx, onnxscript; it is part of the 'test' extra.) The model,
its ONNX export and the runtime: tests/test_neural.py."""

from __future__ import annotations

import csv
import json
import logging

import numpy as np
import pytest
import torch
from _datasets import drag_dataset

from hybridmpm import radius_graph
from hybridmpm.conventions import GNS_KINEMATIC
from hybridmpm.errors import InvalidInputError
from hybridmpm.neural import GnsRuntime
from hybridmpm.train.gns.model import GnsConfig, GnsModel

logging.getLogger("torch.onnx").setLevel(logging.ERROR)


def test_short_training_lowers_the_validation_loss(tmp_path):
    from hybridmpm.train.gns.train import TrainConfig, train

    data = tmp_path / "drag"
    data.mkdir()
    drag_dataset(data)
    cfg = TrainConfig(
        scene="drag", data=str(data), out=str(tmp_path / "model"), latent=16, layers=1, r_t=1, steps=240, batch=2,
        lr=3e-3, lr_final=3e-4, noise_std=1e-5, val_every=60, rollout_steps=10, threads=1,
    )  # fmt: skip
    summary = train(cfg, progress=False)
    rows = list(csv.DictReader(open(tmp_path / "model" / "log.csv")))
    first, last = float(rows[0]["val_one_step"]), float(rows[-1]["val_one_step"])
    assert rows[0]["step"] == "0" and last < 0.3 * first, (first, last)
    assert float(rows[-1]["val_rollout_mse"]) < float(rows[0]["val_rollout_mse"])
    # the exported model carries its metadata and runs
    nm = GnsRuntime(tmp_path / "model" / "model.onnx")
    assert nm.meta["scene"] == "drag" and nm.meta["latent"] == 16 and nm.meta["r_t"] == 1 and nm.meta["particle_types"] == [5]
    assert summary["steps"] == 240
    # every validated step was exported; the shipped model.onnx is the snapshot of the best rollout
    snaps = sorted((tmp_path / "model" / "snapshots").glob("step_*/model.onnx"))
    assert [p.parent.name for p in snaps] == [f"step_{s:07d}" for s in (60, 120, 180, 240)]
    best_step = min(rows[1:], key=lambda r: float(r["val_rollout_mse"]))["step"]
    x = np.random.default_rng(1).uniform(0.3, 0.7, (60, 2)).astype(np.float32)
    hist = np.stack([x + 1e-3 * k for k in range(nm.t_in)]).astype(np.float32)
    pt = np.full(60, 5, np.int64)
    best_snap = GnsRuntime(tmp_path / "model" / "snapshots" / f"step_{int(best_step):07d}" / "model.onnx")
    np.testing.assert_array_equal(nm.predict(hist, pt)[0], best_snap.predict(hist, pt)[0])
    best_row = next(r for r in rows if r["step"] == best_step)
    assert best_snap.meta["val_rollout_mse"] == pytest.approx(float(best_row["val_rollout_mse"]), rel=1e-3)
    others = [GnsRuntime(p) for p in snaps if p.parent.name != f"step_{int(best_step):07d}"]
    assert all(not np.array_equal(nm.predict(hist, pt)[0], o.predict(hist, pt)[0]) for o in others)
    # resuming a finished run does no more steps and keeps the log
    train(cfg, progress=False)
    assert len(list(csv.DictReader(open(tmp_path / "model" / "log.csv")))) == len(rows)
    # another setting in the same directory is refused
    with pytest.raises(InvalidInputError) as e:
        train(TrainConfig(**{**cfg.__dict__, "latent": 32}), progress=False)
    assert e.value.field == "latent"
    json.loads((tmp_path / "model" / "summary.json").read_text())


class _Oracle(torch.nn.Module):
    """Stands in for a GnsModel in a pushforward window: predicts the true
    position at ``t`` plus a fixed error ``err`` (positions [N, D])."""

    def __init__(self, truth: np.ndarray, err: np.ndarray) -> None:
        super().__init__()
        self.next = torch.from_numpy((truth + err).astype(np.float32))
        self.seen: np.ndarray | None = None

    def forward(self, hist, ptype, s, r):
        self.seen = hist.numpy().copy()  # the window it was asked to step
        return None, self.next


def test_pushforward_window_targets_the_true_next_position():
    """Pushforward (Brandstetter et al. 2022): with a perfect one-step
    prediction the window is the plain window; with a prediction off by
    ``err`` the target acceleration still lands on the true position
    ``t + 1`` (x_next = 2·x_t − x_{t−1} + a), i.e. it is the plain target
    minus 2·err, and kinematic particles keep their true positions."""
    from hybridmpm.train.gns.train import _pushforward_window, _window

    rng = np.random.default_rng(0)
    n, frames, t, t_in = 12, 14, 9, 6
    x = np.cumsum(rng.normal(0, 1e-3, (frames, n, 2)), axis=0) + 0.5
    ptype = np.full(n, 5, np.int64)
    ptype[:2] = GNS_KINEMATIC
    traj = (x.astype(np.float32), ptype)
    hist, pt, acc = _window(traj, t, t_in, 0.0, rng)
    zero = np.zeros((n, 2))
    oracle = _Oracle(traj[0][t], zero)
    h0, p0, a0 = _pushforward_window(oracle, traj, t, t_in, 0.0, rng, 0.05, None)
    # the model was asked to step the window ending at t − 1
    np.testing.assert_array_equal(oracle.seen, traj[0][t - t_in : t])
    np.testing.assert_array_equal(h0, hist)
    np.testing.assert_array_equal(p0, pt)
    np.testing.assert_allclose(a0, acc, atol=1e-9)
    err = rng.normal(0, 5e-4, (n, 2))
    h1, _, a1 = _pushforward_window(_Oracle(traj[0][t], err), traj, t, t_in, 0.0, rng, 0.05, None)
    err[ptype == GNS_KINEMATIC] = 0.0
    np.testing.assert_allclose(h1[-1], traj[0][t] + err, atol=1e-7)
    np.testing.assert_array_equal(h1[:-1], hist[:-1])
    np.testing.assert_allclose(a1, acc - 2 * err, atol=1e-6)
    landed = 2 * h1[-1].astype(np.float64) - h1[-2] + a1
    np.testing.assert_allclose(landed, traj[0][t + 1], atol=1e-6)
    # with input noise the target keeps the plain window's convention: it
    # corrects velocity noise, not the last input position's offset
    oracle = _Oracle(traj[0][t], zero)
    h2, _, a2 = _pushforward_window(oracle, traj, t, t_in, 1e-3, np.random.default_rng(5), 0.05, None)
    assert oracle.seen is not None
    np.testing.assert_array_equal(oracle.seen[1:], h2[:-1])  # the same noisy inputs, shifted by one
    offset = h2[-2].astype(np.float64) - traj[0][t - 1]
    assert np.abs(offset[ptype != GNS_KINEMATIC]).max() > 1e-5
    np.testing.assert_allclose(2 * h2[-1].astype(np.float64) - h2[-2] + a2, traj[0][t + 1] + offset, atol=1e-6)


def _option_trains_and_old_runs_resume(tmp_path, tag: str, option: dict, defaults: dict, meta_key: str):
    """A small run on the drag dataset with the TrainConfig fields ``option``
    trains (its validation loss falls by more than half) and records
    ``meta_key`` in its model; a run directory written before the fields of
    ``defaults`` existed (its settings file lacks them) resumes with those
    defaults. Returns ``(cfg, plain)``: the option's config and the old run's."""
    from hybridmpm.train.gns.train import TrainConfig, train

    data = tmp_path / "drag"
    data.mkdir(exist_ok=True)
    drag_dataset(data, n_traj=4, frames=20, n=30)
    cfg = TrainConfig(
        scene="drag", data=str(data), out=str(tmp_path / tag), latent=8, layers=1, r_t=1, steps=120, batch=2,
        lr=3e-3, lr_final=3e-4, noise_std=1e-5, val_every=40, val_windows=4, rollout_steps=5, threads=1, **option,
    )  # fmt: skip
    train(cfg, progress=False)
    rows = list(csv.DictReader(open(tmp_path / tag / "log.csv")))
    assert float(rows[-1]["val_one_step"]) < 0.5 * float(rows[0]["val_one_step"])
    assert GnsRuntime(tmp_path / tag / "model.onnx").meta[meta_key] == option[meta_key]
    old = tmp_path / f"old_{tag}"
    plain = TrainConfig(**{**cfg.__dict__, "out": str(old), "steps": 2, "val_every": 2, **defaults})
    train(plain, progress=False)
    saved = json.loads((old / "train_config.json").read_text())
    for key in defaults:
        del saved[key]
    (old / "train_config.json").write_text(json.dumps(saved))
    assert train(plain, progress=False)["steps"] == 2
    return cfg, plain


def _refused_on_short_data(tmp_path, cfg, frames: int, field: str) -> None:
    """Training ``cfg`` on drag trajectories of ``frames`` frames is refused up front, naming ``field``."""
    from hybridmpm.train.gns.train import TrainConfig, train

    short = tmp_path / "short"
    short.mkdir()
    drag_dataset(short, n_traj=4, frames=frames, n=30)
    with pytest.raises(InvalidInputError) as e:
        train(TrainConfig(**{**cfg.__dict__, "data": str(short), "out": str(tmp_path / "short_run")}), progress=False)
    assert e.value.field == field


def test_pushforward_training_runs_resumes_and_old_runs_still_resume(tmp_path):
    """A run with pushforward trains (its validation loss falls) and is
    recorded in the model; a run directory written before the pushforward
    settings existed resumes with their defaults; bad values name the field."""
    from hybridmpm.train.gns.train import TrainConfig, train

    cfg, plain = _option_trains_and_old_runs_resume(
        tmp_path, "pf", {"pushforward": 0.5, "pushforward_after": 0.25}, {"pushforward": 0.0, "pushforward_after": 0.2}, "pushforward"
    )
    with pytest.raises(InvalidInputError) as e:
        train(TrainConfig(**{**plain.__dict__, "pushforward": 0.3}), progress=False)
    assert e.value.field == "pushforward"
    for bad in (-0.1, 1.5, float("nan")):
        with pytest.raises(InvalidInputError) as e:
            TrainConfig(**{**cfg.__dict__, "pushforward_after": bad}).validate()
        assert e.value.field == "pushforward_after"
    # trajectories one step too short for a pushforward window are refused up front
    _refused_on_short_data(tmp_path, cfg, 6, "pushforward")


def _unroll_model(kinematic_first: int = 0):
    """A small perturbed GnsModel and a trajectory of 40 particles (the first
    ``kinematic_first`` kinematic) for the unrolled-training tests."""
    torch.manual_seed(4)
    cfg = GnsConfig(
        dim=2, radius=0.06, bounds=[[0.0, 1.0], [0.0, 1.0]], vel_mean=[0.0, -1e-4], vel_std=[1e-3, 2e-3], acc_mean=[0.0, -2e-5],
        acc_std=[3e-4, 5e-4], latent=8, layers=2, t_in=6, noise_std=0.0,
    )  # fmt: skip
    model = GnsModel(cfg)
    with torch.no_grad():
        for p in model.parameters():
            p.add_(0.3 * torch.randn_like(p))
    rng = np.random.default_rng(2)
    pos = (0.35 + 0.3 * rng.random((1, 40, 2)) + np.cumsum(rng.normal(0, 1e-3, (14, 40, 2)), axis=0)).astype(np.float32)
    ptype = np.full(40, 5, np.int64)
    ptype[:kinematic_first] = GNS_KINEMATIC
    pos[:, :kinematic_first] = pos[0, :kinematic_first] + np.linspace(0, 0.01, 14)[:, None, None]  # obstacles moved by the scene
    return model, (pos, ptype)


def test_unrolled_loss_is_the_position_error_of_the_models_own_rollout():
    """The unrolled loss (BPTT) against an independent computation: the
    model's own rollout through ``forward`` (its Euler step), positions
    clipped to the bounds and kinematic particles set to the truth, scored
    as the position error to the (noise-shifted) true positions over the
    acceleration scale; one step equals the one-step loss; the gradient
    reaches the first step's prediction (a detached history changes it)."""
    from hybridmpm.train.gns.train import _batch, _loss, _unrolled_loss, _unrolled_window, _window

    model, traj = _unroll_model(kinematic_first=5)
    radius, k = model.config.radius, 4
    windows = [_unrolled_window(traj, t, 6, k, 2e-4, np.random.default_rng(t)) for t in (5, 7)]
    loss = _unrolled_loss(model, windows, radius, None)
    model.zero_grad()
    loss.backward()
    g_bptt = torch.cat([p.grad.flatten() for p in model.parameters()]).clone()

    def brute(detach: bool) -> tuple[float, torch.Tensor]:
        """Each window rolled out on its own through forward(); with ``detach``
        the history is cut from the graph at every step (no BPTT)."""
        errs = []
        for hist0, ptype, targets, truth in windows:
            hist, pt, steps = torch.from_numpy(hist0), torch.from_numpy(ptype), []
            for j in range(k):
                s, r, _, _ = radius_graph(hist[-1].detach().numpy(), radius)
                _, nxt = model(hist, pt, torch.from_numpy(s), torch.from_numpy(r))
                fluid = ptype != GNS_KINEMATIC
                steps.append(((nxt - torch.from_numpy(targets[j])) / model.features.acc_std)[fluid] ** 2)
                nxt = nxt.clamp(0.0, 1.0)
                nxt[~fluid] = torch.from_numpy(truth[j][~fluid])
                hist = torch.cat([hist[1:], (nxt.detach() if detach else nxt)[None]])
            errs.append(steps)
        total = torch.stack([torch.cat([errs[0][j], errs[1][j]]).mean() for j in range(k)]).mean()
        model.zero_grad()
        total.backward()
        return total.item(), torch.cat([p.grad.flatten() for p in model.parameters()]).clone()

    value, g_brute = brute(detach=False)
    assert loss.item() == pytest.approx(value, rel=1e-4) and loss.item() > 0
    assert torch.isfinite(g_bptt).all()
    np.testing.assert_allclose(g_bptt.numpy(), g_brute.numpy(), rtol=2e-3, atol=2e-4 * float(g_brute.abs().max()))
    # the gradient really flows back through the rollout: without it the gradient is another
    value_cut, g_cut = brute(detach=True)
    assert value_cut == pytest.approx(value, rel=1e-4)
    assert float((g_cut - g_bptt).norm()) > 0.05 * float(g_bptt.norm())
    # one step is the one-step loss of the same window
    one = _unrolled_window(traj, 6, 6, 1, 3e-4, np.random.default_rng(9))
    w1 = _window(traj, 6, 6, 3e-4, np.random.default_rng(9))
    assert _unrolled_loss(model, [one], radius, None).item() == pytest.approx(_loss(model, _batch([w1], radius, None)).item(), rel=1e-4)
    np.testing.assert_array_equal(one[0], w1[0])


def test_unrolled_training_trains_resumes_and_refuses_bad_settings(tmp_path):
    """A run with ``unroll`` = 3 trains (validation loss falls), records the
    setting in the model, a run directory written before the setting existed
    resumes with its default, and bad values are refused naming the field."""
    from hybridmpm.train.gns.train import TrainConfig, train

    cfg, plain = _option_trains_and_old_runs_resume(
        tmp_path, "ur", {"unroll": 3, "unroll_after": 0.25}, {"unroll": 1, "unroll_after": 0.0, "clip_grad": 1.0}, "unroll"
    )
    with pytest.raises(InvalidInputError) as e:
        train(TrainConfig(**{**plain.__dict__, "unroll": 2}), progress=False)
    assert e.value.field == "unroll"
    for field, bad in (("unroll", 0), ("unroll", 2.5), ("unroll_after", 1.5), ("clip_grad", 0.0), ("clip_grad", float("nan"))):
        with pytest.raises(InvalidInputError) as e:
            TrainConfig(**{**cfg.__dict__, field: bad}).validate()
        assert e.value.field == field
    with pytest.raises(InvalidInputError) as e:
        TrainConfig(**{**cfg.__dict__, "pushforward": 0.2}).validate()
    assert e.value.field == "unroll"
    _refused_on_short_data(tmp_path, cfg, 7, "unroll")  # 3 unrolled steps after T_in = 6 need 9 frames


def test_wall_reach_trains_resumes_and_refuses_bad_settings(tmp_path):
    """A run with ``wall_reach`` 3 trains, records it in the model; a run made
    before the setting existed resumes with reach 1; resuming with another
    reach and out-of-range reaches are refused naming the field."""
    from hybridmpm.train.gns.train import TrainConfig, train

    cfg, plain = _option_trains_and_old_runs_resume(tmp_path, "wr", {"wall_reach": 3.0}, {"wall_reach": 1.0}, "wall_reach")
    with pytest.raises(InvalidInputError) as e:
        train(TrainConfig(**{**plain.__dict__, "wall_reach": 2.0}), progress=False)
    assert e.value.field == "wall_reach"
    for bad in (0.9, float("inf"), 17.0, "4"):
        with pytest.raises(InvalidInputError) as e:
            TrainConfig(**{**cfg.__dict__, "wall_reach": bad}).validate()
        assert e.value.field == "wall_reach"


def test_training_pools_several_datasets_and_refuses_ones_that_disagree(tmp_path):
    """``data`` as a list pools the datasets split by split: the model's
    normalisation statistics are those of the union of the training splits
    (computed here independently), one directory in a list is stored as the
    plain path (older runs resume), and datasets that disagree on the frame
    time are refused naming ``data``."""
    from hybridmpm.data import GnsDataset, compute_statistics
    from hybridmpm.train.gns.train import TrainConfig, train

    a, b = tmp_path / "a", tmp_path / "b"
    a.mkdir()
    b.mkdir()
    drag_dataset(a, n_traj=4, frames=16, n=30, k=0.2, seed=0, scene="drag")
    drag_dataset(b, n_traj=4, frames=16, n=30, k=0.05, seed=1, scene="slow_drag")  # slower drag: other velocity statistics
    cfg = TrainConfig(
        scene="drag", data=[str(a), str(b)], out=str(tmp_path / "pool"), latent=8, layers=1, r_t=1, steps=4, batch=2,
        lr=3e-3, lr_final=3e-4, noise_std=1e-5, val_every=2, val_windows=2, rollout_steps=3, threads=1,
    )  # fmt: skip
    train(cfg, progress=False)
    union = [(t.positions, t.particle_type) for d in (a, b) for _, t in sorted(GnsDataset(d).split("train").items())]
    only_a = [(t.positions, t.particle_type) for _, t in sorted(GnsDataset(a).split("train").items())]
    want, alone = compute_statistics(union, exclude_types=(GNS_KINEMATIC,)), compute_statistics(only_a, exclude_types=(GNS_KINEMATIC,))
    gns = torch.load(tmp_path / "pool" / "checkpoint.pt", weights_only=False)["gns_config"]  # the ONNX graph folds them in
    for key in ("vel_mean", "vel_std", "acc_mean", "acc_std"):
        np.testing.assert_allclose(gns[key], want[key], rtol=1e-5, atol=1e-12)
    assert not np.allclose(want["vel_std"], alone["vel_std"], rtol=1e-2)  # the pooled set is not the first one alone
    assert json.loads((tmp_path / "pool" / "train_config.json").read_text())["data"] == [str(a), str(b)]
    # the model serves the scene families of every pooled dataset, each once
    snap = GnsRuntime(tmp_path / "pool" / "snapshots" / "step_0000004" / "model.onnx")
    assert snap.meta["scenes"] == ["drag", "slow_drag"]
    ptype = np.full(30, 5, np.int64)
    snap.check_fits(2, ptype, "slow_drag")
    with pytest.raises(InvalidInputError):
        snap.check_fits(2, ptype, "water2d")
    # the validation rollout is that of each dataset's first validation
    # trajectory, averaged: recomputed here through onnxruntime from the
    # step's exported snapshot (the training scored the same weights in torch)
    mses = []
    for d in (a, b):
        pos = next(iter(sorted(GnsDataset(d).split("valid").items())))[1].positions
        hist = pos[:6].copy()
        for k in range(3):
            _, nxt, _ = snap.predict(hist, ptype)
            hist = np.concatenate([hist[1:], nxt[None]])
            mses.append(((nxt - pos[6 + k]) ** 2).mean() / 3 / 2)  # mean over 3 steps, then over 2 datasets
    logged = [r for r in csv.DictReader((tmp_path / "pool" / "log.csv").read_text().splitlines()) if r["step"] == "4"][-1]
    assert float(logged["val_rollout_mse"]) == pytest.approx(sum(mses), rel=1e-3)
    one = TrainConfig(**{**cfg.__dict__, "data": [str(a)], "out": str(tmp_path / "one")}).validate()
    assert one.data == str(a)
    meta_b = json.loads((b / "metadata.json").read_text())
    meta_b["dt"] = 5e-3
    (b / "metadata.json").write_text(json.dumps(meta_b))
    with pytest.raises(InvalidInputError) as e:
        train(TrainConfig(**{**cfg.__dict__, "out": str(tmp_path / "bad")}), progress=False)
    assert e.value.field == "data" and "dt" in str(e.value)
    for bad in ([], [3], None):
        with pytest.raises(InvalidInputError) as e:
            TrainConfig(**{**cfg.__dict__, "data": bad}).validate()
        assert e.value.field == "data"


def test_ema_averages_the_trained_weights_without_changing_training(tmp_path):
    """With ``ema`` = β the trained weights follow exactly the plain run's
    path (the average draws no random numbers), the checkpoint's average is
    ``β·w₁ + (1 − β)·w₂`` after two steps (torch's AveragedModel starts from
    the first step's weights), and ``best.pt`` holds an averaged model, not
    the trained one."""
    from hybridmpm.train.gns.train import TrainConfig, train

    data = tmp_path / "drag"
    data.mkdir()
    drag_dataset(data, n_traj=4, frames=16, n=30)
    base = dict(
        scene="drag", data=str(data), latent=8, layers=1, r_t=1, batch=2, lr=3e-2, lr_final=3e-3,
        noise_std=1e-5, val_every=1, val_windows=2, rollout_steps=3, threads=1,
    )  # fmt: skip
    beta = 0.75
    train(TrainConfig(**base, out=str(tmp_path / "one"), steps=1), progress=False)
    train(TrainConfig(**base, out=str(tmp_path / "two"), steps=2), progress=False)
    train(TrainConfig(**base, out=str(tmp_path / "ema"), steps=2, ema=beta), progress=False)
    w1 = torch.load(tmp_path / "one" / "checkpoint.pt", weights_only=False)["model"]
    w2 = torch.load(tmp_path / "two" / "checkpoint.pt", weights_only=False)["model"]
    state = torch.load(tmp_path / "ema" / "checkpoint.pt", weights_only=False)
    avg = {k[len("module.") :]: v for k, v in state["ema"].items() if k.startswith("module.")}
    moved = 0
    for k, v in w2.items():
        torch.testing.assert_close(state["model"][k], v, rtol=0, atol=0)  # training unchanged
        if v.is_floating_point() and k in dict(GnsModel(GnsConfig(**state["gns_config"])).named_parameters()):
            torch.testing.assert_close(avg[k], beta * w1[k] + (1 - beta) * v, rtol=1e-6, atol=1e-7)
            moved += int(not torch.equal(w1[k], v))
    assert moved > 0  # the two steps did change the weights
    best = torch.load(tmp_path / "ema" / "best.pt", weights_only=True)
    assert any(not torch.equal(best[k], w2[k]) for k in w2 if w2[k].is_floating_point())
    with pytest.raises(InvalidInputError) as e:
        TrainConfig(**base, out=str(tmp_path / "bad"), ema=1.0).validate()
    assert e.value.field == "ema"
