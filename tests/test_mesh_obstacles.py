"""Mesh obstacles (``shape = "mesh"`` in a scene file): the sampled signed
distance against analytic shapes, MPM runs against the analytic sphere and
rotated box, penetration (no particle more than half a cell inside, in every
condition), saving and regridding, and every bad input.

The MPM comparisons here run on a 32³ grid for 120 frames;
benchmarks/bench_mesh_obstacle.py runs the 64³, 200-frame versions."""

from __future__ import annotations

import json
import math
import os
from pathlib import Path
from typing import Any

import numpy as np
import pytest

trimesh = pytest.importorskip("trimesh")

from hybridmpm.errors import InvalidInputError  # noqa: E402
from hybridmpm.metrics import grid_mass_error  # noqa: E402
from hybridmpm.mpm import Box, MpmSolver, Sphere  # noqa: E402
from hybridmpm.mpm.params import SampledSdf  # noqa: E402
from hybridmpm.scenes import SceneSpec, collider_sdf, obstacle_mesh  # noqa: E402
from hybridmpm.sim import MpmSimulator, rollout  # noqa: E402

N = 32
FRAMES = 120
CENTER = [0.5, 0.4, 0.5]
RADIUS = 0.15


def _scene(obstacles: list[dict[str, Any]], n: int = N, frames: int = FRAMES, dim: int = 3) -> dict[str, Any]:
    lo, hi = ([0.38, 0.62, 0.38], [0.62, 0.8, 0.62]) if dim == 3 else ([0.38, 0.62], [0.62, 0.8])
    return {"name": "mesh_test", "dim": dim, "n_grid": n, "frames": frames, "blocks": [{"material": "water", "lo": lo, "hi": hi}], "obstacles": obstacles}


def _rot_z(deg: float) -> np.ndarray:
    a = math.radians(deg)
    return np.array([[math.cos(a), -math.sin(a), 0.0], [math.sin(a), math.cos(a), 0.0], [0.0, 0.0, 1.0]])


@pytest.fixture(scope="module")
def meshes(tmp_path_factory: pytest.TempPathFactory) -> Path:
    d = tmp_path_factory.mktemp("meshes")
    trimesh.creation.icosphere(subdivisions=4, radius=1.0).export(d / "sphere.stl")
    trimesh.creation.box(extents=(2.0, 2.0, 2.0)).export(d / "cube.obj")
    trimesh.creation.box(extents=(2.0, 2.0, 2.0)).export(d / "cube.ply")
    trimesh.creation.box(extents=(2.0, 2.0, 2.0)).export(d / "cube.glb")
    return d


def _deepest(exact: Box | Sphere, pos: np.ndarray) -> float:
    """How deep the deepest particle of any frame of ``pos`` [T, N, 3] lies inside ``exact`` (the analytic
    shape), in grid cells (0 when none is inside)."""
    return float(-collider_sdf(exact, pos.reshape(-1, 3).astype(np.float64)).min(initial=0.0) * N)


def _rollout(spec: SceneSpec) -> np.ndarray:
    """Fluid positions of frames 1 … ``spec.frames``: float32 [T, N, 3]."""
    r = rollout(MpmSimulator(spec.build()), spec.frames)
    return np.asarray(r.positions[1:, : r.num_fluid])


