"""A scene's ``[water]`` and ``[sand]`` tables are its water and sand blocks' parameters.

The rule (docs/materials.md "Scene-level and block-level parameters"): a block naming a model starts from the scene's
table of that model, a block naming a preset from the preset, and the block's own keys override either. Each
parameter is checked to reach the solver through every route a scene takes (a scene file, ``SceneSpec.from_dict``,
a block poured into a session, in-process and over HTTP, and a checkpoint restored into a fresh simulator): the
substep count against the CFL condition computed here from the wave speed (``dt ≤ cfl·dx / c``, water
``c = sqrt(K/ρ)``, sand the P-wave speed ``sqrt((λ + 2μ)/ρ)``), and a result the parameter changes (a sand column's
runout against its friction angle, the same bits as the same column built from ``MpmParams`` directly).
"""

from __future__ import annotations

import math

import numpy as np
import pytest

import hybridmpm as hm
from hybridmpm.errors import InvalidInputError
from hybridmpm.mpm import DT_FRAME, MpmParams, SandParams, WallParams, WaterParams
from hybridmpm.scenes import SceneSpec, make_scene
from hybridmpm.sim import make_simulator, rollout
from hybridmpm.sim.pour import pour_block

N_GRID = 64
COLUMN = {"material": "sand", "lo": [0.05, 0.05], "hi": [0.25, 0.35]}  # a sand column against the left wall
FRAMES = 150  # the column has run out and stopped (0.375 s)


def scene_dict(water: dict | None = None, sand: dict | None = None, blocks: list | None = None) -> dict:
    d: dict = {"name": "tables", "dim": 2, "n_grid": N_GRID, "walls": {"friction": 0.36}, "blocks": blocks or [dict(COLUMN)]}
    if water is not None:
        d["water"] = water
    if sand is not None:
        d["sand"] = sand
    return d


def toml_text(d: dict) -> str:
    import tomli_w

    return tomli_w.dumps(d)


def cfl_substeps(c: float) -> int:
    """The substeps of a frame at rest by the CFL condition, from the wave speed ``c`` [m/s]."""
    cfl = MpmParams().cfl
    return max(1, math.ceil(DT_FRAME * c / (cfl * (1.0 / N_GRID))))


def p_wave(E: float, nu: float, rho: float) -> float:
    mu, lam = E / (2 * (1 + nu)), E * nu / ((1 + nu) * (1 - 2 * nu))
    return math.sqrt((lam + 2 * mu) / rho)


def runout(scene) -> tuple[float, np.ndarray]:
    """The column's runout (largest x of a particle, m) after :data:`FRAMES` frames, and the last positions."""
    r = rollout(make_simulator(scene, "mpm"), FRAMES)
    assert r.failure is None and len(r.positions) == FRAMES + 1
    return float(r.positions[-1][:, 0].max()), r.positions[-1]


@pytest.mark.parametrize("E", [1e5, 1e7])
def test_a_scene_files_sand_table_sets_the_cfl_step(tmp_path, E):
    path = tmp_path / "sand.toml"
    path.write_text(toml_text(scene_dict(sand={"youngs_modulus": E})))
    scene = make_scene(str(path))
    sand = SandParams()
    want = cfl_substeps(p_wave(E, sand.poisson_ratio, sand.density))
    assert scene.make_solver().substeps_for(DT_FRAME) == want
    assert scene.params.sand.youngs_modulus == E and scene.material_set is None  # the blocks run the table itself


@pytest.mark.parametrize("K", [4e4, 4e6])
def test_a_scene_files_water_table_sets_the_cfl_step(tmp_path, K):
    path = tmp_path / "water.toml"
    path.write_text(toml_text(scene_dict(water={"bulk_modulus": K, "density": 900.0}, blocks=[dict(COLUMN, material="water")])))
    scene = make_scene(str(path))
    assert scene.make_solver().substeps_for(DT_FRAME) == cfl_substeps(math.sqrt(K / 900.0))
    # the table's density is the particles' too: their masses add up to the block's area (per unit depth) times it
    assert float(np.sum(scene.make_solver().masses, dtype=np.float64)) == pytest.approx(900.0 * 0.2 * 0.3, rel=1e-5)


