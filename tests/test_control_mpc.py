"""Sketches a user draws and the classical control front: the new metrics
against brute force and hand cases, the force field of model-predictive
control against PD's law, the cross-entropy method on a known optimum, MPC's
settings and each scene's default method."""

from __future__ import annotations

import math
import subprocess
import sys

import numpy as np
import pytest

from hybridmpm.control import Controller, MpcSettings, Sketch, control_episode, default_method, pd_targets, scene_methods, track_path
from hybridmpm.control.controller import DEFAULT_METHODS
from hybridmpm.control.metrics import lateral_deviation, mass_carried, off_sketch_disturbance, sketch_distance
from hybridmpm.control.mpc import FIELD_SIZE, cem, field_feedback, mpc_plan, pd_field
from hybridmpm.conventions import G
from hybridmpm.errors import InvalidInputError
from hybridmpm.mpm import MpmParams
from hybridmpm.scenes import Scene, lattice
from hybridmpm.sim import MpmSimulator


# ---------------------------------------------------------------- metrics
def test_lateral_deviation_of_a_path_off_the_arrow_by_hand():
    sk = Sketch.arrow([0.2, 0.2], [0.5, 0.6])  # length 0.5, direction (0.6, 0.8)
    u, n = np.array([0.6, 0.8]), np.array([-0.8, 0.6])
    s = np.linspace(0, 0.5, 11)
    h = 0.03 * np.sin(np.pi * s / 0.5)  # a bow of 3 cm at the middle
    path = np.array([0.7, 0.1]) + s[:, None] * u + h[:, None] * n  # started anywhere: an arrow is a displacement
    out = lateral_deviation(path, sk)
    assert out["lateral_max_m"] == pytest.approx(0.03, abs=1e-12)
    assert out["lateral_mean_m"] == pytest.approx(float(h.mean()), abs=1e-12)
    assert out["lateral_max_rel"] == pytest.approx(0.06, abs=1e-12)
    assert lateral_deviation(np.array([0.7, 0.1]) + s[:, None] * u, sk)["lateral_max_m"] < 1e-12
    with pytest.raises(ValueError):
        lateral_deviation(path, Sketch.oval([0.5, 0.5], [0.1, 0.05]))


def test_mass_carried_equals_the_brute_force_sum():
    rng = np.random.default_rng(0)
    start = rng.uniform(0.2, 0.8, (300, 2))
    end = start + rng.normal(0.0, 0.1, (300, 2)) + np.array([0.1, 0.05])
    m = rng.uniform(0.5, 2.0, 300)
    sk = Sketch.arrow([0.1, 0.1], [0.3, 0.2])
    v = np.array([0.2, 0.1])
    brute = sum(m[i] for i in range(300) if (end[i] - start[i]) @ v / (v @ v) >= 0.5) / m.sum()
    assert mass_carried(start, end, m, sk) == pytest.approx(brute, rel=1e-12)
    assert mass_carried(start, start + v, m, sk) == 1.0 and mass_carried(start, start, m, sk) == 0.0


def test_distance_to_a_sketch_by_hand():
    arrow = Sketch.arrow([0.2, 0.2], [0.6, 0.2])
    pts = np.array([[0.4, 0.3], [0.7, 0.2], [0.1, 0.1], [0.5, 0.2]])
    np.testing.assert_allclose(sketch_distance(pts, arrow), [0.1, 0.1, math.sqrt(0.02), 0.0], atol=1e-12)
    oval = Sketch.oval([0.5, 0.5], [0.2, 0.1])
    # inside: 0; on the major axis 0.1 beyond the tip: 0.1 (an outline vertex); on the minor axis 0.05 beyond: 0.05 (a vertex)
    d = sketch_distance(np.array([[0.55, 0.52], [0.8, 0.5], [0.5, 0.65]]), oval)
    np.testing.assert_allclose(d, [0.0, 0.1, 0.05], atol=2e-3)


