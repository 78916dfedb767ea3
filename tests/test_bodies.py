"""Rigid bodies from Python (docs/bodies.md): scene files, the simulator's
bodies, checkpoints, trajectories and bad input.

The physics is checked against Archimedes' principle in the order it
predicts (a body denser than water sinks to the floor; of two lighter ones,
the lighter rides higher), the checkpoints against an uninterrupted run (the
same bits), and the trajectory's masses against density × area."""

from __future__ import annotations

import types

import numpy as np
import pytest

from hybridmpm.errors import CheckpointError, InvalidInputError
from hybridmpm.mpm.bodies import MAX_BODIES, Body
from hybridmpm.scenes.spec import SceneSpec
from hybridmpm.sim import MpmSimulator, rollout
from hybridmpm.trajectory import Trajectory

BOX = {"shape": "box", "center": [0.5, 0.35], "half_extents": [0.06, 0.04], "density": 500.0}


def tank(bodies: list[dict], *, n_grid: int = 64, top: float = 0.35, width: tuple[float, float] = (0.05, 0.95)) -> dict:
    """A water tank scene dict with ``bodies``."""
    return {
        "name": "tank",
        "dim": 2,
        "n_grid": n_grid,
        "blocks": [{"material": "water", "lo": [width[0], 0.05], "hi": [width[1], top]}],
        "bodies": bodies,
    }


def small_sim(threads: int = 1, **kw: object) -> MpmSimulator:
    """A narrow tank (about 1,200 particles) with a box at the surface and a circle above it."""
    bodies = [dict(BOX), {"shape": "circle", "center": [0.5, 0.55], "radius": 0.04, "density": 300.0, "angular_velocity": 2.0}]
    return MpmSimulator(SceneSpec.from_dict(tank(bodies, top=0.3, width=(0.3, 0.7))).build(), threads=threads, **kw)


def body_bits(sim: MpmSimulator) -> np.ndarray:
    return np.asarray(sim.solver._core.bodies()["state"])


def test_scene_file_builds_bodies_and_no_particle_inside(tmp_path):
    text = """
name = "two"
dim = 2
n_grid = 64
[[blocks]]
material = "water"
lo = [0.05, 0.05]
hi = [0.95, 0.5]
[[bodies]]
shape = "box"
center = [0.3, 0.3]
half_extents = [0.08, 0.05]
angle_deg = 30.0
density = 400.0
velocity = [0.1, 0.0]
friction = 0.2
[[bodies]]
shape = "circle"
center = [0.7, 0.3]
radius = 0.06
mass = 3.0
"""
    path = tmp_path / "two.toml"
    path.write_text(text)
    spec = SceneSpec.load(path)
    scene = spec.build()
    assert [b.shape for b in scene.bodies] == ["box", "circle"]
    for b in scene.bodies:
        assert (b.sdf(scene.positions) >= 0).all()
    assert scene.info["dropped_particles"][0]["obstacles"] > 0  # counted with the obstacles
    sim = MpmSimulator(scene, threads=1)
    view = sim.bodies
    assert len(view) == 2 and view.center.dtype == np.float64
    np.testing.assert_allclose(view.mass, [400.0 * 0.16 * 0.10, 3.0], rtol=1e-6)
    c, s = np.cos(np.radians(30.0)), np.sin(np.radians(30.0))
    np.testing.assert_allclose(view.rotation[0], [[c, -s], [s, c]], atol=1e-6)
    np.testing.assert_allclose(view.velocity[0], [0.1, 0.0], atol=1e-7)
    with pytest.raises(ValueError):
        view.center[0, 0] = 1.0  # read-only
    # written back and read again: the same bodies
    again = SceneSpec.from_dict(spec.to_dict())
    assert again.params.bodies == spec.params.bodies


