"""A moved obstacle's boundary particles (GNS type 3) follow it in every frame
(docs/obstacles.md, "The hybrid"): after a keyframed move and after
``move_obstacle``, in MpmSimulator's and HybridSimulator's frames and in a
session's recorded frames, each obstacle's boundary particles are the scene's
shifted by (current centre − scene centre); an obstacle that stands where the
scene put it keeps them bit for bit, and so does a static scene."""

from __future__ import annotations

import asyncio
import copy
from typing import Any

import numpy as np
import pytest

from hybridmpm.scenes import Scene, SceneSpec, downsample_scene, make_scene
from hybridmpm.scenes.spec import collider_sdf
from hybridmpm.sim import HybridSimulator, MpmSimulator

PADDLE = [0.3, 0.25]
BALL = [0.75, 0.6]
#: float32 rounding of coordinates below 1 m, added once (the scene's particle and the displacement)
ROUNDING = 2e-7


def tank(paddle_keys: list[dict[str, Any]] | None = None, name: str = "tank") -> SceneSpec:
    """A 64² water tank with a box paddle (on ``paddle_keys`` if given) and a sphere that never moves."""
    paddle: dict[str, Any] = {"shape": "box", "half_extents": [0.04, 0.15], "condition": "separate"}
    if paddle_keys:
        paddle["keyframes"] = paddle_keys
    else:
        paddle["center"] = PADDLE
    ball = {"shape": "sphere", "center": BALL, "radius": 0.06}
    block = {"material": "water", "lo": [0.04, 0.04], "hi": [0.96, 0.2], "hydrostatic": True}
    return SceneSpec.from_dict({"name": name, "dim": 2, "n_grid": 64, "frames": 80, "blocks": [block], "obstacles": [paddle, ball]})


def owners(scene: Scene) -> np.ndarray:
    """Which obstacle each boundary particle lies on, found here by the signed distance at the scene's pose."""
    assert scene.boundary_positions is not None
    sdf = np.stack([np.abs(collider_sdf(c, scene.boundary_positions)) for c in scene.params.colliders])
    return np.argmin(sdf, axis=0)


def check_follows(sim: MpmSimulator, positions: np.ndarray) -> None:
    """Each obstacle's boundary particles in ``positions`` [N + B, D] are the scene's moved with it."""
    scene = sim.scene
    assert scene.boundary_positions is not None
    own = owners(scene)
    assert len(np.unique(own)) == len(scene.params.colliders)
    n = sim.particles.num_fluid
    got = positions[n:]
    assert got.dtype == np.float32 and got.shape == scene.boundary_positions.shape
    for i, c in enumerate(scene.params.colliders):
        start = np.asarray(c.keyframes[0].center if c.keyframes else c.center, np.float64)
        shift = sim.obstacle_centers[i] - start
        want = scene.boundary_positions[own == i].astype(np.float64) + shift
        assert np.allclose(got[own == i], want, rtol=0.0, atol=ROUNDING), (i, shift, np.abs(got[own == i] - want).max())
        if np.array_equal(sim.solver.collider_positions[i], start.astype(np.float32)):  # where the scene put it: bit for bit
            assert got[own == i].tobytes() == scene.boundary_positions[own == i].tobytes()


def test_boundary_particles_follow_a_keyframed_obstacle_and_a_move_in_mpm_frames():
    keys = [{"t": 0.0, "center": PADDLE}, {"t": 0.05, "center": [0.4, 0.3]}]
    sim = MpmSimulator(tank(keys).build(), threads=1)
    moved = 0.0
    for _ in range(25):
        fr = sim.advance()
        check_follows(sim, fr.positions)
        moved = max(moved, float(np.abs(sim.obstacle_centers[0] - PADDLE).max()))
    assert moved > 0.09  # the paddle went 0.1 m along its path
    # the sphere was never moved: its particles are the scene's bit for bit
    own, n = owners(sim.scene), sim.particles.num_fluid
    assert fr.positions[n:][own == 1].tobytes() == sim.scene.boundary_positions[own == 1].tobytes()
    assert not np.allclose(fr.positions[n:][own == 0], sim.scene.boundary_positions[own == 0], atol=0.05)
    check_follows(sim, sim.positions)

    still = MpmSimulator(tank().build(), threads=1)
    for k in range(6):
        still.move_obstacle(1, [BALL[0] - 0.01 * (k + 1), BALL[1] + 0.005 * (k + 1)])
        check_follows(still, still.advance().positions)
    assert np.allclose(still.obstacle_centers[1], [BALL[0] - 0.06, BALL[1] + 0.03], atol=1e-6)


