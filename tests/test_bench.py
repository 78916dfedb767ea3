"""Benchmarks and tuning: the Pareto front on hand-made points, the
cheapest configuration within a budget on a hand-made table, a tiny bench
that must produce every file with the right columns (and whose reference and
MPM-at-r_p errors are checked against the dataset generator's independent
rollout), resuming, and ``simulate --solver auto``."""

from __future__ import annotations

import csv
import json
import math
import os
from pathlib import Path

import numpy as np
import pytest

from hybridmpm.bench import VALID_SEED0, bench, choose, load_tuned, methods_for, pareto_front, report
from hybridmpm.bench.methods import Method, shipped_default_method
from hybridmpm.bench.report import CHART_METRICS, RESULT_COLUMNS, SWEEP_COLUMNS, front_error_at, mpm_front
from hybridmpm.bench.tune import write_tuned
from hybridmpm.cli import main
from hybridmpm.errors import InvalidInputError
from hybridmpm.metrics import grid_mass_error
from hybridmpm.models import shipped_default
from hybridmpm.scenes import make_scene
from hybridmpm.train.datasets import simulate_trajectory, trajectory_seed

# ------------------------------------------------------------------ Pareto front


def test_pareto_front_on_hand_made_points():
    pts = [
        (1.0, 5.0),  # 0: fastest -> front
        (2.0, 3.0),  # 1: front
        (2.5, 3.0),  # 2: dominated by 1 (slower, same error)
        (3.0, 4.0),  # 3: dominated by 1
        (4.0, 1.0),  # 4: front
        (10.0, 0.0),  # 5: exact -> front
        (11.0, 0.0),  # 6: dominated by 5
        (float("nan"), 0.1),  # 7: never on the front
    ]
    assert pareto_front(pts) == [0, 1, 4, 5]


def test_pareto_front_ties_and_brute_force():
    # identical points do not dominate each other: both stay
    assert pareto_front([(1.0, 1.0), (1.0, 1.0), (2.0, 2.0)]) == [0, 1]
    rng = np.random.default_rng(0)
    pts = [tuple(p) for p in rng.uniform(0, 1, size=(40, 2))]
    front = set(pareto_front(pts))
    for i, (x, y) in enumerate(pts):  # brute force, the definition
        dominated = any(x2 <= x and y2 <= y and (x2, y2) != (x, y) for x2, y2 in pts)
        assert (i in front) == (not dominated)


# ------------------------------------------------------------------ tune


def _row(key: str, err: float, ms: float, **kw: object) -> dict:
    r = {"key": key, "kind": "hybrid", "label": key, "r_p": 0.5714, "r_t": 4, "r_c": 0.8, "model": None, "role": "hybrid", "params": 7362}
    r.update(error_mean=err, error_last=2 * err, ms_mean=ms, ms_median=ms, ms_p95=ms, mpm_share=0.5, failures=0)
    r.update(kw)
    return r


def test_choose_returns_cheapest_within_budget():
    rows = [
        _row("mpm_full", 0.0, 4.0, kind="mpm"),
        _row("mpm_rp", 0.3, 2.0, kind="mpm"),
        _row("hybrid_rc0.8", 0.5, 1.5),
        _row("neural", 0.9, 1.0, kind="neural"),
        _row("broken", 0.1, 0.5, failures=1),  # cheapest and accurate, but a rollout broke off
    ]
    assert choose(rows, 1.0)["key"] == "neural"
    assert choose(rows, 0.6)["key"] == "hybrid_rc0.8"
    assert choose(rows, 0.3)["key"] == "mpm_rp"
    assert choose(rows, 0.29)["key"] == "mpm_full"
    assert choose(rows, 0.0)["key"] == "mpm_full"
    assert choose(rows, 0.99, metric="error_last")["key"] == "mpm_rp"  # last = 2 x mean in _row: hybrid 1.0 > 0.99
    with pytest.raises(InvalidInputError, match="error_budget"):
        choose(rows, -0.1)
    with pytest.raises(InvalidInputError, match="error_budget"):
        choose(rows, float("nan"))
    with pytest.raises(InvalidInputError, match="no configuration"):
        choose([_row("neural", 0.9, 1.0)], 0.5)
    with pytest.raises(InvalidInputError, match="metric"):
        choose(rows, 1.0, metric="rmse")


# ------------------------------------------------------------------ a tiny bench

FRAMES = 32


