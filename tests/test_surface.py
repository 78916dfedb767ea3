"""Fluid surfaces from particles (hybridmpm.render.surface): geometry against
the block the particles fill, closure, per-material meshes, determinism, bad input."""

from __future__ import annotations

import hashlib
import itertools
import os
import subprocess
import sys
from pathlib import Path

import meshio
import numpy as np
import pytest
import trimesh

from hybridmpm import _core
from hybridmpm.cli import main
from hybridmpm.conventions import GNS_KINEMATIC, GNS_SAND, GNS_WATER
from hybridmpm.errors import InvalidInputError
from hybridmpm.mpm import Box, MpmParams, Sphere
from hybridmpm.render import surface as surface_module
from hybridmpm.render import surface_field
from hybridmpm.render.surface import MAX_GRID_NODES, VOLUME_TOL, export_surfaces, surface_contours, surface_mesh, write_surface
from hybridmpm.scenes import collider_sdf
from hybridmpm.scenes.core import lattice

N_GRID = 32
DX = 1.0 / N_GRID
FACE = 2 * DX  # the wall face of a 32-cell grid with a 3-cell wall band
DOMAIN3 = ([FACE] * 3, [1 - FACE] * 3)
DOMAIN2 = ([FACE] * 2, [1 - FACE] * 2)


def block(lo_cells, size_cells, dim=3):
    """A block of the scenes' lattice (2 particles per cell per axis) resting at
    ``lo_cells`` [cells from the wall face]: positions, lo, hi [m]."""
    lo = FACE + np.asarray(lo_cells, float) * DX
    hi = lo + np.asarray(size_cells, float) * DX
    return lattice(lo, hi, DX / 2).astype(np.float64), lo, hi


def test_resting_block_surface_is_closed_has_the_block_volume_and_its_top():
    p, lo, hi = block([0, 0, 0], [12, 10, 14])  # on the floor, in a corner of the walls
    (mesh,) = surface_mesh(p, np.full(len(p), GNS_WATER), domain=DOMAIN3, dx=DX)
    assert mesh.material == "water" and len(mesh.faces) > 0
    tm = trimesh.Trimesh(mesh.vertices, mesh.faces, process=False)
    assert tm.is_watertight and tm.is_winding_consistent
    volume = float(np.prod(hi - lo))
    assert tm.volume > 0  # outward normals
    assert abs(tm.volume / volume - 1) < 0.05
    assert abs(mesh.volume - tm.volume) < 1e-9
    free_surface = p[:, 1].max() + DX / 4  # highest particle + half the particle spacing
    assert abs(mesh.vertices[:, 1].max() - free_surface) < DX / 2
    # closed against the walls: the floor and the two side walls the block rests on hold the surface
    assert np.allclose(mesh.vertices.min(axis=0), FACE, atol=1e-9)


def test_free_block_keeps_its_volume_and_place():
    p, lo, hi = block([8, 6, 9], [8, 8, 8])
    (mesh,) = surface_mesh(p, np.full(len(p), GNS_WATER), domain=DOMAIN3, dx=DX)
    assert trimesh.Trimesh(mesh.vertices, mesh.faces, process=False).is_watertight
    assert abs(mesh.volume / np.prod(hi - lo) - 1) < 0.05
    assert np.all(np.abs(mesh.vertices.min(axis=0) - lo) < DX / 2)
    assert np.all(np.abs(mesh.vertices.max(axis=0) - hi) < DX / 2)


def test_fixed_iso_half_puts_flat_faces_on_the_block_faces():
    p, lo, hi = block([5, 0, 5], [10, 10, 10])
    (mesh,) = surface_mesh(p, np.full(len(p), GNS_WATER), domain=DOMAIN3, dx=DX, iso=0.5)
    assert mesh.iso == 0.5
    # the middle of the top face (away from the rounded edges) lies on the block's top
    centre = np.all(np.abs(mesh.vertices[:, [0, 2]] - (lo[[0, 2]] + hi[[0, 2]]) / 2) < 2 * DX, axis=1)
    assert np.allclose(mesh.vertices[centre, 1].max(), hi[1], atol=0.05 * DX)