def test_a_restored_state_and_an_obstacle_moved_back_carry_their_boundary():
    spec = tank()
    a = MpmSimulator(spec.build(), threads=1)
    for k in range(4):
        a.move_obstacle(0, [PADDLE[0] + 0.01 * (k + 1), PADDLE[1]])
        a.advance()
    state = a.state()
    b = MpmSimulator(spec.build(), threads=1)
    b.restore(copy.deepcopy(state))
    assert b.frame.positions.tobytes() == a.frame.positions.tobytes()
    check_follows(b, b.frame.positions)
    # back where the scene put it: the scene's boundary particles again, bit for bit
    a.move_obstacle(0, PADDLE)
    fr = a.advance()
    n = a.particles.num_fluid
    assert a.obstacle_offsets is None
    assert fr.positions[n:].tobytes() == a.scene.boundary_positions.tobytes()


def test_boundary_particles_follow_obstacles_in_hybrid_frames():
    # the water2d model's r_p and r_t; its cheap half is the coarse-grid twin (no network needed)
    keys = [{"t": 0.1, "center": PADDLE}, {"t": 0.15, "center": [0.34, PADDLE[1]]}]
    sim = HybridSimulator(tank(keys, name="water2d").build(), cheap="mpm-coarse", mpm_threads=1)
    if sim.scene.info.get("r_p", 1.0) < 1.0:
        assert sim.particles.boundary_obstacle is not None
        assert np.array_equal(sim.particles.boundary_obstacle, owners(sim.scene))  # merged particles keep their obstacle
    solvers = []
    for _ in range(80 // sim.r_t):
        fr = sim.advance()
        solvers.append(fr.solver)
        check_follows(sim.mpm, fr.positions)
    assert "coarse" in solvers and solvers[-1] == "mpm"  # the cheap half ran while the paddle stood; MPM once it moved
    assert abs(sim.obstacle_centers[0][0] - 0.34) < 1e-6
    sim.move_obstacle(1, [BALL[0] + 0.01, BALL[1]])
    fr = sim.advance()
    assert fr.solver == "mpm"
    check_follows(sim.mpm, fr.positions)
    check_follows(sim.mpm, sim.positions)


def test_a_static_scene_frames_carry_the_scene_boundary_unchanged():
    scene = make_scene("water_ramps2d", seed=1)
    sim = MpmSimulator(scene, threads=1)
    n = sim.particles.num_fluid
    for _ in range(3):
        fr = sim.advance()
        assert fr.positions[n:].tobytes() == scene.boundary_positions.tobytes()
    assert sim.obstacle_offsets is None
    assert sim.particles.boundary_at(None) is sim.particles.boundary
    assert sim.particles.boundary_at(np.zeros((len(scene.params.colliders), 2))) is sim.particles.boundary


def test_downsampling_keeps_each_boundary_particle_s_obstacle():
    scene = tank().build()
    low = downsample_scene(scene, 0.3).scene
    assert low.boundary_obstacle is not None and low.boundary_positions is not None
    assert len(low.boundary_obstacle) == len(low.boundary_positions) < len(scene.boundary_positions)
    assert np.array_equal(low.boundary_obstacle, owners(low))
    assert np.array_equal(scene.boundary_obstacle, owners(scene))


def test_a_session_records_the_moved_boundary():
    pytest.importorskip("fastapi", reason="the service extra")
    from hybridmpm.service.config import ServiceConfig
    from hybridmpm.service.sessions import SessionManager

    async def go() -> tuple[np.ndarray, np.ndarray, np.ndarray, int]:
        m = SessionManager(ServiceConfig(compute_threads=1, max_sessions=2))
        s = await m.create("water_ramps2d", 2, "mpm", 0.8)  # two ramps: one moved, one not
        core = m.core_of(s)
        c0 = np.asarray(core.sim.obstacle_centers[0])
        await m.move_obstacle(s, 0, (c0 + [0.02, 0.01]).tolist(), None)
        await m.rollout(s, 1)
        ((_, pos, _, _, centers, _),) = await m.recorded(s, 1)
        assert centers is not None and np.array_equal(centers, core.sim.obstacle_centers)
        return pos, core.sim.obstacle_centers[0] - c0, core.sim.scene.boundary_positions, core.sim.particles.num_fluid

    pos, shift, boundary, n = asyncio.run(go())
    own = owners(make_scene("water_ramps2d", seed=2))
    assert 0 < np.sum(own == 0) < len(own)
    assert np.allclose(shift, [0.02, 0.01], atol=1e-6)
    assert np.allclose(pos[n:][own == 0], boundary[own == 0] + shift, rtol=0.0, atol=ROUNDING)
    assert pos[n:][own != 0].tobytes() == boundary[own != 0].tobytes()
