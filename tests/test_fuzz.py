"""Property-based fuzz (hypothesis) of what a user can hand in: scene files
and solver parameters. Whatever the input, the outcome is a working object or
an :class:`InvalidInputError` naming a field — never another exception, and
never an allocation beyond the (here small) memory budget."""

from __future__ import annotations

import json

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from hybridmpm.errors import HybridMpmError, InvalidInputError
from hybridmpm.limits import set_memory_budget
from hybridmpm.mpm import MpmParams, MpmSolver
from hybridmpm.scenes import SceneSpec

FUZZ = settings(max_examples=120, deadline=None, suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture])

garbage = st.one_of(
    st.none(),
    st.booleans(),
    st.integers(-(2**70), 2**70),
    st.floats(allow_nan=True, allow_infinity=True),
    st.text(max_size=5),
    st.lists(st.integers(-3, 3), max_size=4),
)
coord = st.one_of(st.floats(-0.5, 1.5, allow_nan=False), st.floats(allow_nan=True, allow_infinity=True), garbage)


@st.composite
def vec(draw, dim: int):  # type: ignore[no-untyped-def]
    if draw(st.integers(0, 9)) == 0:
        return draw(garbage)
    return [draw(st.floats(0.0, 1.0)) if draw(st.booleans()) else draw(coord) for _ in range(draw(st.sampled_from([dim, dim, dim, dim - 1, dim + 1])))]


@st.composite
def scene_dicts(draw):  # type: ignore[no-untyped-def]
    dim = draw(st.sampled_from([2, 2, 3, 1, "2", 2.0]))
    d_ = dim if type(dim) is int and dim in (2, 3) else 2
    d: dict = {"name": draw(st.sampled_from(["fuzz", "", 3])), "dim": dim}
    if draw(st.booleans()):
        d["n_grid"] = draw(st.one_of(st.integers(4, 200), st.integers(-5, 10**6), st.floats(), garbage))
    blocks = []
    for _ in range(draw(st.integers(0, 3))):
        b = {"lo": draw(vec(d_)), "hi": draw(vec(d_)), "material": draw(st.sampled_from(["water", "sand", "lava", 0]))}
        if draw(st.booleans()):
            b["velocity"] = draw(vec(d_))
        blocks.append(b)
    d["blocks"] = blocks if draw(st.integers(0, 9)) else draw(garbage)
    if draw(st.booleans()):
        obs = {"shape": draw(st.sampled_from(["box", "sphere", "cone"])), "center": draw(vec(d_))}
        obs["half_extents" if obs["shape"] == "box" else "radius"] = draw(vec(d_)) if obs["shape"] == "box" else draw(coord)
        if draw(st.booleans()):
            obs["angle_deg"] = draw(coord)
        d["obstacles"] = [obs]
    for key, strat in (
        ("walls", st.fixed_dictionaries({"cells": st.one_of(st.integers(-2, 40), garbage), "friction": coord})),
        ("gravity", vec(d_)),
        ("cfl", coord),
        ("frames", st.one_of(st.integers(-3, 10**12), garbage)),
        ("particles_per_cell", st.one_of(st.integers(-1, 50), garbage)),
        ("water", st.fixed_dictionaries({"bulk_modulus": coord})),
        ("sand", st.fixed_dictionaries({"friction_angle_deg": coord})),
    ):
        if draw(st.integers(0, 3)) == 0:
            d[key] = draw(strat)
    if draw(st.integers(0, 9)) == 0:
        d[draw(st.sampled_from(["bogus", "obstacle", "Blocks"]))] = 1
    return d


@pytest.fixture
def small_budget():
    set_memory_budget("256M")
    yield
    set_memory_budget(None)


@FUZZ
@given(d=scene_dicts())
def test_any_scene_file_builds_or_names_the_field(tmp_path_factory, small_budget, d):
    path = tmp_path_factory.mktemp("fuzz") / "scene.json"
    try:
        path.write_text(json.dumps(d))
    except ValueError:  # a float JSON cannot hold (hypothesis found NaN keys): json writes NaN, which we read back
        return
    try:
        scene = SceneSpec.load(path).build()
    except InvalidInputError as e:
        assert e.field, f"no field named: {e}"
        return
    assert np.isfinite(scene.positions).all() and scene.num_particles > 0
    sim = scene.make_solver(num_threads=1)
    assert sim.num_particles == scene.num_particles


@st.composite
def params(draw):  # type: ignore[no-untyped-def]
    dim = draw(st.sampled_from([2, 3]))
    p = MpmParams(dim=dim).to_dict()
    for key, strat in (
        ("n_grid", st.one_of(st.integers(8, 96), st.integers(-3, 2**40), garbage)),
        ("cfl", st.one_of(st.floats(0.05, 1.0), coord)),
        ("substeps", st.one_of(st.none(), st.integers(1, 4), st.integers(-3, 2**40), garbage)),
        ("max_substeps", st.one_of(st.integers(1, 64), garbage)),
        ("gravity", vec(dim)),
    ):
        if draw(st.booleans()):
            p[key] = draw(strat)
    if draw(st.booleans()):
        p["water"] = {**p["water"], "bulk_modulus": draw(st.one_of(st.floats(1e3, 1e7), coord)), "viscosity": draw(st.one_of(st.floats(0, 10), coord))}
    if draw(st.booleans()):
        p["sand"] = {
            **p["sand"],
            "youngs_modulus": draw(st.one_of(st.floats(1e3, 1e7), coord)),
            "poisson_ratio": draw(st.one_of(st.floats(0, 0.49), coord)),
            "friction_angle_deg": draw(st.one_of(st.floats(0, 60), coord)),
            "cohesion": draw(st.one_of(st.floats(0, 1e4), coord)),
        }
    return p


@FUZZ
@given(p=params(), material=st.sampled_from([0, 1]), speed=st.floats(0, 20))
def test_any_solver_parameters_run_or_name_the_field(small_budget, p, material, speed):
    try:
        sim = MpmSolver(MpmParams.from_dict(p))
    except InvalidInputError as e:
        assert e.field, f"no field named: {e}"
        return
    dim = sim.dim
    n = 6 if dim == 2 else 4
    grid = np.stack(np.meshgrid(*[np.linspace(0.45, 0.55, n)] * dim, indexing="ij"), -1).reshape(-1, dim).astype(np.float32)
    sim.add_particles(grid, material, velocities=np.full_like(grid, speed / np.sqrt(dim)))
    for _ in range(3):
        try:
            sim.step_frame()
        except HybridMpmError:  # a SimulationError (rolled back) or a refused frame
            break
    assert np.isfinite(sim.positions).all()
    MpmSolver.from_checkpoint(sim.checkpoint())  # a solver always accepts its own checkpoint
