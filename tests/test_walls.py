"""Per-face wall boundary conditions: physics (Coulomb friction on the face
that carries the load, none on the others), the all-walls form unchanged,
parameter and scene-file round trips, checkpoints, and errors naming the field."""

from __future__ import annotations

import json

import numpy as np
import pytest

from hybridmpm.conventions import MATERIAL_SAND, MATERIAL_WATER
from hybridmpm.errors import CheckpointError, InvalidInputError
from hybridmpm.mpm import MpmParams, MpmSolver, SandParams, WallFace, WallParams
from hybridmpm.scenes import SceneSpec, hydrostatic_volume_ratio, lattice, wall_face

G_N = 9.8  # load pressing the block onto the face [m/s²]
G_T = 4.0  # push along the face [m/s²]


def slide(dim: int, n_grid: int, gravity, walls: WallParams, lo, hi, axis: int, frames: int = 100) -> float:
    """Acceleration [m/s²] along ``axis`` of a cohesive sand block pushed along a
    wall by a tilted gravity (the inclined-plane problem): least-squares slope of
    the mean velocity after the first 25 ms (contact settling)."""
    # 500 Pa of cohesion keeps the block in one piece (a cohesionless block
    # slumps while it slides), so it moves like the rigid block of the analytic
    # answer: a = g_t − μ·g_n while sliding, 0 once friction can hold it.
    params = MpmParams(dim=dim, n_grid=n_grid, gravity=list(gravity), walls=walls, sand=SandParams(cohesion=500.0))
    sim = MpmSolver(params)
    sim.add_particles(lattice(lo, hi, sim.dx / 2), MATERIAL_SAND)
    t, v = [], []
    for _ in range(frames):
        sim.step_frame()
        t.append(sim.time)
        v.append(float(sim.velocities[:, axis].mean()))
    return float(np.polyfit(t[10:], v[10:], 1)[0])


@pytest.mark.parametrize("mu", [0.0, 0.2, 0.3, 0.5])
def test_rough_floor_decelerates_a_sliding_block_at_mu_g(mu):
    """Floor ``y-`` with Coulomb μ, every other face frictionless: a block pushed
    along the floor by g_t = 4 m/s² while pressed onto it by g_n = 9.8 m/s²
    accelerates at g_t − μ·g_n (friction decelerates it by μ·g_n); μ = 0.5
    holds it (μ·g_n > g_t)."""
    n = 64
    face = wall_face(MpmParams(n_grid=n))
    walls = WallParams(condition="slip", faces={"y-": WallFace("separate", mu)})
    a = slide(2, n, [G_T, -G_N], walls, [0.2, face], [0.35, face + 0.06], axis=0)
    expect = max(0.0, G_T - mu * G_N)
    if expect > 0:
        assert abs(a - expect) < 0.05 * G_T, (mu, a, expect)
    else:
        assert 0.0 <= a < 0.1 * G_T, (mu, a)  # held (a slow creep at most)


def test_side_wall_friction_is_its_own():
    """The same block pressed onto the left wall ``x-`` and pushed down along
    it: a frictionless ``x-`` lets it slide at the full g_t although every
    other face is rough (μ = 0.5); ``x-`` with μ = 0.2 slows it by μ·g_n."""
    n = 64
    face = wall_face(MpmParams(n_grid=n))
    box = ([face, 0.5], [face + 0.06, 0.65])
    free = WallParams(condition="separate", friction=0.5, faces={"x-": WallFace("separate", 0.0)})
    rough = WallParams(condition="separate", friction=0.5, faces={"x-": WallFace(friction=0.2)})
    a_free = slide(2, n, [-G_N, -G_T], free, *box, axis=1)
    a_rough = slide(2, n, [-G_N, -G_T], rough, *box, axis=1)
    assert abs(a_free + G_T) < 0.01 * G_T, a_free
    assert abs(a_rough + (G_T - 0.2 * G_N)) < 0.05 * G_T, a_rough


def test_3d_back_wall_friction():
    """3D: a block pressed onto ``z+`` slides down it at g_t when ``z+`` is
    frictionless (the other faces rough), at g_t − μ·g_n with μ = 0.2."""
    n = 32
    face = wall_face(MpmParams(dim=3, n_grid=n))
    box = ([0.4, 0.5, 1 - face - 0.1], [0.55, 0.65, 1 - face])
    for mu in (0.0, 0.2):
        walls = WallParams(condition="separate", friction=0.5, faces={"z+": WallFace("separate", mu)})
        a = slide(3, n, [0.0, -G_T, G_N], walls, *box, axis=1)
        assert abs(a + (G_T - mu * G_N)) < 0.05 * G_T, (mu, a)