@pytest.fixture(scope="module")
def tiny(tmp_path_factory: pytest.TempPathFactory) -> dict:
    out = tmp_path_factory.mktemp("bench") / "water2d"
    res = bench("water2d", seeds=[1000], frames=FRAMES, out=out, r_cs=(0.0, 0.8), warmup=8, mpm_threads=1, progress=False)
    return {"out": out, "res": res}


def test_bench_writes_every_file_with_the_right_columns(tiny: dict):
    out: Path = tiny["out"]
    for f in ("results.csv", "threshold_sweep.csv", "pareto.png", "pareto.svg", "error_trajectory.png", "report.md"):
        assert (out / f).is_file() and (out / f).stat().st_size > 0, f
    methods = methods_for("water2d", r_cs=(0.0, 0.8))
    with open(out / "results.csv") as f:
        rd = csv.DictReader(f)
        assert tuple(rd.fieldnames or ()) == RESULT_COLUMNS
        rows = list(rd)
    assert [r["method"] for r in rows] == [m.key for m in methods]  # one row per method x seed
    for r in rows:
        assert r["scene"] == "water2d" and r["seed"] == "1000" and r["frames"] == str(FRAMES)
        assert r["commit"] and r["onnxruntime"] and r["machine"] and r["mpm_threads"] == "1"
        assert float(r["ms_median"]) > 0 and float(r["ms_p95"]) >= float(r["ms_median"])
    with open(out / "threshold_sweep.csv") as f:
        rd = csv.DictReader(f)
        assert tuple(rd.fieldnames or ()) == SWEEP_COLUMNS
        assert [float(r["r_c"]) for r in rd] == [0.0, 0.8]
    report = (out / "report.md").read_text()
    assert "![" in report and "pareto.png" in report and "## Pareto front" in report
    assert "Table 2" in report


def test_the_shipped_default_runs_and_is_judged_on_every_front(tiny: dict):
    """The configuration `hybridmpm simulate water2d` runs is one of the bench's rows, flagged, and the report's verdict
    on each score (on that score's plain-MPM front, or its value over the front's at its time) is what the rows say."""
    key = shipped_default("water2d")["config"]["key"]
    rows = tiny["res"]["rows"]
    flagged = [r for r in rows if r["shipped_default"]]
    assert tiny["res"]["shipped_default"] == key and [r["key"] for r in flagged] == [key]
    d = flagged[0]
    section = (tiny["out"] / "report.md").read_text().split("## The shipped default", 1)[1]
    assert d["label"] in section and f"`hybridmpm simulate water2d` runs **{d['label']}**" in section
    checked = 0
    for m in ("error_mean", *CHART_METRICS):
        if not math.isfinite(d.get(m, math.nan)):
            continue
        line = next(ln for ln in section.splitlines() if ln.startswith(f"| `{m}` |"))
        front = mpm_front(rows, m)
        if d["key"] in {q["key"] for q in front}:
            assert line.endswith("| on it |"), line
        else:
            f = front_error_at(front, d["ms_mean"], m)
            last = line.rstrip(" |").rsplit("|", 1)[1]
            if not math.isfinite(f):  # faster than every plain MPM measured
                assert last.strip() == "faster than every plain MPM", line
            elif f <= 0:  # slower than the full-resolution reference (its error is 0): no ratio to give
                assert "×" not in last, line
            else:
                assert f"({d[m] / f:.2f}×)" in last, line
        checked += 1
    assert checked >= 4  # the long-horizon error, the short-horizon error, Sinkhorn, kinetic energy


@pytest.mark.parametrize(
    ("front", "cell"),
    [(0.02, "0.02 (2.00×)"), (0.0, "0"), (math.nan, "faster than every plain MPM")],
    ids=["ratio", "slower-than-the-reference", "faster-than-every-mpm"],
)
def test_the_default_section_gives_a_ratio_only_over_a_positive_front(front: float, cell: str):
    """The default's cell against the plain-MPM front at its time: a ratio where the front's value is positive, the
    bare 0 where the default is slower than the full-resolution reference (the front's value there is the reference's
    own error, 0), and no number where no plain MPM was as fast (timing noise can put a run in either of the last two)."""
    d = {"key": "hyb", "label": "hybrid", "shipped_default": True, "ms_mean": 2.0, "error_mean": 0.04, "mpm_front": False, "front_error": front}
    lo = {"key": "mpm_rp", "label": "MPM at r_p", "shipped_default": False, "ms_mean": 1.0, "error_mean": 0.05}
    line = next(ln for ln in report.default_section("water2d", [lo, d]) if ln.startswith("| `error_mean` |"))
    assert line == f"| `error_mean` | 0.04 | 0.05 | 0.80 | {cell} |"