# ------------------------------------------------------------------ the sampled signed distance
def test_sampled_sdf_matches_the_analytic_sphere_and_python_interpolates_the_samples(meshes: Path) -> None:
    spec = SceneSpec.from_dict(_scene([{"shape": "mesh", "path": "sphere.stl", "center": CENTER, "scale": RADIUS}], n=64), base_dir=meshes)
    c = spec.params.colliders[0]
    assert isinstance(c, SampledSdf)
    dx = 1 / 64
    assert c.cell == pytest.approx(dx)
    dims = np.asarray(c.values.shape)
    nodes = np.asarray(c.origin) + c.cell * np.stack(np.meshgrid(*[np.arange(n) for n in dims], indexing="ij"), -1).reshape(-1, 3)
    exact = np.linalg.norm(nodes - CENTER, axis=1) - RADIUS
    # icosphere(4) lies inside the sphere by at most r(1 - cos(half its edge angle)), 0.0003 m here
    assert np.abs(c.values.ravel() - exact).max() < 0.05 * dx
    # the grid covers the mesh plus the margin, on the scene's nodes
    assert np.allclose(np.asarray(c.origin) * 64, np.round(np.asarray(c.origin) * 64), atol=1e-4)
    assert c.values.ravel()[0] > 0 and dims.min() >= 2 * RADIUS * 64 + 2 * obstacle_mesh.MARGIN_CELLS - 1
    # collider_sdf: the same samples at the nodes, interpolated between, conservative outside
    assert np.allclose(collider_sdf(c, nodes), c.values.ravel(), atol=1e-6)
    top = np.asarray(c.origin) + c.cell * (dims - 1)
    p = np.random.default_rng(0).uniform(np.asarray(c.origin), top, (2000, 3))
    exact_p = np.linalg.norm(p - CENTER, axis=1) - RADIUS
    err = np.abs(collider_sdf(c, p) - exact_p)
    # interpolation error: O(dx²/R) near the surface, larger only at the cone point of the centre
    assert err[np.abs(exact_p) < 3 * dx].max() < 0.05 * dx and err.max() < 0.25 * dx
    # outside the sampled box: positive and never below the true distance
    far = np.array([[0.05, 0.05, 0.05], [0.95, 0.5, 0.5], [0.5, 0.9, 0.5]])
    assert np.all(collider_sdf(c, far) >= np.linalg.norm(far - CENTER, axis=1) - RADIUS - 1e-6)


def test_sampled_rotated_box_matches_the_analytic_box(meshes: Path) -> None:
    rot = _rot_z(-20.0)
    half = np.array([0.2, 0.05, 0.15])
    trimesh.creation.box(extents=2 * half).export(meshes / "slab.obj")
    ob = {"shape": "mesh", "path": "slab.obj", "center": [0.5, 0.3, 0.5], "rotation": rot.tolist()}
    c = SceneSpec.from_dict(_scene([ob], n=64), base_dir=meshes).params.colliders[0]
    box = Box(center=[0.5, 0.3, 0.5], half_extents=half.tolist(), rotation=rot.tolist())
    top = np.asarray(c.origin) + c.cell * (np.asarray(c.values.shape) - 1)
    p = np.random.default_rng(1).uniform(np.asarray(c.origin), top, (4000, 3))
    got, want = collider_sdf(c, p), collider_sdf(box, p)
    err = np.abs(got - want)
    near = np.abs(want) < 3 / 64
    # multilinear interpolation is exact for planes, off near edges, corners and the inner ridges only
    assert np.median(err[near]) < 0.02 / 64 and np.percentile(err[near], 95) < 0.2 / 64 and err.max() < 0.6 / 64
    clear = np.abs(want) > 0.5 / 64
    assert np.array_equal(got[clear] < 0, want[clear] < 0)


def test_every_file_kind_gives_the_same_samples(meshes: Path) -> None:
    vals = []
    for name in ("cube.obj", "cube.ply", "cube.glb"):
        spec = SceneSpec.from_dict(_scene([{"shape": "mesh", "path": name, "center": [0.5, 0.3125, 0.5], "scale": 0.1}]), base_dir=meshes)
        vals.append(spec.params.colliders[0].values)
    assert all(np.array_equal(v, vals[0]) for v in vals)
    assert vals[0].min() == pytest.approx(-0.1, abs=1e-6)  # the cube's centre is a node, 0.1 m inside


# ------------------------------------------------------------------ MPM against the analytic shapes
def test_mesh_sphere_follows_the_analytic_sphere(meshes: Path) -> None:
    mesh = SceneSpec.from_dict(_scene([{"shape": "mesh", "path": "sphere.stl", "center": CENTER, "scale": RADIUS}]), base_dir=meshes)
    ana = SceneSpec.from_dict(_scene([{"shape": "sphere", "center": CENTER, "radius": RADIUS}]))
    free = SceneSpec.from_dict(_scene([]))
    pm, pa, pf = _rollout(mesh), _rollout(ana), _rollout(free)
    err = grid_mass_error(pm, pa, N)
    assert err.max() <= 0.05, err.max()
    assert grid_mass_error(pf, pa, N).max() > 10 * err.max()  # the obstacle matters: without it the flow differs
    # no particle ends a frame more than half a cell inside the sphere (an independent, analytic distance)
    sphere = Sphere(center=CENTER, radius=RADIUS)
    assert _deepest(sphere, pm) <= 0.5 and _deepest(sphere, pa) <= 0.5, (_deepest(sphere, pm), _deepest(sphere, pa))