def test_the_friction_angle_of_a_scene_file_changes_the_runout_as_the_same_column_built_from_params(tmp_path):
    out = {}
    for phi in (10.0, 45.0):
        path = tmp_path / f"phi{phi:g}.toml"
        path.write_text(toml_text(scene_dict(sand={"friction_angle_deg": phi, "youngs_modulus": 1e5})))
        out[phi] = runout(make_scene(str(path)))
        # the route that always held: the solver's parameters given in Python, the same particles
        scene = make_scene(str(path))
        params = MpmParams(dim=2, n_grid=N_GRID, sand=SandParams(youngs_modulus=1e5, friction_angle_deg=phi), walls=WallParams(friction=0.36))
        solver = hm.MpmSolver(params)
        solver.add_particles(scene.positions, scene.material, velocities=scene.velocities, volumes=scene.volumes)
        sim = make_simulator(scene, "mpm")
        sim.solver.restore(solver.checkpoint(), same_particles=True)
        r = rollout(sim, FRAMES)
        np.testing.assert_array_equal(r.positions[-1], out[phi][1])
    # a 10° sand spreads far; a 45° column barely slumps (0.82 and 0.48 m)
    assert out[10.0][0] > out[45.0][0] + 0.2, {k: v[0] for k, v in out.items()}


def test_a_blocks_own_keys_override_the_scene_table():
    table = SceneSpec.from_dict(scene_dict(sand={"friction_angle_deg": 10.0, "youngs_modulus": 1e5}))
    # the same column with its own angle: the block's key wins, the rest is the table's
    own = SceneSpec.from_dict(scene_dict(sand={"friction_angle_deg": 10.0, "youngs_modulus": 1e5}, blocks=[dict(COLUMN, friction_angle_deg=45.0)]))
    direct = SceneSpec.from_dict(scene_dict(sand={"friction_angle_deg": 45.0, "youngs_modulus": 1e5}))
    scene = own.build()
    assert scene.params.sets == [SandParams(youngs_modulus=1e5, friction_angle_deg=45.0)]
    assert runout(scene)[0] == runout(direct.build())[0] != runout(table.build())[0]
    # a preset starts from itself, not from the scene's table: soil keeps its own angle and modulus
    soil = SceneSpec.from_dict(scene_dict(sand={"friction_angle_deg": 10.0}, blocks=[dict(COLUMN, material="soil")])).build()
    assert soil.params.sets == [hm.materials.PRESETS["soil"].to_params()]
    # a block's key checked against the table's merged values, and named
    with pytest.raises(InvalidInputError) as e:
        SceneSpec.from_dict(scene_dict(sand={"friction_angle_deg": 10.0}, blocks=[dict(COLUMN, nu=0.7)]))
    assert e.value.field == "blocks[0].nu"


def test_the_tables_and_overrides_survive_to_dict_save_and_load(tmp_path):
    d = scene_dict(
        water={"bulk_modulus": 4e4},
        sand={"friction_angle_deg": 10.0, "youngs_modulus": 1e5},
        blocks=[
            dict(COLUMN),
            {"material": "sand", "lo": [0.5, 0.05], "hi": [0.6, 0.2], "cohesion": 50.0},
            {"material": "water", "lo": [0.7, 0.05], "hi": [0.9, 0.2]},
        ],
    )
    spec = SceneSpec.from_dict(d)
    back = spec.to_dict()
    assert back["sand"]["friction_angle_deg"] == 10.0 and back["water"]["bulk_modulus"] == 4e4
    # each block writes its own keys only: the table is not copied into it
    assert [{k: v for k, v in b.items() if k not in ("material", "lo", "hi")} for b in back["blocks"]] == [{}, {"cohesion": 50.0}, {}]
    for again in (SceneSpec.from_dict(back), SceneSpec.load(spec.save(tmp_path / "s.toml")), SceneSpec.load(spec.save(tmp_path / "s.json"))):
        a, b = spec.build(), again.build()
        assert a.params.to_dict() == b.params.to_dict()
        set_a, set_b = (x.material if x.material_set is None else x.material_set for x in (a, b))
        assert np.array_equal(set_a, set_b) and a.params.sets == [SandParams(youngs_modulus=1e5, friction_angle_deg=10.0, cohesion=50.0)]
        assert a.make_solver().substeps_for(DT_FRAME) == b.make_solver().substeps_for(DT_FRAME)


