"""Calibrated coarse materials (docs/correction.md "Rung 1"): the ``--calibrated`` switch, the shipped
fits and what their cards record."""

from __future__ import annotations

import math
from pathlib import Path

import pytest

from hybridmpm.bench.methods import methods_for
from hybridmpm.cli import main
from hybridmpm.errors import InvalidInputError
from hybridmpm.metrics import grid_mass_error
from hybridmpm.models.calibrated import calibration, shipped_calibrations
from hybridmpm.mpm.params import CALIBRATION_BOUNDS, with_calibration
from hybridmpm.scenes import make_scene, scene_spec
from hybridmpm.scenes.resolution import full_resolution, on_grid
from hybridmpm.sim import MpmSimulator, make_simulator, rollout, tuned_settings

FITS = shipped_calibrations()


def _fit(name: str) -> dict:
    scene, grid = name.rsplit("_g", 1)
    base = scene_spec(scene, seed=0).params.resolved_n_grid()
    return calibration(scene, int(grid), base, 2)


def _value(d: dict, key: str) -> float:
    node = d
    for part in key.split("."):
        node = node.get(part, {}) if isinstance(node, dict) else {}
    if node == {} and key.startswith("walls.faces."):
        return float(d["walls"]["friction"])  # a face without an override has the walls' friction
    return float(node)  # type: ignore[arg-type]


def test_a_scene_or_grid_without_a_fit_is_refused_naming_the_flag(tmp_path: Path, capsys: pytest.CaptureFixture[str]):
    # the scene's own grid: nothing to calibrate, no silent fallback to the defaults
    assert main(["simulate", "sand2d", "--solver", "mpm", "--calibrated", "--frames", "2", "--out", str(tmp_path), "--quiet", "--no-render"]) == 2
    err = capsys.readouterr().err.strip()
    assert "--calibrated" in err and len(err.splitlines()) == 1
    # a scene without a fit, on its half grid, through the Python API
    with pytest.raises(InvalidInputError, match="--calibrated") as e:
        MpmSimulator(make_scene("water_columns2d", seed=1), n_grid=64, calibrated=True)
    assert e.value.field == "calibrated"
    # a clustered run and a network solver are refused too
    with pytest.raises(InvalidInputError, match="calibrated"):
        make_simulator(make_scene("sand2d", seed=1), "neural", calibrated=True)


def test_calibration_values_are_bounded_and_named():
    params = make_scene("sand2d", seed=1).params
    with pytest.raises(InvalidInputError) as e:
        with_calibration(params, {"sand.friction_angle_deg": 80.0})
    assert e.value.field == "calibrated.sand.friction_angle_deg"
    with pytest.raises(InvalidInputError) as e:
        with_calibration(params, {"sand.density": 1500.0})
    assert e.value.field == "calibrated.sand.density"
    p = with_calibration(params, {"walls.faces.y-.friction": 0.4, "sand.youngs_modulus": 2.0e5})
    assert p.walls.face("y-") == ("separate", 0.4) and p.walls.face("x-")[1] == pytest.approx(params.walls.friction)
    assert p.sand.youngs_modulus == 2.0e5 and params.sand.youngs_modulus != 2.0e5  # a copy


@pytest.mark.skipif(not FITS, reason="no calibrated fit shipped")
@pytest.mark.parametrize("name", FITS)
def test_shipped_fits_load_within_their_bounds_and_differ_from_the_defaults(name: str):
    fit = _fit(name)
    assert fit["name"] == name and fit["params"]
    moved = 0.0
    for key, value in fit["params"].items():
        lo, hi = CALIBRATION_BOUNDS[key]
        assert lo <= value <= hi and fit["bounds"][key] == [lo, hi]
        moved = max(moved, abs(value - fit["defaults"][key]) / (hi - lo))
    assert moved > 0.01  # a fit that stayed at the defaults is no calibration
    assert set(fit["fit_seeds"]).isdisjoint(fit["held_out"]["seeds"])
    # the switch sets exactly those values on the coarse grid; the reference keeps the scene's material
    scene = make_scene(fit["scene"], seed=fit["held_out"]["seeds"][0])
    sim = MpmSimulator(scene, n_grid=fit["n_grid"], calibrated=True)
    got = sim.scene.params.to_dict()
    for key, value in fit["params"].items():
        assert _value(got, key) == pytest.approx(value)
    assert sim.scene.info["calibrated"] == name
    full = full_resolution(sim.scene).params.to_dict()
    assert all(_value(full, k) == pytest.approx(fit["defaults"][k]) for k in fit["params"])
    assert on_grid(scene, fit["n_grid"]).params.to_dict() != got


@pytest.mark.skipif(not FITS, reason="no calibrated fit shipped")
@pytest.mark.parametrize("name", [n for n in FITS if n.startswith("sand2d")])
def test_the_card_holds_for_a_held_out_seed_recomputed(name: str):
    """The held-out errors the card reports, recomputed on its first held-out seed (400 frames, one thread: the
    same bits as the fit's script): the calibrated half grid is as close to full-resolution MPM as recorded."""
    fit = _fit(name)
    seed = fit["held_out"]["seeds"][0]
    rec = fit["held_out"]["per_seed"][str(seed)]
    scene = make_scene(fit["scene"], seed=seed)
    frames = fit["held_out"]["frames"]
    ref = rollout(MpmSimulator(scene, threads=1), frames).fluid_positions
    n0 = scene.params.resolved_n_grid()
    got = {k: float(grid_mass_error(rollout(MpmSimulator(scene, n_grid=fit["n_grid"], threads=1, calibrated=k == "calibrated"), frames).fluid_positions, ref, n0).mean())
           for k in ("plain", "calibrated")}  # fmt: skip
    for k, v in got.items():
        assert math.isclose(v, rec[k], rel_tol=0.02), (k, v, rec[k])
    assert (got["calibrated"] < got["plain"]) == (rec["calibrated"] < rec["plain"])


@pytest.mark.skipif(not FITS, reason="no calibrated fit shipped")
def test_bench_and_tune_see_a_calibrated_member_as_plain_mpm():
    name = FITS[0]
    fit = _fit(name)
    keys = {m.key: m for m in methods_for(fit["scene"], r_cs=(), error_tols=(), variants=False)}
    m = keys[f"mpm_g{fit['n_grid']}_cal"]
    assert m.kind == "mpm" and m.role == "mpm_grid" and m.calibrated and m.r_p == 1.0
    doc = {"config": m.config()}
    assert tuned_settings(doc) == {"solver": "mpm", "r_p": 1.0, "n_grid": fit["n_grid"], "calibrated": True}
    assert "calibrated" not in tuned_settings({"config": {**m.config(), "calibrated": False}})