def test_mesh_box_ramp_follows_the_analytic_rotated_box(meshes: Path) -> None:
    half = [0.25, 0.04, 0.2]
    trimesh.creation.box(extents=2 * np.asarray(half)).export(meshes / "ramp.stl")
    rot = _rot_z(-20.0).tolist()
    centre = [0.5, 0.45, 0.5]
    mesh = SceneSpec.from_dict(_scene([{"shape": "mesh", "path": "ramp.stl", "center": centre, "rotation": rot}]), base_dir=meshes)
    ana = SceneSpec.from_dict(_scene([{"shape": "box", "center": centre, "half_extents": half, "rotation": rot}]))
    free = SceneSpec.from_dict(_scene([]))
    pm, pa, pf = _rollout(mesh), _rollout(ana), _rollout(free)
    err = grid_mass_error(pm, pa, N)
    assert err.max() <= 0.05, err.max()
    assert grid_mass_error(pf, pa, N).max() > 10 * err.max()
    box = Box(center=centre, half_extents=half, rotation=rot)
    assert _deepest(box, pm) <= 0.5 and _deepest(box, pa) <= 0.5, (_deepest(box, pm), _deepest(box, pa))


def test_a_body_rests_on_a_mesh_shelf_as_on_the_box(tmp_path: Path) -> None:
    """Bodies meet mesh obstacles in their rigid world, as voxels of the sampled distance (docs/bodies.md "Shapes"):
    a heavy crate dropped on a mesh slab rests on it within half a cell of its top face, as on the same slab as a
    box obstacle (without the contact it falls through to the floor)."""
    trimesh.creation.box(extents=(0.4, 0.1, 0.4)).export(tmp_path / "slab.obj")
    crate = {"shape": "box", "center": [0.5, 0.47, 0.5], "half_extents": [0.06, 0.06, 0.06], "density": 2000.0}

    def bottom(shelf: dict[str, Any]) -> float:
        d = {
            "name": "shelf", "dim": 3, "n_grid": N, "frames": 60,
            "blocks": [{"material": "water", "lo": [0.8, 0.1, 0.8], "hi": [0.9, 0.2, 0.9]}],
            "obstacles": [shelf], "bodies": [crate],
        }  # fmt: skip
        sim = MpmSimulator(SceneSpec.from_dict(d, base_dir=tmp_path).build())
        rollout(sim, 60)
        return float(sim.bodies.center[0, 1]) - 0.06

    top, dx = 0.35, 1.0 / N
    box = bottom({"shape": "box", "center": [0.5, 0.3, 0.5], "half_extents": [0.2, 0.05, 0.2]})
    mesh = bottom({"shape": "mesh", "path": "slab.obj", "center": [0.5, 0.3, 0.5]})
    print(f"crate bottom on the box {box:.5f}, on the mesh {mesh:.5f} (top face {top}; cell {dx:.5f})")
    assert abs(box - top) < 0.1 * dx, box
    assert abs(mesh - top) < 0.6 * dx, mesh


