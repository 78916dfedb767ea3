"""Moving obstacles (docs/obstacles.md, "Moving obstacles"): a paddle moved
through a water tank pushes the water (momentum, the surface ahead of it)
and keeps it out (no particle more than half a cell inside, in every
condition); a keyframed path is followed exactly; an obstacle that
does not move is the static one bit for bit; a state saved mid-motion
continues bit for bit; bad input names the field."""

from __future__ import annotations

import copy
import math
from dataclasses import replace
from typing import Any

import numpy as np
import pytest

from hybridmpm.errors import InvalidInputError
from hybridmpm.mpm import MpmSolver
from hybridmpm.mpm.motion import MAX_KEYFRAMES
from hybridmpm.scenes import SceneSpec
from hybridmpm.scenes.spec import collider_sdf
from hybridmpm.sim import HybridSimulator, MpmSimulator

N_GRID = 64
DX = 1.0 / N_GRID
#: The paddle: a box 0.06 × 0.30 m (3.8 × 19 cells) whose bottom is 0.10 m above the floor.
HALF = [0.03, 0.15]
START = [0.3, 0.25]
#: Water 0.04 .. 0.22 m deep (the paddle dips 0.12 m into it).
TOP = 0.22
SPEED = 0.5  # m/s
DURATION = 0.2  # s: 80 frames of 2.5 ms
G = 9.8


def tank(obstacle: dict[str, Any], velocity: list[float] | None = None) -> SceneSpec:
    block: dict[str, Any] = {"material": "water", "lo": [0.04, 0.04], "hi": [0.96, TOP], "hydrostatic": True}
    if velocity is not None:
        block["velocity"] = velocity
    return SceneSpec.from_dict({"name": "paddle", "dim": 2, "n_grid": N_GRID, "frames": 80, "blocks": [block], "obstacles": [obstacle]})


def paddle(condition: str, *, moving: bool = True) -> dict[str, Any]:
    ob: dict[str, Any] = {"shape": "box", "half_extents": HALF, "condition": condition}
    if moving:
        ob["keyframes"] = [{"t": 0.0, "center": START}, {"t": DURATION, "center": [START[0] + SPEED * DURATION, START[1]]}]
    else:
        ob["center"] = START
    return ob


def run(sim: MpmSimulator | HybridSimulator, steps: int) -> tuple[list[np.ndarray], list[float]]:
    """Positions of the fluid and the deepest particle inside the obstacle
    [cells], by the analytic distance at the obstacle's pose, after each step."""
    c = sim.scene.params.colliders[0]
    out, depth = [], []
    for _ in range(steps):
        fr = sim.advance()
        pos = sim.particles.fluid(fr.positions)
        at = replace(c, center=list(sim.obstacle_centers[0]), keyframes=None)
        depth.append(float(-collider_sdf(at, pos).min()) / DX)
        out.append(pos.copy())
    return out, depth


def surface(pos: np.ndarray, lo: float, hi: float) -> float:
    """The free surface's height [m] over ``lo < x < hi``: the highest particle there."""
    band = pos[(pos[:, 0] > lo) & (pos[:, 0] < hi)]
    return float(band[:, 1].max())


@pytest.fixture(scope="module")
def pushed() -> dict[str, Any]:
    sims = {}
    for name, cond, moving in (("moving", "separate", True), ("still", "separate", False), ("sticky", "sticky", True), ("slip", "slip", True)):
        sim = MpmSimulator(tank(paddle(cond, moving=moving)).build(), threads=1)
        pos, depth = run(sim, 80)
        sims[name] = {"sim": sim, "pos": pos, "depth": depth}
    return sims


def test_the_paddle_pushes_the_water(pushed):
    sim, pos = pushed["moving"]["sim"], pushed["moving"]["pos"][-1]
    still = pushed["still"]["sim"]
    xc = float(sim.obstacle_centers[0][0])
    assert xc == np.float32(START[0] + SPEED * DURATION)
    # momentum [kg·m/s per metre of depth]: at least a piston's, the swept water ρ·h·U·t moving at U
    immersed = TOP - (START[1] - HALF[1])
    piston = 1000.0 * immersed * SPEED * DURATION * SPEED
    px = float((still.solver.masses * sim.velocities[:, 0]).sum())
    px_still = float((still.solver.masses * still.velocities[:, 0]).sum())
    assert px - px_still > piston, (px, px_still, piston)
    # the surface rises ahead of the paddle and falls behind it: a piston wavemaker of depth h raises
    # the water ahead by U·h/√(g·depth) (mass balance of the wave it sends at the shallow-water speed);
    # the paddle is a partial piston (water passes under it), so half of its immersed depth's rise is asked
    rest = float(pushed["moving"]["pos"][0][:, 1].max())
    depth = TOP - 0.04
    rise = 0.5 * SPEED * immersed / math.sqrt(G * depth)
    ahead = surface(pos, xc + HALF[0], xc + HALF[0] + 0.1)
    behind = surface(pos, xc - HALF[0] - 0.1, xc - HALF[0])
    assert ahead > rest + rise, (ahead, rest, rise)
    assert behind < rest, (behind, rest)
    assert ahead - behind > 2 * rise


