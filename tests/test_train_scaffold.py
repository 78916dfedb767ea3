"""The training scaffold (hybridmpm.train.scaffold) that the GNS, the grid
model and the controller train through: a run killed right after a
mid-run checkpoint and started again reaches the weights, optimiser state
and validation curve of an uninterrupted run, bit for bit, in every family
(the checkpoint carries the model, the optimiser, the step and both random
streams); without its random streams it does not, so the comparison can
fail. Then the parts on their own: settings refused naming the field, a run
directory resumed only by the settings that made it, the curve's files, the
atomic checkpoint, the export metadata. (Needs the 'train' extra.)
"""

from __future__ import annotations

import csv
import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from training_data import control_cases, drag_dataset, gns_config  # noqa: E402

from hybridmpm.errors import InvalidInputError  # noqa: E402
from hybridmpm.train.scaffold import (  # noqa: E402
    CURVE_FILE,
    Parts,
    RunConfig,
    TrainingLoop,
    ValidationCurve,
    data_sha256,
    export_metadata,
    integer,
    number,
    processes,
    save_torch,
    setting,
)
from hybridmpm.train.scaffold import loop as loop_module  # noqa: E402


class _Killed(Exception):
    """The process dies right after the checkpoint of a given step."""


@pytest.fixture(scope="module")
def data(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return drag_dataset(tmp_path_factory.mktemp("scaffold") / "drag")


@pytest.fixture(scope="module")
def cases(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return control_cases(tmp_path_factory.mktemp("scaffold") / "cases")


# Each family's tiny run: (train(out), checkpoint file name, step to kill at, the curve's non-timing columns).
def _gns(data: Path, cases: Path, **kw: Any) -> tuple[Any, str, int, tuple[str, ...]]:
    from hybridmpm.train.gns.train import train

    def run(out: Path) -> None:
        train(gns_config(data, out, batch=2, steps=12, val_every=4, **kw), progress=False)

    return run, "checkpoint.pt", 8, ("step", "lr", "train_loss", "val_one_step", "val_rollout_mse")


def _grid(data: Path, cases: Path) -> tuple[Any, str, int, tuple[str, ...]]:
    from hybridmpm.train.grid import GridTrainConfig, train_grid

    def run(out: Path) -> None:
        cfg = GridTrainConfig(
            scene="water2d", data=str(data), out=str(out), grid=16, width=4, levels=2, r_t=1, t_in=3, steps=12, batch=2, lr=1e-3, warmup=3,
            unroll=2, density_weight=0.5, val_every=4, val_steps=3, val_trajectories=1, noise=3e-4,
        )  # fmt: skip
        train_grid(cfg, progress=False)

    return run, "checkpoint.pt", 4, ("step", "train_loss", "valid_error", "unroll")


def _control(data: Path, cases: Path) -> tuple[Any, str, int, tuple[str, ...]]:
    from hybridmpm.train.control.train import train_control

    def run(out: Path) -> None:
        kw = dict(steps=12, lr=3e-3, latent_state=8, latent_head=8, valid_fraction=0.25, checkpoint_every=4, prior="sketch_ramp", batch=2)
        train_control("water2d", cases, out, progress=False, **kw)  # type: ignore[arg-type]

    return run, "ckpt.pt", 8, ("step", "loss", "valid")


FAMILIES = {
    "gns-pushforward-ema": lambda d, c: _gns(d, c, pushforward=0.5, pushforward_after=0.25, ema=0.9),
    "gns-unrolled": lambda d, c: _gns(d, c, pushforward=0.0, unroll=2),
    "grid": _grid,
    "control": _control,
}


def _no_control_export(monkeypatch: pytest.MonkeyPatch) -> None:
    # the controller's ONNX export (torch.export) is most of its run's time and not what is compared here
    from hybridmpm.train.control import train as control_train

    monkeypatch.setattr(control_train, "export_control", lambda *a, **k: None)


def _kill_after(monkeypatch: pytest.MonkeyPatch, at: int) -> None:
    save = TrainingLoop.save

    def save_then_die(self: TrainingLoop) -> None:
        save(self)
        if self.step == at:
            raise _Killed

    monkeypatch.setattr(TrainingLoop, "save", save_then_die)


def _interrupted(run: Any, out: Path, name: str, at: int, monkeypatch: pytest.MonkeyPatch, edit: Any = None) -> dict[str, Any]:
    """Run, killed after the checkpoint of step ``at`` (``edit`` applied to that checkpoint), then run again; its final checkpoint."""
    with monkeypatch.context() as m:
        _kill_after(m, at)
        with pytest.raises(_Killed):
            run(out)
    ck = torch.load(out / name, weights_only=False)
    assert ck["step"] == at
    if edit is not None:
        edit(ck)
        torch.save(ck, out / name)
    run(out)
    return torch.load(out / name, weights_only=False)  # type: ignore[no-any-return]


def _same_tensors(a: Any, b: Any) -> bool:
    if isinstance(a, torch.Tensor):
        return isinstance(b, torch.Tensor) and a.dtype == b.dtype and torch.equal(a, b)
    if isinstance(a, dict):
        return isinstance(b, dict) and a.keys() == b.keys() and all(_same_tensors(a[k], b[k]) for k in a)
    if isinstance(a, (list, tuple)):
        return isinstance(b, (list, tuple)) and len(a) == len(b) and all(_same_tensors(x, y) for x, y in zip(a, b))
    return bool(a == b or (isinstance(a, float) and math.isnan(a) and math.isnan(b)))


def _columns(rows: list[dict[str, Any]], keys: tuple[str, ...]) -> list[tuple[Any, ...]]:
    return [tuple(r[k] for k in keys) for r in rows]


@pytest.mark.parametrize("family", list(FAMILIES))
def test_a_run_resumed_from_a_mid_run_checkpoint_ends_where_an_uninterrupted_run_does(
    family: str, data: Path, cases: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    _no_control_export(monkeypatch)
    run, name, at, keys = FAMILIES[family](data, cases)
    run(tmp_path / "whole")
    whole = torch.load(tmp_path / "whole" / name, weights_only=False)
    resumed = _interrupted(run, tmp_path / "resumed", name, at, monkeypatch)
    assert whole["step"] == resumed["step"] == 12
    for key in ("model", "optimizer", "ema"):
        if key in whole:
            assert _same_tensors(whole[key], resumed[key]), key
    assert _same_tensors(whole["rng"], resumed["rng"]) and torch.equal(whole["torch_rng"], resumed["torch_rng"])
    # the curve: the rows before the kill come back from the checkpoint, those after are the uninterrupted run's
    assert _same_tensors(_columns(whole["curve"], keys), _columns(resumed["curve"], keys))
    written = json.loads((tmp_path / "resumed" / CURVE_FILE).read_text())
    assert [r["step"] for r in written] == [r["step"] for r in whole["curve"]]
    assert whole["best"] == resumed["best"] and whole["best_step"] == resumed["best_step"]


@pytest.mark.parametrize("family", ["gns-pushforward-ema", "control"])
def test_a_resume_without_its_random_streams_ends_elsewhere(family: str, data: Path, cases: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    # what the checkpoint carries decides: a numpy stream drawn afresh (and, for the controller's noise, torch's reseeded
    # at the step, as its checkpoints once did) gives other batches after the kill, so other weights
    _no_control_export(monkeypatch)
    run, name, at, _ = FAMILIES[family](data, cases)
    run(tmp_path / "whole")
    whole = torch.load(tmp_path / "whole" / name, weights_only=False)

    def forget_streams(ck: dict[str, Any]) -> None:
        ck["rng"] = np.random.default_rng(1234).bit_generator.state
        del ck["torch_rng"]

    resumed = _interrupted(run, tmp_path / "resumed", name, at, monkeypatch, edit=forget_streams)
    assert resumed["step"] == 12
    assert not _same_tensors(whole["model"], resumed["model"])


# ----------------------------------------------------------------- the parts
@dataclass
class _Settings(RunConfig):
    out: str
    steps: int = setting(10, integer(1))
    batch: int = setting(2, integer(1, 64))
    lr: float = setting(1e-3, number(0, 1, low_open=True))
    width: int = setting(4, integer(1))
    nproc: int = setting(1, processes)


@pytest.mark.parametrize(
    "field,bad", [("steps", 0), ("steps", 2.5), ("steps", True), ("batch", 65), ("lr", 0.0), ("lr", float("nan")), ("lr", "1e-3"), ("nproc", 0)]
)
def test_a_bad_setting_is_refused_naming_its_field(field: str, bad: Any) -> None:
    with pytest.raises(InvalidInputError) as e:
        _Settings(out="x", **{field: bad}).validate()
    assert e.value.field == field and field in str(e.value)
    assert _Settings(out="x").validate().steps == 10


def test_the_families_settings_are_checked_by_field() -> None:
    from hybridmpm.train.control.train import ControlTrainConfig
    from hybridmpm.train.grid import GridTrainConfig

    for cfg, field in (
        (GridTrainConfig(scene="water2d", data="d", out="o", noise=-1.0), "noise"),
        (GridTrainConfig(scene="water2d", data="d", out="o", flip_init=1.0), "flip_init"),
        (GridTrainConfig(scene="water2d", data="d", out="o", warmup=-1), "warmup"),
        (ControlTrainConfig(scene="water2d", data_root="d", out="o", batch=0), "batch"),
        (ControlTrainConfig(scene="water2d", data_root="d", out="o", prior="nonsense"), "prior"),
        (ControlTrainConfig(scene="water2d", data_root="d", out="o", lr=1e-4, lr_final=1e-3), "lr"),
    ):
        with pytest.raises(InvalidInputError) as e:
            cfg.validate()
        assert e.value.field == field


def test_a_run_directory_is_resumed_only_by_the_settings_that_made_it() -> None:
    cfg = _Settings(out="o", steps=10, batch=2, width=4)
    saved = {**cfg.to_dict(), "ranks": 1}
    assert cfg.resume_error(saved, 1, "o") is None
    assert _Settings(out="elsewhere", steps=50, batch=2, width=4).resume_error(saved, 1, "o") is None  # steps and out may change
    err = _Settings(out="o", width=8).resume_error(saved, 1, "o")
    assert err is not None and err.field == "width" and "width = 4" in str(err)
    # the global batch is compared: 2 ranks of 1 resume 1 rank of 2; 2 ranks of 2 do not
    assert _Settings(out="o", batch=1).resume_error(saved, 2, "o") is None
    err = cfg.resume_error(saved, 2, "o")
    assert err is not None and err.field == "batch"
    # a setting added since the run was made counts with its default
    old = {k: v for k, v in saved.items() if k != "width"}
    assert cfg.resume_error(old, 1, "o") is None
    err = _Settings(out="o", width=5).resume_error(old, 1, "o")
    assert err is not None and err.field == "width"


def test_the_curve_is_written_beside_the_checkpoint(tmp_path: Path) -> None:
    curve = ValidationCurve(tmp_path, "log.csv", {"loss": ".3f"})
    curve.record({"step": 0, "loss": math.nan, "score": math.inf})
    curve.record({"step": 5, "loss": 0.12345, "score": 2.5})
    assert json.loads((tmp_path / CURVE_FILE).read_text()) == [{"step": 0, "loss": None, "score": None}, {"step": 5, "loss": 0.12345, "score": 2.5}]
    assert list(csv.reader(open(tmp_path / "log.csv"))) == [["step", "loss", "score"], ["0", "nan", "inf"], ["5", "0.123", "2.5"]]
    # a log begun with fewer columns keeps them; a JSON-lines log holds every row
    (tmp_path / "old").mkdir()
    (tmp_path / "old" / "log.csv").write_text("step,loss\n0,1.0\n")
    ValidationCurve(tmp_path / "old", "log.csv").record({"step": 5, "loss": 0.5, "ranks": 2})
    assert (tmp_path / "old" / "log.csv").read_text().splitlines() == ["step,loss", "0,1.0", "5,0.5"]
    lines = ValidationCurve(tmp_path / "old", "log.jsonl")
    lines.record({"step": 1, "loss": None})
    assert [json.loads(x) for x in (tmp_path / "old" / "log.jsonl").read_text().splitlines()] == [{"step": 1, "loss": None}]


def test_a_checkpoint_that_fails_to_save_leaves_the_last_one_whole(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    net = torch.nn.Linear(3, 2)
    opt = torch.optim.Adam(net.parameters())
    loop = TrainingLoop(tmp_path, _ranks(), Parts(net, opt, np.random.default_rng(0)), steps=4, every=2, desc="t", progress=False)
    loop.step = 2
    loop.save()
    before = (tmp_path / "checkpoint.pt").read_bytes()

    def torn(obj: Any, fh: Any) -> None:
        fh.write(b"half a checkpoint")
        raise OSError("disk full")

    monkeypatch.setattr(loop_module.torch, "save", torn)
    loop.step = 4
    with pytest.raises(OSError):
        loop.save()
    monkeypatch.undo()
    assert (tmp_path / "checkpoint.pt").read_bytes() == before and torch.load(tmp_path / "checkpoint.pt", weights_only=False)["step"] == 2
    assert [p.name for p in tmp_path.iterdir()] == ["checkpoint.pt"]  # no temporary file left
    save_torch({"a": 1}, tmp_path / "x.pt")
    assert torch.load(tmp_path / "x.pt") == {"a": 1}


def _ranks() -> Any:
    from hybridmpm.train.distributed import SINGLE

    return SINGLE


def test_the_loop_sets_the_schedule_counts_steps_and_keeps_the_best(tmp_path: Path) -> None:
    net = torch.nn.Linear(1, 1, bias=False)
    opt = torch.optim.SGD(net.parameters(), lr=1.0)
    seen: list[float] = []
    best: list[int] = []

    def step(k: int) -> float:
        seen.append(opt.param_groups[0]["lr"])
        return float(k)

    scores = {2: 5.0, 4: 3.0, 6: 4.0}
    loop = TrainingLoop(
        tmp_path, _ranks(), Parts(net, opt, np.random.default_rng(0), lr=lambda k: 0.5**k), steps=6, every=2, desc="t", progress=False, score="s"
    )
    loop.run(step, lambda k, loss: {"step": k, "loss": loss, "s": scores[k]}, on_best=best.append)
    assert seen == [0.5**k for k in range(6)]
    assert [r["loss"] for r in loop.curve.rows] == [0.5, 2.5, 4.5]  # the mean loss since the last evaluation
    assert (loop.best, loop.best_step) == (3.0, 4) and best == [2, 4]
    ck = torch.load(tmp_path / "checkpoint.pt", weights_only=False)
    assert ck["step"] == 6 and ck["best_step"] == 4 and len(ck["curve"]) == 3


def test_the_export_metadata_names_the_run() -> None:
    net = torch.nn.Sequential(torch.nn.Linear(3, 4), torch.nn.Linear(4, 2))  # 3·4 + 4 + 4·2 + 2 = 26 parameters
    meta = {"sha256": {"train": "ab" * 32}, "r_p": 0.5}
    got = export_metadata(net, scene="water2d", steps=7, data=meta, train_seconds=1.5)
    assert got == {"scene": "water2d", "steps": 7, "parameters": 26, "data_sha256": "ab" * 32, "r_p": 0.5, "train_seconds": 1.5}
    pooled = export_metadata(net, scene="water2d", steps=7, data=[meta, {}])
    assert pooled["data_sha256"] == ["ab" * 32, None] and pooled["r_p"] == 0.5
    assert export_metadata(net, scene="s", steps=1) == {"scene": "s", "steps": 1, "parameters": 26}
    assert data_sha256({"sha256": "not a table"}) is None
