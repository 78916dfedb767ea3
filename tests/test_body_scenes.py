"""The registered scenes with rigid bodies (``crates2d``, ``crates3d``):
that they are registered and seeded, what they show (the heavy body on the
floor, the light ones afloat in Archimedes' order, no water inside a body),
that the learned simulators refuse them naming ``bodies``, and that the CLI
writes their body arrays."""

from __future__ import annotations

import json

import numpy as np
import pytest

import hybridmpm as hm
from hybridmpm.cli import main
from hybridmpm.models import shipped_default
from hybridmpm.scenes import DOMAINS, PAPER_FRAMES, make_scene
from hybridmpm.scenes.body_scenes import BODY_SCENE_DOMAINS, CRATE_DENSITIES
from hybridmpm.sim import default_settings


def _run(name: str, frames: int) -> tuple[hm.MpmSimulator, hm.Trajectory]:
    scene = make_scene(name)
    sim = hm.make_simulator(scene, "mpm", threads=1)
    return sim, hm.rollout(sim, frames)


@pytest.fixture(scope="module")
def crates2d_run():
    return _run("crates2d", 300)


@pytest.fixture(scope="module")
def crates3d_run():
    return _run("crates3d", 200)


def _deepest_inside_cells(sim: hm.MpmSimulator) -> float:
    """How deep [cells] the deepest water particle lies inside any body (0 when none is inside), at the bodies' pose now."""
    now, dx = sim.bodies, 1.0 / sim.scene.params.resolved_n_grid()
    depth = [-b.sdf(sim.fluid_positions, now.center[k], now.rotation[k]).min() for k, b in enumerate(sim.solver.params.bodies)]
    return max(0.0, max(depth)) / dx


def _floor(sim: hm.MpmSimulator) -> float:
    """rapier's floor [m]: the wall band's inner face (docs/bodies.md "Where a body may be")."""
    p = sim.scene.params
    return p.walls.cells / p.resolved_n_grid()


@pytest.mark.parametrize("name", sorted(BODY_SCENE_DOMAINS))
def test_registered_seeded_and_refused_by_the_learned_simulators(name):
    assert name in DOMAINS and PAPER_FRAMES[name] >= 200
    scene = make_scene(name, 0)
    assert len(scene.params.bodies) >= 2 and set(np.unique(scene.material).tolist()) == {0}
    assert shipped_default(name) == {} and default_settings(name) == {"solver": "mpm"}
    other = make_scene(name, 3)
    assert [b.center for b in other.params.bodies] != [b.center for b in scene.params.bodies]
    assert [b.center for b in make_scene(name, 3).params.bodies] == [b.center for b in other.params.bodies]
    for solver in ("neural", "hybrid"):
        with pytest.raises(hm.InvalidInputError, match="bodies") as e:
            hm.make_simulator(scene, solver)
        assert e.value.field == "bodies"


def test_crates2d_heavy_on_the_floor_light_ones_afloat_in_order(crates2d_run):
    sim, ro = crates2d_run
    assert ro.failure is None and np.isfinite(ro.positions).all()
    dx = 1.0 / 128
    y = sim.bodies.center[:, 1]
    half_h = sim.solver.params.bodies[0].half_extents[1]
    assert list(CRATE_DENSITIES) == [250.0, 500.0, 750.0, 2000.0]
    assert y[3] - half_h - _floor(sim) < dx, y  # 2000 kg/m³: its bottom within a cell of the floor
    assert y[0] > y[2] and y[1] > y[2], y  # 250 and 500 ride above 750
    assert y[2] - half_h > _floor(sim) + 0.2, y  # 750 afloat, far above the floor
    level = sim.scene.info["level"]
    assert all(abs(y[k] - level) < 2 * half_h for k in range(3)), (y, level)  # the three at the surface
    assert _deepest_inside_cells(sim) < 0.25


def test_crates3d_ball_sinks_cube_floats(crates3d_run):
    sim, ro = crates3d_run
    assert ro.failure is None and np.isfinite(ro.positions).all()
    dx = 1.0 / 32
    cube, ball = sim.bodies.center
    radius = sim.solver.params.bodies[1].radius
    start = ro.body_center[0, 1, 1]
    # the ball: from 0.1 m above the surface to the floor (its bottom within 2 cells of it: the last
    # cells of water under it drain slowly on this coarse grid, docs/bodies.md "Scenes")
    assert ball[1] - radius - _floor(sim) < 2 * dx and start - ball[1] > 0.15, (start, ball)
    level = sim.scene.info["level"]
    assert abs(cube[1] - level) < 0.07 and cube[1] > ball[1] + 0.05, (cube, level)  # the cube at the surface, above the ball
    assert _deepest_inside_cells(sim) < 0.25


def test_cli_simulate_writes_the_body_arrays(tmp_path):
    out = tmp_path / "run"
    assert main(["simulate", "crates2d", "--frames", "20", "--threads", "1", "--out", str(out), "--quiet", "--no-render"]) == 0
    traj = hm.Trajectory.load(out / "trajectory.npz")
    assert traj.body_center.shape == (21, 4, 2) and traj.body_rotation.shape == (21, 4, 2, 2) and traj.body_mass.shape == (4,)
    np.testing.assert_allclose(traj.body_mass, np.array(CRATE_DENSITIES) * 0.12 * 0.08, rtol=1e-6)
    # summary.json: each body as given, its mass, its centre at the first and last frame (the trajectory's)
    summary = json.loads((out / "summary.json").read_text())
    assert [b["density"] for b in summary["bodies"]] == list(CRATE_DENSITIES)
    np.testing.assert_allclose([b["mass"] for b in summary["bodies"]], traj.body_mass)
    np.testing.assert_array_equal([b["center_start"] for b in summary["bodies"]], traj.body_center[0])
    np.testing.assert_array_equal([b["center_end"] for b in summary["bodies"]], traj.body_center[-1])
