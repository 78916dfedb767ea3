"""Defaults that follow the chart (docs/hybrid.md "Defaults per scene"): the choice rule against brute force, the
shipped choices against their own recorded candidates, and ``hybridmpm simulate SCENE`` running them."""

from __future__ import annotations

import itertools
import json
import math
from pathlib import Path

import numpy as np
import pytest

from hybridmpm.bench.tune import DEFAULT_METRICS, choose_default, default_budget
from hybridmpm.cli import main
from hybridmpm.errors import InvalidInputError
from hybridmpm.models import shipped_default, shipped_models
from hybridmpm.sim import HybridSimulator, MpmSimulator, default_settings, make_simulator
from hybridmpm.trajectory import Trajectory

SHIPPED = [s for s in sorted(shipped_models()) if shipped_default(s)]


def _rows(rng: np.random.Generator, n: int) -> list[dict]:
    rows = [{"key": "mpm_rp", "ms_mean": 1.0, "error_mean": 0.5, "sinkhorn": 0.002, "failures": 0}]
    for i in range(n):
        rows.append(
            {
                "key": f"c{i}",
                "ms_mean": float(rng.uniform(0.1, 1.5)),
                "error_mean": float(rng.uniform(0.3, 0.9)),
                "sinkhorn": float(rng.uniform(0.001, 0.004)),
                "failures": int(rng.random() < 0.2),
            }
        )
    return rows


@pytest.mark.parametrize("seed", range(20))
def test_the_default_is_the_fastest_row_within_budget_on_every_metric_brute_force(seed: int):
    rng = np.random.default_rng(seed)
    rows = _rows(rng, 12)
    budget = float(rng.choice([1.0, 1.15, 1.3]))
    chosen = choose_default(rows, budget)
    base = rows[0]
    ok = [r for r in rows if not r["failures"] and all(r[m] <= budget * base[m] for m in DEFAULT_METRICS)]
    assert chosen["ms_mean"] == min(r["ms_mean"] for r in ok)
    assert chosen in ok and chosen["key"] != "c-none"
    # a row outside the budget on either metric is never chosen, however fast
    for r, m in itertools.product(rows, DEFAULT_METRICS):
        if r[m] > budget * base[m]:
            assert r is not chosen


def test_mpm_at_r_p_is_the_default_when_nothing_else_qualifies_and_bad_budgets_are_refused():
    rows = [{"key": "mpm_rp", "ms_mean": 1.0, "error_mean": 0.5, "sinkhorn": 0.002, "failures": 0}]
    rows.append({"key": "fast_but_wrong", "ms_mean": 0.1, "error_mean": 0.9, "sinkhorn": 0.002, "failures": 0})
    rows.append({"key": "fast_but_broke_off", "ms_mean": 0.1, "error_mean": 0.4, "sinkhorn": 0.001, "failures": 1})
    assert choose_default(rows, 1.15)["key"] == "mpm_rp"
    for bad in (0.9, math.nan, math.inf, "1.2"):
        with pytest.raises(InvalidInputError) as e:
            choose_default(rows, bad)  # type: ignore[arg-type]
        assert e.value.field == "error_budget"
    with pytest.raises(InvalidInputError) as e:
        choose_default(rows[1:], 1.15)
    assert e.value.field == "rows"


def test_every_scene_with_a_network_has_a_shipped_default():
    assert SHIPPED == sorted(shipped_models())


@pytest.mark.parametrize("scene", SHIPPED)
def test_each_shipped_default_is_the_fastest_of_its_own_candidates_within_its_budget(scene: str):
    d = shipped_default(scene)
    assert d["budget"] == default_budget(scene)
    cands = d["candidates"]
    base = next(c for c in cands if c["key"] == "mpm_rp")
    assert base["ratios"]["time"] == pytest.approx(1.0) and base["ratios"]["error_mean"] == pytest.approx(1.0)
    ok = [c for c in cands if not c["failures"] and all(c["ratios"][m] is not None and c["ratios"][m] <= d["budget"] * (1 + 1e-3) for m in d["metrics"])]
    fastest = min(ok, key=lambda c: c["ratios"]["time"])
    assert d["label"] == fastest["label"]
    assert d["ratios_to_mpm_rp"] == fastest["ratios"]
    # the configuration builds the simulator it names
    kind = d["config"]["kind"]
    sim = make_simulator(scene, "default", seed=3, threads=1)
    assert isinstance(sim, {"mpm": MpmSimulator, "hybrid": HybridSimulator}[kind])
    if kind == "mpm" and d["config"].get("n_grid"):
        assert sim.scene.params.resolved_n_grid() == d["config"]["n_grid"]
    assert default_settings(scene)["solver"] == kind


def test_the_default_refuses_settings_of_another_configuration_naming_them(tmp_path: Path, capsys: pytest.CaptureFixture[str]):
    with pytest.raises(InvalidInputError) as e:
        make_simulator("water2d", "default", r_p=0.5)
    assert e.value.field == "r_p"
    with pytest.raises(InvalidInputError) as e:
        make_simulator("water2d", "default", cheap="mpm-coarse")
    assert e.value.field == "cheap"
    assert main(["simulate", "water2d", "--frames", "4", "--audit-tol", "2", "--out", str(tmp_path / "o"), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert "--audit-tol" in err and "--solver hybrid" in err and len(err.strip().splitlines()) == 1
    assert not (tmp_path / "o" / "summary.json").exists()


def test_a_scene_file_without_a_default_runs_plain_mpm_as_given():
    assert default_settings("no_such_scene_has_a_default") == {"solver": "mpm"}


@pytest.mark.parametrize("scene", SHIPPED[:1] + [s for s in SHIPPED if shipped_default(s)["config"]["kind"] == "hybrid"][:1])
def test_simulate_runs_the_shipped_default_and_says_which_cheap_half_ran_and_its_share(scene: str, tmp_path: Path):
    out = tmp_path / scene
    assert main(["simulate", scene, "--seed", "1001", "--frames", "24", "--out", str(out), "--quiet", "--no-render", "--threads", "1"]) == 0
    s = json.loads((out / "summary.json").read_text())
    d = shipped_default(scene)
    assert s["configuration"] == "default" and s["default"]["label"] == d["label"] and s["default"]["config"] == d["config"]
    assert s["solver"] == d["config"]["kind"]
    tr = Trajectory.load(out / "trajectory.npz")
    if s["solver"] == "mpm":
        assert s["cheap_half"] is None and s["cheap_share"] is None
        n = d["config"].get("n_grid")
        assert s["n_grid"] == (n if n else s["n_grid"])
    else:
        tags = tr.extras["solver"][1:]
        assert s["cheap_half"] == (d["config"].get("cheap") or "neural")
        assert s["cheap_share"] == pytest.approx(float((tags != 0).mean()))