def test_2d_block_outline_is_closed_with_the_block_area():
    p, lo, hi = block([0, 0], [20, 12], dim=2)
    (c,) = surface_contours(p, np.full(len(p), GNS_WATER), domain=DOMAIN2, dx=DX)
    assert len(c.loops) == 1
    loop = c.loops[0]
    assert np.array_equal(loop[0], loop[-1])  # closed
    assert c.area > 0  # outer loop counter-clockwise
    assert abs(c.area / np.prod(hi - lo) - 1) < 0.05
    assert abs(loop[:, 1].max() - (p[:, 1].max() + DX / 4)) < DX / 2


def test_mixed_water_and_sand_give_two_separate_meshes():
    pw, lw, hw = block([0, 0, 0], [8, 8, 8])
    ps, ls, hs = block([12, 0, 0], [8, 6, 8])
    p = np.concatenate([ps, pw])  # sand first: the output is still sorted by type
    pt = np.concatenate([np.full(len(ps), GNS_SAND), np.full(len(pw), GNS_WATER)])
    boundary = np.full((5, 3), 0.5)  # kinematic particles are not meshed
    meshes = surface_mesh(np.concatenate([p, boundary]), np.concatenate([pt, np.full(5, GNS_KINEMATIC)]), domain=DOMAIN3, dx=DX)
    assert [m.material for m in meshes] == ["water", "sand"]
    for m, lo, hi in zip(meshes, (lw, ls), (hw, hs)):
        assert trimesh.Trimesh(m.vertices, m.faces, process=False).is_watertight
        assert abs(m.volume / np.prod(hi - lo) - 1) < 0.05
        assert np.all(m.vertices.min(axis=0) > lo - DX / 2) and np.all(m.vertices.max(axis=0) < hi + DX / 2)


def test_surface_does_not_enter_obstacles():
    # a block resting on a box obstacle, a sphere pressed into its side
    shelf = Box(center=[0.4, 0.3, 0.4], half_extents=[0.2, 0.05, 0.2])
    ball = Sphere(center=[0.62, 0.45, 0.4], radius=0.06)
    lo = np.array([0.25, 0.35, 0.25])
    hi = np.array([0.55, 0.55, 0.55])
    p = lattice(lo, hi, DX / 2).astype(np.float64)
    p = p[collider_sdf(ball, p) > DX / 4]
    (mesh,) = surface_mesh(p, np.full(len(p), GNS_WATER), domain=DOMAIN3, dx=DX, obstacles=[shelf, ball])
    assert trimesh.Trimesh(mesh.vertices, mesh.faces, process=False).is_watertight
    for ob in (shelf, ball):
        assert collider_sdf(ob, mesh.vertices).min() > -0.05 * DX
    # the bottom rests on the shelf's top face
    assert abs(mesh.vertices[:, 1].min() - 0.35) < 0.05 * DX


def test_same_bytes_twice_and_for_any_particle_order(tmp_path):
    rng = np.random.default_rng(1)
    p, _, _ = block([3, 0, 3], [10, 8, 10])
    p = p + rng.normal(0, 0.1 * DX, p.shape)  # a disordered frame
    pt = np.full(len(p), GNS_WATER)
    a, b, c = (tmp_path / f"{k}.ply" for k in "abc")
    write_surface(surface_mesh(p, pt, domain=DOMAIN3, dx=DX)[0], a)
    write_surface(surface_mesh(p, pt, domain=DOMAIN3, dx=DX)[0], b)
    perm = rng.permutation(len(p))
    write_surface(surface_mesh(p[perm], pt[perm], domain=DOMAIN3, dx=DX)[0], c)
    assert a.read_bytes() == b.read_bytes() == c.read_bytes()


def _reference_p2g(p, frac, h, g_lo, shape):
    """The quantised p2g in plain numpy: weights 0.5(1.5 − f)², 0.75 − (f − 1)², 0.5(f − 0.5)² rounded to 2^-10."""
    xs = p.T / h
    base = np.floor(xs - 0.5)
    fx = xs - base
    w = np.rint(np.stack([0.5 * (1.5 - fx) ** 2, 0.75 - (fx - 1.0) ** 2, 0.5 * (fx - 0.5) ** 2], axis=1) * 2**10) / 2**10  # [D, 3, N]
    out = np.zeros(shape)
    for offs in itertools.product(range(3), repeat=p.shape[1]):
        wt = frac.copy()
        for k, a in enumerate(offs):
            wt = wt * w[k, a]
        np.add.at(out, tuple(base[k].astype(np.int64) - g_lo[k] + a for k, a in enumerate(offs)), wt)
    return out