def test_off_sketch_disturbance_counts_only_fluid_away_from_the_sketch():
    sk = Sketch.oval([0.5, 0.5], [0.1, 0.1])
    start = np.array([[0.5, 0.5], [0.9, 0.5], [0.5, 0.05], [0.62, 0.5]])  # inside, far, far, 2 cm outside
    free = start + 0.01
    end = free.copy()
    end[1] += [0.03, 0.04]  # far particle pushed 5 cm off its free motion
    end[0] += 1.0  # the particle inside the oval may move anywhere
    end[3] += 1.0  # near the sketch (within 0.1 m): not counted
    out = off_sketch_disturbance(start, end, free, sk, radius=0.1)
    assert out["off_sketch_share"] == pytest.approx(0.5)
    assert out["off_sketch_mean_m"] == pytest.approx(0.025)
    assert out["off_sketch_max_m"] == pytest.approx(0.05)
    none = off_sketch_disturbance(start[:1], end[:1], free[:1], sk)
    assert none["off_sketch_share"] == 0.0 and math.isnan(none["off_sketch_mean_m"])


# ---------------------------------------------------------------- the force field and the optimiser
def test_pd_field_is_pd_attraction_with_gravity_fed_forward():
    """The field at PD's point equals the PD controller's law ω²(y − x) − 2ω v − g with ω = 2π/τ, in every quarter."""
    rng = np.random.default_rng(1)
    x, v = rng.uniform(0.3, 0.7, (50, 2)), rng.normal(0, 0.5, (50, 2))
    g = np.array([0.0, -9.8])
    y = pd_targets(x, Sketch.oval([0.6, 0.4], [0.1, 0.05], 0.3))
    frames, dt = 100, 2.5e-3
    omega = 2 * math.pi / (frames * dt)
    theirs = track_path(y[None], omega, dt, gravity=g)
    ours = field_feedback(pd_field(g), y, frames, dt)
    assert pd_field(g).shape == (FIELD_SIZE,)
    for k in (0, 30, 60, 99):
        np.testing.assert_allclose(ours(k, x, v), theirs(k, x, v), rtol=1e-5, atol=1e-4)


def test_the_field_switches_quarter_by_quarter():
    th = np.zeros(FIELD_SIZE)
    th[[0, 4, 8, 12]] = [1.0, 2.0, 3.0, 4.0]  # push x per quarter, in g
    fb = field_feedback(th, np.zeros((3, 2)), 100, 2.5e-3)
    x = np.zeros((3, 2))
    for k, want in ((0, 1.0), (24, 1.0), (25, 2.0), (50, 3.0), (99, 4.0)):
        assert fb(k, x, x)[0, 0] == pytest.approx(want * G)


def test_cem_finds_a_quadratic_optimum_and_never_returns_worse_than_its_start():
    target = np.array([0.7, -0.4, 0.2, 1.1])

    def f(t: np.ndarray) -> float:
        return -float(((t - target) ** 2).sum())

    best, score = cem(f, np.zeros(4), rollouts=400, rounds=10, std=np.ones(4), rng=np.random.default_rng(0))
    np.testing.assert_allclose(best, target, atol=0.05)
    assert score == pytest.approx(f(best))
    start = np.array([0.7, -0.4, 0.2, 1.1])  # already optimal: a bad spread cannot make it worse
    best, score = cem(f, start, rollouts=4, rounds=2, std=np.full(4, 5.0), rng=np.random.default_rng(1))
    assert score == 0.0 and np.array_equal(best, start)


# ---------------------------------------------------------------- the controller
def _blob() -> Scene:
    p = MpmParams(dim=2)
    x = lattice([0.3, 0.1], [0.45, 0.2], 0.5 / 128)
    return Scene("blob", p, x, np.zeros(len(x), np.int32), np.zeros_like(x))


