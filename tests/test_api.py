"""The Python API: errors that name the field, state in and out, checkpoints,
particle add/remove, determinism across thread counts, the CFL substep count."""

from __future__ import annotations

import math

import numpy as np
import pytest

from hybridmpm import CheckpointError, InvalidInputError, SimulationError
from hybridmpm.conventions import MATERIAL_SAND, MATERIAL_WATER
from hybridmpm.mpm import Box, MpmParams, MpmSolver, SandParams, Sphere, WaterParams
from hybridmpm.scenes import dam_break2d, make_scene


def small(dim=2, **kw):
    sim = MpmSolver(MpmParams(dim=dim, **kw))
    rng = np.random.default_rng(0)
    x = rng.uniform(0.4, 0.6, (200, dim)).astype(np.float32)
    sim.add_particles(x, MATERIAL_WATER)
    return sim


@pytest.mark.parametrize(
    "params, field",
    [
        (dict(n_grid=8), "n_grid"),
        (dict(cfl=0.0), "cfl"),
        (dict(cfl=float("nan")), "cfl"),
        (dict(substeps=0), "substeps"),
        (dict(water=WaterParams(bulk_modulus=-1.0)), "water.bulk_modulus"),
        (dict(water=WaterParams(density=0.0)), "water.density"),
        (dict(sand=SandParams(poisson_ratio=0.5)), "sand.poisson_ratio"),
        (dict(sand=SandParams(friction_angle_deg=90.0)), "sand.friction_angle_deg"),
        (dict(sand=SandParams(cohesion=-1.0)), "sand.cohesion"),
        (dict(colliders=[Sphere(center=[0.5, 0.5], radius=-0.1)]), "colliders[0].radius"),
        (dict(colliders=[Box(center=[0.5, 0.5], half_extents=[0.1, 0.0])]), "colliders[0].half_extents"),
        (dict(colliders=[Box(center=[0.5, 0.5], half_extents=[0.1, 0.1], condition="glue")]), "colliders[0].condition"),  # type: ignore[arg-type]
        (dict(gravity=[0.0, float("inf")]), "gravity[1]"),
    ],
)
def test_bad_parameters_name_the_field(params, field):
    with pytest.raises(InvalidInputError) as e:
        MpmSolver(MpmParams(dim=2, **params))
    assert e.value.field == field
    assert str(e.value).startswith(field)
    assert isinstance(e.value, ValueError)


def test_unknown_parameter_is_rejected():
    from hybridmpm import _core

    with pytest.raises(InvalidInputError, match="wter"):
        _core.MpmSolver({"dim": 2, "wter": {}})
    with pytest.raises(InvalidInputError, match="water.bulk"):
        _core.MpmSolver({"dim": 2, "water": {"bulk": 1.0}})
    with pytest.raises(InvalidInputError) as e:
        _core.MpmSolver({"dim": 4})
    assert e.value.field == "dim"


@pytest.mark.parametrize(
    "kwargs, field",
    [
        (dict(positions=np.full((3, 2), 0.5, np.int64)), "positions"),
        (dict(positions=np.full((3, 3), 0.5, np.float32)), "positions"),
        (dict(positions=np.full((3,), 0.5, np.float32)), "positions"),
        (dict(positions=np.array([[0.5, np.nan]], np.float32)), "positions"),
        (dict(positions=np.array([[0.5, 1.2]], np.float32)), "positions"),
        (dict(positions=np.array([[0.5, 0.0]], np.float32)), "positions"),
        (dict(positions=np.full((2, 2), 0.5, np.float32), material=7), "material"),
        (dict(positions=np.full((2, 2), 0.5, np.float32), material=np.array([0, 1, 0])), "material"),
        (dict(positions=np.full((2, 2), 0.5, np.float32), velocities=np.zeros((3, 2), np.float32)), "velocities"),
        (dict(positions=np.full((2, 2), 0.5, np.float32), masses=np.array([1.0, -1.0], np.float32)), "masses"),
        (dict(positions=np.full((2, 2), 0.5, np.float32), volumes=np.array([1.0, np.inf], np.float32)), "volumes"),
    ],
)
def test_bad_particles_name_the_field_and_change_nothing(kwargs, field):
    sim = small()
    before = sim.checkpoint()
    kwargs.setdefault("material", MATERIAL_WATER)
    with pytest.raises(InvalidInputError) as e:
        sim.add_particles(**kwargs)
    assert e.value.field == field, str(e.value)
    assert sim.checkpoint() == before


def test_float64_input_is_converted():
    sim = MpmSolver()
    assert sim.add_particles(np.full((4, 2), 0.5), MATERIAL_WATER) == 4
    assert sim.positions.dtype == np.float32


