"""Data-parallel training on several processes (hybridmpm.train.distributed,
docs/neural.md "Training on several processes"): N ranks of batch b train the
weights of one process of batch N·b from the same seed, for the GNS, the
controller and the grid model; a run whose ranks draw their own batches, or whose gradients are
not averaged, does not; bad counts and half a torchrun environment are
refused naming the field. (Needs the 'train' extra.)

The tolerance of the equivalence (rtol 1e-4, atol 1e-6 on every parameter
after 50 Adam steps, 12 AdamW or 20 Adam steps): the ranks' gradients are
the single process's sums split in two and added by gloo's all-reduce in
another order, so they differ by float32 rounding (~1e-7 relative), which
the optimiser's normalised steps carry into the weights without growing it
much (measured: at most ~7e-7 absolute on weights of ~0.3, against ~3e-5
allowed). The mutations move the GNS weights by ~0.04, so the check can
fail; a rank averaging its loss over its own slice instead of weighing it by
the global batch's particles moves them as much.
"""

from __future__ import annotations

import csv
import json
from dataclasses import replace
from pathlib import Path

import pytest

torch = pytest.importorskip("torch")

from training_data import control_cases, drag_dataset, gns_config  # noqa: E402

from hybridmpm.errors import InvalidInputError  # noqa: E402
from hybridmpm.train import distributed  # noqa: E402
from hybridmpm.train.distributed import Ranks, launch  # noqa: E402
from hybridmpm.train.gns import train as gns_train  # noqa: E402
from hybridmpm.train.gns.train import TrainConfig, train  # noqa: E402

RTOL, ATOL = 1e-4, 1e-6