def test_mpc_scores_at_least_pd_on_its_model_and_is_deterministic():
    sim = MpmSimulator(_blob(), threads=1)
    sk = Sketch.oval([0.55, 0.3], [0.1, 0.05])
    s = MpcSettings(rollouts=6, rounds=2, seed=3)
    a = mpc_plan(sim, sk, 40, s)
    pd_only = mpc_plan(sim, sk, 40, MpcSettings(rollouts=1, rounds=1, seed=3))  # the first rollout is PD's field
    np.testing.assert_array_equal(pd_only.theta, pd_field(np.array([0.0, -9.8])))
    assert a.score >= pd_only.score
    b = mpc_plan(sim, sk, 40, s)
    np.testing.assert_array_equal(a.theta, b.theta)
    assert a.centroids.shape == (41, 2)
    ep = control_episode(sim, sk, Controller("mpc", frames=40, mpc=s))
    assert ep.metrics["inside"] > 0.5 and ep.metrics["effort_max_g"] <= 50.0 * (1 + 1e-5)
    assert ep.plan.summary() is not None  # the page draws the model's centroid path


@pytest.mark.parametrize(
    ("kw", "field"),
    [({"rollouts": 0}, "rollouts"), ({"rollouts": 4, "rounds": 5}, "rounds"), ({"effort_weight": -1.0}, "effort_weight"), ({"effort_weight": math.nan}, "effort_weight"),
     ({"rollouts": True}, "rollouts"), ({"seed": -1}, "seed")],
)  # fmt: skip
def test_mpc_settings_refuse_bad_values_naming_the_field(kw, field):
    with pytest.raises(InvalidInputError) as e:
        MpcSettings(**kw)
    assert e.value.field == field and field in str(e.value)


@pytest.mark.parametrize(("kw", "field"), [({"gain": 0.0}, "gain"), ({"cap_g": 0.0}, "cap_g"), ({"cap_g": 51.0}, "cap_g"), ({"mpc": {"rollouts": 4}}, "mpc")])
def test_controller_refuses_bad_front_settings(kw, field):
    with pytest.raises(InvalidInputError) as e:
        Controller("pd", **kw)
    assert e.value.field == field


def test_the_cap_clips_pd_and_the_gain_scales_the_constant_force():
    sk = Sketch.arrow([0.37, 0.15], [0.6, 0.4])
    sim = MpmSimulator(_blob(), threads=1)
    ep = control_episode(sim, sk, Controller("pd", frames=20, settle=0.25, cap_g=5.0))
    assert ep.metrics["effort_max_g"] <= 5.0 + 1e-5
    a = Controller("constant", frames=20).plan(MpmSimulator(_blob(), threads=1), sk).accelerations
    b = Controller("constant", frames=20, gain=1.5).plan(MpmSimulator(_blob(), threads=1), sk).accelerations
    np.testing.assert_allclose(b, 1.5 * a, rtol=1e-6)


def test_each_scene_has_a_default_among_its_methods():
    for scene in ("water2d", "sand2d", "water3d", "sand3d", "no-such-scene"):
        offer = scene_methods(scene)
        assert offer["default"] in offer["methods"] and {"none", "constant", "pd", "mpc"} <= set(offer["methods"])
        assert default_method(scene) == DEFAULT_METHODS.get(scene, "pd")
    assert "diffusion" in scene_methods("water2d")["methods"] and "diffusion" not in scene_methods("no-such-scene")["methods"]
    assert Controller.for_scene("water2d").method == default_method("water2d")


@pytest.mark.parametrize(
    ("args", "field"), [(["--rollouts", "0"], "rollouts"), (["--rollouts", "4", "--rounds", "5"], "rounds"), (["--effort-weight", "-1"], "effort_weight")]
)
def test_cli_refuses_bad_mpc_settings_in_one_line(tmp_path, args, field):
    sketch = tmp_path / "a.json"
    sketch.write_text('{"kind": "arrow", "points": [[0.3, 0.2], [0.55, 0.35]]}')
    r = subprocess.run(
        [sys.executable, "-m", "hybridmpm", "control", "water2d", "--sketch", str(sketch), "--method", "mpc", *args, "--out", str(tmp_path / "o"), "--quiet"],
        capture_output=True, text=True, timeout=120,
    )  # fmt: skip
    assert r.returncode == 2
    lines = [ln for ln in r.stderr.strip().splitlines() if ln]
    assert len(lines) == 1 and field in lines[0] and "Traceback" not in r.stderr
