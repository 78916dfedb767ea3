"""Mesh bodies from big meshes (docs/bodies.md "Shapes"): ``Body.sdf`` (the
core's distance) holds only its ``N`` distances, and a hull of
more than ``MAX_HULL_FACES`` triangles is cut to a lattice's cubes
(``simplify_hull``): an 81,920-triangle icosphere STL in a 24³ tank builds
and runs in a few seconds and a few tens of MB (it asked for 7-11 GiB and
died), its hull within the cap, its volume within 2 % of the sphere's, the
same vertices each time and from the file as inline."""

from __future__ import annotations

import time
import tracemalloc

import numpy as np
import pytest
from scipy.spatial import ConvexHull

from hybridmpm.errors import InvalidInputError
from hybridmpm.mpm.bodies import Body
from hybridmpm.scenes.body_mesh import HULL_LATTICE_CELLS, MAX_HULL_FACES, resolve_mesh_body, simplify_hull
from hybridmpm.scenes.spec import SceneSpec
from hybridmpm.sim import MpmSimulator, rollout

R = 0.15  # the icosphere's radius [m]
N_GRID = 24


def fibonacci_sphere(n: int, r: float) -> np.ndarray:
    """``n`` points spread over a sphere of radius ``r`` [m], float64 [n, 3]: a hull of 2n - 4 triangles."""
    i = np.arange(n) + 0.5
    polar, azimuth = np.arccos(1.0 - 2.0 * i / n), np.pi * (1.0 + 5.0**0.5) * i
    return np.stack([np.cos(azimuth) * np.sin(polar), np.sin(azimuth) * np.sin(polar), np.cos(polar)], axis=1) * r


@pytest.fixture(scope="module")
def ico(tmp_path_factory):
    """A folder holding ``ico.stl`` (an icosphere of 81,920 triangles, radius R, watertight) and ``scene.toml``
    (a 24³ water tank with it as a 500 kg/m³ body above the water); the mesh's vertices as float32 [40962, 3]."""
    trimesh = pytest.importorskip("trimesh")
    d = tmp_path_factory.mktemp("ico")
    mesh = trimesh.creation.icosphere(subdivisions=6, radius=R)
    assert len(mesh.faces) == 81_920 and mesh.is_watertight
    mesh.export(d / "ico.stl")
    (d / "scene.toml").write_text(
        f"""name = "ico"
dim = 3
n_grid = {N_GRID}

[[blocks]]
material = "water"
lo = [0.1, 0.1, 0.1]
hi = [0.9, 0.35, 0.9]

[[bodies]]
shape = "mesh"
path = "ico.stl"
center = [0.5, 0.6, 0.5]
density = 500.0
"""
    )
    return d, np.asarray(mesh.vertices, np.float32)


def hull_planes(hull: dict[str, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """A hull's face planes, independently of the core: outward unit normals float64 [F, 3] and offsets [F] [m]."""
    v = np.asarray(hull["vertices"], np.float64)
    t = v[np.asarray(hull["faces"], np.int64)]
    n = np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0])
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    return n, np.einsum("fk,fk->f", n, t[:, 0])


def test_sdf_of_a_big_hull_at_many_points_holds_only_its_distances():
    # a hull of 4,096 faces at 32,768 points: 134 M point-plane distances, 1 GiB as one numpy product
    body = Body(shape="mesh", center=[0.5, 0.5, 0.5], vertices=fibonacci_sphere(2050, 0.2).tolist(), density=500.0)
    assert len(body.hull()["faces"]) == 4096
    p = np.random.default_rng(0).uniform(0.2, 0.8, (32_768, 3))
    tracemalloc.start()
    try:
        tracemalloc.reset_peak()
        base = tracemalloc.get_traced_memory()[0]
        d = body.sdf(p)
        peak = tracemalloc.get_traced_memory()[1] - base
    finally:
        tracemalloc.stop()
    assert peak < 4 * p.nbytes, f"{peak / 2**20:.1f} MiB"  # the distances and the points' copies, no [N, F] block
    r = np.linalg.norm(p - body.center_of_mass(3), axis=1)
    inside = r < 0.19  # the hull's faces lie within 0.2 m and, with 4,096 of them, outside 0.19 m
    assert (d[inside] < 0).all() and (d[r > 0.2] > 0).all()