@pytest.fixture(scope="module")
def data(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return drag_dataset(tmp_path_factory.mktemp("ddp") / "drag")


def _weights(out: Path) -> dict[str, torch.Tensor]:
    return torch.load(out / "checkpoint.pt", weights_only=False)["model"]


def _agree(a: dict[str, torch.Tensor], b: dict[str, torch.Tensor]) -> bool:
    assert a.keys() == b.keys()
    return all(torch.allclose(a[k], b[k], rtol=RTOL, atol=ATOL) for k in a)


def _gap(a: dict[str, torch.Tensor], b: dict[str, torch.Tensor]) -> float:
    return max(float((a[k] - b[k]).abs().max()) for k in a)


# the mutations run in the ranks' processes (module-level functions: the launcher pickles them by name)
def _own_streams(ranks: Ranks, config: TrainConfig, progress: bool) -> dict:
    """Each rank draws from its own random stream (seed + rank), the usual data-parallel slip."""
    return gns_train._train(ranks, replace(config, seed=config.seed + ranks.rank), progress)


def _no_averaging(ranks: Ranks, config: TrainConfig, progress: bool) -> dict:
    """The ranks' gradients are not all-reduced (no DistributedDataParallel)."""
    Ranks.wrap = lambda self, module: module  # type: ignore[method-assign]
    return gns_train._train(ranks, config, progress)


def test_two_ranks_train_the_weights_of_one_process_of_twice_the_batch(data: Path, tmp_path: Path) -> None:
    # plain windows for the first half, pushforward windows (the model's own step, drawn by one rank) after it
    one = gns_config(data, tmp_path / "one", batch=4)
    two = gns_config(data, tmp_path / "two", batch=2, nproc=2)
    train(one, progress=False)
    summary = train(two, progress=False)
    a, b = _weights(tmp_path / "one"), _weights(tmp_path / "two")
    assert _agree(a, b), _gap(a, b)
    # what the run records: the ranks, the core-seconds of both, rank 0's export
    assert summary["steps"] == 50 and summary["ranks"] == 2 and summary["core_seconds"] > 0
    assert json.loads((tmp_path / "two" / "train_config.json").read_text())["ranks"] == 2
    rows = list(csv.DictReader(open(tmp_path / "two" / "log.csv")))
    assert [r["step"] for r in rows] == ["0", "50"] and rows[-1]["ranks"] == "2" and float(rows[-1]["core_seconds"]) > 0
    assert json.loads((tmp_path / "two" / "summary.json").read_text())["ranks"] == 2
    from hybridmpm.neural import GnsRuntime

    assert GnsRuntime(tmp_path / "two" / "model.onnx").meta["steps"] == 50
    # the same command again resumes the finished run (rank 0 sends the checkpoint): no step more, no row more
    assert train(two, progress=False)["steps"] == 50
    assert len(list(csv.DictReader(open(tmp_path / "two" / "log.csv")))) == len(rows)
    assert _agree(_weights(tmp_path / "two"), b)
    # another split of the same global batch resumes it; another global batch is refused
    assert train(replace(two, batch=4, nproc=1), progress=False)["steps"] == 50
    with pytest.raises(InvalidInputError) as e:
        train(replace(two, nproc=1), progress=False)
    assert e.value.field == "batch"

    # mutations: ranks drawing their own batches, or gradients left unaveraged, do not train those weights
    for i, mutation in enumerate((_own_streams, _no_averaging)):
        out = tmp_path / f"mutant{i}"
        launch(mutation, 2, replace(two, out=str(out)), False)
        assert not _agree(a, _weights(out)), mutation.__name__
        assert _gap(a, _weights(out)) > 100 * ATOL, (mutation.__name__, _gap(a, _weights(out)))


def test_train_control_on_two_ranks_trains_the_weights_of_one_process_of_twice_the_batch(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    from hybridmpm.control.diffusion import ControlModel
    from hybridmpm.train.control import train as control_train
    from hybridmpm.train.control.train import train_control

    control_cases(tmp_path / "cases")
    kw = dict(steps=12, lr=3e-3, latent_state=8, latent_head=8, valid_fraction=0.25, checkpoint_every=100, prior="sketch_ramp", progress=False)
    with monkeypatch.context() as m:  # the reference run's export is not looked at (the ONNX export is most of the time)
        m.setattr(control_train, "export_control", lambda *a, **k: None)
        train_control("water2d", tmp_path / "cases", tmp_path / "one", batch=2, **kw)  # type: ignore[arg-type]
    summary = train_control("water2d", tmp_path / "cases", tmp_path / "two", batch=1, nproc=2, **kw)  # type: ignore[arg-type]
    a = torch.load(tmp_path / "one" / "ckpt.pt", weights_only=False)
    b = torch.load(tmp_path / "two" / "ckpt.pt", weights_only=False)
    for key in ("model", "ema"):
        assert _agree(a[key], b[key]), (key, _gap(a[key], b[key]))
    assert summary["steps"] == 12 and summary["ranks"] == 2 and b["ranks"] == 2 and b["batch"] == 1
    log = [json.loads(line) for line in (tmp_path / "two" / "log.jsonl").read_text().splitlines()]
    assert log[-1]["ranks"] == 2 and log[-1]["core_seconds"] > 0
    # rank 0's export loads
    assert ControlModel(tmp_path / "two" / "model").meta["config"]["latent_state"] == 8


def test_train_grid_on_two_ranks_trains_the_weights_of_one_process_of_twice_the_batch(data: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    from hybridmpm.train.grid import GridTrainConfig, train_grid
    from hybridmpm.train.grid import train as grid_train

    # unrolled calls and the density loss: both divide by the global batch's fluid particles
    base = dict(
        scene="water2d", data=str(data), grid=16, width=4, levels=2, r_t=1, t_in=3, steps=20, lr=1e-3, warmup=5, unroll=2,
        density_weight=0.5, val_every=20, val_steps=3, val_trajectories=1,
    )  # fmt: skip
    with monkeypatch.context() as m:  # the reference run's export is not looked at
        m.setattr(grid_train, "export_grid", lambda *a, **k: None)
        train_grid(GridTrainConfig(out=str(tmp_path / "one"), batch=4, **base), progress=False)  # type: ignore[arg-type]
    summary = train_grid(GridTrainConfig(out=str(tmp_path / "two"), batch=2, nproc=2, **base), progress=False)  # type: ignore[arg-type]
    a, b = _weights(tmp_path / "one"), _weights(tmp_path / "two")
    assert _agree(a, b), _gap(a, b)
    assert summary["ranks"] == 2 and summary["curve"][-1]["ranks"] == 2 and summary["core_seconds"] > 0
    assert (tmp_path / "two" / "model.onnx").exists()


def test_bad_process_counts_and_half_a_torchrun_environment_are_refused(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    for v in TORCHRUN:
        monkeypatch.delenv(v, raising=False)
    cfg = gns_config(tmp_path / "nowhere", tmp_path / "out", batch=2)
    for bad in (0, -1, distributed.max_local_processes() + 1, 10**6, 1.5, True):
        with pytest.raises(InvalidInputError) as e:
            train(replace(cfg, nproc=bad), progress=False)  # type: ignore[arg-type]
        assert e.value.field == "nproc"
    from hybridmpm.cli import main

    assert main(["train", "drag", "--data", str(tmp_path), "--out", str(tmp_path / "o"), "--nproc", "0", "--quiet"]) == 2
    # half a torchrun environment: refused, naming the first missing variable
    monkeypatch.setenv("RANK", "0")
    monkeypatch.setenv("WORLD_SIZE", "2")
    with pytest.raises(InvalidInputError) as e:
        launch(_never, 1)
    assert e.value.field == "LOCAL_RANK"
    monkeypatch.setenv("LOCAL_RANK", "0")
    monkeypatch.setenv("MASTER_ADDR", "127.0.0.1")
    monkeypatch.setenv("MASTER_PORT", "70000")
    with pytest.raises(InvalidInputError) as e:
        launch(_never, 1)
    assert e.value.field == "MASTER_PORT"
    monkeypatch.setenv("MASTER_PORT", "29500")
    monkeypatch.setenv("RANK", "2")
    with pytest.raises(InvalidInputError) as e:
        launch(_never, 1)
    assert e.value.field == "RANK"
    # under torchrun the ranks are torchrun's: --nproc stays 1
    monkeypatch.setenv("RANK", "1")
    with pytest.raises(InvalidInputError) as e:
        launch(_never, 2)
    assert e.value.field == "nproc"
    assert not distributed.is_main_process()


TORCHRUN = (*distributed.TORCHRUN_VARIABLES, "LOCAL_WORLD_SIZE")


def _never(ranks: Ranks) -> None:
    raise AssertionError("launched")
