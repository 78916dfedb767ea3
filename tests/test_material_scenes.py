"""The registered scenes that show each solid with water: what each shows
(physics), that the CLI runs them with MPM (no shipped default) and that the
learned simulators refuse them naming the material."""

from __future__ import annotations

import json

import numpy as np
import pytest

import hybridmpm as hm
from hybridmpm.cli import main
from hybridmpm.models import shipped_default
from hybridmpm.scenes import DOMAINS, PAPER_FRAMES, make_scene
from hybridmpm.scenes.material_scenes import SNOWBALL_SPEED, SOLID_SCENE_DOMAINS
from hybridmpm.sim import default_settings

SOLID = {"jelly_dam_break2d": ("elastic", 2), "jelly_dam_break3d": ("elastic", 2), "snowball2d": ("snow", 3), "mud_slump2d": ("viscoplastic", 4)}


def _extent(p: np.ndarray) -> np.ndarray:
    return p.max(0) - p.min(0)


@pytest.mark.parametrize("name", sorted(SOLID_SCENE_DOMAINS))
def test_registered_with_water_and_their_solid_and_no_default(name):
    assert name in DOMAINS and PAPER_FRAMES[name] >= 200
    scene = make_scene(name, 0)
    assert set(np.unique(scene.material).tolist()) == {0, SOLID[name][1]}
    assert shipped_default(name) == {} and default_settings(name) == {"solver": "mpm"}
    assert not np.array_equal(make_scene(name, 3).positions, scene.positions) or len(make_scene(name, 3).positions) != len(scene.positions)
    for solver in ("neural", "hybrid"):
        with pytest.raises(hm.InvalidInputError, match=SOLID[name][0]) as e:
            hm.make_simulator(scene, solver)
        assert e.value.field == "material"


def test_the_jelly_rides_the_dam_break_surge_keeping_its_shape():
    scene = make_scene("jelly_dam_break2d")
    traj = hm.rollout(hm.make_simulator(scene, "mpm"), scene.frames)
    jelly, water = traj.material == 2, traj.material == 0
    p0, p1 = traj.positions[0], traj.positions[-1]
    assert np.isfinite(traj.positions).all()
    # the surge carries it most of the way to the far wall (0.55 m -> beyond 0.8 m)...
    assert p1[jelly, 0].mean() - p0[jelly, 0].mean() > 0.25
    assert p1[water, 0].mean() - p0[water, 0].mean() > 0.3
    # ...as a body: its extents stay within 30 % of the cube's (water spread over the whole floor)
    e0, e1 = _extent(p0[jelly]), _extent(p1[jelly])
    assert np.all(np.abs(e1 / e0 - 1) < 0.3), (e0, e1)
    assert _extent(p1[water])[0] > 4 * _extent(p0[water])[0] * 0.9


def test_the_snowball_hits_the_wall_and_keeps_a_dent():
    scene = make_scene("snowball2d")
    sim = hm.make_simulator(scene, "mpm")
    traj = hm.rollout(sim, 60)
    snow = traj.material == 3
    x_wall = scene.info["x_wall"]
    assert np.allclose(scene.velocities[scene.material == 3], [SNOWBALL_SPEED, 0.0])
    reach = traj.positions[:, snow, 0].max(axis=1)
    assert reach.max() > x_wall - 2.5 / 128  # it reached the wall (a particle within 2.5 cells of its face)...
    assert reach[-1] < reach.max() - 1.0 / 128  # ...and came off it
    # compacted where it hit: the plastic volume ratio J_P fell below 1 - theta_c (snow's compression limit, 2.5e-2)
    j_p = np.asarray(sim.solver.volume_ratio)[: scene.num_particles][snow]
    assert j_p.min() < 1 - 2.5e-2 and np.isfinite(j_p).all()
    # squashed along the throw: narrower in x than the square it was
    e0, e1 = _extent(traj.positions[0][snow]), _extent(traj.positions[-1][snow])
    assert e1[0] < 0.95 * e0[0]


def test_the_mud_slumps_and_slows_while_the_water_moves_on():
    scene = make_scene("mud_slump2d")
    traj = hm.rollout(hm.make_simulator(scene, "mpm"), 320)
    mud = traj.material == 4
    p = traj.positions
    assert _extent(p[-1][mud])[0] > 2.5 * _extent(p[0][mud])[0]  # slumped: twice as wide and more
    assert _extent(p[-1][mud])[1] < 0.5 * _extent(p[0][mud])[1]
    speed = np.linalg.norm(p[-1][mud] - p[-11][mud], axis=1).mean() / (10 * scene.dt_frame)
    early = np.linalg.norm(p[40][mud] - p[30][mud], axis=1).mean() / (10 * scene.dt_frame)
    assert speed < 0.25 * early  # nearly at rest under its yield stress


def test_the_cli_runs_a_material_scene_with_mpm(tmp_path, capsys):
    out = tmp_path / "snow"
    assert main(["simulate", "snowball2d", "--frames", "3", "--out", str(out)]) == 0
    assert "no default was chosen for snowball2d" in capsys.readouterr().out
    traj = np.load(out / "trajectory.npz")
    assert set(np.unique(traj["material"]).tolist()) == {0, 3}
    assert json.loads((out / "summary.json").read_text())["frames"] == 3
    assert main(["simulate", "snowball2d", "--solver", "neural", "--frames", "3", "--out", str(tmp_path / "n"), "--quiet"]) != 0
