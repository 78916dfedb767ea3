"""Capsules and mesh bodies (docs/bodies.md "Shapes"): scene files, masses
against the analytic values, a mesh read from a file taken as its convex
hull (scipy's volume), bad input named and nothing changed, checkpoints bit
for bit, their meshes in exports, and the service's description and
request schema."""

from __future__ import annotations

import numpy as np
import pytest
from pydantic import ValidationError
from scipy.spatial import ConvexHull

from hybridmpm.errors import InvalidInputError
from hybridmpm.mpm.bodies import Body
from hybridmpm.render.bodies import body_surface, local_mesh, local_outline
from hybridmpm.scenes.body_mesh import resolve_mesh_body
from hybridmpm.scenes.spec import SceneSpec
from hybridmpm.service.schemas import MAX_BODY_VERTICES, BodyAdd
from hybridmpm.sim import MpmSimulator, rollout

CAPSULE = {"shape": "capsule", "center": [0.5, 0.35], "radius": 0.04, "half_height": 0.06, "angle_deg": 90.0, "density": 500.0}


def write_obj(path, vertices, faces) -> str:
    """An OBJ file of ``vertices`` [V, 3] and triangles ``faces`` [F, 3] (0-based)."""
    lines = [f"v {float(x)!r} {float(y)!r} {float(z)!r}" for x, y, z in np.asarray(vertices, float)]
    lines += [f"f {a + 1} {b + 1} {c + 1}" for a, b, c in faces]
    path.write_text("\n".join(lines) + "\n")
    return str(path)


def box_obj(path, h=(1.0, 1.0, 1.0)) -> str:
    """A box of half extents ``h`` about the origin, 12 outward triangles."""
    corners = np.array([[(1 if (k >> a) & 1 else -1) * h[a] for a in range(3)] for k in range(8)], float)
    faces = [[0, 2, 3], [0, 3, 1], [4, 5, 7], [4, 7, 6], [0, 1, 5], [0, 5, 4], [2, 6, 7], [2, 7, 3], [0, 4, 6], [0, 6, 2], [1, 3, 7], [1, 7, 5]]
    return write_obj(path, corners, faces)


def l_obj(path) -> str:
    """An L-shaped prism (the unit square's three quarters, 1 deep): not convex."""
    outline = [[0, 0], [1, 0], [1, 0.5], [0.5, 0.5], [0.5, 1], [0, 1]]
    v = [[x, y, z] for x, y in outline for z in (0.0, 1.0)]
    k = len(outline)
    faces = []
    for i in range(k):
        j = (i + 1) % k
        faces += [[2 * i, 2 * j, 2 * j + 1], [2 * i, 2 * j + 1, 2 * i + 1]]
    # the two L faces as triangles: (0,1,2,3) rectangle, (0,3,4,5) rectangle
    for quad in ([0, 1, 2, 3], [0, 3, 4, 5]):
        a, b, c, d = quad
        faces += [[2 * a, 2 * d, 2 * c], [2 * a, 2 * c, 2 * b], [2 * a + 1, 2 * b + 1, 2 * c + 1], [2 * a + 1, 2 * c + 1, 2 * d + 1]]
    return write_obj(path, v, faces)


def tank3(bodies: list[dict], top: float = 0.3) -> dict:
    return {"name": "t3", "dim": 3, "n_grid": 32, "blocks": [{"material": "water", "lo": [0.1, 0.1, 0.1], "hi": [0.9, top, 0.9]}], "bodies": bodies}


def body_bits(sim: MpmSimulator) -> np.ndarray:
    return np.asarray(sim.solver._core.bodies()["state"])