@pytest.mark.parametrize("dim", [2, 3])
def test_the_compiled_p2g_is_the_quantised_spline_splat_in_any_order(dim):
    rng = np.random.default_rng(dim)
    h = 1 / 48  # not a power of two: x/h is rounded
    p = rng.uniform(0.3, 0.6, (3000, dim))
    frac = np.rint(rng.uniform(0.5, 2.0, len(p)) / 8 * 2**14) / 2**14
    g_lo = np.floor(p.min(axis=0) / h).astype(np.int64) - 2
    shape = [int(s) for s in np.floor(p.max(axis=0) / h).astype(np.int64) - g_lo + 3]
    field = _core.surface_p2g(p, frac, h, [int(g) for g in g_lo], shape, 2.0**10)
    assert field.dtype == np.float64 and list(field.shape) == shape
    assert np.array_equal(field, _reference_p2g(p, frac, h, g_lo, shape))
    perm = rng.permutation(len(p))
    assert np.array_equal(_core.surface_p2g(p[perm], frac[perm], h, [int(g) for g in g_lo], shape, 2.0**10), field)
    assert abs(field.sum() / frac.sum() - 1) < 1e-4  # the weights keep the volume (to their rounding, 2^-11 per weight)


@pytest.mark.parametrize(
    ("change", "field"),
    [
        ({"positions": np.full((2, 3), 0.5, np.float32)}, "positions"),
        ({"positions": np.array([[0.5, 0.5, np.nan], [0.5, 0.5, 0.5]])}, "positions"),
        ({"positions": np.array([[0.5, 0.5, 0.5], [0.9, 0.5, 0.5]])}, "positions"),  # its stencil leaves the grid
        ({"values": np.ones(3)}, "values"),
        ({"values": np.array([1.0, np.inf])}, "values"),
        ({"spacing": 0.0}, "spacing"),
        ({"origin": [0, 0]}, "origin"),
        ({"shape": [8, 8]}, "shape"),
        ({"weight_scale": 2.0**60}, "weight_scale"),
    ],
)
def test_the_compiled_p2g_names_bad_input(change, field):
    kw = {
        "positions": np.full((2, 3), 0.5),
        "values": np.ones(2),
        "spacing": 1 / 16,
        "origin": [4, 4, 4],
        "shape": [8, 8, 8],
        "weight_scale": 2.0**10,
        **change,
    }
    with pytest.raises(InvalidInputError) as e:
        _core.surface_p2g(**kw)
    assert e.value.field == field


@pytest.mark.parametrize(("lo_cells", "size_cells"), [([0, 0, 0], [12, 10, 14]), ([8, 6, 9], [8, 8, 8]), ([2, 0, 2], [6, 6, 6])])
def test_the_volume_level_holds_the_particles_volume(lo_cells, size_cells):
    p, lo, hi = block(lo_cells, size_cells)
    (mesh,) = surface_mesh(p, np.full(len(p), GNS_WATER), domain=DOMAIN3, dx=DX)
    assert abs(mesh.volume / np.prod(hi - lo) - 1) <= VOLUME_TOL  # the default volumes are the lattice's: the block's volume


def test_the_volume_estimate_follows_marching_cubes_and_solves_for_the_level():
    p, lo, hi = block([8, 6, 9], [8, 8, 8])
    lo3, hi3 = (np.asarray(b, float) for b in DOMAIN3)
    f = surface_field.field(p, np.full(len(p), (DX / 2) ** 3), lo3, hi3, DX, 1, [])
    labels, n, targets = surface_field.bodies(f)
    assert n == 1 and np.isclose(targets[0], np.prod(hi - lo))
    est = surface_field.VolumeEstimate(f.phi, f.sdf, DX, labels, n)
    levels = (0.35, 0.45, 0.55, 0.65)
    volumes = [est.volumes(c)[0] for c in levels]
    assert all(a > b for a, b in zip(volumes, volumes[1:]))
    for c, v in zip(levels, volumes):
        drawn = surface_module._mc_measure(surface_field.closed(f.phi, f.clip, DX, c), c, f.origin, f)[1]
        assert 1.0 <= v / drawn < 1.03  # marching cubes cuts the rounded edges with flat triangles: a little less
    (c,) = est.levels(targets)
    assert 0.35 < c < 0.55 and abs(est.volumes(c)[0] / targets[0] - 1) < 1e-6