def test_a_shipped_default_outside_the_grid_of_methods_is_added(monkeypatch: pytest.MonkeyPatch):
    methods = [Method("mpm_full", "mpm", "MPM full resolution")]
    twin = {"key": "hybrid_twin", "kind": "hybrid", "label": "twin", "r_p": 0.5, "cheap": "mpm-coarse", "safeguard": "error", "rule": {"x": 1}}
    monkeypatch.setattr("hybridmpm.bench.methods.shipped_default", lambda scene: {"config": twin})
    m = shipped_default_method("water2d", methods)
    assert m is methods[-1] and len(methods) == 2
    assert (m.key, m.kind, m.cheap, m.safeguard, m.r_p) == ("hybrid_twin", "hybrid", "mpm-coarse", "error", 0.5)
    assert shipped_default_method("water2d", methods) is m and len(methods) == 2  # found, not added twice
    monkeypatch.setattr("hybridmpm.bench.methods.shipped_default", lambda scene: {})
    assert shipped_default_method("water2d", methods) is None


def test_the_twin_with_its_own_particles_is_benchmarked_as_such():
    """The bench's own-particle twin is the hybrid whose coarse grid carries its own particle set (fewer particles
    than the network's set the other twin carries), not a relabelled copy of the other twin."""
    from hybridmpm.bench.run import BenchConfig, method_simulator
    from hybridmpm.sim.coarse import CoarseMpmHalf, CoarseOwnHalf

    ms = {m.key: m for m in methods_for("water2d", r_cs=(), error_tols=(), variants=False)}
    cfg = BenchConfig("water2d", (1000,), 32, warmup=8).validate()
    own, net = (method_simulator(ms[k], make_scene("water2d", seed=1000), 1000, cfg) for k in ("hybrid_coarse_own", "hybrid_coarse"))
    assert isinstance(own.half, CoarseOwnHalf) and isinstance(net.half, CoarseMpmHalf)
    assert ms["hybrid_coarse_own"].cheap_particles == "grid" and ms["hybrid_coarse"].cheap_particles is None


def test_bench_errors_against_an_independent_reference(tiny: dict):
    """The reference stepped by hand on the solver, and MPM at r_p through the
    dataset generator (other code paths): the bench's errors must match."""
    rows = {r["key"]: r for r in tiny["res"]["rows"]}
    assert rows["mpm_full"]["error_mean"] == 0.0
    solver = make_scene("water2d", seed=1000).make_solver(num_threads=1)
    ref_pos = [solver.positions]
    for _ in range(FRAMES):
        solver.step_frame()
        ref_pos.append(solver.positions)
    ref = {"positions": np.stack(ref_pos)}
    n = solver.num_particles
    cached = np.load(tiny["out"] / "cells" / "ref_seed1000.npz")["positions"]
    np.testing.assert_array_equal(cached, ref["positions"][:, :n])
    low = simulate_trajectory("water2d", 1000, FRAMES, r_p=0.5714, num_threads=1)
    nl = len(low["material"])
    err = grid_mass_error(low["positions"][:, :nl], ref["positions"][:, :n], 128)
    # averaged at the frames every method produces (multiples of the shipped model's r_t = 4)
    assert rows["mpm_rp"]["error_mean"] == pytest.approx(float(err[::4].mean()), rel=1e-6)
    assert rows["mpm_rp"]["error_last"] == pytest.approx(float(err[-1]), rel=1e-6)
    assert 0.02 < rows["mpm_rp"]["error_mean"] < 0.6  # coarser MPM is close, not exact
    # the exact reference is always on the front (nothing has lower error)
    assert rows["mpm_full"]["pareto"]
    # hybrid r_c = 0 is the network with the failure checks on: on this seed and horizon the network
    # does not fail, so it is the same rollout as the network alone
    assert rows["hybrid_rc0.0"]["switches"] == 0
    assert rows["hybrid_rc0.0"]["error_mean"] == pytest.approx(rows["neural"]["error_mean"], rel=1e-6)