def test_heavy_sinks_light_floats_higher_and_trajectory_arrays(tmp_path):
    # the dense box starts under water, the light ones at the surface (0.25 m)
    bodies = [dict(BOX, center=[0.2, 0.12], density=2000.0), dict(BOX, center=[0.5, 0.25], density=250.0), dict(BOX, center=[0.8, 0.25], density=750.0)]
    sim = MpmSimulator(SceneSpec.from_dict(tank(bodies, top=0.25)).build(), threads=1)
    ro = rollout(sim, 120)
    assert ro.failure is None
    y = sim.bodies.center[:, 1]
    dx = 1 / 64
    assert y[0] - 0.04 < 3 * dx + dx, y  # the dense box on the floor (rapier's: the 3-cell wall band's face), within a cell
    assert y[1] > y[2] + 0.02 > y[0], y  # 250 kg/m³ rides higher than 750 kg/m³ (Archimedes: 4 cm apart)
    assert (np.abs(sim.bodies.force[:, 1]) > 0).all()  # the fluid pushes every body
    # the trajectory's body arrays: shapes, dtypes, units
    path = ro.save(tmp_path / "trajectory.npz")
    with np.load(path) as f:
        t = f["positions"].shape[0]
        assert f["body_center"].shape == (t, 3, 2) and f["body_center"].dtype == np.float64
        assert f["body_rotation"].shape == (t, 3, 2, 2) and f["body_rotation"].dtype == np.float64
        assert f["body_mass"].shape == (3,) and f["body_mass"].dtype == np.float64
        np.testing.assert_allclose(f["body_mass"], np.array([2000.0, 250.0, 750.0]) * 0.12 * 0.08, rtol=1e-6)  # kg per metre of depth
        np.testing.assert_allclose(f["body_center"][0], [[0.2, 0.12], [0.5, 0.25], [0.8, 0.25]], atol=1e-7)
        np.testing.assert_allclose(f["body_center"][-1], sim.bodies.center)
    back = Trajectory.load(path)
    assert back.body_center.shape == (t, 3, 2) and np.array_equal(back.body_mass, ro.body_mass)


def test_checkpoint_restore_continues_bit_for_bit():
    a = small_sim()
    rollout(a, 15)
    state = a.state()
    force, torque = a.bodies.force.copy(), a.bodies.torque.copy()
    rollout(a, 15)
    b = small_sim()  # a fresh simulator of the same scene
    b.restore(state)
    # the bodies restored are the checkpoint's, as a solver made from it holds them
    held = type(b.solver).from_checkpoint(state["solver"]).bodies
    for key in ("center", "rotation", "velocity", "angular_velocity", "mass"):
        assert np.array_equal(getattr(b.bodies, key), getattr(held, key)), key
    # the fluid's force on each body over the frame before the checkpoint comes back with it (restore and from_checkpoint)
    assert np.abs(force).max() > 0 and np.array_equal(b.bodies.force, force) and np.array_equal(b.bodies.torque, torque)
    fresh = type(b.solver).from_checkpoint(a.solver.checkpoint())
    assert np.array_equal(fresh.bodies.force, a.bodies.force) and np.array_equal(fresh.bodies.torque, a.bodies.torque)
    rollout(b, 15)
    assert np.array_equal(a.fluid_positions, b.fluid_positions)
    assert np.array_equal(body_bits(a), body_bits(b))
    assert not np.array_equal(body_bits(a)[:, 7:10], 0)  # the bodies moved


def test_added_body_in_checkpoint_and_old_checkpoint_without_bodies():
    a = small_sim()
    rollout(a, 5)
    a.add_body({"shape": "sphere", "center": [0.6, 0.6], "radius": 0.03, "density": 800.0})
    rollout(a, 5)
    state = a.state()
    rollout(a, 10)
    b = small_sim()  # its scene has two bodies; the state three
    b.restore(state)
    assert len(b.bodies) == 3
    rollout(b, 10)
    assert np.array_equal(body_bits(a), body_bits(b)) and np.array_equal(a.fluid_positions, b.fluid_positions)
    # a scene without bodies: no body key in its checkpoint header, and it restores as before
    plain = MpmSimulator(SceneSpec.from_dict(tank([], top=0.3, width=(0.3, 0.7))).build(), threads=1)
    assert b'"bod' not in plain.solver.checkpoint()[:4096]
    plain.restore(plain.state())