def test_sdf_of_a_hull_is_its_largest_face_plane_distance():
    body = Body(shape="mesh", center=[0.4, 0.5, 0.45], vertices=fibonacci_sphere(40, 0.1).tolist(), density=500.0, rotation=[[0, -1, 0], [1, 0, 0], [0, 0, 1]])
    p = np.random.default_rng(1).uniform(0.2, 0.7, (97, 3))
    c, rot = np.array([0.41, 0.52, 0.46]), np.array([[1.0, 0, 0], [0, 0, -1], [0, 1, 0]])
    n, off = hull_planes(body.hull())
    for args in ((), (c, rot)):
        got = body.sdf(p, *args)
        # a brute force over the planes point by point, in float64 (the core's distance is float32)
        q = (p - (body.center_of_mass(3) if not args else c)) @ (body.rotation_matrix(3) if not args else rot)
        brute = np.array([max(float(np.dot(nk, x)) - ok for nk, ok in zip(n, off)) for x in q])
        assert got.dtype == np.float64 and got.shape == (97,)
        np.testing.assert_allclose(got, brute, rtol=0, atol=2e-7)


def test_sdf_of_the_primitive_shapes_matches_their_closed_forms():
    rng = np.random.default_rng(2)
    theta = 0.7
    rot2 = np.array([[np.cos(theta), -np.sin(theta)], [np.sin(theta), np.cos(theta)]])
    p2 = rng.uniform(0.0, 1.0, (200, 2))
    box = Body(shape="box", center=[0.5, 0.4], half_extents=[0.2, 0.1], angle_deg=float(np.degrees(theta)), density=500.0)
    q = (p2 - [0.5, 0.4]) @ rot2
    e = np.abs(q) - [0.2, 0.1]
    want = np.linalg.norm(np.maximum(e, 0.0), axis=1) + np.minimum(e.max(axis=1), 0.0)
    np.testing.assert_allclose(box.sdf(p2), want, rtol=0, atol=3e-7)
    p3 = rng.uniform(0.0, 1.0, (200, 3))
    ball = Body(shape="sphere", center=[0.5, 0.5, 0.5], radius=0.15, density=500.0)
    np.testing.assert_allclose(ball.sdf(p3), np.linalg.norm(p3 - 0.5, axis=1) - 0.15, rtol=0, atol=3e-7)
    cap = Body(shape="capsule", center=[0.5, 0.5, 0.5], radius=0.1, half_height=0.2, density=500.0)
    q3 = p3 - 0.5
    q3[:, 1] -= np.clip(q3[:, 1], -0.2, 0.2)
    np.testing.assert_allclose(cap.sdf(p3), np.linalg.norm(q3, axis=1) - 0.1, rtol=0, atol=3e-7)
    # moved and turned: the same distances of the points moved with it
    turn = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    np.testing.assert_allclose(cap.sdf(0.5 + (p3 - 0.5) @ turn.T + 0.05, [0.55, 0.55, 0.55], turn), cap.sdf(p3), rtol=0, atol=3e-7)
    for bad, field in (([[0.1, 0.2, 0.3, 0.4]], "points"), ([[np.nan, 0.2, 0.3]], "points")):
        with pytest.raises(InvalidInputError, match=field):
            ball.sdf(np.array(bad))
    with pytest.raises(InvalidInputError, match="center"):
        ball.sdf(p3, [0.5, 0.5], np.eye(3))


def test_an_81920_triangle_icosphere_builds_and_runs_in_bounded_memory_and_time(ico):
    d, _ = ico
    t0 = time.perf_counter()
    tracemalloc.start()
    try:
        spec = SceneSpec.load(d / "scene.toml")
        body = spec.params.bodies[0]
        # checked before anything evaluates the hull at the particles (unbounded before: 10.6 GiB at once)
        assert len(body.hull()["faces"]) <= MAX_HULL_FACES
        scene = spec.build()
        sim = MpmSimulator(scene, threads=1)
        rollout(sim, 2)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    took = time.perf_counter() - t0
    assert peak < 500 * 2**20, f"{peak / 2**20:.0f} MiB traced"
    assert took < 30.0, f"{took:.1f} s"
    # the water stays out of the body, which floats where it was put
    assert (body.sdf(scene.positions) >= 0).all()
    np.testing.assert_allclose(sim.bodies.center[0], [0.5, 0.6, 0.5], atol=0.01)
    (report,) = spec.info["simplified_body_hulls"]
    assert report["field"] == "bodies[0].path" and report["faces_given"] == 81_920 and report["n_grid"] == N_GRID
    assert report["faces"] == len(body.hull()["faces"])
    # the mass is the simplified hull's: within 2 % of the sphere's, below it (the hull lies inside the mesh's)
    sphere = 4.0 / 3.0 * np.pi * R**3
    assert 0.98 * sphere < body.hull()["volume"] < sphere
    assert sim.bodies.mass[0] == pytest.approx(500.0 * body.hull()["volume"], rel=1e-5)