def test_capsule_scene_mass_outline_and_checkpoint_bit_for_bit():
    spec = SceneSpec.from_dict(
        {"name": "c", "dim": 2, "n_grid": 64, "blocks": [{"material": "water", "lo": [0.3, 0.05], "hi": [0.7, 0.3]}], "bodies": [CAPSULE]}
    )
    a = MpmSimulator(spec.build(), threads=1)
    r, h = 0.04, 0.06
    assert a.bodies.mass[0] == pytest.approx(500.0 * (4 * r * h + np.pi * r * r), rel=1e-6)
    body = spec.params.bodies[0]
    # no particle seeded inside it; its outline lies on its surface
    assert (body.sdf(a.fluid_positions) >= 0).all()
    pose = (a.bodies.center[0], a.bodies.rotation[0])
    assert np.abs(body.sdf(body_surface(body, *pose).loops[0], *pose)).max() < 1e-6  # the core's distance is float32
    rollout(a, 10)
    state = a.state()
    rollout(a, 10)
    b = MpmSimulator(spec.build(), threads=1)
    b.restore(state)
    rollout(b, 10)
    assert np.array_equal(a.fluid_positions, b.fluid_positions) and np.array_equal(body_bits(a), body_bits(b))
    assert not np.array_equal(body_bits(a)[:, 7:10], 0)


def test_a_box_mesh_has_the_boxs_mass_and_its_origin_goes_to_center(tmp_path):
    box_obj(tmp_path / "box.obj")
    # the file's box is centred on its origin; shifted by the rotation the centre of mass stays at center
    spec = SceneSpec.from_dict(
        tank3(
            [{"shape": "mesh", "path": "box.obj", "scale": 0.05, "center": [0.5, 0.45, 0.5], "density": 400.0, "rotation": [[0, -1, 0], [1, 0, 0], [0, 0, 1]]}]
        ),
        base_dir=tmp_path,
    )
    sim = MpmSimulator(spec.build(), threads=1)
    assert sim.bodies.mass[0] == pytest.approx(400.0 * 0.1**3, rel=1e-5)
    np.testing.assert_allclose(sim.bodies.center[0], [0.5, 0.45, 0.5], atol=1e-7)
    b = spec.params.bodies[0]
    assert b.path == "box.obj" and b.scale is None and len(b.vertices) == 8
    v, f = local_mesh(b)
    assert np.abs(np.abs(v) - 0.05).max() < 1e-7 and f.shape == (12, 3)
    # a mesh whose origin is off its centre: the centre of mass is the hull's
    write_obj(tmp_path / "off.obj", np.array([[(1 if (k >> a) & 1 else -1) for a in range(3)] for k in range(8)]) + [2.0, 0, 0], _BOX_TRIS)
    off = Body.from_dict(
        resolve_mesh_body({"shape": "mesh", "path": str(tmp_path / "off.obj"), "scale": 0.05, "center": [0.4, 0.6, 0.5], "density": 400.0}, "bodies[0]", 3)
    )
    np.testing.assert_allclose(off.center_of_mass(3), [0.5, 0.6, 0.5], atol=1e-7)


_BOX_TRIS = [[0, 2, 3], [0, 3, 1], [4, 5, 7], [4, 7, 6], [0, 1, 5], [0, 5, 4], [2, 6, 7], [2, 7, 3], [0, 4, 6], [0, 6, 2], [1, 3, 7], [1, 7, 5]]


def test_a_non_convex_mesh_is_its_convex_hull(tmp_path):
    l_obj(tmp_path / "l.obj")
    b = Body.from_dict(
        resolve_mesh_body({"shape": "mesh", "path": str(tmp_path / "l.obj"), "scale": 0.2, "center": [0.4, 0.4, 0.4], "density": 1000.0}, "bodies[0]", 3)
    )
    pts = np.array([[x, y, z] for x, y in [[0, 0], [1, 0], [1, 0.5], [0.5, 0.5], [0.5, 1], [0, 1]] for z in (0.0, 1.0)]) * 0.2
    want = ConvexHull(pts).volume
    assert b.hull()["volume"] == pytest.approx(want, rel=1e-5)
    assert want == pytest.approx(0.875 * 0.008, rel=1e-9)  # the L's own volume is 0.75 of the prism's
    mass = MpmSimulator(SceneSpec.from_dict(tank3([b.to_dict()], top=0.2)).build(), threads=1).bodies.mass[0]
    assert mass == pytest.approx(1000.0 * want, rel=1e-5)