_THREADS_SCRIPT = """
import sys, hashlib, numpy as np
from hybridmpm.render.surface import surface_mesh, write_surface
from hybridmpm.scenes.core import lattice
rng = np.random.default_rng(2)
p = lattice([0.1, 0.0625, 0.1], [0.5, 0.4, 0.45], 1 / 64).astype(float) + rng.normal(0, 0.002, (1, 3))
p = p + rng.normal(0, 0.003, p.shape)
m = surface_mesh(p, np.full(len(p), 5), domain=([0.0625] * 3, [0.9375] * 3), dx=1 / 32)[0]
write_surface(m, sys.argv[1])
"""


def test_same_bytes_with_one_and_two_threads(tmp_path):
    digests = []
    for threads in ("1", "2"):
        env = {**os.environ, "OMP_NUM_THREADS": threads, "OPENBLAS_NUM_THREADS": threads, "MKL_NUM_THREADS": threads, "RAYON_NUM_THREADS": threads}
        out = tmp_path / f"t{threads}.ply"
        subprocess.run([sys.executable, "-c", _THREADS_SCRIPT, str(out)], check=True, env=env)
        digests.append(hashlib.sha256(out.read_bytes()).hexdigest())
    assert digests[0] == digests[1]


@pytest.mark.parametrize("fmt", ["ply", "obj", "glb"])
def test_written_files_read_back_with_other_libraries(tmp_path, fmt):
    p, lo, hi = block([2, 0, 2], [6, 6, 6])
    (mesh,) = surface_mesh(p, np.full(len(p), GNS_WATER), domain=DOMAIN3, dx=DX)
    path = write_surface(mesh, tmp_path / f"s.{fmt}")
    back = trimesh.load(path, force="mesh", process=False)
    assert len(back.faces) == len(mesh.faces)
    assert back.is_watertight or fmt == "obj"  # OBJ carries no connectivity beyond indices; trimesh may split it
    assert abs(back.volume - mesh.volume) < 1e-6
    if fmt != "glb":
        m = meshio.read(path)
        assert m.points.shape == mesh.vertices.shape
        assert np.allclose(m.points, mesh.vertices, atol=1e-6)


def test_2d_outlines_written_as_closed_edge_loops(tmp_path):
    p, _, _ = block([0, 0], [10, 10], dim=2)
    paths = export_surfaces(p[None], np.full(len(p), GNS_WATER), tmp_path, fmt="ply", domain=DOMAIN2, dx=DX)
    assert [x.name for x in paths] == ["water_00000.ply"]
    back = trimesh.load(paths[0], process=False)  # PLY edge elements: a path
    assert isinstance(back, trimesh.path.Path3D) and len(back.entities) == 1
    assert np.all(back.vertices[:, 2] == 0)
    (c,) = surface_contours(p, np.full(len(p), GNS_WATER), domain=DOMAIN2, dx=DX)
    assert len(back.vertices) == len(c.loops[0]) - 1  # the repeated closing point is not stored
    assert back.entities[0].closed
    with pytest.raises(InvalidInputError) as e:
        export_surfaces(p[None], np.full(len(p), GNS_WATER), tmp_path, fmt="glb", domain=DOMAIN2, dx=DX)
    assert e.value.field == "fmt"


