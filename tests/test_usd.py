"""USD export (hybridmpm.render.usd, ``--export usd``): read back with pxr."""

from __future__ import annotations

import sys

import numpy as np
import pytest

from hybridmpm.cli import main
from hybridmpm.conventions import GNS_KINEMATIC, GNS_WATER
from hybridmpm.errors import InvalidInputError
from hybridmpm.mpm import Box, Sphere
from hybridmpm.render.surface import surface_contours
from hybridmpm.render.usd import write_usd
from hybridmpm.scenes import collider_sdf
from hybridmpm.scenes.core import lattice

pxr = pytest.importorskip("pxr")
from pxr import Gf, Usd, UsdGeom  # noqa: E402


def test_water3d_run_reads_back_one_sample_per_frame(tmp_path):
    out = tmp_path / "w3"
    argv = ["simulate", "water3d", "--solver", "mpm", "--frames", "3", "--out", str(out), "--quiet", "--no-render", "--threads", "1", "--export", "usd"]
    assert main(argv) == 0
    traj = np.load(out / "trajectory.npz")
    frames, n = traj["positions"].shape[:2]
    dt = float(traj["dt_frame"])
    stage = Usd.Stage.Open(str(out / "export" / "run.usd"))
    assert UsdGeom.GetStageMetersPerUnit(stage) == 1.0 and UsdGeom.GetStageUpAxis(stage) == UsdGeom.Tokens.y
    assert stage.GetFramesPerSecond() == pytest.approx(1 / dt) and stage.GetTimeCodesPerSecond() == pytest.approx(1 / dt)
    assert (stage.GetStartTimeCode(), stage.GetEndTimeCode()) == (0, frames - 1)
    pts = UsdGeom.Points(stage.GetPrimAtPath("/Run/Particles"))
    assert pts.GetPointsAttr().GetTimeSamples() == list(range(frames))
    for t in range(frames):
        p = np.asarray(pts.GetPointsAttr().Get(t))
        assert p.shape == (n, 3) and np.allclose(p, traj["positions"][t], atol=1e-7)
    v = np.asarray(pts.GetVelocitiesAttr().Get(2))
    assert np.allclose(v, (traj["positions"][2] - traj["positions"][1]) / dt, atol=1e-3)
    assert np.array_equal(np.asarray(pts.GetIdsAttr().Get()), np.arange(n))
    pv = UsdGeom.PrimvarsAPI(pts)
    assert np.array_equal(np.asarray(pv.GetPrimvar("material").Get()), traj["particle_type"])
    assert pv.GetPrimvar("solver").GetAttr().GetTimeSamples() == list(range(frames))
    assert list(pv.GetPrimvar("solver").Get(1)) == [0]  # MPM
    mesh = UsdGeom.Mesh(stage.GetPrimAtPath("/Run/Surfaces/water"))
    for attr in (mesh.GetPointsAttr(), mesh.GetFaceVertexCountsAttr(), mesh.GetFaceVertexIndicesAttr()):
        assert attr.GetTimeSamples() == list(range(frames))
    idx = np.asarray(mesh.GetFaceVertexIndicesAttr().Get(1))
    assert len(idx) == 3 * len(mesh.GetFaceVertexCountsAttr().Get(1)) > 0
    assert idx.max() < len(mesh.GetPointsAttr().Get(1))
    assert stage.GetPrimAtPath("/Run/Domain").GetTypeName() == "BasisCurves"