def test_a_body_on_a_mesh_keeps_its_bits_on_any_thread_count_and_through_a_checkpoint(tmp_path: Path) -> None:
    """Water poured on a crate that rests on a mesh slab: 1 and 2 threads give the same bits, bodies included, and a
    checkpoint taken half way restores into a fresh simulator that goes on bit for bit (its voxels made again from the
    same samples)."""
    trimesh.creation.box(extents=(0.4, 0.1, 0.4)).export(tmp_path / "slab.obj")
    d = {
        "name": "shelf", "dim": 3, "n_grid": N, "frames": 30,
        "blocks": [{"material": "water", "lo": [0.4, 0.6, 0.4], "hi": [0.6, 0.75, 0.6]}],
        "obstacles": [{"shape": "mesh", "path": "slab.obj", "center": [0.5, 0.3, 0.5]}],
        "bodies": [{"shape": "box", "center": [0.45, 0.45, 0.5], "half_extents": [0.06, 0.06, 0.06], "density": 800.0}],
    }  # fmt: skip

    def sim(threads: int) -> MpmSimulator:
        return MpmSimulator(SceneSpec.from_dict(d, base_dir=tmp_path).build(), threads=threads)

    one, two = sim(1), sim(2)
    rollout(one, 15)
    state = one.state()
    r1, r2 = rollout(one, 15), rollout(two, 30)
    assert np.array_equal(r1.positions[-1], r2.positions[-1]) and np.array_equal(r1.body_center[-1], r2.body_center[-1])
    back = sim(1)
    back.restore(state)
    r3 = rollout(back, 15)
    assert np.array_equal(r3.positions, r1.positions) and np.array_equal(r3.body_rotation, r1.body_rotation)
    assert not np.array_equal(r1.body_center[0], r1.body_center[-1])  # the water moved the crate


@pytest.mark.parametrize("condition", ["sticky", "slip"])
def test_no_particle_ends_half_a_cell_inside_in_any_condition(meshes: Path, condition: str) -> None:
    """The sphere and the rotated box of the two tests above (which run ``separate``), mesh and analytic,
    in the other conditions: no particle more than half a cell inside at any frame's end. Without the
    particle projection (``project = false``) the analytic sphere lets them deeper with ``slip`` (``sticky``
    holds them to ~0.14 cells on its own here)."""
    ramp = {"center": [0.5, 0.45, 0.5], "half_extents": [0.25, 0.04, 0.2], "rotation": _rot_z(-20.0).tolist()}
    trimesh.creation.box(extents=2 * np.asarray(ramp["half_extents"])).export(meshes / "ramp.stl")
    cases = [
        (Sphere(center=CENTER, radius=RADIUS), {"shape": "mesh", "path": "sphere.stl", "center": CENTER, "scale": RADIUS}),
        (Sphere(center=CENTER, radius=RADIUS), {"shape": "sphere", "center": CENTER, "radius": RADIUS}),
        (Box(**ramp), {"shape": "mesh", "path": "ramp.stl", "center": ramp["center"], "rotation": ramp["rotation"]}),
        (Box(**ramp), {"shape": "box", **ramp}),
    ]
    for exact, ob in cases:
        pos = _rollout(SceneSpec.from_dict(_scene([{**ob, "condition": condition}]), base_dir=meshes))
        assert _deepest(exact, pos) <= 0.5, (condition, ob["shape"], _deepest(exact, pos))
    if condition == "slip":
        off = _rollout(SceneSpec.from_dict(_scene([{**cases[1][1], "condition": condition, "project": False}])))
        assert _deepest(cases[1][0], off) > 0.5, (condition, _deepest(cases[1][0], off))


def test_boundary_particles_lie_on_the_mesh_surface_deterministically(meshes: Path) -> None:
    ob = {"shape": "mesh", "path": "sphere.stl", "center": CENTER, "scale": RADIUS}
    a = SceneSpec.from_dict(_scene([ob]), base_dir=meshes).build().boundary_positions
    b = SceneSpec.from_dict(_scene([ob]), base_dir=meshes).build().boundary_positions
    ana = SceneSpec.from_dict(_scene([{"shape": "sphere", "center": CENTER, "radius": RADIUS}])).build().boundary_positions
    assert a is not None and b is not None and ana is not None
    assert np.array_equal(a, b)
    s = 1 / (2 * N)
    r = np.linalg.norm(a - CENTER, axis=1)
    assert r.max() <= RADIUS + 0.02 * s and r.min() >= RADIUS - s - 0.1 / N
    assert abs(len(a) - len(ana)) < 0.15 * len(ana)