@pytest.mark.parametrize(
    ("key", "value"),
    [
        ("body_state", [[0.0] * 13]),  # one body's state for two bodies
        ("body_state", [[float("nan")] * 13] * 2),
        ("body_force", [[0.0] * 5] * 2),  # 5 lanes, not 6
        ("body_force", [[1e309] * 6] * 2),  # inf
        ("body_force", "much"),
    ],
)
def test_a_checkpoint_with_broken_body_arrays_is_refused_and_nothing_changes(key, value):
    a = small_sim()
    rollout(a, 5)
    blob = a.solver.checkpoint()
    broken = a.solver.with_header(blob, {key: value})
    before = (body_bits(a).copy(), a.bodies.force.copy(), a.fluid_positions.copy())
    with pytest.raises(CheckpointError, match=key.replace("_", " ")):
        a.solver.restore(broken)
    with pytest.raises(CheckpointError, match=key.replace("_", " ")):
        type(a.solver).from_checkpoint(broken)
    after = (body_bits(a), a.bodies.force, a.fluid_positions)
    assert all(np.array_equal(x, y) for x, y in zip(before, after))


def test_one_and_two_threads_same_bits():
    one, two = small_sim(threads=1), small_sim(threads=2)
    rollout(one, 20)
    rollout(two, 20)
    assert np.array_equal(one.fluid_positions, two.fluid_positions)
    assert np.array_equal(body_bits(one), body_bits(two))


def test_add_and_remove_between_frames():
    sim = small_sim()
    rollout(sim, 3)
    i = sim.add_body({"shape": "box", "center": [0.4, 0.7], "half_extents": [0.03, 0.03], "mass": 1.0, "angle_deg": 45.0})
    assert i == 2 and len(sim.bodies) == 3
    assert sim.frame.body_center.shape == (3, 2)
    np.testing.assert_allclose(sim.bodies.mass[2], 1.0, rtol=1e-6)
    rollout(sim, 3)
    y_before = sim.bodies.center[2, 1]
    sim.remove_body(0)
    assert len(sim.bodies) == 2 and sim.bodies.center[1, 1] == y_before  # the later ones move down one
    assert [b.shape for b in sim.solver.params.bodies] == ["circle", "box"]
    ro = rollout(sim, 3)
    assert ro.body_center.shape == (4, 2, 2)
    with pytest.raises(InvalidInputError) as e:
        sim.remove_body(5)
    assert e.value.field == "index"


BAD = [
    ({"density": 0.0}, "bodies[{i}].density"),
    ({"density": -1.0}, "bodies[{i}].density"),
    ({"density": float("nan")}, "bodies[{i}].density"),
    ({"mass": 0.0, "density": None}, "bodies[{i}].mass"),
    ({"half_extents": [0.06, 0.005]}, "bodies[{i}].half_extents"),
    ({"half_extents": [0.0, 0.04]}, "bodies[{i}].half_extents"),
    ({"center": [0.97, 0.5]}, "bodies[{i}].center"),
    ({"center": [0.5, float("nan")]}, "bodies[{i}].center"),
    ({"colour": "red"}, "bodies[{i}].colour"),
    ({"shape": None}, "bodies[{i}].shape"),
    ({"shape": "cone"}, "bodies[{i}].shape"),
    ({"rotation": [[1.0, 1.0], [0.0, 1.0]]}, "bodies[{i}].rotation"),
]


def _bad(change: dict) -> dict:
    return {k: v for k, v in {**BOX, **change}.items() if v is not None}


@pytest.mark.parametrize(("change", "field"), BAD)
def test_bad_body_named_and_nothing_changes(change, field):
    with pytest.raises(InvalidInputError) as e:
        SceneSpec.from_dict(tank([dict(BOX, center=[0.3, 0.35]), _bad(change)]))
    assert e.value.field == field.format(i=1)
    sim = small_sim()
    before = sim.solver.checkpoint()
    with pytest.raises(InvalidInputError) as e:
        sim.add_body(_bad(change))
    assert e.value.field == field.format(i=2)
    assert sim.solver.checkpoint() == before and len(sim.bodies) == 2