def test_obstacles_are_placed_where_the_colliders_are(tmp_path):
    rot = Gf.Matrix3d(Gf.Rotation(Gf.Vec3d(0, 0, 1), 30))
    r = np.array([[rot[i][j] for j in range(3)] for i in range(3)]).T  # columns: the box's axes
    box = Box(center=[0.5, 0.3, 0.4], half_extents=[0.2, 0.03, 0.1], rotation=r.tolist())
    ball = Sphere(center=[0.3, 0.6, 0.5], radius=0.07)
    p = np.full((1, 2, 3), 0.5)
    path = write_usd(tmp_path / "o.usda", p, np.full(2, GNS_WATER), 2.5e-3, obstacles=[box, ball], domain=([0.1] * 3, [0.9] * 3))
    stage = Usd.Stage.Open(str(path))
    cube = stage.GetPrimAtPath("/Run/Obstacles/obstacle_0")
    assert cube.GetTypeName() == "Cube"
    m = UsdGeom.Xformable(cube).ComputeLocalToWorldTransform(0)
    size = UsdGeom.Cube(cube).GetSizeAttr().Get() / 2
    corners = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)], float) * size
    world = np.array([list(m.Transform(Gf.Vec3d(*c))) for c in corners])
    # the corners of the collider: center + R · (± half extents)
    expect = np.array(box.center) + (corners * np.array(box.half_extents)) @ r.T
    assert np.allclose(np.sort(world, axis=0), np.sort(expect, axis=0), atol=1e-9)
    assert np.allclose(collider_sdf(box, world), 0, atol=1e-9)  # on the collider's surface, as the solver sees it
    sph = UsdGeom.Sphere(stage.GetPrimAtPath("/Run/Obstacles/obstacle_1"))
    assert sph.GetRadiusAttr().Get() == pytest.approx(0.07)
    assert np.allclose(list(UsdGeom.Xformable(sph).ComputeLocalToWorldTransform(0).ExtractTranslation()), ball.center)
    dom = np.asarray(UsdGeom.BasisCurves(stage.GetPrimAtPath("/Run/Domain")).GetPointsAttr().Get())
    assert np.allclose(dom.min(axis=0), 0.1) and np.allclose(dom.max(axis=0), 0.9) and len(dom) == 24  # 12 edges


def test_2d_run_has_points_at_z0_and_closed_outline_curves(tmp_path):
    dx = 1 / 32
    p = lattice([0.0625, 0.0625], [0.4, 0.3], dx / 2).astype(float)
    pt = np.full(len(p), GNS_WATER)
    surf = surface_contours(p, pt, domain=([0.0625] * 2, [0.9375] * 2), dx=dx)
    path = write_usd(tmp_path / "r.usdc", np.stack([p, p]), pt, 0.01, surfaces=[surf, surf])
    stage = Usd.Stage.Open(str(path))
    assert stage.GetFramesPerSecond() == pytest.approx(100.0)
    q = np.asarray(UsdGeom.Points(stage.GetPrimAtPath("/Run/Particles")).GetPointsAttr().Get(1))
    assert np.all(q[:, 2] == 0) and np.allclose(q[:, :2], p, atol=1e-7)
    curves = UsdGeom.BasisCurves(stage.GetPrimAtPath("/Run/Surfaces/water"))
    assert curves.GetWrapAttr().Get() == UsdGeom.Tokens.periodic
    assert list(curves.GetCurveVertexCountsAttr().Get(0)) == [len(surf[0].loops[0]) - 1]


@pytest.mark.parametrize(
    ("change", "field"),
    [
        ({"path": "run.abc"}, "path"),
        ({"path": "missing/run.usd"}, "path"),
        ({"positions": np.zeros((2, 3))}, "positions"),
        ({"positions": np.full((1, 2, 3), np.nan)}, "positions"),
        ({"particle_type": np.zeros(3, np.int64)}, "particle_type"),
        ({"dt_frame": 0.0}, "dt_frame"),
        ({"solver": np.zeros(5)}, "solver"),
        ({"surfaces": [[], []]}, "surfaces"),
    ],
)
def test_bad_input_names_the_field(tmp_path, change, field):
    kw = {"path": "run.usd", "positions": np.full((1, 2, 3), 0.5), "particle_type": np.full(2, GNS_KINEMATIC), "dt_frame": 2.5e-3, **change}
    kw["path"] = tmp_path / kw["path"]
    with pytest.raises(InvalidInputError) as e:
        write_usd(kw.pop("path"), kw.pop("positions"), kw.pop("particle_type"), kw.pop("dt_frame"), **kw)
    assert e.value.field == field


def test_missing_pxr_is_an_error_naming_export(tmp_path, monkeypatch, capsys):
    monkeypatch.setitem(sys.modules, "pxr", None)  # import pxr now raises ImportError
    argv = ["simulate", "water3d", "--solver", "mpm", "--frames", "1", "--out", str(tmp_path / "x"), "--quiet", "--no-render", "--export", "usd"]
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert "--export usd" in err and "hybridmpm[usd]" in err
    assert not (tmp_path / "x" / "trajectory.npz").exists()  # refused before the run