def test_the_simplified_hull_is_within_its_stated_tolerance_and_deterministic(ico):
    d, verts = ico
    mesh = {"shape": "mesh", "path": "ico.stl", "center": [0.5, 0.6, 0.5], "density": 500.0}
    reports: list[dict] = []
    a = resolve_mesh_body(dict(mesh), "bodies[0]", 3, base_dir=d, n_grid=N_GRID, simplified=reports)
    b = resolve_mesh_body(dict(mesh), "bodies[0]", 3, base_dir=d, n_grid=N_GRID)
    assert a == b  # the same vertices, bit for bit
    kept = np.asarray(a["vertices"], np.float64)
    hull = Body.from_dict(a, "bodies[0]", 3).hull()
    assert len(hull["faces"]) <= MAX_HULL_FACES and len(kept) <= MAX_HULL_FACES // 2 + 2
    (report,) = reports
    tol = report["tolerance_m"]
    assert HULL_LATTICE_CELLS / N_GRID * 3**0.5 <= tol < 2.0 / N_GRID  # a quarter cell's diagonal at least, under 2 cells
    # a subset of the mesh's vertices (so inside its hull), and every vertex within tol of the simplified hull
    assert {tuple(x) for x in kept.astype(np.float32).tolist()} <= {tuple(x) for x in verts.tolist()}
    eq = ConvexHull(kept).equations
    outside = (verts.astype(np.float64) @ eq[:, :3].T + eq[:, 3]).max(axis=1)
    assert 0 < outside.max() <= tol
    # the same points given inline, in the mesh's order (not the file's), come out the same; resolved again, nothing changes
    inline = resolve_mesh_body({**mesh, "path": None, "vertices": verts.tolist()}, "bodies[0]", 3, n_grid=N_GRID)
    assert inline["vertices"] == a["vertices"]
    assert resolve_mesh_body(a, "bodies[0]", 3, n_grid=N_GRID) is a
    # without the scene's grid (MpmSimulator.add_body): the finest grid's quarter cell, coarsened to the cap
    reports.clear()
    c = resolve_mesh_body(dict(mesh), "bodies[0]", 3, base_dir=d, simplified=reports)
    assert len(Body.from_dict(c, "bodies[0]", 3).hull()["faces"]) <= MAX_HULL_FACES and "n_grid" not in reports[0]


def test_a_hull_within_the_cap_is_kept_as_it_was(ico, tmp_path):
    trimesh = pytest.importorskip("trimesh")
    small = trimesh.creation.icosphere(subdivisions=3, radius=R)  # 1,280 triangles: over the cap
    smaller = trimesh.creation.icosphere(subdivisions=2, radius=R)  # 320: within it
    small.export(tmp_path / "small.stl")
    smaller.export(tmp_path / "smaller.stl")
    mesh = {"shape": "mesh", "center": [0.5, 0.6, 0.5], "density": 500.0}
    reports: list[dict] = []
    kept = resolve_mesh_body({**mesh, "path": "smaller.stl"}, "bodies[0]", 3, base_dir=tmp_path, n_grid=64, simplified=reports)
    assert reports == [] and len(kept["vertices"]) == 162
    assert simplify_hull(np.asarray(smaller.vertices, np.float32), "bodies[0].vertices", 64) is None
    cut = resolve_mesh_body({**mesh, "path": "small.stl"}, "bodies[0]", 3, base_dir=tmp_path, n_grid=64, simplified=reports)
    assert len(cut["vertices"]) < 642 and reports[0]["faces_given"] == 1280
    assert Body.from_dict(cut, "bodies[0]", 3).hull()["volume"] > 0.97 * 4.0 / 3.0 * np.pi * R**3
