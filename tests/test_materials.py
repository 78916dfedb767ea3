"""The materials as Python and scene files give them: models and presets,
per-block parameter sets, bad input naming the field, checkpoints with
parameter sets, and the learned solvers refusing what they were not trained on."""

from __future__ import annotations

import struct

import numpy as np
import pytest

import hybridmpm as hm
from hybridmpm.conventions import GNS_TYPE_OF_MATERIAL, MATERIALS
from hybridmpm.materials import MODELS, PRESET_SOURCES, PRESETS, Elastic, Viscoplastic
from hybridmpm.mpm import MpmParams, MpmSolver


def _spec(*blocks: dict) -> hm.SceneSpec:
    return hm.SceneSpec.from_dict({"name": "t", "dim": 2, "n_grid": 64, "frames": 10, "blocks": list(blocks)})


def test_codes_are_the_solvers_and_every_preset_has_a_source():
    assert {m.name: m.code for m in MODELS.values()} == MATERIALS
    assert set(PRESETS) == {"jello", "rubber", "snow", "mud", "plasticine", "honey", "soil"} == set(PRESET_SOURCES)
    assert set(GNS_TYPE_OF_MATERIAL) == set(MATERIALS.values())
    assert hm.materials.Elastic(E=1e5, nu=0.3).to_params().youngs_modulus == 1e5


def test_blocks_of_one_model_with_other_parameters_get_their_own_sets():
    spec = _spec(
        {"material": "water", "lo": [0.05, 0.05], "hi": [0.3, 0.3]},
        {"material": "jello", "lo": [0.5, 0.5], "hi": [0.6, 0.6]},
        {"material": "elastic", "E": 3e5, "lo": [0.7, 0.5], "hi": [0.8, 0.6]},
        {"material": "jello", "lo": [0.5, 0.2], "hi": [0.6, 0.3]},
        {"material": "snow", "lo": [0.35, 0.1], "hi": [0.45, 0.2]},
    )
    scene = spec.build()
    assert len(scene.params.sets) == 2  # the two jellies share one set
    assert scene.material_set is not None
    sim = scene.make_solver(num_threads=1)
    assert np.array_equal(sim.material_set, scene.material_set)
    # the default mass is the set's density times the volume
    jello = scene.material_set == 5
    np.testing.assert_allclose(sim.masses[jello], PRESETS["jello"].density * sim.volumes[jello], rtol=1e-6)
    for _ in range(5):
        sim.step_frame()
    again = hm.SceneSpec.from_dict(spec.to_dict())
    assert again.to_dict() == spec.to_dict()


@pytest.mark.parametrize(
    ("block", "field"),
    [
        ({"material": "elastic", "E": 0.0}, "blocks[0].E"),
        ({"material": "elastic", "nu": 0.5}, "blocks[0].nu"),
        ({"material": "elastic", "nu": -0.1}, "blocks[0].nu"),
        ({"material": "snow", "theta_c": 1.0}, "blocks[0].theta_c"),
        ({"material": "snow", "theta_s": 0.0}, "blocks[0].theta_s"),
        ({"material": "mud", "yield_stress": -1.0}, "blocks[0].yield_stress"),
        ({"material": "viscoplastic", "viscosity": -1.0}, "blocks[0].viscosity"),
        ({"material": "water", "density": 0.0}, "blocks[0].density"),
        ({"material": "sand", "density": float("nan")}, "blocks[0].density"),
        ({"material": "elastic", "model": "linear"}, "blocks[0].model"),
        ({"material": "water", "E": 1e5}, "blocks[0].E"),
        ({"material": "lava"}, "blocks[0].material"),
    ],
)
def test_bad_material_input_names_the_field(block, field):
    with pytest.raises(hm.InvalidInputError) as e:
        _spec({**block, "lo": [0.4, 0.4], "hi": [0.5, 0.5]})
    assert e.value.field == field


def test_the_engine_names_a_bad_set_and_a_foreign_set_index():
    with pytest.raises(hm.InvalidInputError) as e:
        MpmSolver(MpmParams(sets=[hm.mpm.ViscoplasticParams(yield_stress=-1.0)]))
    assert e.value.field == "sets[0].viscoplastic.yield_stress"
    sim = MpmSolver(MpmParams())
    x = np.full((4, 2), 0.5, np.float32)
    with pytest.raises(hm.InvalidInputError) as e:
        sim.add_particles(x, 2, material_set=1)  # set 1 is sand's
    assert e.value.field == "material_set"
    assert sim.num_particles == 0


_NAMES = "'water', 'sand', 'elastic', 'snow', 'viscoplastic'"


@pytest.mark.parametrize(
    ("entry", "field", "message"),
    [
        ({}, "sets[1]", f"expected a dict naming exactly one of {_NAMES}, got an empty dict"),
        ({"water": {}, "sand": {}}, "sets[1]", f"expected a dict naming exactly one of {_NAMES}, got 2 keys: 'water', 'sand'"),
        ({"jelly": {}}, "sets[1]", f"must be one of {_NAMES}, got 'jelly'"),
        ("elastic", "sets[1]", "'elastic' takes parameters: expected a dict {'elastic': {...}}, got 'elastic'"),
        ({"elastic": {"youngs": 1.0}}, "sets[1].elastic.youngs", "unknown parameter (allowed: density, youngs_modulus, poisson_ratio, model)"),
    ],
)
def test_the_core_reads_a_set_as_a_dict_of_one_material_naming_the_entry(entry, field, message):
    d = MpmParams(n_grid=16, sets=[hm.mpm.ElasticParams()]).to_dict()
    d["sets"].append(entry)
    with pytest.raises(hm.InvalidInputError) as e:
        hm._core.MpmSolver(d)
    assert (e.value.field, str(e.value)) == (field, f"{field}: {message}")
    sim = MpmSolver(MpmParams(n_grid=16, sets=[hm.mpm.ElasticParams()]))
    with pytest.raises(hm.InvalidInputError) as e:
        sim._core.add_parameter_set(entry)
    assert (e.value.field, str(e.value)) == (field, f"{field}: {message}")