def test_bench_resumes_without_rerunning_cells(tiny: dict, monkeypatch: pytest.MonkeyPatch):
    import hybridmpm.bench.run as run

    def boom(*a: object, **k: object) -> None:
        raise AssertionError("a finished cell was rerun")

    monkeypatch.setattr(run, "run_cell", boom)
    monkeypatch.setattr(run, "reference", boom)
    res = bench("water2d", seeds=[1000], frames=FRAMES, out=tiny["out"], r_cs=(0.0, 0.8), warmup=8, mpm_threads=1, progress=False)
    assert [r["key"] for r in res["rows"]] == [r["key"] for r in tiny["res"]["rows"]]
    with pytest.raises(InvalidInputError, match="out"):
        bench("water2d", seeds=[1000], frames=FRAMES + 4, out=tiny["out"], r_cs=(0.0, 0.8), warmup=8, mpm_threads=1, progress=False)


def test_bench_recomputes_cells_made_with_another_model(tiny: dict, tmp_path: Path, monkeypatch: pytest.MonkeyPatch):
    """A finished cell is reused only if it was made with the same model file:
    after a model is re-shipped (here: the neural cell records another hash,
    the hybrid cell predates the hash), those cells rerun and the MPM cells
    are reused."""
    import shutil

    import hybridmpm.bench.run as run

    out = tmp_path / "water2d"
    shutil.copytree(tiny["out"], out)
    neural = out / "cells" / "neural_seed1000.json"
    cell = json.loads(neural.read_text())
    assert cell["model_sha256"] == run.model_digest(next(m for m in methods_for("water2d") if m.key == "neural"))
    neural.write_text(json.dumps({**cell, "model_sha256": "0" * 64}))
    hybrid = out / "cells" / "hybrid_rc0.8_seed1000.json"
    hybrid.write_text(json.dumps({k: v for k, v in json.loads(hybrid.read_text()).items() if k != "model_sha256"}))
    rerun: list[str] = []
    real = run.run_cell

    def spy(m, *a, **k):
        rerun.append(m.key)
        return real(m, *a, **k)

    monkeypatch.setattr(run, "run_cell", spy)
    bench("water2d", seeds=[1000], frames=FRAMES, out=out, r_cs=(0.0, 0.8), warmup=8, mpm_threads=1, progress=False)
    assert sorted(rerun) == ["hybrid_rc0.8", "neural"]
    assert json.loads(neural.read_text())["model_sha256"] == cell["model_sha256"]


def test_networks_alone_run_on_their_own_thread_setting(tiny: dict, tmp_path: Path, monkeypatch: pytest.MonkeyPatch):
    """The networks run alone get ``nn_alone_threads`` onnxruntime threads
    (all cores by default: MPM is idle then), the hybrid ``nn_threads``;
    results.csv records each row's; a run made before the setting resumes
    as one whose networks ran on the hybrid's threads."""
    import shutil

    import hybridmpm.bench.run as run
    from hybridmpm.scenes import make_scene

    cfg = run.BenchConfig("water2d", (1000,), FRAMES, 8, 1, nn_threads=1, nn_alone_threads=2).validate()
    kinds = {m.kind: m for m in methods_for("water2d", r_cs=(0.8,), variants=False)}
    scene = make_scene("water2d", seed=1000)
    assert run.method_simulator(kinds["neural"], scene, 1000, cfg).model.threads == 2
    assert run.method_simulator(kinds["hybrid"], scene, 1000, cfg).model.threads == 1
    with open(tiny["out"] / "results.csv") as f:
        rows = list(csv.DictReader(f))
    assert {r["nn_threads"] for r in rows if r["kind"] == "neural"} == {"0"}
    assert {r["nn_threads"] for r in rows if r["kind"] == "hybrid"} == {"1"}
    assert "onnxruntime threads 1 in the hybrid, all for the networks alone" in (tiny["out"] / "report.md").read_text()
    with pytest.raises(InvalidInputError, match="nn_alone_threads"):
        run.BenchConfig("water2d", (1000,), FRAMES, nn_alone_threads=-1).validate()
    # an older run's bench.json has no nn_alone_threads: its networks alone ran on nn_threads (1)
    out = tmp_path / "water2d"
    shutil.copytree(tiny["out"], out)
    meta = json.loads((out / "bench.json").read_text())
    del meta["settings"]["nn_alone_threads"]
    (out / "bench.json").write_text(json.dumps(meta))

    def boom(*a: object, **k: object) -> None:
        raise AssertionError("a finished cell was rerun")

    monkeypatch.setattr(run, "run_cell", boom)
    monkeypatch.setattr(run, "reference", boom)
    bench("water2d", seeds=[1000], frames=FRAMES, out=out, r_cs=(0.0, 0.8), warmup=8, mpm_threads=1, nn_alone_threads=1, progress=False)
    assert json.loads((out / "bench.json").read_text())["settings"]["nn_alone_threads"] == 1
    with pytest.raises(InvalidInputError, match="nn_alone_threads"):  # the default (all cores) is another setting
        bench("water2d", seeds=[1000], frames=FRAMES, out=out, r_cs=(0.0, 0.8), warmup=8, mpm_threads=1, progress=False)


