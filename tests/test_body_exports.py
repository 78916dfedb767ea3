"""Rigid bodies in the pictures and exports (docs/bodies.md "Pictures and
exports"): the GIF draws each body at its pose, the mesh sequences hold one
mesh per body per frame at its pose, and the USD file one Xform per body whose
samples are the trajectory's poses."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

import hybridmpm as hm
from hybridmpm.cli import main
from hybridmpm.errors import InvalidInputError
from hybridmpm.mpm.bodies import Body
from hybridmpm.render import render_gif
from hybridmpm.render.bodies import CIRCLE_SEGMENTS, body_prism, icosphere, local_mesh, local_outline, place
from hybridmpm.render.gif import BODY_FILL, frame_pixel
from hybridmpm.render.surface import frame_surfaces, mesh_volume, surface_settings
from hybridmpm.scenes import make_scene


def ply_vertices(path: Path) -> np.ndarray:
    """float32 [V, 3] of a binary PLY as :func:`~hybridmpm.render.surface.write_surface` writes it."""
    data = path.read_bytes()
    end = data.index(b"end_header\n") + len(b"end_header\n")
    count = int(next(line for line in data[:end].decode().splitlines() if line.startswith("element vertex")).split()[2])
    return np.frombuffer(data[end:], "<f4", count=3 * count).reshape(count, 3)


def obj_vertices(path: Path) -> np.ndarray:
    return np.array([[float(v) for v in line.split()[1:]] for line in path.read_text().splitlines() if line.startswith("v ")])


@pytest.fixture(scope="module", params=["crates2d", "crates3d"])
def exported(request, tmp_path_factory):
    """A short run of the scene, written by ``simulate`` with the mesh sequences (OBJ in 2D, PLY in 3D) and USD."""
    name = request.param
    out = tmp_path_factory.mktemp(name)
    fmt = "obj" if name == "crates2d" else "ply"
    argv = ["simulate", name, "--frames", "6", "--threads", "1", "--out", str(out), "--quiet", "--mesh-format", fmt, "--export", "mesh"]
    argv += ["usd"] if _has_pxr() else []
    assert main(argv) == 0
    return name, out, fmt, hm.Trajectory.load(out / "trajectory.npz")


def _has_pxr() -> bool:
    try:
        import pxr  # noqa: F401  (in the function: the usd extra is optional)
    except ImportError:
        return False
    return True


def _expected(body: Body, center: np.ndarray, rotation: np.ndarray) -> np.ndarray:
    """The body's shape at the pose, [V, 3] (z = 0 in 2D)."""
    if len(center) == 2:
        return np.c_[place(local_outline(body), center, rotation), np.zeros(len(local_outline(body)))]
    return place(local_mesh(body)[0], center, rotation)


def test_every_body_mesh_at_every_frame_is_its_shape_at_its_pose(exported):
    name, out, fmt, traj = exported
    bodies = make_scene(name).params.bodies
    assert traj.body_center.shape[:2] == (7, len(bodies))
    assert not np.array_equal(traj.body_center[0], traj.body_center[-1])  # they moved
    for t in range(traj.num_frames):
        for i, body in enumerate(bodies):
            path = out / "export" / f"body_{i}_{t:05d}.{fmt}"
            got = ply_vertices(path) if fmt == "ply" else obj_vertices(path)
            np.testing.assert_allclose(got, _expected(body, traj.body_center[t, i], traj.body_rotation[t, i]), atol=1e-6)
    assert not list((out / "export").glob(f"body_{len(bodies)}_*"))


def test_the_water_surface_ends_on_the_bodies(exported):
    """The exported water surface (3D triangles, 2D outlines) ends on each body at its pose, as on an obstacle: no
    vertex lies deeper than 0.3 cell inside a body (linear interpolation across a box's edge cuts its corner by a
    fraction of a cell); drawn without the bodies, the same frame's surface reaches 0.56-0.68 cell inside."""
    name, out, fmt, traj = exported
    params = make_scene(name).params
    dx = 1.0 / params.resolved_n_grid()
    t = traj.num_frames - 1
    path = out / "export" / f"water_{t:05d}.{fmt}"
    v = (ply_vertices(path) if fmt == "ply" else obj_vertices(path))[:, : traj.dim].astype(np.float64)
    depth = [-b.sdf(v, traj.body_center[t, i], traj.body_rotation[t, i]).min() / dx for i, b in enumerate(params.bodies)]
    touching = [int((np.abs(b.sdf(v, traj.body_center[t, i], traj.body_rotation[t, i])) < dx).sum()) for i, b in enumerate(params.bodies)]
    print(f"{name}: deepest surface vertex inside each body {np.round(depth, 3)} cells; vertices within a cell of each {touching}")
    assert max(depth) <= 0.3 and sum(touching) > 0, (depth, touching)
    settings = surface_settings(params, traj.particle_type, traj.masses)
    (bare,) = frame_surfaces(traj.positions[t], traj.particle_type, **settings)  # the same frame, the bodies left out
    w = bare.vertices if traj.dim == 3 else np.concatenate(bare.loops)
    assert max(-b.sdf(w, traj.body_center[t, i], traj.body_rotation[t, i]).min() / dx for i, b in enumerate(params.bodies)) > 0.4