@pytest.mark.parametrize("name", ["moving", "sticky", "slip", "still"])
def test_the_paddle_keeps_the_water_out(pushed, name):
    # no particle deeper than half a cell inside the paddle at its pose of each frame, moving in every condition
    assert max(pushed[name]["depth"]) <= 0.5, max(pushed[name]["depth"])


@pytest.mark.parametrize("condition", ["sticky", "slip", "separate"])
def test_water_streaming_past_a_static_paddle_stays_out(condition):
    # the static paddle in the moving paddle's relative flow (the water streaming past at -U, Galilean
    # equivalent near the paddle): no particle deeper than half a cell. Without the particle projection
    # (project = false) particles end ~1 cell inside with slip and separate (0.4 with sticky): MPM
    # constrains nodes, not particles
    depths = {}
    for project in (True, False):
        ob = paddle(condition, moving=False)
        ob["center"] = [0.5, START[1]]
        ob["project"] = project
        _, depths[project] = run(MpmSimulator(tank(ob, velocity=[-SPEED, 0.0]).build(), threads=1), 80)
    assert max(depths[True]) <= 0.5, max(depths[True])
    if condition != "sticky":
        assert max(depths[False]) > 0.5, max(depths[False])


def test_a_keyframed_path_is_followed_exactly():
    keys = [
        {"t": 0.0, "center": [0.3, 0.5]},
        {"t": 0.02, "center": [0.35, 0.55]},
        {"t": 0.05, "center": [0.35, 0.55]},
        {"t": 0.07, "center": [0.25, 0.45]},
    ]
    ob = {"shape": "sphere", "radius": 0.05, "keyframes": keys}
    spec = SceneSpec.from_dict(
        {"name": "path", "dim": 2, "n_grid": N_GRID, "blocks": [{"material": "water", "lo": [0.1, 0.1], "hi": [0.6, 0.3]}], "obstacles": [ob]}
    )
    ts = np.asarray([k["t"] for k in keys])
    cs = np.asarray([k["center"] for k in keys])
    for r_t in (1, 3):
        sim = MpmSimulator(spec.build(), r_t=r_t, threads=1)
        for _ in range(35 // r_t):
            fr = sim.advance()
            t = fr.frame_index * sim.dt_frame
            want = np.asarray([np.interp(t, ts, cs[:, d]) for d in range(2)], np.float32)
            assert np.array_equal(sim.solver.collider_positions[0], want), (t, sim.solver.collider_positions[0], want)
        # after the last key it stays at the last key's centre
        assert np.array_equal(sim.solver.collider_positions[0], cs[-1].astype(np.float32))


def test_an_obstacle_that_does_not_move_is_the_static_one_bit_for_bit():
    static = tank(paddle("separate", moving=False))
    still_path = paddle("separate")
    still_path["keyframes"] = [{"t": 0.0, "center": START}, {"t": 0.05, "center": START}]
    runs = [MpmSimulator(static.build(), threads=1), MpmSimulator(tank(still_path).build(), threads=1)]
    runs += [MpmSimulator(static.build(), threads=1), MpmSimulator(static.build(), threads=1)]
    out = []
    for k, sim in enumerate(runs):
        for _ in range(30):
            if k == 2:
                sim.move_obstacle(0, START)  # a move to where it is: velocity 0
            if k == 3:
                sim.move_obstacle(0, START, velocity=[0.0, 0.0])
            sim.advance()
        out.append(sim.fluid_positions)
    for pos in out[1:]:
        assert pos.tobytes() == out[0].tobytes()


def test_a_state_saved_mid_motion_continues_bit_for_bit():
    spec = tank(paddle("separate"))
    a = MpmSimulator(spec.build(), threads=1)
    run(a, 20)
    state = a.state()
    rest, _ = run(a, 15)
    b = MpmSimulator(spec.build(), threads=1)
    b.restore(copy.deepcopy(state))
    assert np.array_equal(b.solver.collider_positions, a.solver.collider_positions) is False  # a moved on; b is at step 20
    again, _ = run(b, 15)
    assert all(x.tobytes() == y.tobytes() for x, y in zip(rest, again))
    assert np.array_equal(b.obstacle_centers, a.obstacle_centers)
    # a user move pending when the state is taken, and the solver's own checkpoint
    static = tank(paddle("separate", moving=False))
    c = MpmSimulator(static.build(), threads=1)
    for k in range(10):
        c.move_obstacle(0, [START[0] + 0.002 * (k + 1), START[1]])
        c.advance()
    c.move_obstacle(0, [0.33, 0.26], velocity=[0.4, 0.1])
    state = c.state()
    raw = MpmSolver.from_checkpoint(c.solver.checkpoint())  # the solver's own checkpoint carries the pose
    fr_c = c.advance()
    d = MpmSimulator(static.build(), threads=1)
    d.restore(copy.deepcopy(state))
    assert d.advance().positions.tobytes() == fr_c.positions.tobytes()
    assert np.array_equal(raw.collider_positions[0], np.float32([START[0] + 0.02, START[1]]))
    raw.move_collider(0, [0.34, 0.26], [0.4, 0.1])  # and a move pending in the solver
    again = MpmSolver.from_checkpoint(raw.checkpoint())
    assert again.collider_moves == raw.collider_moves == [(0, [np.float32(0.34), np.float32(0.26)], [np.float32(0.4), np.float32(0.1)])]
    assert np.array_equal(again.collider_positions, raw.collider_positions)
    # a solver whose colliders never moved writes the checkpoint it wrote before obstacles could move
    assert b"collider_state" not in MpmSimulator(static.build(), threads=1).solver.checkpoint()


def test_the_hybrid_runs_mpm_while_an_obstacle_moves_or_stands_elsewhere():
    # the water2d model and its switching rule; the network's half is the coarse-grid twin (no network needed)
    ob = paddle("separate")
    ob["half_extents"] = [0.04, 0.15]  # 2.6 cells thick on the twin's 32² grid
    ob["keyframes"] = [{"t": 0.1, "center": START}, {"t": 0.15, "center": [0.33, START[1]]}]
    spec = tank(ob)
    spec.name = "water2d"
    sim = HybridSimulator(spec.build(), cheap="mpm-coarse", mpm_threads=1)
    frames = []
    for _ in range(80 // sim.r_t):
        fr = sim.advance()
        frames.append((fr.frame_index * sim.dt_frame, fr.solver))
    moving_or_moved = [s for t, s in frames if t > 0.1 + 1e-9]
    assert moving_or_moved and set(moving_or_moved) == {"mpm"}
    assert "coarse" in [s for t, s in frames if t <= 0.1 + 1e-9]  # the cheap half ran while the paddle stood still
    assert np.array_equal(sim.obstacle_centers[0].astype(np.float32), np.float32([0.33, START[1]]))


def test_scene_files_keep_the_path(tmp_path):
    spec = tank(paddle("slip"))
    for path in (tmp_path / "s.toml", tmp_path / "s.json"):
        back = SceneSpec.load(spec.save(path))
        assert back.to_dict() == spec.to_dict()
        assert back.params.colliders[0].keyframes == spec.params.colliders[0].keyframes
    assert spec.to_dict()["obstacles"][0]["keyframes"][1] == {"t": DURATION, "center": [START[0] + SPEED * DURATION, START[1]]}
    assert spec.on_grid(128).params.colliders[0].keyframes == spec.params.colliders[0].keyframes


BAD_KEYFRAMES = [
    ([{"t": 0.0, "center": START}, {"t": 0.0, "center": START}], "obstacles[0].keyframes[1].t"),
    ([{"t": 0.1, "center": START}, {"t": 0.05, "center": START}], "obstacles[0].keyframes[1].t"),
    ([{"t": float("nan"), "center": START}], "obstacles[0].keyframes[0].t"),
    ([{"t": -1.0, "center": START}], "obstacles[0].keyframes[0].t"),
    ([{"t": "0", "center": START}], "obstacles[0].keyframes[0].t"),
    ([{"t": 0.0, "center": [0.3, 1.5]}], "obstacles[0].keyframes[0].center"),
    ([{"t": 0.0, "center": [0.3, float("inf")]}], "obstacles[0].keyframes[0].center"),
    ([{"t": 0.0, "center": [0.3]}], "obstacles[0].keyframes[0].center"),
    ([{"t": 0.0}], "obstacles[0].keyframes[0].center"),
    ([{"t": 0.0, "center": START, "angle": 3}], "obstacles[0].keyframes[0].angle"),
    ([START], "obstacles[0].keyframes[0]"),
    ([], "obstacles[0].keyframes"),
    ("fast", "obstacles[0].keyframes"),
    ([{"t": k * 1e-3, "center": START} for k in range(MAX_KEYFRAMES + 1)], "obstacles[0].keyframes"),
]


@pytest.mark.parametrize(("keys", "field"), BAD_KEYFRAMES)
def test_bad_keyframes_name_the_field(keys, field):
    ob = paddle("separate")
    ob["keyframes"] = keys
    with pytest.raises(InvalidInputError) as e:
        tank(ob)
    assert e.value.field == field, str(e.value)


def test_a_centre_other_than_the_path_start_names_the_centre():
    ob = paddle("separate")
    ob["center"] = [0.4, 0.25]
    with pytest.raises(InvalidInputError) as e:
        tank(ob)
    assert e.value.field == "obstacles[0].center"


@pytest.mark.parametrize(
    ("args", "field"),
    [
        ((1, START), "index"),
        ((-1, START), "index"),
        ((True, START), "index"),
        ((0, [0.3, float("nan")]), "center"),
        ((0, [0.3, 1.2]), "center"),
        ((0, [0.3]), "center"),
        ((0, "middle"), "center"),
        ((0, START, [1.0]), "velocity"),
        ((0, START, [1.0, float("inf")]), "velocity"),
    ],
)
def test_bad_moves_name_the_field(args, field):
    sim = MpmSimulator(tank(paddle("separate", moving=False)).build(), threads=1)
    with pytest.raises(InvalidInputError) as e:
        sim.move_obstacle(*args)
    assert e.value.field == field, str(e.value)
    path = MpmSimulator(tank(paddle("separate")).build(), threads=1)
    with pytest.raises(InvalidInputError) as e:
        path.move_obstacle(0, START)
    assert e.value.field == "index"  # it follows its path
    with pytest.raises(InvalidInputError) as e:
        sim.solver.move_collider(0, [0.3, 2e3])
    assert e.value.field == "position"


def test_an_obstacle_is_not_moved_faster_than_the_cap():
    """No obstacle moves faster than MAX_OBSTACLE_SPEED (a faster one would ask the CFL rule for more substeps
    than a frame takes): a given velocity, a one-step move and a keyframe leg beyond it are refused by name."""
    from hybridmpm.mpm.motion import MAX_OBSTACLE_SPEED, check_keyframes, check_velocity
    from hybridmpm.sim import make_simulator

    with pytest.raises(InvalidInputError) as e:
        check_velocity("velocity", [MAX_OBSTACLE_SPEED * 1.01, 0.0], 2)
    assert e.value.field == "velocity"
    assert check_velocity("velocity", [MAX_OBSTACLE_SPEED * 0.99, 0.0], 2)[0] > 0
    with pytest.raises(InvalidInputError) as e:
        check_keyframes("obstacles[0].keyframes", [{"t": 0.0, "center": [0.2, 0.5]}, {"t": 0.001, "center": [0.8, 0.5]}], 2)
    assert e.value.field == "obstacles[0].keyframes[1].center"
    sim = make_simulator("water_ramps2d", "mpm", seed=1)
    c = sim.obstacle_centers[0]
    step_s = sim.r_t * sim.dt_frame
    far = c + [min(0.9 - c[0], MAX_OBSTACLE_SPEED * step_s * 1.5), 0.0]
    with pytest.raises(InvalidInputError) as e:
        sim.move_obstacle(0, far.tolist())
    assert e.value.field == "center"
    # at the cap exactly, from the centre the simulator reports, in any direction: accepted (the float32
    # centres' rounding once refused such a drag as "50 m/s ... at most 50 m/s")
    rng = np.random.default_rng(3)
    for _ in range(200):
        d = rng.normal(size=2)
        sim.move_obstacle(0, (c + MAX_OBSTACLE_SPEED * step_s * d / np.linalg.norm(d)).tolist())
    with pytest.raises(InvalidInputError):
        sim.move_obstacle(0, (c + [MAX_OBSTACLE_SPEED * step_s * 1.001, 0.0]).tolist())