@pytest.mark.parametrize(
    ("change", "field"),
    [
        ({"radius": float("nan")}, "bodies[0].radius"),
        ({"radius": -0.04}, "bodies[0].radius"),
        ({"half_height": -0.01}, "bodies[0].half_height"),
        ({"half_height": None}, "bodies[0].half_height"),
        ({"half_height": 0.005}, "bodies[0].half_height"),  # under a cell (1/64 m)
        ({"radius": 0.005}, "bodies[0].radius"),
        ({"half_height": 0.4}, "bodies[0].center"),  # past the walls
    ],
)
def test_bad_capsules_are_named(change, field):
    d = {k: v for k, v in {**CAPSULE, **change, "angle_deg": 0.0}.items() if v is not None}
    with pytest.raises(InvalidInputError) as e:
        SceneSpec.from_dict({"name": "c", "dim": 2, "n_grid": 64, "blocks": [{"material": "water", "lo": [0.3, 0.05], "hi": [0.7, 0.3]}], "bodies": [d]})
    assert e.value.field == field


def test_bad_meshes_are_named_and_nothing_changes(tmp_path):
    box_obj(tmp_path / "box.obj")
    (tmp_path / "broken.obj").write_text("v 0 0 0\nf 1 2 3\nthis is no mesh\n")
    write_obj(tmp_path / "nan.obj", [[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, float("nan")]], [[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]])
    box_obj(tmp_path / "slab.obj", h=(1.0, 0.1, 1.0))
    mesh = {"shape": "mesh", "center": [0.5, 0.6, 0.5], "density": 500.0, "scale": 0.1}
    sim = MpmSimulator(SceneSpec.from_dict(tank3([])).build(), threads=1)
    before = sim.solver.checkpoint()
    cases = [
        ({"path": str(tmp_path / "missing.obj")}, "bodies[0].path"),
        ({"path": str(tmp_path / "broken.obj")}, "bodies[0].path"),
        ({"path": str(tmp_path / "nan.obj")}, "bodies[0].path"),
        ({"path": str(tmp_path / "slab.obj")}, "bodies[0].path"),  # 0.02 m thick: under 2 cells of 1/32 m
        ({"path": str(tmp_path / "box.obj"), "scale": -1.0}, "bodies[0].scale"),
        ({"scale": None, "vertices": [[0, 0, 0], [0.1, 0, 0], [0, 0.1, 0], [0.1, 0.1, 0]]}, "bodies[0].vertices"),  # one plane
        ({"scale": None, "vertices": [[0, 0, 0], [0.1, 0, 0], [0, 0.1, 0]]}, "bodies[0].vertices"),
        ({"vertices": [[0, 0, 0], [0.1, 0, 0], [0, 0.1, 0], [0, 0, 0.1]]}, "bodies[0].scale"),  # scale goes with a path only
    ]
    for change, field in cases:
        with pytest.raises(InvalidInputError) as e:
            sim.add_body({k: v for k, v in {**mesh, **change}.items() if v is not None})
        assert e.value.field == field, (change, e.value)
        assert sim.solver.checkpoint() == before and len(sim.bodies) == 0
    with pytest.raises(InvalidInputError) as e:  # 2D refuses a mesh naming its shape
        SceneSpec.from_dict(
            {
                "name": "c",
                "dim": 2,
                "n_grid": 64,
                "blocks": [{"material": "water", "lo": [0.3, 0.05], "hi": [0.7, 0.3]}],
                "bodies": [{**mesh, "center": [0.5, 0.6], "path": "box.obj"}],
            },
            base_dir=tmp_path,
        )
    assert e.value.field == "bodies[0].shape"
    with pytest.raises(InvalidInputError) as e:  # confined to the scene's folder, as mesh obstacles are
        SceneSpec.from_dict(tank3([{**mesh, "path": "../box.obj"}]), base_dir=tmp_path / "sub", confine=True)
    assert e.value.field == "bodies[0].path"