def test_usd_has_one_xform_per_body_sampled_at_the_trajectory_poses(exported):
    pytest.importorskip("pxr")
    from pxr import Usd, UsdGeom

    name, out, _, traj = exported
    bodies = make_scene(name).params.bodies
    stage = Usd.Stage.Open(str(out / "export" / "run.usd"))
    kids = stage.GetPrimAtPath("/Run/Bodies").GetChildren()
    assert [k.GetName() for k in kids] == [f"body_{i}" for i in range(len(bodies))]
    dim = traj.dim
    for i, (prim, body) in enumerate(zip(kids, bodies)):
        assert prim.GetTypeName() == "Xform"
        xf = UsdGeom.Xformable(prim)
        ops = {op.GetOpName(): op for op in xf.GetOrderedXformOps()}
        translate = ops["xformOp:translate"]
        assert translate.GetTimeSamples() == list(range(traj.num_frames))
        shape = UsdGeom.Mesh(stage.GetPrimAtPath(f"/Run/Bodies/body_{i}/shape"))
        local = np.array(shape.GetPointsAttr().Get(), np.float64)
        for t in range(traj.num_frames):
            np.testing.assert_allclose(np.array(translate.Get(t))[:dim], traj.body_center[t, i], atol=1e-12)
            m = np.array(xf.ComputeLocalToWorldTransform(t))  # row vectors: p' = p · M
            world = np.c_[local, np.ones(len(local))] @ m
            if dim == 3:
                np.testing.assert_allclose(world[:, :3], _expected(body, traj.body_center[t, i], traj.body_rotation[t, i]), atol=1e-6)
            else:  # the outline extruded: both caps over the outline at the pose
                ring = _expected(body, traj.body_center[t, i], traj.body_rotation[t, i])[:, :2]
                np.testing.assert_allclose(world[:, :2], np.concatenate([ring, ring]), atol=1e-6)


def test_the_gif_draws_each_body_at_its_pose(tmp_path):
    from matplotlib.colors import to_rgb

    fill = np.array(to_rgb(BODY_FILL)) * 255
    for name in ("crates2d", "crates3d"):
        scene = make_scene(name)
        ro = hm.rollout(hm.make_simulator(scene, "mpm", threads=1), 4)
        path = render_gif(
            ro.positions, ro.particle_type, tmp_path / f"{name}.gif", dt_frame=ro.dt_frame,
            bodies=scene.params.bodies, body_center=ro.body_center, body_rotation=ro.body_rotation,
        )  # fmt: skip
        import imageio.v3 as iio  # in the function: the GIF reader only here

        frames = iio.imread(path, index=None)
        for t in (0, len(frames) - 1):
            for c in ro.body_center[t]:
                row, col = frame_pixel(c[:2])
                assert np.abs(frames[t][row, col].astype(float) - fill).max() < 12, (name, t, c, frames[t][row, col])
        plain = render_gif(ro.positions, ro.particle_type, tmp_path / "plain.gif", dt_frame=ro.dt_frame)  # no bodies given: none drawn
        row, col = frame_pixel(ro.body_center[0, 0, :2])
        assert np.abs(iio.imread(plain, index=None)[0][row, col].astype(float) - fill).max() > 40


def test_the_shapes_are_closed_and_outward():
    v, f = icosphere()
    assert len(v) == 162 and len(f) == 320 and np.allclose(np.linalg.norm(v, axis=1), 1.0)
    assert 0.95 * 4 / 3 * np.pi < mesh_volume(v, f) < 4 / 3 * np.pi
    box = Body(shape="box", center=[0.5, 0.5, 0.5], half_extents=[0.1, 0.2, 0.3], density=500.0)
    assert mesh_volume(*local_mesh(box)) == pytest.approx(0.2 * 0.4 * 0.6)
    square = Body(shape="box", center=[0.5, 0.5], half_extents=[0.1, 0.2], density=500.0)
    assert mesh_volume(*body_prism(square, 0.05)) == pytest.approx(0.2 * 0.4 * 0.1)
    circle = Body(shape="circle", center=[0.5, 0.5], radius=0.1, density=500.0)
    assert len(local_outline(circle)) == CIRCLE_SEGMENTS and mesh_volume(*body_prism(circle, 0.05)) > 0


def test_poses_for_other_bodies_are_refused(tmp_path):
    from hybridmpm.render.bodies import export_bodies

    bodies = make_scene("crates2d").params.bodies
    with pytest.raises(InvalidInputError) as e:
        export_bodies(tmp_path, bodies, np.zeros((2, 3, 2)), np.zeros((2, 3, 2, 2)))
    assert e.value.field == "body_center"
    with pytest.raises(InvalidInputError) as e:
        export_bodies(tmp_path, bodies, np.zeros((2, 4, 2)), np.zeros((2, 4, 3, 3)))
    assert e.value.field == "body_rotation"