def water_column(walls: WallParams, frames: int = 60):
    """A 16 × 32-cell water column against ``x-`` at hydrostatic rest, released."""
    params = MpmParams(dim=2, n_grid=64, walls=walls)
    face = wall_face(params)
    a = 16 / 64
    x = lattice([face, face], [face + a, face + 2 * a], 0.5 / 64)
    sim = MpmSolver(params)
    sim.add_particles(x, MATERIAL_WATER)
    sim.volume_ratio = hydrostatic_volume_ratio(x, face + 2 * a, params)
    for _ in range(frames):
        sim.step_frame()
    return x, sim.positions


def test_sticky_floor_with_slip_walls_differs_from_all_slip_and_all_sticky():
    """A collapsing water column. Sticky floor + slip walls: the bottom row stays
    nearly in place (it runs out freely over an all-slip floor) while the
    particles against the left wall slide down it (they stay stuck when every
    wall is sticky)."""
    x, slip = water_column(WallParams(condition="slip"))
    _, mixed = water_column(WallParams(condition="slip", faces={"y-": WallFace("sticky")}))
    _, sticky = water_column(WallParams(condition="sticky"))
    bottom = x[:, 1] == x[:, 1].min()
    left = x[:, 0] == x[:, 0].min()
    run_slip = (slip[bottom, 0] - x[bottom, 0]).max()
    run_mixed = (mixed[bottom, 0] - x[bottom, 0]).max()
    assert run_slip > 0.1 and run_mixed < 0.2 * run_slip, (run_slip, run_mixed)
    drop_mixed = (mixed[left, 1] - x[left, 1]).mean()
    drop_sticky = (sticky[left, 1] - x[left, 1]).mean()
    assert drop_mixed < -0.03 and abs(drop_sticky) < 0.2 * abs(drop_mixed), (drop_mixed, drop_sticky)


@pytest.mark.parametrize("dim", [2, 3])
def test_per_face_form_equal_to_all_walls_is_bitwise_identical(dim):
    """Every face set like the all-walls form (and a different all-walls
    default, which the overrides must hide) gives bitwise the same run."""
    n = 64 if dim == 2 else 32
    faces = ["x-", "x+", "y-", "y+", "z-", "z+"][: 2 * dim]
    forms = [
        WallParams(condition="separate", friction=0.4),
        WallParams(condition="sticky", friction=3.0, faces={f: WallFace("separate", 0.4) for f in faces}),
    ]
    runs = []
    for walls in forms:
        sim = MpmSolver(MpmParams(dim=dim, n_grid=n, walls=walls))
        lo = [0.1] * dim
        lo[1] = 0.06
        x = lattice(lo, [v + 0.15 for v in lo], sim.dx / 2)
        v = np.zeros_like(x)
        v[:, 0] = -1.5  # into the x- wall, sliding on the floor
        sim.add_particles(x, MATERIAL_SAND, velocities=v)
        for _ in range(20):
            sim.step_frame()
        runs.append((sim.positions, sim.velocities, sim.affine, sim.deformation_gradient))
    for a, b in zip(*runs):
        assert np.array_equal(a, b)


def test_params_round_trip_and_resolve():
    walls = WallParams(condition="slip", faces={"y-": WallFace("separate", 0.6), "x+": {"friction": 0.2}})
    p = MpmParams(dim=2, walls=walls)
    d = p.to_dict()
    assert d["walls"]["faces"] == {"x+": {"friction": 0.2}, "y-": {"condition": "separate", "friction": 0.6}}
    back = MpmParams.from_dict(json.loads(json.dumps(d)))
    assert back.to_dict() == d
    assert back.walls.face("y-") == ("separate", 0.6)
    assert back.walls.face("x+") == ("slip", 0.2)  # condition from the all-walls value
    assert back.walls.face("x-") == ("slip", 0.0)
    # the all-walls form serialises exactly as before (no "faces" key)
    assert MpmParams().to_dict()["walls"] == {"cells": 3, "condition": "separate", "friction": 0.0}