def test_bench_rejects_bad_parameters(tmp_path: Path):
    with pytest.raises(InvalidInputError, match="r_c"):
        bench("water2d", seeds=[1000], frames=FRAMES, out=tmp_path, r_cs=(1.5,), progress=False)
    with pytest.raises(InvalidInputError, match="frames"):
        bench("water2d", seeds=[1000], frames=1, out=tmp_path, progress=False)
    with pytest.raises(InvalidInputError, match="warmup"):
        bench("water2d", seeds=[1000], frames=10, warmup=10, out=tmp_path, progress=False)
    with pytest.raises(InvalidInputError, match="seeds"):
        bench("water2d", seeds=[1000, 1000], frames=10, out=tmp_path, progress=False)


def test_held_out_seeds_are_not_dataset_seeds():
    seeds = {trajectory_seed(0, i) for i in range(2000)}
    assert not seeds & set(range(1000, 1100)) and not seeds & set(range(VALID_SEED0, VALID_SEED0 + 100))


# ------------------------------------------------------------------ tuned config and --solver auto


def test_tuned_config_drives_simulate_auto(tiny: dict, tmp_path: Path):
    rows = tiny["res"]["rows"]
    chosen = choose(rows, 0.0)  # only the exact reference qualifies
    assert chosen["key"] == "mpm_full"
    # a budget above MPM at r_p's error picks something at least as fast
    mid = choose(rows, next(r for r in rows if r["key"] == "mpm_rp")["error_mean"])
    assert mid["ms_mean"] <= next(r for r in rows if r["key"] == "mpm_rp")["ms_mean"]
    mpm_rp = next(r for r in rows if r["key"] == "mpm_rp")
    path = tmp_path / "tuned.json"
    write_tuned(path, "water2d", 1.0, "error_mean", mpm_rp, rows, [2000], {"frames": FRAMES})
    doc = load_tuned("water2d", path)
    assert doc["config"]["kind"] == "mpm" and doc["config"]["r_p"] == pytest.approx(0.5714)
    out = tmp_path / "sim"
    assert (
        main(["simulate", "water2d", "--solver", "auto", "--tuned", str(path), "--seed", "1000", "--frames", "4", "--out", str(out), "--no-render", "--quiet"])
        == 0
    )
    summary = json.loads((out / "summary.json").read_text())
    assert summary["solver"] == "mpm" and summary["r_p"] == pytest.approx(0.5714)
    assert summary["particles"] == rows[1]["particles"]  # MPM at r_p: the clustered particles
    hyb = next(r for r in rows if r["key"] == "hybrid_rc0.8")
    write_tuned(path, "water2d", 1.0, "error_mean", hyb, rows, [2000], {"frames": FRAMES})
    assert main(["simulate", "water2d", "--solver", "auto", "--tuned", str(path), "--frames", "8", "--out", str(out), "--no-render", "--quiet"]) == 0
    summary = json.loads((out / "summary.json").read_text())
    assert summary["solver"] == "hybrid" and summary["r_c"] == pytest.approx(0.8) and summary["r_t"] == 4
    assert (summary["safeguard"], summary["audit_tol"]) == ("audit", 1.0)
    # a configuration of the error rule carries its rule and tolerance to --solver auto
    err = next(r for r in rows if r["key"] == "hybrid_err2")
    write_tuned(path, "water2d", 1.0, "error_mean", err, rows, [2000], {"frames": FRAMES})
    assert load_tuned("water2d", path)["config"]["safeguard"] == "error"
    assert main(["simulate", "water2d", "--solver", "auto", "--tuned", str(path), "--frames", "8", "--out", str(out), "--no-render", "--quiet"]) == 0
    summary = json.loads((out / "summary.json").read_text())
    assert (summary["safeguard"], summary["audit_tol"]) == ("error", 2.0)