def test_the_usd_quaternion_of_any_rotation():
    from scipy.spatial.transform import Rotation

    from hybridmpm.render.usd import quaternion

    rots = list(Rotation.random(50, random_state=1).as_matrix()) + [np.diag([1.0, -1.0, -1.0]), np.diag([-1.0, 1.0, -1.0]), np.diag([-1.0, -1.0, 1.0])]
    for r in rots:
        w, x, y, z = quaternion(r)
        back = np.array(
            [
                [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
            ]
        )
        np.testing.assert_allclose(back, r, atol=1e-12)


def test_each_entry_point_checks_the_bodies_once_and_a_track_not_again(tmp_path, monkeypatch):
    """The bodies travel as one BodyTrack: a public entry point given the loose arrays makes one at its top (one
    check, however many frames it draws), one given a rollout's track checks nothing, and both write the same;
    nothing below them (the frame loop, posed_settings, the body meshes) checks the poses again."""
    from hybridmpm.cli.export import write_exports
    from hybridmpm.mpm.bodies import BodyTrack
    from hybridmpm.render.bodies import export_bodies
    from hybridmpm.render.surface import export_surfaces
    from hybridmpm.render.surface_scene import posed_settings

    scene = make_scene("crates2d")
    ro = hm.rollout(hm.make_simulator(scene, "mpm", threads=1), 3)
    track, shapes = ro.bodies, scene.params.bodies
    assert track is not None and track.num_frames == 4
    settings = surface_settings(scene.params, ro.particle_type, ro.masses)
    checks: list[BodyTrack] = []
    check = BodyTrack.__post_init__

    def counted(self: BodyTrack) -> None:
        checks.append(self)
        check(self)

    monkeypatch.setattr(BodyTrack, "__post_init__", counted)
    loose = {"bodies": shapes, "body_center": ro.body_center, "body_rotation": ro.body_rotation}
    entry_points = {
        "render_gif": lambda kw, out: render_gif(ro.positions, ro.particle_type, out / "run.gif", dt_frame=ro.dt_frame, max_frames=2, **kw),
        "export_surfaces": lambda kw, out: export_surfaces(ro.positions, ro.particle_type, out, bodies=_tuple(kw), **settings),
        "export_bodies": lambda kw, out: export_bodies(out, *_tuple(kw)) if "body_center" in kw else export_bodies(out, kw["bodies"]),
        "posed_settings": lambda kw, out: posed_settings(settings, None, 3, _tuple(kw)),  # one frame's settings
    }
    if _has_pxr():
        from hybridmpm.render.usd import write_usd

        entry_points["write_usd"] = lambda kw, out: write_usd(out / "run.usda", ro.positions, ro.particle_type, ro.dt_frame, **kw)
    for name, call in entry_points.items():
        a, b = tmp_path / name / "loose", tmp_path / name / "track"
        a.mkdir(parents=True)
        b.mkdir(parents=True)
        checks.clear()
        got_loose = call(loose, a)
        assert len(checks) == 1, (name, len(checks))
        checks.clear()
        got_track = call({"bodies": track}, b)
        assert not checks, name
        if name == "posed_settings":  # the bodies at frame 3, where the surfaces end
            posed = [[o for o in got["obstacles"] if hasattr(o, "body")] for got in (got_loose, got_track)]
            assert len(posed[0]) == len(posed[1]) == len(shapes)
            for i, (x, y) in enumerate(zip(*posed)):
                assert x.body == y.body == shapes[i] and np.array_equal(x.center, y.center) and np.array_equal(x.rotation, y.rotation)
                assert np.array_equal(y.center, ro.body_center[3, i]) and np.array_equal(y.rotation, ro.body_rotation[3, i])
        files = sorted(p.name for p in a.iterdir())
        assert files == sorted(p.name for p in b.iterdir()), name
        if name in ("export_bodies", "export_surfaces", "render_gif"):
            assert files and all((a / f).read_bytes() == (b / f).read_bytes() for f in files), name
    # a saved trajectory's exports: the scene's bodies at its poses, made into one track once for the meshes and USD
    saved = hm.Trajectory.load(ro.save(tmp_path / "trajectory.npz"))
    checks.clear()
    done = write_exports(tmp_path / "exports", ["mesh"] + (["usd"] if _has_pxr() else []), saved, scene.params)
    assert len(checks) == 1 and done["body"] == 4 * len(shapes)


def _tuple(kw: dict) -> tuple | object:
    """An entry point's ``bodies`` argument: ``(bodies as given, body_center, body_rotation)`` for loose arrays, else the track."""
    return (kw["bodies"], kw["body_center"], kw["body_rotation"]) if "body_center" in kw else kw["bodies"]