def test_checkpoints_keep_the_sets_bit_for_bit():
    params = MpmParams(n_grid=64, sets=[hm.mpm.ElasticParams(youngs_modulus=3e4), hm.mpm.SnowParams(hardening=5.0)])
    sim = MpmSolver(params)
    rng = np.random.default_rng(0)
    for code, set_, lo in ((2, 5, 0.2), (3, 6, 0.5), (4, 4, 0.7), (2, 2, 0.35)):
        sim.add_particles(rng.uniform(lo, lo + 0.1, (200, 2)).astype(np.float32), code, material_set=set_)
    for _ in range(5):
        sim.step_frame()
    blob = sim.checkpoint()
    for _ in range(5):
        sim.step_frame()
    end = sim.checkpoint()
    other = MpmSolver.from_checkpoint(blob)
    assert np.array_equal(other.material_set, sim.material_set)
    for _ in range(5):
        other.step_frame()
    assert other.checkpoint() == end


def test_a_set_appended_in_place_steps_as_one_given_at_the_start_and_a_bad_one_changes_nothing():
    rng = np.random.default_rng(1)
    sim = MpmSolver(MpmParams(n_grid=64))
    sim.add_particles(rng.uniform(0.1, 0.3, (300, 2)).astype(np.float32), 0)
    for _ in range(5):
        sim.step_frame()
    mid = sim.checkpoint()
    before = sim.params
    with pytest.raises(hm.InvalidInputError) as e:
        sim.add_parameter_set(hm.mpm.ElasticParams(youngs_modulus=-1.0))
    assert e.value.field == "sets[0].elastic.youngs_modulus"
    with pytest.raises(hm.InvalidInputError) as e:  # the core refuses what the Python check would pass on
        sim._core.add_parameter_set({"elastic": {"youngs": 1.0}})
    assert e.value.field == "sets[0].elastic.youngs"
    assert sim.params == before and sim.checkpoint() == mid
    jelly = hm.mpm.ElasticParams(youngs_modulus=5e4)
    assert sim.add_parameter_set(jelly) == len(MATERIALS)
    # a solver given the set from the start, restored from the same state
    other = MpmSolver(MpmParams(n_grid=64, sets=[jelly]))
    other.restore(MpmSolver.with_header(mid, {"sets": other.params.to_dict()["sets"]}))
    assert sim.params == other.params
    block = rng.uniform(0.5, 0.6, (100, 2)).astype(np.float32)
    for s in (sim, other):
        s.add_particles(block, 2, material_set=len(MATERIALS))
        for _ in range(10):
            s.step_frame()
    assert sim.checkpoint() == other.checkpoint()


def test_learned_solvers_refuse_new_materials_and_mpm_runs_them():
    scene = _spec(
        {"material": "water", "lo": [0.05, 0.05], "hi": [0.3, 0.3]},
        {"material": "mud", "lo": [0.5, 0.5], "hi": [0.6, 0.6]},
    ).build()
    for solver in ("neural", "hybrid"):
        with pytest.raises(hm.InvalidInputError, match="viscoplastic") as e:
            hm.make_simulator(scene, solver)
        assert e.value.field == "material"
    traj = hm.rollout(hm.make_simulator(scene, "mpm"), 3)
    assert set(np.unique(traj.material).tolist()) == {0, 4}


def test_material_objects_validate_like_scene_files():
    with pytest.raises(hm.InvalidInputError) as e:
        Elastic(E=-1.0).validate()
    assert e.value.field == "E"
    Viscoplastic(yield_stress=0.0, viscosity=0.0).validate()


def test_a_checkpoint_from_before_parameter_sets_restores():
    # the core format before parameter sets (HMPMCKP2): no set per particle, each takes its material's default
    sim = MpmSolver(MpmParams(n_grid=64))
    sim.add_particles(np.random.default_rng(0).uniform(0.3, 0.6, (50, 2)).astype(np.float32), 1)
    sim.step_frame()
    blob = sim.checkpoint()
    (hlen,) = struct.unpack("<Q", blob[8:16])
    head, core = blob[: 16 + hlen], blob[16 + hlen :]
    per = 4 * (3 * 2 + 3 * 4 + 4) + 3
    records = np.frombuffer(core, np.uint8, 50 * per, 36).reshape(50, per)[:, :-2]
    old = b"HMPMCKP2" + core[8:36] + records.tobytes()
    other = MpmSolver(MpmParams(n_grid=64))
    other.add_particles(np.full((50, 2), 0.5, np.float32), 1)
    other.restore(head + old, same_particles=True)
    assert np.array_equal(other.positions, sim.positions)
    assert np.array_equal(other.material_set, np.ones(50, np.int32))