def test_load_tuned_errors(tmp_path: Path, capsys: pytest.CaptureFixture):
    with pytest.raises(InvalidInputError, match="tuned"):
        load_tuned("water2d", tmp_path / "missing.json")
    bad = tmp_path / "bad.json"
    bad.write_text("{not json")
    with pytest.raises(InvalidInputError, match="tuned"):
        load_tuned("water2d", bad)
    bad.write_text(json.dumps({"scene": "sand2d", "config": {"kind": "mpm"}}))
    with pytest.raises(InvalidInputError, match="sand2d"):
        load_tuned("water2d", bad)
    assert main(["simulate", "water2d", "--solver", "auto", "--tuned", str(tmp_path / "none.json"), "--frames", "2", "--quiet"]) == 2
    assert "hybridmpm tune water2d" in capsys.readouterr().err


def test_tune_cli_writes_the_cheapest_within_budget(tmp_path: Path):
    """End to end on a tiny validation run: the written choice must be the
    cheapest row of the work directory's own table within the budget."""
    out = tmp_path / "tuned.json"
    work = tmp_path / "work"
    rc = main(["tune", "water2d", "--error-budget", "0.3", "--frames", "24", "--warmup", "4", "--seeds", "1", "--r-c", "0.8",
               "--no-variants", "--threads", "1", "--out", str(out), "--work", str(work), "--quiet"])  # fmt: skip
    assert rc == 0
    doc = json.loads(out.read_text())
    with open(work / "results.csv") as f:
        rows = [r for r in csv.DictReader(f)]
    assert all(r["seed"] == str(VALID_SEED0) for r in rows)
    ok = [r for r in rows if float(r["error_mean"]) <= 0.3 and not r["failure"]]
    best = min(ok, key=lambda r: float(r["ms_mean"]))
    assert doc["config"]["key"] == best["method"]
    assert math.isclose(doc["measured"]["ms_mean"], float(best["ms_mean"]))
    assert os.path.basename(str(doc["path"] if "path" in doc else out)) == "tuned.json"


def test_taichi_peer_without_taichi_says_how_to_install(monkeypatch: pytest.MonkeyPatch):
    """The Taichi peer is a benchmark script (benchmarks/taichi_peer.py), not part of the package."""
    import importlib.util
    import sys

    from hybridmpm.errors import HybridMpmError

    path = Path(__file__).resolve().parents[1] / "benchmarks" / "taichi_peer.py"
    spec = importlib.util.spec_from_file_location("taichi_peer_script", path)
    assert spec is not None and spec.loader is not None
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    monkeypatch.setitem(sys.modules, "taichi", None)  # import taichi -> ImportError
    with pytest.raises(HybridMpmError, match=r"hybridmpm\[bench\]"):
        mod.bench_peer("water2d", 1000, 10, 2)
    assert importlib.util.find_spec("hybridmpm.bench.taichi_peer") is None  # out of the wheel


@pytest.mark.parametrize("latent,layers,dim", [(16, 2, 2), (32, 3, 3)])
def test_gnn_flops_match_the_layers_torch_runs(latent: int, layers: int, dim: int):
    """Brute force: count 2·in·out per row over every nn.Linear call of a forward pass."""
    import torch  # the training extra, which the test setup installs

    from hybridmpm.bench.cost import gnn_flops
    from hybridmpm.train.gns.model import GnsConfig, GnsModel

    n = 50
    rng = np.random.default_rng(0)
    cfg = GnsConfig(
        dim=dim, latent=latent, layers=layers, radius=0.05, bounds=[[0.0, 1.0]] * dim, vel_mean=[0.0] * dim, vel_std=[1.0] * dim,
        acc_mean=[0.0] * dim, acc_std=[1.0] * dim,
    )  # fmt: skip
    model = GnsModel(cfg)
    pos = torch.tensor(rng.uniform(0.3, 0.7, size=(cfg.t_in, n, dim)), dtype=torch.float32)
    s = torch.tensor(rng.integers(0, n, 317), dtype=torch.int64)
    r = torch.tensor(rng.integers(0, n, 317), dtype=torch.int64)
    counted = [0]

    def hook(mod: torch.nn.Linear, inp: tuple, out: torch.Tensor) -> None:
        counted[0] += 2 * mod.in_features * mod.out_features * int(np.prod(out.shape[:-1]))

    for m in model.modules():
        if isinstance(m, torch.nn.Linear):
            m.register_forward_hook(hook)
    with torch.no_grad():
        model(pos, torch.full((n,), 5, dtype=torch.int64), s, r)
    assert gnn_flops(latent, layers, dim, n, 317, t_in=cfg.t_in, embedding=cfg.embedding) == counted[0]