def test_checkpoint_round_trips_per_face_walls():
    walls = WallParams(condition="slip", faces={"y-": WallFace("separate", 0.5)})
    sim = MpmSolver(MpmParams(dim=2, n_grid=64, walls=walls))
    face = wall_face(sim.params)
    x = lattice([0.3, face], [0.4, face + 0.05], sim.dx / 2)
    sim.add_particles(x, MATERIAL_SAND, velocities=np.tile([1.0, 0.0], (len(x), 1)).astype(np.float32))
    sim.step_frame()
    blob = sim.checkpoint()
    back = MpmSolver.from_checkpoint(blob)
    assert back.params.to_dict() == sim.params.to_dict()
    assert back.params.walls.face("y-") == ("separate", 0.5)
    for _ in range(10):
        sim.step_frame()
        back.step_frame()
    assert np.array_equal(sim.positions, back.positions) and np.array_equal(sim.velocities, back.velocities)
    # restoring into a solver whose walls differ is refused
    other = MpmSolver(MpmParams(dim=2, n_grid=64, walls=WallParams(condition="slip")))
    with pytest.raises(CheckpointError):
        other.restore(blob)


SCENE_TOML = """
name = "collapse"
dim = 2
n_grid = 64

[walls]
condition = "slip"

[walls.faces.y-]
condition = "separate"
friction = 0.6

[walls.faces."x+"]
condition = "sticky"

[[blocks]]
material = "sand"
lo = [0.05, 0.05]
hi = [0.2, 0.3]
"""


@pytest.mark.parametrize("suffix", [".toml", ".json"])
def test_scene_file_sets_walls_per_face(tmp_path, suffix):
    path = tmp_path / "collapse.toml"
    path.write_text(SCENE_TOML)
    spec = SceneSpec.load(path)
    assert spec.params.walls.face("y-") == ("separate", 0.6)
    assert spec.params.walls.face("x+") == ("sticky", 0.0)
    assert spec.params.walls.face("x-") == ("slip", 0.0)
    again = SceneSpec.load(spec.save(tmp_path / f"again{suffix}"))
    assert again.to_dict() == spec.to_dict()
    sim = again.build().make_solver()
    sim.step_frame()  # the binding accepts it


@pytest.mark.parametrize(
    "walls, field",
    [
        ({"faces": {"y-": {"friction": -0.1}}}, "walls.faces.y-.friction"),
        ({"faces": {"y-": {"condition": "glue"}}}, "walls.faces.y-.condition"),
        ({"faces": {"z-": {"friction": 0.1}}}, "walls.faces.z-"),  # no z wall in 2D
        ({"faces": {"floor": {}}}, "walls.faces.floor"),
        ({"faces": {"y-": {"mu": 0.1}}}, "walls.faces.y-.mu"),
        ({"faces": {"y-": 0.3}}, "walls.faces.y-"),
        ({"faces": ["y-"]}, "walls.faces"),
        ({"friction": -1.0}, "walls.friction"),
        ({"condition": "rough"}, "walls.condition"),
        ({"roughness": 1.0}, "walls.roughness"),
    ],
)
def test_bad_walls_name_the_field(walls, field):
    d = {"dim": 2, "n_grid": 64, "walls": walls, "blocks": [{"material": "sand", "lo": [0.2, 0.2], "hi": [0.3, 0.3]}]}
    with pytest.raises(InvalidInputError) as e:
        SceneSpec.from_dict(d)
    assert e.value.field == field and str(e.value).startswith(field + ":"), str(e.value)
    if field == "walls.faces.y-.friction":
        assert "must be >= 0" in str(e.value)


@pytest.mark.parametrize(
    "walls, field",
    [
        ({"faces": {"y-": {"friction": -0.1}}}, "walls.faces.y-.friction"),
        ({"faces": {"y-": {"condition": "glue"}}}, "walls.faces.y-.condition"),
        ({"faces": {"z+": {}}}, "walls.faces.z+"),
        ({"faces": {"y-": {"mu": 0.1}}}, "walls.faces.y-.mu"),
    ],
)
def test_the_binding_validates_walls_too(walls, field):
    """The native module checks the same fields (the Python layer is not the only guard)."""
    from hybridmpm import _core

    with pytest.raises(InvalidInputError) as e:
        _core.MpmSolver({"dim": 2, "walls": walls})
    assert e.value.field == field, str(e.value)


def test_3d_scene_accepts_z_faces():
    walls = WallParams(faces={"z-": WallFace("sticky"), "z+": {"friction": 0.3}})
    p = MpmParams.from_dict(MpmParams(dim=3, n_grid=32, walls=walls).to_dict())
    assert p.walls.face("z-") == ("sticky", 0.0) and p.walls.face("z+") == ("separate", 0.3)
    MpmSolver(p).step_frame()