def test_a_checkpoint_restores_the_tables_into_a_fresh_simulator(tmp_path):
    path = tmp_path / "mixed.toml"
    blocks = [dict(COLUMN), {"material": "water", "lo": [0.5, 0.05], "hi": [0.8, 0.3]}]
    path.write_text(toml_text(scene_dict(water={"bulk_modulus": 4e6}, sand={"youngs_modulus": 1e5, "friction_angle_deg": 10.0}, blocks=blocks)))
    scene = make_scene(str(path))
    sim = make_simulator(scene, "mpm")
    rollout(sim, 5)
    state = sim.state()
    fresh = make_simulator(make_scene(str(path)), "mpm")
    fresh.restore(state)
    assert fresh.solver.substeps_for(DT_FRAME) == sim.solver.substeps_for(DT_FRAME) >= cfl_substeps(math.sqrt(4e6 / 1000.0))
    assert fresh.solver.params.water.bulk_modulus == 4e6 and fresh.solver.params.sand.friction_angle_deg == 10.0
    np.testing.assert_array_equal(rollout(fresh, 5).positions[-1], rollout(sim, 5).positions[-1])
    # and the checkpoint restored into a solver of its own (MpmSolver.from_checkpoint) keeps them
    solo = hm.MpmSolver.from_checkpoint(sim.solver.checkpoint())
    assert solo.params.water == WaterParams(bulk_modulus=4e6) and solo.params.sand == sim.solver.params.sand


def test_a_poured_block_takes_the_scene_table(tmp_path):
    path = tmp_path / "pour.toml"
    path.write_text(toml_text(scene_dict(sand={"youngs_modulus": 1e7, "friction_angle_deg": 10.0})))
    sim = make_simulator(make_scene(str(path)), "mpm")
    before = sim.solver.substeps_for(DT_FRAME)
    pour_block(sim, {"material": "sand", "lo": [0.6, 0.1], "hi": [0.7, 0.2]})
    assert sim.solver.params.sets == [] and sim.solver.substeps_for(DT_FRAME) == before  # the table's own set
    pour_block(sim, {"material": "sand", "lo": [0.6, 0.3], "hi": [0.7, 0.4], "cohesion": 100.0})
    assert sim.solver.params.sets == [SandParams(youngs_modulus=1e7, friction_angle_deg=10.0, cohesion=100.0)]


def test_a_block_poured_over_http_takes_the_sessions_scene_table():
    """The service's scene description (a block poured into a session): a registered scene's sand table (sand2d:
    the friction angle its walls are made for) is a poured sand block's base, and a key of the request overrides it."""
    pytest.importorskip("fastapi")
    from fastapi.testclient import TestClient

    from hybridmpm.scenes import scene_spec
    from hybridmpm.service import checkpoint as ckpt
    from hybridmpm.service import create_app

    table = scene_spec("sand2d", seed=0).params.sand
    with TestClient(create_app()) as c:
        sid = c.post("/v1/sessions", json={"scene": "sand2d", "seed": 0, "solver": "mpm"}).json()["id"]
        r = c.post(f"/v1/sessions/{sid}/blocks", json={"material": "sand", "lo": [0.45, 0.6], "hi": [0.5, 0.65]})
        assert r.status_code == 201, r.text
        r = c.post(f"/v1/sessions/{sid}/blocks", json={"material": "sand", "lo": [0.6, 0.6], "hi": [0.65, 0.65], "cohesion": 20.0})
        assert r.status_code == 201, r.text
        r = c.get(f"/v1/sessions/{sid}/checkpoint")
        assert r.status_code == 200
    state, _ = ckpt.loads(r.content, 1 << 28)
    params = hm.MpmSolver.from_checkpoint(state["solver"]).params
    assert params.sand == table and params.sets == [SandParams(**{**vars(table), "cohesion": 20.0})]