def test_shipped_variants_are_what_their_roles_say():
    """Every variant in variants/index.json loads, fits its scene, has the
    resolution its role names (full: r_p = r_t = 1; spatial: r_p < 1, r_t = 1;
    temporal: r_p = 1, r_t > 1) and a row in the variants card."""
    from importlib import resources

    from hybridmpm.bench.methods import neural_role
    from hybridmpm.models import shipped_models, variant_models
    from hybridmpm.neural import GnsRuntime
    from hybridmpm.scenes import make_scene

    card = resources.files("hybridmpm.models").joinpath("variants", "README.md").read_text()
    seen = 0
    for scene in shipped_models():
        for v in variant_models(scene):
            m = GnsRuntime(v["path"])
            sc = make_scene(scene, seed=1000)
            m.check_fits(sc.dim, sc.particle_type(), scene)
            if v["role"] != "size":
                assert neural_role(m.r_p, m.r_t) == v["role"], v["name"]
            assert f"| {scene} | {v['name']} |" in card
            seen += 1
    assert seen >= 5  # a full-resolution network for every 2D domain
    assert {v["role"] for v in variant_models("water2d")} >= {"full", "spatial", "temporal"}


def test_a_broken_off_rollout_is_never_on_the_front():
    from hybridmpm.bench.methods import Method
    from hybridmpm.bench.report import aggregate

    ms = [Method("mpm_full", "mpm", "ref"), Method("neural_x", "neural", "x", role="full"), Method("neural", "neural", "n", role="lowres")]

    def cell(key: str, err: float, ms_: float, failure: str | None = None) -> dict:
        return {"method": key, "seed": 1, "particles": 10, "frames_done": 5 if failure else 10, "failure": failure,
                "error_mean": err, "error_last": err, "ms_mean": ms_, "ms_median": ms_, "ms_p95": ms_, "mpm_share": 0.0, "switches": 0}  # fmt: skip

    # neural_x is fastest and accurate over the frames it did, but it collapsed
    rows = aggregate(ms, [cell("mpm_full", 0.0, 5.0), cell("neural_x", 0.1, 0.5, "collapsed"), cell("neural", 0.5, 1.0)])
    front = {r["key"] for r in rows if r["pareto"]}
    assert front == {"mpm_full", "neural"}
    assert next(r for r in rows if r["key"] == "neural_x")["failures"] == 1


def test_errors_are_averaged_over_the_same_frames():
    from hybridmpm.bench.report import on_common_frames

    every = {"error_mean": 0.0, "series": {"frame": list(range(9)), "error": [0, 1, 2, 3, 4, 5, 6, 7, 8]}}
    strided = {"error_mean": 0.0, "series": {"frame": [0, 4, 8], "error": [0, 4, 8]}}
    assert on_common_frames(every, 4)["error_mean"] == pytest.approx(4.0)  # frames 0, 4, 8
    assert on_common_frames(strided, 4)["error_mean"] == pytest.approx(4.0)
    assert on_common_frames(every, 1)["error_mean"] == pytest.approx(4.0)
    assert on_common_frames({"series": {"frame": [0, 1, 2, 3, 4, 5], "error": [1, 9, 9, 9, 3, 9]}}, 4)["error_mean"] == pytest.approx(2.0)


def test_held_still_freezes_every_frame_after_the_warmup():
    """The trivial model of the benchmarks: frames up to the warm-up as given,
    every later frame equal to the warm-up's (also with a strided frame index,
    as a network rollout records), the input untouched."""
    from hybridmpm.bench.run import held_still

    rng = np.random.default_rng(0)
    pos = rng.random((7, 5, 2))
    frames = np.array([0, 4, 8, 12, 16, 20, 24])
    before = pos.copy()
    still = held_still(pos, frames, 8)
    np.testing.assert_array_equal(pos, before)
    for i, f in enumerate(frames):
        np.testing.assert_array_equal(still[i], pos[i] if f <= 8 else pos[2])