def test_get_set_round_trip_every_field():
    sim = small()
    n = sim.num_particles
    rng = np.random.default_rng(1)
    values = {
        "positions": rng.uniform(0.3, 0.7, (n, 2)),
        "velocities": rng.normal(size=(n, 2)),
        "affine": rng.normal(size=(n, 2, 2)),
        "deformation_gradient": np.eye(2) + 0.01 * rng.normal(size=(n, 2, 2)),
        "volume_ratio": rng.uniform(0.9, 1.1, n),
        "masses": rng.uniform(0.1, 0.2, n),
        "volumes": rng.uniform(1e-5, 2e-5, n),
        "external_acceleration": rng.normal(size=(n, 2)),
    }
    for name, v in values.items():
        setattr(sim, name, v)
        got = getattr(sim, name)
        assert got.dtype == np.float32 and got.shape == v.shape, name
        assert np.array_equal(got, v.astype(np.float32)), name
    sim.material = np.array([MATERIAL_SAND] * n)
    assert (sim.material == MATERIAL_SAND).all()
    assert sim.stress.shape == (n, 2, 2)
    with pytest.raises(InvalidInputError) as e:
        sim.volume_ratio = np.full(n, -1.0)
    assert e.value.field == "volume_ratio"
    with pytest.raises(InvalidInputError) as e:
        sim.deformation_gradient = np.tile(np.diag([1.0, -1.0]), (n, 1, 1))
    assert e.value.field == "deformation_gradient"
    with pytest.raises(AttributeError):
        sim.stress = np.zeros((n, 2, 2))  # type: ignore[misc]


def test_water_stress_is_the_weakly_compressible_law():
    sim = small(water=WaterParams(bulk_modulus=1e5))
    J = np.linspace(0.9, 1.1, sim.num_particles).astype(np.float32)
    sim.volume_ratio = J
    tau = sim.stress
    expect = 1e5 * J * (J - 1)
    assert np.allclose(tau[:, 0, 0], expect, rtol=1e-5, atol=1e-3)
    assert np.allclose(tau[:, 0, 1], 0)


def test_nonfinite_state_raises_with_substep_and_keeps_state():
    sim = small()
    ext = np.zeros((sim.num_particles, 2), np.float32)
    ext[3] = [3e38, 0.0]
    sim.external_acceleration = ext
    before = sim.checkpoint()
    with pytest.raises(SimulationError) as e:
        sim.step_frame()
    assert e.value.substep == 0
    assert sim.checkpoint() == before


def test_checkpoint_restores_bit_for_bit():
    scene = make_scene("sand2d", seed=3)
    a = scene.make_solver()
    for _ in range(10):
        a.step_frame()
    blob = a.checkpoint()
    b = MpmSolver.from_checkpoint(blob)
    assert b.time == a.time and b.frame == a.frame
    for _ in range(10):
        a.step_frame()
        b.step_frame()
    assert np.array_equal(a.positions, b.positions)
    assert np.array_equal(a.deformation_gradient, b.deformation_gradient)
    c = scene.make_solver()
    c.restore(blob)
    assert c.frame == 10
    with pytest.raises(CheckpointError):
        MpmSolver.from_checkpoint(blob[:-5])
    with pytest.raises(CheckpointError):
        MpmSolver.from_checkpoint(b"not a checkpoint")
    with pytest.raises(CheckpointError):
        MpmSolver(MpmParams(dim=2, n_grid=64)).restore(blob)


def test_add_and_remove_particles_between_frames():
    sim = small()
    x0 = sim.positions
    sim.step_frame()
    n = sim.add_particles(np.array([[0.2, 0.8], [0.8, 0.8]], np.float32), MATERIAL_SAND, velocities=np.zeros((2, 2), np.float32))
    assert n == 202
    assert list(sim.material[-2:]) == [MATERIAL_SAND, MATERIAL_SAND]
    mask = np.zeros(n, bool)
    mask[::2] = True
    kept_before = sim.positions[~mask]
    assert sim.remove_particles(mask) == n - mask.sum()
    assert np.array_equal(sim.positions, kept_before)
    sim.step_frame()
    assert np.isfinite(sim.positions).all()
    with pytest.raises(InvalidInputError) as e:
        sim.remove_particles(np.zeros(3, bool))
    assert e.value.field == "mask"
    assert x0.shape == (200, 2)


def test_bitwise_identical_for_one_and_two_threads():
    scene = dam_break2d()
    runs = []
    for threads in (1, 2):
        sim = scene.make_solver(num_threads=threads)
        for _ in range(20):
            sim.step_frame()
        runs.append((sim.positions, sim.velocities, sim.volume_ratio))
    for a, b in zip(*runs):
        assert np.array_equal(a, b)


