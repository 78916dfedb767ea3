"""Each material drawn and exported as itself: the render GIF's colours, a
surface per material in the mesh and USD exports (elastic_*, snow_*,
viscoplastic_* beside water_* and sand_*), each holding its particles' volume."""

from __future__ import annotations

import imageio.v3 as iio
import meshio
import numpy as np
import trimesh

from hybridmpm.cli import main
from hybridmpm.conventions import GNS_ELASTIC, GNS_GOOP, GNS_KINEMATIC, GNS_SNOW, GNS_WATER
from hybridmpm.render.gif import SNOW_BACKGROUND, particle_colours, render_gif
from hybridmpm.render.surface import rest_densities, surface_contours, surface_mesh
from hybridmpm.scenes import make_scene
from hybridmpm.scenes.core import lattice

DX = 1.0 / 32
FACE = 2 * DX


def _block(lo_cells, size_cells, dim=3):
    lo = FACE + np.asarray(lo_cells, float) * DX
    hi = lo + np.asarray(size_cells, float) * DX
    return lattice(lo, hi, DX / 2).astype(np.float64), lo, hi


def test_each_solid_gets_its_own_closed_surface_with_its_volume():
    blocks = [(GNS_WATER, [0, 0, 0]), (GNS_ELASTIC, [10, 0, 0]), (GNS_SNOW, [0, 0, 12]), (GNS_GOOP, [12, 0, 12])]
    parts = [(t, *_block(at, [6, 6, 6])) for t, at in blocks]
    p = np.concatenate([q for _, q, _, _ in parts] + [np.full((4, 3), 0.5)])
    pt = np.concatenate([np.full(len(q), t) for t, q, _, _ in parts] + [np.full(4, GNS_KINEMATIC)])
    meshes = surface_mesh(p, pt, domain=([FACE] * 3, [1 - FACE] * 3), dx=DX)
    assert [m.material for m in meshes] == ["water", "viscoplastic", "elastic", "snow"]  # sorted by GNS type: 5, 7, 8, 9
    by_name = {m.material: m for m in meshes}
    for t, _, lo, hi in parts:
        m = by_name[{GNS_WATER: "water", GNS_ELASTIC: "elastic", GNS_SNOW: "snow", GNS_GOOP: "viscoplastic"}[t]]
        assert trimesh.Trimesh(m.vertices, m.faces, process=False).is_watertight
        assert abs(m.volume / np.prod(hi - lo) - 1) < 0.05
        assert np.all(m.vertices.min(axis=0) > lo - DX / 2) and np.all(m.vertices.max(axis=0) < hi + DX / 2)


def test_rest_densities_take_each_blocks_preset():
    scene = make_scene("jelly_dam_break2d")
    rho = rest_densities(scene.params, scene.particle_type())
    assert set(rho[scene.material == 0].tolist()) == {1000.0} and set(rho[scene.material == 2].tolist()) == {1050.0}  # jello's


def test_a_jelly_scene_exports_water_and_elastic_meshes_and_usd_surfaces(tmp_path):
    out = tmp_path / "j3"
    args = ["simulate", "jelly_dam_break3d", "--frames", "1", "--out", str(out), "--quiet", "--no-render", "--threads", "1", "--export", "mesh"]
    try:  # USD too where pxr is installed
        import pxr  # noqa: F401

        args.append("usd")
    except ImportError:
        pass
    assert main(args) == 0
    ex = out / "export"
    assert sorted(x.name for x in ex.glob("elastic_*.ply")) == ["elastic_00000.ply", "elastic_00001.ply"]
    assert sorted(x.name for x in ex.glob("water_*.ply")) == ["water_00000.ply", "water_00001.ply"]
    traj = np.load(out / "trajectory.npz")
    jelly = traj["particle_type"] == GNS_ELASTIC
    first = meshio.read(ex / "elastic_00000.ply")
    tm = trimesh.Trimesh(first.points, first.cells_dict["triangle"], process=False)
    assert tm.is_watertight
    assert abs(tm.volume / (traj["masses"][jelly].sum() / 1050.0) - 1) < 0.05  # the jello's density, not water's
    if "usd" in args:
        from pxr import Usd, UsdGeom

        stage = Usd.Stage.Open(str(ex / "run.usd"))
        for name in ("water", "elastic"):
            mesh = UsdGeom.Mesh(stage.GetPrimAtPath(f"/Run/Surfaces/{name}"))
            assert mesh and mesh.GetPointsAttr().GetTimeSamples() == [0, 1]


def test_2d_outlines_per_solid():
    p_mud, lo, hi = _block([0, 0], [10, 8], dim=2)
    p_w, _, _ = _block([14, 0], [10, 4], dim=2)
    p_mud, p_w = p_mud[:, :2], p_w[:, :2]
    loops = surface_contours(
        np.concatenate([p_mud, p_w]), np.r_[np.full(len(p_mud), GNS_GOOP), np.full(len(p_w), GNS_WATER)], domain=([FACE] * 2, [1 - FACE] * 2), dx=DX
    )
    assert [c.material for c in loops] == ["water", "viscoplastic"]


def _close(img: np.ndarray, rgb: tuple[float, float, float], tol: float = 0.06) -> int:
    return int((np.abs(img[..., :3] / 255.0 - np.asarray(rgb)) < tol).all(axis=-1).sum())


def test_the_gif_draws_jelly_translucent_snow_white_and_mud_brown(tmp_path):
    colours = particle_colours(np.array([GNS_WATER, GNS_ELASTIC, GNS_SNOW, GNS_GOOP, 42]))
    assert colours[1, 3] < 1.0 and (colours[[0, 2, 3], 3] == 1.0).all()  # only jelly translucent
    assert colours[2, :3].min() > 0.95  # snow white
    r, g, b = colours[3, :3]
    assert r > g > b and r < 0.6  # mud a dark brown
    # a frame of each solid scene: the picture holds its colour (and snow its background)
    for name, rgb, tol in (("mud_slump2d", tuple(colours[3, :3]), 0.08), ("snowball2d", tuple(colours[2, :3]), 0.03)):
        scene = make_scene(name)
        path = render_gif(scene.positions[None], scene.particle_type(), tmp_path / f"{name}.gif", dt_frame=scene.dt_frame, size_px=200)
        img = np.asarray(iio.imread(path, index=0))
        assert _close(img, rgb, tol) > 50, name
    from matplotlib.colors import to_rgb

    assert _close(img, to_rgb(SNOW_BACKGROUND), 0.03) > 1000  # snowball2d: snow on a grey-blue ground
    # jelly: blended with the white ground (translucent), lighter than its colour, and present
    scene = make_scene("jelly_dam_break2d")
    img = np.asarray(iio.imread(render_gif(scene.positions[None], scene.particle_type(), tmp_path / "j.gif", dt_frame=0.0025, size_px=200), index=0))
    px = img[..., :3] / 255.0
    pink = (px[..., 0] > px[..., 1] + 0.15) & (px[..., 0] > px[..., 2])
    assert pink.sum() > 50
    # the ground shows through: few pixels reach the opaque colour (drawn opaque, the block's inside would)
    assert _close(img, tuple(colours[1, :3]), 0.03) < 0.5 * pink.sum()
