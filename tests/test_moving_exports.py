"""Exports of runs whose obstacles move (docs/mesh.md, docs/usd.md, "Moving
obstacles"): every frame records each obstacle's centre
(``Frame.obstacle_centers``), the rollout and trajectory.npz keep them
(``obstacle_centers`` [T, C, D]), the fluid surfaces end on each obstacle
where it is in that frame, and the USD file samples a moving obstacle's
translation per frame.

The scene: a 64² water tank, a box paddle standing in the water that a
keyframed path carries 0.15 m to the right in 0.1 s (then it stands), and a
sphere above the water that never moves."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from hybridmpm.cli import main
from hybridmpm.cli.export import PARAMS_KEY, params_json, params_of
from hybridmpm.errors import InvalidInputError
from hybridmpm.mpm import MpmParams, SampledSdf
from hybridmpm.render.surface import posed_settings, surface_contours, surface_settings
from hybridmpm.scenes import SceneSpec
from hybridmpm.scenes.obstacles import collider_sdf, obstacle_center, obstacles_at
from hybridmpm.sim import HybridSimulator, MpmSimulator, Rollout, rollout
from hybridmpm.trajectory import Trajectory

START, END = [0.3, 0.24], [0.45, 0.24]
BALL = [0.8, 0.6]
FRAMES = 60
DX = 1 / 64


def tank(**paddle: Any) -> SceneSpec:
    box = {"shape": "box", "half_extents": [0.04, 0.12], "condition": "separate", **paddle}
    if "center" not in box:
        box["keyframes"] = [{"t": 0.0, "center": START}, {"t": 0.1, "center": END}]
    ball = {"shape": "sphere", "center": BALL, "radius": 0.06}
    block = {"material": "water", "lo": [0.04, 0.04], "hi": [0.96, 0.3], "hydrostatic": True}
    return SceneSpec.from_dict({"name": "tank", "dim": 2, "n_grid": 64, "frames": FRAMES, "blocks": [block], "obstacles": [box, ball]})


@pytest.fixture(scope="module")
def run() -> tuple[MpmSimulator, Rollout, list[np.ndarray]]:
    sim = MpmSimulator(tank().build(), threads=1)
    seen = [sim.obstacle_centers.copy()]
    ro = rollout(sim, FRAMES, on_frame=lambda fr: seen.append(sim.obstacle_centers.copy()))
    return sim, ro, seen


def inside(points: np.ndarray, loops: tuple[np.ndarray, ...]) -> np.ndarray:
    """bool [N]: inside the closed outlines ``loops`` (even-odd rule)."""
    x, y = points[:, 0:1], points[:, 1:2]
    odd = np.zeros(len(points), bool)
    for lp in loops:
        a, b = lp[:-1], lp[1:]
        crosses = (a[:, 1] > y) != (b[:, 1] > y)
        with np.errstate(divide="ignore", invalid="ignore"):
            xc = a[:, 0] + (y - a[:, 1]) * (b[:, 0] - a[:, 0]) / (b[:, 1] - a[:, 1])
        odd ^= (np.sum(crosses & (x < xc), axis=1) % 2).astype(bool)
    return odd


def ply_vertices(path: Path | bytes) -> np.ndarray:
    """float32 [V, 3] of a binary PLY (a file or its bytes) as :func:`~hybridmpm.render.surface.write_surface` writes it."""
    data = path if isinstance(path, bytes) else path.read_bytes()
    end = data.index(b"end_header\n") + len(b"end_header\n")
    count = int(next(line for line in data[:end].decode().splitlines() if line.startswith("element vertex")).split()[2])
    return np.frombuffer(data[end:], "<f4", count=3 * count).reshape(count, 3)


# ---------------------------------------------------------------------- recording
def test_every_frame_records_the_centres_and_the_file_keeps_them(run, tmp_path):
    sim, ro, seen = run
    oc = ro.obstacle_centers
    assert oc is not None and oc.dtype == np.float64 and oc.shape == (FRAMES + 1, 2, 2)
    assert np.array_equal(oc, np.stack(seen))  # the simulator's centres after every step
    assert np.allclose(oc[0, 0], START) and np.allclose(oc[-1, 0], END, atol=1e-6)  # the paddle went along its path
    assert np.all(oc[:, 1] == oc[0, 1]) and np.allclose(oc[0, 1], BALL)  # the sphere never moved
    assert sim.frame.obstacle_centers is not None and np.array_equal(sim.frame.obstacle_centers, sim.obstacle_centers)
    back = Trajectory.load(ro.save(tmp_path / "trajectory.npz"))
    assert back.obstacle_centers is not None and back.obstacle_centers.dtype == np.float64
    assert np.array_equal(back.obstacle_centers, oc) and "obstacle_centers" not in back.extras
    # an older file without them loads as before: the obstacles stand where the scene put them
    old = tmp_path / "old.npz"
    np.savez(old, positions=ro.positions, particle_type=ro.particle_type, dt_frame=ro.dt_frame)
    assert Trajectory.load(old).obstacle_centers is None


def test_a_scene_without_obstacles_records_none():
    block = {"material": "water", "lo": [0.1, 0.1], "hi": [0.4, 0.4]}
    spec = SceneSpec.from_dict({"name": "box", "dim": 2, "n_grid": 32, "frames": 2, "blocks": [block]})
    ro = rollout(MpmSimulator(spec.build(), threads=1), 2)
    assert ro.obstacle_centers is None and "obstacle_centers" not in ro.to_arrays()


def test_hybrid_frames_record_the_moved_centres():
    spec = tank(center=START)
    spec.name = "water2d"  # its switching rule; the cheap half is the coarse-grid twin (no network needed)
    sim = HybridSimulator(spec.build(), cheap="mpm-coarse", mpm_threads=1)
    assert sim.frame.obstacle_centers is not None and np.allclose(sim.frame.obstacle_centers, [START, BALL])
    for k in range(3):
        sim.move_obstacle(0, [START[0] + 0.01 * (k + 1), START[1]])
        fr = sim.advance()
        assert fr.obstacle_centers is not None and np.array_equal(fr.obstacle_centers, sim.obstacle_centers)
    assert np.allclose(fr.obstacle_centers[0], [START[0] + 0.03, START[1]], atol=1e-6)


# ---------------------------------------------------------------------- surfaces
def test_the_surface_ends_on_the_paddle_where_it_is(run):
    sim, ro, _ = run
    params, t = sim.scene.params, FRAMES
    assert ro.obstacle_centers is not None
    now = obstacles_at(params.colliders, ro.obstacle_centers[t])
    was = params.colliders[0]
    assert now[1] is params.colliders[1]  # the sphere that never moved: the scene's own
    fluid = ro.fluid_positions[t]
    # the water flowed back into where the paddle stood, and none is inside it now
    refilled = fluid[collider_sdf(was, fluid) < -DX]
    assert len(refilled) >= 20
    assert collider_sdf(now[0], fluid).min() > -DX / 2
    settings = surface_settings(params, ro.particle_type, ro.masses)
    ((posed,),) = [surface_contours(ro.positions[t], ro.particle_type, **posed_settings(settings, ro.obstacle_centers, t))]
    v = np.concatenate(posed.loops)
    assert collider_sdf(now[0], v).min() > -DX / 2  # no vertex half a cell inside the paddle where it is
    assert inside(refilled, posed.loops).mean() > 0.9  # the water where the paddle was is inside the surface (all but the free surface's)
    assert not inside(np.asarray([END]), posed.loops).any()  # the paddle's place is not
    # at the scene's poses the surface is clipped where the paddle was: the water there is left out
    ((stale,),) = [surface_contours(ro.positions[t], ro.particle_type, **settings)]
    assert not inside(refilled, stale.loops).any()


def test_obstacles_at_moves_each_shape_and_refuses_bad_centres():
    rng = np.random.default_rng(0)
    xs = np.linspace(-0.2, 0.2, 9)
    vals = (np.hypot(*np.meshgrid(xs, xs, indexing="ij")) - 0.1).astype(np.float32)
    mesh = SampledSdf(origin=[0.3, 0.3], cell=0.05, values=vals, source={"center": [0.5, 0.5], "path": "x.obj"})
    spec = tank(center=START)
    cols = [*spec.params.colliders, mesh]
    shift = np.array([[0.1, -0.05], [0.0, 0.0], [-0.07, 0.02]])
    moved = obstacles_at(cols, np.stack([obstacle_center(c) for c in cols]) + shift)
    assert moved[1] is cols[1] and moved[0] is not cols[0]
    p = rng.uniform(0.1, 0.9, (200, 2))
    for c, m, s in zip(cols, moved, shift):
        assert np.allclose(collider_sdf(m, p + s), collider_sdf(c, p), atol=1e-9)
        assert np.allclose(obstacle_center(m), obstacle_center(c) + s)
    assert mesh.origin == [0.3, 0.3] and mesh.source == {"center": [0.5, 0.5], "path": "x.obj"}  # copies
    for bad in (np.zeros((2, 2)), np.zeros((3, 3)), np.full((3, 2), np.nan)):
        with pytest.raises(InvalidInputError) as e:
            obstacles_at(cols, bad)
        assert e.value.field == "obstacle_centers"


def test_scene_params_keep_a_mesh_obstacles_centre():
    xs = np.linspace(-0.2, 0.2, 9)
    vals = (np.hypot(*np.meshgrid(xs, xs, indexing="ij")) - 0.1).astype(np.float32)
    mesh = SampledSdf(origin=[0.3, 0.3], cell=0.05, values=vals, source={"center": [0.5, 0.5], "path": "x.obj"})
    raw = params_json(MpmParams(dim=2, n_grid=64, colliders=[mesh]))
    traj = Trajectory(np.zeros((1, 1, 2)) + 0.5, np.array([5]), 2.5e-3, extras={PARAMS_KEY: raw})
    params, _ = params_of(traj)
    assert np.array_equal(obstacle_center(params.colliders[0]), [0.5, 0.5])
    assert json.loads(str(raw))["colliders"][0]["scene_center"] == [0.5, 0.5]


# ---------------------------------------------------------------------- files
def test_simulate_and_export_write_the_surfaces_and_usd_at_each_frames_poses(tmp_path):
    pxr = pytest.importorskip("pxr")
    from pxr import Usd, UsdGeom

    assert pxr
    scene = tank().save(tmp_path / "tank.toml")
    out = tmp_path / "run"
    argv = ["simulate", str(scene), "--solver", "mpm", "--frames", str(FRAMES), "--out", str(out), "--quiet", "--no-render", "--threads", "1"]
    assert main([*argv, "--export", "mesh", "usd"]) == 0
    traj = Trajectory.load(out / "trajectory.npz")
    oc = traj.obstacle_centers
    assert oc is not None and oc.shape == (FRAMES + 1, 2, 2)
    params = SceneSpec.load(scene).params
    was, now = params.colliders[0], obstacles_at(params.colliders, oc[FRAMES])[0]
    v = ply_vertices(out / "export" / f"water_{FRAMES:05d}.ply")[:, :2].astype(np.float64)
    assert collider_sdf(now, v).min() > -DX / 2  # the surface ends on the paddle where it is
    assert collider_sdf(was, v).min() < -DX  # and crosses the water where it was
    # hybridmpm export of the saved file: the same surfaces (poses from the file, scene from its scene_params)
    again = tmp_path / "again"
    assert main(["export", str(out / "trajectory.npz"), "--mesh", "--usd", "--out", str(again), "--quiet"]) == 0
    for f in sorted((out / "export").glob("water_*.ply")):
        assert (again / f.name).read_bytes() == f.read_bytes()
    for path in (out / "export" / "run.usd", again / "run.usd"):
        stage = Usd.Stage.Open(str(path))
        paddle = UsdGeom.Xformable(stage.GetPrimAtPath("/Run/Obstacles/obstacle_0"))
        ops = paddle.GetOrderedXformOps()
        assert [op.GetOpType() for op in ops] == [UsdGeom.XformOp.TypeTranslate, UsdGeom.XformOp.TypeTransform]
        assert ops[0].GetTimeSamples() == list(range(FRAMES + 1))
        got = np.array([list(ops[0].Get(t)) for t in range(FRAMES + 1)])
        assert np.array_equal(got[:, :2], oc[:, 0]) and not got[:, 2].any()
        # the box's corner follows: local (1, 1, 0) lands on the paddle's corner in every frame
        for t in (0, 30, FRAMES):
            m = np.array(paddle.ComputeLocalToWorldTransform(t))
            corner = np.array([1.0, 1.0, 0.0, 1.0]) @ m
            assert np.allclose(corner[:2], oc[t, 0] + [0.04, 0.12], atol=1e-9)
        ball = UsdGeom.Xformable(stage.GetPrimAtPath("/Run/Obstacles/obstacle_1"))
        (op,) = ball.GetOrderedXformOps()
        assert op.GetTimeSamples() == [] and np.allclose(list(op.Get()), [*BALL, 0.0])  # written once, as for a static scene


def test_a_static_scene_writes_its_obstacles_once(tmp_path):
    pytest.importorskip("pxr")
    from pxr import Usd, UsdGeom

    scene = tank(center=START).save(tmp_path / "still.toml")
    out = tmp_path / "run"
    argv = ["simulate", str(scene), "--solver", "mpm", "--frames", "3", "--out", str(out), "--quiet", "--no-render", "--threads", "1"]
    assert main([*argv, "--export", "usd"]) == 0
    oc = Trajectory.load(out / "trajectory.npz").obstacle_centers
    assert oc is not None and np.all(oc == oc[0])
    stage = Usd.Stage.Open(str(out / "export" / "run.usd"))
    (op,) = UsdGeom.Xformable(stage.GetPrimAtPath("/Run/Obstacles/obstacle_0")).GetOrderedXformOps()
    assert op.GetOpType() == UsdGeom.XformOp.TypeTransform and op.GetTimeSamples() == []
    assert np.allclose(np.array(op.Get())[3, :2], START)


def test_the_services_mesh_zip_places_the_obstacles_per_frame(run):
    pytest.importorskip("fastapi")
    import io
    import zipfile

    from hybridmpm.service.routes.trajectory import trajectory_mesh_zip

    sim, ro, _ = run
    assert ro.obstacle_centers is not None
    traj = Trajectory(ro.positions[-2:], ro.particle_type, ro.dt_frame, masses=ro.masses, obstacle_centers=ro.obstacle_centers[-2:])
    settings = surface_settings(sim.scene.params, ro.particle_type, ro.masses)
    with zipfile.ZipFile(io.BytesIO(trajectory_mesh_zip(traj, settings))) as z:
        last = z.read("water_00001.ply")
    was, now = sim.scene.params.colliders[0], obstacles_at(sim.scene.params.colliders, ro.obstacle_centers[-1])[0]
    v = ply_vertices(last)[:, :2].astype(np.float64)
    assert collider_sdf(now, v).min() > -DX / 2 and collider_sdf(was, v).min() < -DX


# ---------------------------------------------------------------------- bad input
@pytest.mark.parametrize(
    "bad",
    [np.zeros((2, 2, 2)), np.zeros((3, 2, 3)), np.zeros((3, 2)), np.full((3, 1, 2), np.nan), np.full((3, 1, 2), np.inf), np.array([["a"] * 2] * 3)],
)
def test_bad_obstacle_centres_name_the_field(bad, tmp_path):
    pos, ptype = np.full((3, 4, 2), 0.5), np.full(4, 5)
    with pytest.raises(InvalidInputError) as e:
        Trajectory(pos, ptype, 2.5e-3, obstacle_centers=bad)
    assert e.value.field == "obstacle_centers" and "obstacle_centers" in str(e.value)
    path = tmp_path / "bad.npz"
    np.savez(path, positions=pos, particle_type=ptype, dt_frame=2.5e-3, obstacle_centers=bad)
    with pytest.raises(InvalidInputError) as e:
        Trajectory.load(path)
    assert e.value.field == "obstacle_centers"


def test_export_refuses_centres_for_other_obstacles(run, tmp_path):
    sim, ro, _ = run
    traj = Trajectory(ro.positions[:2], ro.particle_type, ro.dt_frame, obstacle_centers=ro.obstacle_centers[:2, :1])
    from hybridmpm.cli.export import write_exports

    with pytest.raises(InvalidInputError) as e:
        write_exports(tmp_path / "x", ["mesh"], traj, sim.scene.params)
    assert e.value.field == "obstacle_centers"