# ------------------------------------------------------------------ saving, regridding, the solver
def test_save_keeps_the_mesh_description_and_regridding_samples_again(meshes: Path, tmp_path: Path) -> None:
    ob = {"shape": "mesh", "path": "sphere.stl", "center": CENTER, "scale": RADIUS, "condition": "slip", "friction": 0.2}
    spec = SceneSpec.from_dict(_scene([ob]), base_dir=meshes)
    saved = spec.save(meshes / "saved.toml")
    text = saved.read_text()
    assert 'path = "sphere.stl"' in text and "values" not in text
    again = SceneSpec.load(saved)
    assert again.params.colliders[0] == spec.params.colliders[0]
    moved = spec.save(tmp_path / "elsewhere.json")
    assert SceneSpec.load(moved).params.colliders[0] == spec.params.colliders[0]
    fine = spec.on_grid(48)
    c48 = fine.params.colliders[0]
    assert isinstance(c48, SampledSdf) and c48.cell == pytest.approx(1 / 48) and c48.condition == "slip"
    top = np.asarray(c48.origin) + c48.cell * (np.asarray(c48.values.shape) - 1)
    p = np.random.default_rng(2).uniform(np.asarray(c48.origin), top, (2000, 3))
    exact = np.linalg.norm(p - CENTER, axis=1) - RADIUS
    assert np.abs(collider_sdf(c48, p) - exact)[np.abs(exact) < 3 / 48].max() < 0.1 / 48
    MpmSolver(fine.params)  # the solver takes the new samples


def test_the_solver_refuses_a_thin_sampled_grid() -> None:
    from hybridmpm.mpm import MpmParams

    values = np.full((4, 4, 4), 0.01, np.float32)
    values[1:3, 1:3, 1:3] = -0.2 / 32  # 0.2 cells deep
    params = MpmParams(dim=3, n_grid=32, colliders=[SampledSdf(origin=[0.4, 0.4, 0.4], cell=1 / 32, values=values)])
    with pytest.raises(InvalidInputError) as e:
        MpmSolver(params)
    assert e.value.field == "colliders[0].values"
    values[1:3, 1:3, 1:3] = -1.5 / 32
    MpmSolver(params)


# ------------------------------------------------------------------ bad input
def _err(d: dict[str, Any], base: Path, confine: bool = False) -> InvalidInputError:
    with pytest.raises(InvalidInputError) as e:
        SceneSpec.from_dict(d, base_dir=base, confine=confine)
    return e.value


def _mesh(**kw: Any) -> dict[str, Any]:
    return {"shape": "mesh", "path": "sphere.stl", "center": CENTER, "scale": RADIUS, **kw}


def test_bad_mesh_files_are_refused_naming_the_path(meshes: Path, tmp_path: Path) -> None:
    (tmp_path / "garbage.stl").write_bytes(b"\x00\x01 this is no mesh" * 5)
    (tmp_path / "text.obj").write_text("hello world\n")
    (tmp_path / "adir.obj").mkdir()
    open_box = trimesh.creation.box(extents=(2, 2, 2))
    open_box.update_faces(np.arange(len(open_box.faces)) != 0)
    open_box.export(tmp_path / "open.stl")
    (tmp_path / "nan.obj").write_text("v 0 0 0\nv 1 0 0\nv 0 nan 0\nv 0 0 1\nf 1 2 3\nf 1 2 4\nf 1 3 4\nf 2 3 4\n")
    tet = "v 0 0 0\nv 1 0 0\nv 0 1 0\nv 0 0 1\nv 2 0 0\nf 1 3 2\nf 1 2 4\nf 1 4 3\nf 2 3 4\nf 1 2 5\n"
    (tmp_path / "degenerate.obj").write_text(tet)
    trimesh.creation.icosphere(subdivisions=1).export(tmp_path / "small.stl")
    for name in ("missing.stl", "garbage.stl", "text.obj", "adir.obj", "open.stl", "nan.obj", "degenerate.obj", "sphere.ply.txt"):
        e = _err(_scene([_mesh(path=name)]), tmp_path)
        assert e.field == "obstacles[0].path", (name, e)
    assert "watertight" in str(_err(_scene([_mesh(path="open.stl")]), tmp_path))
    assert "degenerate" in str(_err(_scene([_mesh(path="degenerate.obj")]), tmp_path))
    assert "non-finite" in str(_err(_scene([_mesh(path="nan.obj")]), tmp_path))