def test_more_bodies_than_the_cap():
    grid = [[0.1 + 0.1 * (k % 9), 0.1 + 0.1 * (k // 9)] for k in range(MAX_BODIES + 1)]
    many = [{"shape": "circle", "center": c, "radius": 0.02, "density": 500.0} for c in grid]
    with pytest.raises(InvalidInputError) as e:
        SceneSpec.from_dict(tank(many))
    assert e.value.field == "bodies"
    from hybridmpm.mpm import MpmParams, MpmSolver

    solver = MpmSolver(MpmParams(n_grid=64, bodies=[Body(**b) for b in many[:MAX_BODIES]]))
    with pytest.raises(InvalidInputError) as e:
        solver.add_body(many[-1])
    assert e.value.field == "bodies" and len(solver.bodies) == MAX_BODIES


def test_learned_simulators_and_diffusion_refuse_bodies():
    from hybridmpm.control.controller import Controller
    from hybridmpm.control.sketch import Sketch
    from hybridmpm.sim import HybridSimulator, NeuralSimulator

    scene = SceneSpec.from_dict(tank([dict(BOX)], top=0.3, width=(0.3, 0.7))).build()
    for make in (lambda: NeuralSimulator(scene), lambda: HybridSimulator(scene), lambda: HybridSimulator(scene, cheap="mpm-coarse")):
        with pytest.raises(InvalidInputError) as e:
            make()
        assert e.value.field == "bodies"
    stand_in = types.SimpleNamespace(sample_steps=10, dim=2, needs_free=False)
    ctl = Controller("diffusion", model=stand_in)  # type: ignore[arg-type]
    with pytest.raises(InvalidInputError) as e:
        ctl.plan(MpmSimulator(scene, threads=1), Sketch.arrow([0.4, 0.2], [0.6, 0.2]))
    assert e.value.field == "bodies"


def test_a_pour_seeds_no_particle_inside_a_body():
    from hybridmpm.sim.pour import pour_block

    sim = small_sim()
    rollout(sim, 2)
    sim.add_body({"shape": "box", "center": [0.35, 0.5], "half_extents": [0.02, 0.02], "density": 500.0})
    n0 = sim.solver.num_particles
    n = pour_block(sim, {"material": "water", "lo": [0.31, 0.44], "hi": [0.48, 0.62]})
    new = sim.fluid_positions[n0:n]
    now = sim.bodies
    for k, b in enumerate(sim.solver.params.bodies):
        assert (b.sdf(new, now.center[k], now.rotation[k]) >= 0).all()
    assert len(sim.bodies) == 3  # the pour kept the bodies


def test_3d_bodies_rotate_and_restore_bit_for_bit():
    bodies = [
        {
            "shape": "box",
            "center": [0.5, 0.45, 0.5],
            "half_extents": [0.1, 0.06, 0.08],
            "rotation": [[0, -1, 0], [1, 0, 0], [0, 0, 1]],
            "density": 500.0,
            "angular_velocity": [0, 1, 0],
        },
        {"shape": "sphere", "center": [0.3, 0.6, 0.3], "radius": 0.06, "density": 1500.0},
    ]
    spec = SceneSpec.from_dict(
        {"name": "t3", "dim": 3, "n_grid": 32, "blocks": [{"material": "water", "lo": [0.1, 0.1, 0.1], "hi": [0.9, 0.4, 0.9]}], "bodies": bodies}
    )
    a = MpmSimulator(spec.build(), threads=1)
    np.testing.assert_allclose(a.bodies.rotation[0], [[0, -1, 0], [1, 0, 0], [0, 0, 1]], atol=1e-6)
    ro = rollout(a, 20)
    assert ro.body_center.shape == (21, 2, 3) and ro.body_rotation.shape == (21, 2, 3, 3)
    assert a.bodies.angular_velocity.shape == (2, 3) and a.bodies.torque.shape == (2, 3)
    r = a.bodies.rotation[0]
    np.testing.assert_allclose(r.T @ r, np.eye(3), atol=1e-5)
    state = a.state()
    rollout(a, 10)
    b = MpmSimulator(spec.build(), threads=1)
    b.restore(state)
    rollout(b, 10)
    assert np.array_equal(a.fluid_positions, b.fluid_positions) and np.array_equal(body_bits(a), body_bits(b))
    with pytest.raises(InvalidInputError) as e:
        b.add_body({"shape": "box", "center": [0.5, 0.7, 0.5], "half_extents": [0.05, 0.05, 0.05], "density": 500.0, "angle_deg": 10.0})
    assert e.value.field == "bodies[2].angle_deg"  # 2D only


# ------------------------------------------------------------------ the bodies over a run: one BodyTrack
SQUARE = Body(shape="box", center=[0.5, 0.5], half_extents=[0.05, 0.05], density=500.0)
DISC = Body(shape="circle", center=[0.3, 0.6], radius=0.04, density=300.0)


def _poses(t: int = 3, b: int = 2, d: int = 2) -> tuple[np.ndarray, np.ndarray]:
    """Good poses: ``t`` frames of ``b`` bodies in ``d``-D (centres [T, B, D], identity rotations [T, B, D, D])."""
    return np.full((t, b, d), 0.5), np.broadcast_to(np.eye(d), (t, b, d, d)).copy()


def _nan_at(a: np.ndarray, index: tuple[int, ...]) -> np.ndarray:
    a = a.copy()
    a[index] = np.nan
    return a


BAD_TRACKS = [
    ("a center for 3 bodies", lambda c, r: {"center": np.zeros((3, 3, 2))}, "body_center"),
    ("a center without frames", lambda c, r: {"center": c[0]}, "body_center"),
    ("a center in 4D", lambda c, r: {"center": np.zeros((3, 2, 4))}, "body_center"),
    ("a NaN center", lambda c, r: {"center": _nan_at(c, (1, 0, 1))}, "body_center"),
    ("text for a center", lambda c, r: {"center": np.full((3, 2, 2), "x")}, "body_center"),
    ("a ragged center", lambda c, r: {"center": [[[0.5, 0.5], [0.5]]]}, "body_center"),
    ("no center", lambda c, r: {"center": None}, "body_center"),
    ("4 frames where 3 are stored", lambda c, r: {"center": np.full((4, 2, 2), 0.5), "rotation": np.broadcast_to(np.eye(2), (4, 2, 2, 2))}, "body_center"),
    ("a 3D rotation of 2D poses", lambda c, r: {"rotation": np.broadcast_to(np.eye(3), (3, 2, 3, 3))}, "body_rotation"),
    ("a rotation with one frame less", lambda c, r: {"rotation": r[:2]}, "body_rotation"),
    ("an infinite rotation", lambda c, r: {"rotation": np.where(np.arange(2) == 1, np.inf, r)}, "body_rotation"),
    ("no rotation", lambda c, r: {"rotation": None}, "body_rotation"),
    ("a mass per frame", lambda c, r: {"mass": np.ones((3, 2))}, "body_mass"),
    ("a zero mass", lambda c, r: {"mass": [1.0, 0.0]}, "body_mass"),
    ("a NaN mass", lambda c, r: {"mass": [1.0, np.nan]}, "body_mass"),
    ("no list of bodies", lambda c, r: {"shapes": None}, "bodies"),
]


@pytest.mark.parametrize(("what", "change", "field"), BAD_TRACKS, ids=[b[0] for b in BAD_TRACKS])
def test_a_body_track_is_checked_when_made_and_names_the_field(what, change, field):
    from hybridmpm.mpm.bodies import BodyTrack, check_poses

    center, rotation = _poses()
    given = {"shapes": [SQUARE, DISC], "center": center, "rotation": rotation, "mass": [1.0, 2.0], **change(center, rotation)}
    with pytest.raises(InvalidInputError) as e:
        BodyTrack.make(given["shapes"], given["center"], given["rotation"], given["mass"], t_count=3)
    assert e.value.field == field, (what, e.value)
    assert str(e.value).startswith(field + ":"), str(e.value)
    if field in ("body_center", "body_rotation") and given["shapes"] is not None:  # the old entry point says the same
        with pytest.raises(InvalidInputError) as e:
            check_poses(given["shapes"], given["center"], given["rotation"], 3)
        assert e.value.field == field


def test_a_body_track_holds_its_own_read_only_float64_arrays():
    from hybridmpm.mpm.bodies import BodyTrack, as_body_track, check_poses

    center, rotation = _poses()
    track = BodyTrack.make([SQUARE, DISC], center.astype(np.float32), rotation, [1, 2], t_count=3)
    assert track.shapes == (SQUARE, DISC) and (track.num_frames, track.dim) == (3, 2)
    for a, shape in ((track.center, (3, 2, 2)), (track.rotation, (3, 2, 2, 2)), (track.mass, (2,))):
        assert a is not None and a.dtype == np.float64 and a.shape == shape and not a.flags.writeable
    center[0, 0, 0] = 9.0  # the caller's array is not the track's
    assert track.center[0, 0, 0] == 0.5
    with pytest.raises(ValueError):
        track.center[0, 0, 0] = 1.0
    # the public entry points' rule: a track as it is, loose arrays made into one, nothing without poses or bodies
    assert as_body_track(track, t_count=3) is track
    assert as_body_track([SQUARE, DISC], None, None) is None and as_body_track([], center, rotation) is None and as_body_track(None) is None
    for bad in ({"t_count": 4}, {"center": center}):
        with pytest.raises(InvalidInputError) as e:
            as_body_track(track, **bad)
        assert e.value.field == "body_center"
    c, r = check_poses([SQUARE, DISC], center, rotation, 3)
    assert np.array_equal(c, center) and np.array_equal(r, rotation)


def _run_recorded(sim: MpmSimulator, frames: int, add_after: int | None = None):
    """``rollout(sim, frames)`` and the records of the same frames as a session's recording keeps them
    (:class:`hybridmpm.service.budget.Recording`, the solver's bodies as given), a body added after the
    ``add_after``-th frame when given."""
    from hybridmpm.service.budget import MemoryBudget, Recording
    from hybridmpm.sim.rollout import given_bodies

    recording = Recording(MemoryBudget(1 << 30), 100, sim.r_t)

    def record(fr) -> None:
        given = given_bodies(sim)
        recording.add(fr.frame_index, fr.positions, fr.solver, fr.controlled, None, (given, fr.body_center, fr.body_rotation, fr.body_mass))

    seen: list[int] = []

    def on_frame(fr) -> None:
        record(fr)
        seen.append(fr.frame_index)
        if add_after is not None and len(seen) == add_after:
            sim.add_body({"shape": "box", "center": [0.4, 0.7], "half_extents": [0.03, 0.03], "mass": 1.0})

    record(sim.frame)
    ro = rollout(sim, frames, on_frame=on_frame)
    return ro, recording.last(len(recording))


def test_the_rollout_and_the_session_download_stack_the_bodies_by_one_rule():
    """BodyTrack.stack: the rollout's bodies and a session's recent trajectory (service/routes/trajectory.py) of the
    same frames are the same arrays; a body added mid-run leaves both without bodies, and the frames after it have
    them again."""
    from hybridmpm.mpm.bodies import BodyTrack
    from hybridmpm.service.routes.trajectory import recorded_bodies
    from hybridmpm.sim.rollout import body_frame

    sim = small_sim()
    ro, held = _run_recorded(sim, 4)
    track, served = ro.bodies, recorded_bodies(held)
    assert track is not None and served is not None and len(held) == 5
    assert track.shapes == served.shapes == tuple(sim.solver.params.bodies)
    for got in (track, served):
        assert np.array_equal(got.center, ro.body_center) and np.array_equal(got.rotation, ro.body_rotation) and np.array_equal(got.mass, ro.body_mass)
    assert ro.body_center.shape == (5, 2, 2) and np.array_equal(ro.body_center[-1], sim.bodies.center)
    # the rule itself, on frame records (the rollout's own maker of them)
    frames = [body_frame(sim.frame, sim.solver.params.bodies)] * 2
    assert BodyTrack.stack(frames).center.shape == (2, 2, 2)
    assert BodyTrack.stack([]) is None and BodyTrack.stack([*frames, None]) is None
    other_masses = (frames[0][0], frames[0][1], frames[0][2], frames[0][3] * 2)
    assert BodyTrack.stack([*frames, other_masses]) is None

    ro, held = _run_recorded(sim, 4, add_after=2)  # a body joins after the second frame
    assert ro.bodies is None and ro.body_center is None and ro.body_rotation is None and ro.body_mass is None
    assert recorded_bodies(held) is None
    after = recorded_bodies(held[3:])  # the frames since it joined share their bodies
    assert after is not None and after.center.shape == (2, 3, 2) and np.array_equal(after.center[-1], sim.bodies.center)
    ro, held = _run_recorded(sim, 2)
    assert ro.bodies is not None and ro.bodies.center.shape == (3, 3, 2)
    assert np.array_equal(recorded_bodies(held).center, ro.bodies.center)