def test_substeps_follow_the_cfl_condition():
    sim = small()
    sim.velocities = np.tile([3.0, 0.0], (sim.num_particles, 1))
    dx = sim.dx
    c = math.sqrt(4e5 / 1000)
    expect = math.ceil(2.5e-3 / (0.4 * dx / (c + 3.0)))
    assert sim.substeps_for(2.5e-3) == expect
    assert sim.step_frame()["substeps"] == expect
    fixed = small(substeps=7)
    assert fixed.step_frame()["substeps"] == 7
    # more substeps than max_substeps: a SimulationError naming the speed, state unchanged
    capped = small(max_substeps=5)
    before = capped.checkpoint()
    with pytest.raises(
        SimulationError, match=r"particles moving at up to 0 m/s and parameter set 0 \(water\) \(wave speed 20 m/s\) need 16 substeps.*max_substeps = 5"
    ) as s:
        capped.step_frame()
    assert s.value.substep is None
    assert capped.checkpoint() == before
    for bad in (-1.0, 0.0, 2.0, float("nan"), True, "0.1"):
        with pytest.raises(InvalidInputError) as e:
            sim.step_frame(bad)  # type: ignore[arg-type]
        assert e.value.field == "dt_frame"
        with pytest.raises(InvalidInputError):
            sim.substeps_for(bad)  # type: ignore[arg-type]


def test_colliders_keep_particles_out():
    ramp = Box(center=[0.5, 0.35], half_extents=[0.25, 0.03], angle_deg=-20.0, condition="separate", friction=0.2)
    ball = Sphere(center=[0.3, 0.15], radius=0.05, condition="sticky")
    sim = MpmSolver(MpmParams(dim=2, colliders=[ramp, ball]))
    from hybridmpm.scenes import lattice

    sim.add_particles(lattice([0.35, 0.5], [0.55, 0.6], sim.dx / 2), MATERIAL_WATER)
    for _ in range(150):
        sim.step_frame()
    x = sim.positions.astype(np.float64)
    # inside the rotated ramp: distance along its normal below half thickness
    c, s = math.cos(math.radians(-20.0)), math.sin(math.radians(-20.0))
    local = (x - [0.5, 0.35]) @ np.array([[c, -s], [s, c]])
    inside_ramp = (np.abs(local[:, 0]) < 0.25 - sim.dx) & (np.abs(local[:, 1]) < 0.03 - sim.dx)
    inside_ball = np.linalg.norm(x - [0.3, 0.15], axis=1) < 0.05 - sim.dx
    assert not inside_ramp.any() and not inside_ball.any()
    # the water slid down the ramp (to the right, since the ramp descends to the right)
    assert x[:, 0].mean() > 0.5


def _step_in_child(sim, q):
    sim.step_frame()
    q.put(float(sim.positions.sum()))


def test_solver_works_in_a_forked_child():
    """rayon and fork: a child forked after the pool started rebuilds it
    (PyTorch DataLoader workers fork) instead of deadlocking."""
    import multiprocessing as mp

    sim = small(num_threads=2)
    sim.step_frame()
    ctx = mp.get_context("fork")
    q = ctx.Queue()
    p = ctx.Process(target=_step_in_child, args=(sim, q))
    p.start()
    p.join(timeout=30)
    assert p.exitcode == 0, "child hung or crashed"
    sim.step_frame()
    assert q.get(timeout=5) == pytest.approx(float(sim.positions.sum()))


def test_mode_runs_count_every_frame_attempt():
    """``mode_runs`` counts each frame attempt as run alone or by the team:
    with one thread every attempt runs alone; on two, attempts of either kind
    add up to at least the frames taken (CFL retries add attempts)."""
    for threads in (1, 2):
        sim = small(2, num_threads=threads)
        assert sim.mode_runs == (0, 0)
        for _ in range(6):
            sim.step_frame()
        alone, team = sim.mode_runs
        assert alone + team >= 6
        if threads == 1:
            assert team == 0


def test_both_compiled_frame_loops_give_the_same_bits():
    """The frame loop runs the copy compiled for the CPU (x86-64-v3 where it
    has AVX2/FMA) or the portable one: same bits for water and sand, 2D and
    3D; an unknown name is refused naming ``isa``."""
    for dim in (2, 3):
        runs = {}
        for isa in ("baseline", None):
            sim = small(dim)
            sim.add_particles(np.full((8, dim), 0.6, np.float32) + 0.01 * np.arange(8, dtype=np.float32)[:, None], MATERIAL_SAND)
            if isa is not None:
                sim.set_isa(isa)
                assert sim.isa == isa
            for _ in range(5):
                sim.step_frame()
            runs[sim.isa] = sim.checkpoint()
        assert len(set(runs.values())) == 1, sorted(runs)
    sim = small(2)
    with pytest.raises(InvalidInputError) as e:
        sim.set_isa("avx9000")
    assert e.value.field == "isa"