def test_mesh_and_capsule_in_3d_restore_bit_for_bit_and_keep_water_out(tmp_path):
    box_obj(tmp_path / "box.obj")
    bodies = [
        {"shape": "mesh", "path": "box.obj", "scale": 0.06, "center": [0.35, 0.35, 0.5], "density": 600.0, "angular_velocity": [0, 1, 0]},
        {"shape": "capsule", "center": [0.65, 0.4, 0.5], "radius": 0.05, "half_height": 0.06, "rotation": [[0, -1, 0], [1, 0, 0], [0, 0, 1]], "density": 800.0},
    ]
    spec = SceneSpec.from_dict(tank3(bodies), base_dir=tmp_path)
    a = MpmSimulator(spec.build(), threads=1)
    rollout(a, 15)
    state = a.state()
    rollout(a, 15)
    b = MpmSimulator(spec.build(), threads=1)
    b.restore(state)
    rollout(b, 15)
    assert np.array_equal(a.fluid_positions, b.fluid_positions) and np.array_equal(body_bits(a), body_bits(b))
    dx = 1.0 / 32
    for k, body in enumerate(spec.params.bodies):
        depth = -body.sdf(a.fluid_positions, a.bodies.center[k], a.bodies.rotation[k]).min()
        assert depth <= 0.25 * dx, (k, depth / dx)
        # the exported mesh at the pose lies on the body's surface
        surf = body_surface(body, a.bodies.center[k], a.bodies.rotation[k])
        assert np.abs(body.sdf(surf.vertices, a.bodies.center[k], a.bodies.rotation[k])).max() < 1e-6


def test_capsule_meshes_and_outlines_lie_on_the_surface():
    c3 = Body.from_dict({**CAPSULE, "center": [0.5, 0.5, 0.5], "angle_deg": None, "radius": 0.05, "half_height": 0.08})
    v, f = local_mesh(c3)
    assert np.abs(c3.sdf(v, np.zeros(3), np.eye(3))).max() < 1e-6 and f.max() == len(v) - 1
    tri = v[f]
    vol = np.einsum("fi,fi->f", tri[:, 0], np.cross(tri[:, 1], tri[:, 2])).sum() / 6.0
    assert 0.98 < vol / (np.pi * 0.05**2 * 0.16 + 4 / 3 * np.pi * 0.05**3) < 1.0  # outward, inscribed
    o = local_outline(Body.from_dict(CAPSULE))
    assert np.abs(Body.from_dict(CAPSULE).sdf(o, np.zeros(2), np.eye(2))).max() < 1e-6