def test_too_many_triangles_and_a_thin_mesh_are_refused(meshes: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(obstacle_mesh, "MAX_MESH_TRIANGLES", 1000)  # icosphere(4) has 5120
    e = _err(_scene([_mesh()]), meshes)
    assert e.field == "obstacles[0].path" and "5120 triangles" in str(e)
    monkeypatch.undo()
    trimesh.creation.box(extents=(0.3, 1.5 / N, 0.3)).export(meshes / "plate.stl")  # 1.5 cells thick
    e = _err(_scene([_mesh(path="plate.stl", scale=1.0, center=[0.5, 0.3125, 0.5])]), meshes)
    assert e.field == "obstacles[0].path" and "thinner" in str(e)
    trimesh.creation.box(extents=(0.3, 3.0 / N, 0.3)).export(meshes / "thick.stl")  # 3 cells: held
    SceneSpec.from_dict(_scene([_mesh(path="thick.stl", scale=1.0, center=[0.5, 0.3125, 0.5])]), base_dir=meshes)


@pytest.mark.parametrize(
    ("change", "field"),
    [
        ({"scale": 0.0}, "scale"),
        ({"scale": -1.0}, "scale"),
        ({"scale": float("nan")}, "scale"),
        ({"scale": float("inf")}, "scale"),
        ({"scale": True}, "scale"),
        ({"scale": "1"}, "scale"),
        ({"center": [0.5, 0.5]}, "center"),
        ({"center": [0.5, float("nan"), 0.5]}, "center"),
        ({"center": [0.95, 0.5, 0.5]}, "center"),  # sticks out of the domain
        ({"center": [3.0, 3.0, 3.0]}, "center"),  # wholly outside
        ({"rotation": [[1, 0, 0], [0, 2, 0], [0, 0, 1]]}, "rotation"),
        ({"rotation": [[1, 0], [0, 1]]}, "rotation"),
        ({"angle_deg": 20.0}, "angle_deg"),
        ({"friction": -1.0}, "friction"),
        ({"condition": "glue"}, "condition"),
        ({"radius": 0.1}, "radius"),
        ({"path": 3}, "path"),
        ({"path": ""}, "path"),
    ],
)
def test_bad_mesh_obstacle_fields_are_refused_naming_them(meshes: Path, change: dict[str, Any], field: str) -> None:
    e = _err(_scene([_mesh(**change)]), meshes)
    assert e.field == f"obstacles[0].{field}", e


def test_a_2d_scene_refuses_a_mesh(meshes: Path) -> None:
    e = _err(_scene([_mesh(center=[0.5, 0.4])], dim=2), meshes)
    assert e.field == "obstacles[0].shape" and "3D only" in str(e)


def test_confined_paths_stay_in_the_scene_folder(tmp_path: Path) -> None:
    scene_dir = tmp_path / "served"
    (scene_dir / "sub").mkdir(parents=True)
    trimesh.creation.icosphere(subdivisions=2).export(scene_dir / "sub" / "ok.stl")
    trimesh.creation.icosphere(subdivisions=2).export(tmp_path / "outside.stl")
    os.symlink(tmp_path / "outside.stl", scene_dir / "link.stl")
    for i, path in enumerate((str(tmp_path / "outside.stl"), "../outside.stl", "sub/../../outside.stl", "link.stl")):
        d = _scene([{"shape": "box", "center": [0.2, 0.2, 0.2], "half_extents": [0.05, 0.05, 0.05]}, _mesh(path=path)])
        f = scene_dir / f"scene{i}.json"
        f.write_text(json.dumps(d))
        with pytest.raises(InvalidInputError) as e:
            SceneSpec.load(f, confine=True)
        assert e.value.field == "obstacles[1].path", (path, e.value)
        SceneSpec.load(f)  # trusted: allowed
    f = scene_dir / "good.json"
    f.write_text(json.dumps(_scene([_mesh(path="sub/ok.stl")])))
    assert isinstance(SceneSpec.load(f, confine=True).params.colliders[0], SampledSdf)