@pytest.mark.parametrize(
    ("change", "field"),
    [
        ({"positions": np.full((4, 3), np.nan)}, "positions"),
        ({"positions": np.zeros((4, 2))}, "positions"),
        ({"positions": np.zeros((2, 4, 3))}, "positions"),
        ({"particle_type": np.zeros(3, np.int64)}, "particle_type"),
        ({"particle_type": np.zeros(4)}, "particle_type"),
        ({"dx": 0.0}, "dx"),
        ({"dx": -1.0}, "dx"),
        ({"dx": float("nan")}, "dx"),
        ({"dx": 1e-3}, "dx"),  # 1000^3 nodes > the cap
        ({"refine": 0}, "refine"),
        ({"iso": 1.0}, "iso"),
        ({"iso": "area"}, "iso"),
        ({"smooth": -1}, "smooth"),
        ({"domain": ([0, 0, 0], [1, 1])}, "domain"),
        ({"domain": ([1, 0, 0], [0, 1, 1])}, "domain"),
        ({"volumes": np.ones(3)}, "volumes"),
        ({"volumes": -np.ones(4)}, "volumes"),
        ({"obstacles": ["box"]}, "obstacles[0]"),
    ],
)
def test_bad_input_names_the_field(change, field):
    kw = {"positions": np.full((4, 3), 0.5), "particle_type": np.full(4, GNS_WATER), "domain": DOMAIN3, "dx": DX, **change}
    with pytest.raises(InvalidInputError) as e:
        surface_mesh(kw.pop("positions"), kw.pop("particle_type"), **kw)
    assert e.value.field == field
    assert 512**3 == MAX_GRID_NODES


def test_simulate_exports_point_clouds_and_meshes_and_export_rebuilds_them(tmp_path):
    out = tmp_path / "w3"
    args = ["simulate", "water3d", "--solver", "mpm", "--frames", "3", "--out", str(out), "--quiet", "--no-render", "--threads", "1"]
    assert main([*args, "--export", "ply", "mesh"]) == 0
    ex = out / "export"
    assert sorted(x.name for x in ex.glob("frame_*.ply")) == [f"frame_{t:05d}.ply" for t in range(4)]
    assert sorted(x.name for x in ex.glob("water_*.ply")) == [f"water_{t:05d}.ply" for t in range(4)]
    traj = np.load(out / "trajectory.npz")
    first = meshio.read(ex / "water_00000.ply")
    fluid = traj["positions"][0][traj["particle_type"] != GNS_KINEMATIC]
    # the first frame's surface wraps the initial blocks: their volume (mass / density), their bounds within half a cell
    tm = trimesh.Trimesh(first.points, first.cells_dict["triangle"], process=False)
    assert tm.is_watertight
    volume = traj["masses"][traj["particle_type"] != GNS_KINEMATIC].sum() / MpmParams(dim=3).water.density
    assert abs(tm.volume / volume - 1) < 0.05
    spacing = 1 / 128  # water3d: 64 cells, 2 particles per cell per axis
    assert np.all(np.abs(first.points.min(axis=0) - (fluid.min(axis=0) - spacing / 2)) < 0.5 / 64)
    assert np.all(np.abs(first.points.max(axis=0) - (fluid.max(axis=0) + spacing / 2)) < 0.5 / 64)
    # export from the saved trajectory: the same bytes
    again = tmp_path / "again"
    assert main(["export", str(out / "trajectory.npz"), "--mesh", "--out", str(again), "--quiet"]) == 0
    for t in range(4):
        assert (again / f"water_{t:05d}.ply").read_bytes() == (ex / f"water_{t:05d}.ply").read_bytes()


def test_export_needs_something_to_write(tmp_path):
    out = tmp_path / "db"
    assert main(["simulate", "dam_break2d", "--solver", "mpm", "--frames", "1", "--out", str(out), "--quiet", "--no-render", "--export", "ply"]) == 0
    assert len(list((out / "export").glob("frame_*.ply"))) == 2  # --export ply keeps writing the point clouds
    r = main(["export", str(out / "trajectory.npz"), "--out", str(tmp_path / "x"), "--quiet"])
    assert r == 2
    assert main(["export", str(out / "trajectory.npz"), "--mesh", "--mesh-format", "obj", "--out", str(tmp_path / "x"), "--quiet"]) == 0
    text = Path(tmp_path / "x" / "water_00001.obj").read_text()
    assert text.count("\nl ") == text.count("\nv ") > 10  # closed outlines: one edge per point