def test_service_schema_takes_capsules_and_inline_vertices_only():
    BodyAdd.model_validate({"shape": "capsule", "center": [0.5, 0.5], "radius": 0.04, "half_height": 0.05, "density": 500})
    cube = [[x, y, z] for x in (0, 0.1) for y in (0, 0.1) for z in (0, 0.1)]
    assert BodyAdd.model_validate({"shape": "mesh", "center": [0.5, 0.5, 0.5], "vertices": cube, "density": 500}).vertices is not None
    for bad in ({"path": "/etc/passwd"}, {"scale": 2.0}, {"vertices": cube * (MAX_BODY_VERTICES // 8 + 1)}, {"vertices": [[0, 0]] * 4}):
        with pytest.raises(ValidationError):
            BodyAdd.model_validate({"shape": "mesh", "center": [0.5, 0.5, 0.5], "vertices": cube, "density": 500, **bad})


def test_session_description_lists_capsule_and_hull():
    from fastapi.testclient import TestClient  # import time: the service's test client only here

    from hybridmpm.service.app import ServiceConfig, create_app

    cube = [[x, y, z] for x in (-0.05, 0.05) for y in (-0.05, 0.05) for z in (-0.05, 0.05)]
    with TestClient(create_app(ServiceConfig(max_sessions=4, max_sessions_per_client=4, idle_ttl_s=600))) as client:
        sid = client.post("/v1/sessions", json={"scene": "dam_break3d", "solver": "mpm", "seed": 0}).json()["id"]
        r = client.post(f"/v1/sessions/{sid}/bodies", json={"shape": "mesh", "center": [0.7, 0.7, 0.5], "vertices": cube, "density": 500})
        assert r.status_code == 201, r.text
        r = client.post(f"/v1/sessions/{sid}/bodies", json={"shape": "capsule", "center": [0.4, 0.7, 0.5], "radius": 0.05, "half_height": 0.06, "density": 500})
        assert r.status_code == 201, r.text
        bodies = client.get(f"/v1/sessions/{sid}").json()["bodies"]
        hull, cap = bodies
        assert hull["shape"] == "mesh" and len(hull["vertices"]) == 8 and len(hull["faces"]) == 12
        assert np.abs(np.abs(hull["vertices"]) - 0.05).max() < 1e-7
        assert cap["radius"] == 0.05 and cap["half_height"] == 0.06
        r = client.post(f"/v1/sessions/{sid}/bodies", json={"shape": "mesh", "center": [0.3, 0.3, 0.5], "vertices": cube[:4], "density": 500})
        assert r.status_code == 422 and "vertices" in r.text


def test_overlapping_bodies_are_refused_and_a_restore_takes_them():
    scene = {"name": "c", "dim": 2, "n_grid": 64, "blocks": [{"material": "water", "lo": [0.3, 0.05], "hi": [0.7, 0.25]}]}
    ball = {"shape": "circle", "center": [0.5, 0.45], "radius": 0.05, "density": 900.0}
    with pytest.raises(InvalidInputError) as e:  # the capsule's lower end reaches into the ball
        SceneSpec.from_dict({**scene, "bodies": [ball, {**CAPSULE, "angle_deg": 0.0, "center": [0.5, 0.55]}]})
    assert e.value.field == "bodies[1].center"
    post = {"shape": "box", "center": [0.5, 0.6], "half_extents": [0.1, 0.02]}
    with pytest.raises(InvalidInputError) as e:  # a body inside an obstacle
        SceneSpec.from_dict({**scene, "obstacles": [post], "bodies": [{**ball, "center": [0.5, 0.65]}]})
    assert e.value.field == "bodies[0].center"
    sim = MpmSimulator(SceneSpec.from_dict({**scene, "bodies": [ball]}).build(), threads=1)
    before = sim.solver.checkpoint()
    with pytest.raises(InvalidInputError) as e:
        sim.add_body({**ball, "center": [0.52, 0.5]})
    assert e.value.field == "bodies[1].center" and sim.solver.checkpoint() == before
    # the ball falls; a second one where it started is taken, and a checkpoint of both restores
    for _ in range(30):  # until it is a diameter below where it started (it floats at about 0.25 m)
        rollout(sim, 10)
        if sim.bodies.center[0][1] < 0.345:
            break
    assert sim.bodies.center[0][1] < 0.345
    sim.add_body(ball)
    rollout(sim, 5)
    state = sim.state()
    rollout(sim, 5)
    other = MpmSimulator(SceneSpec.from_dict({**scene, "bodies": [ball]}).build(), threads=1)
    other.restore(state)
    rollout(other, 5)
    assert np.array_equal(body_bits(sim), body_bits(other))


@pytest.mark.parametrize("suffix", ["stl", "ply", "glb"])
def test_a_mesh_body_from_each_file_kind_added_between_frames(tmp_path, suffix, monkeypatch):
    import trimesh  # import time: only this test writes the other file kinds

    path = tmp_path / f"box.{suffix}"
    trimesh.creation.box(extents=(2.0, 2.0, 2.0)).export(path)
    sim = MpmSimulator(SceneSpec.from_dict(tank3([])).build(), threads=1)
    monkeypatch.chdir(tmp_path)  # MpmSimulator.add_body reads a path relative to the working directory
    i = sim.add_body({"shape": "mesh", "path": path.name, "scale": 0.05, "center": [0.5, 0.6, 0.5], "density": 300.0})
    assert i == 0 and sim.bodies.mass[0] == pytest.approx(300.0 * 0.1**3, rel=1e-5)
    assert len(sim.solver.params.bodies[0].vertices) == 8


def test_a_body_rests_on_an_obstacle_in_a_scene():
    scene = {
        "name": "shelf",
        "dim": 2,
        "n_grid": 64,
        "blocks": [{"material": "water", "lo": [0.8, 0.05], "hi": [0.9, 0.1]}],
        "obstacles": [{"shape": "box", "center": [0.4, 0.3], "half_extents": [0.15, 0.03]}],
        "bodies": [{**CAPSULE, "center": [0.4, 0.45], "density": 1500.0}],
    }
    sim = MpmSimulator(SceneSpec.from_dict(scene).build(), threads=1)
    rollout(sim, 60)
    # lying flat (its axis along x), its lowest point on the shelf's top (0.33 m)
    assert sim.bodies.center[0][1] - 0.04 == pytest.approx(0.33, abs=0.1 / 64)
