"""A session's MPM integrator over HTTP (``POST /v1/sessions`` with
``integrator``): a projection session of a water scene runs the projection
(bit for bit what :func:`hybridmpm.sim.make_simulator` runs with it, an
independent path), says so in its info, keeps its water's volume, and comes
back as one from the store; a scene or solver that cannot take it, or a
name that is none, answers 422 naming ``integrator``, never a 500."""

from __future__ import annotations

import time

import numpy as np
import pytest

pytest.importorskip("fastapi")
pytest.importorskip("httpx")

from fastapi.testclient import TestClient  # noqa: E402

from hybridmpm.errors import InvalidInputError  # noqa: E402
from hybridmpm.mpm import INTEGRATORS  # noqa: E402
from hybridmpm.service import ServiceConfig, create_app  # noqa: E402
from hybridmpm.service import checkpoint as ckpt  # noqa: E402
from hybridmpm.service.testing import step_binary  # noqa: E402
from hybridmpm.sim import make_simulator, rollout  # noqa: E402

#: Cells per axis of the grid the water's occupied area is counted on (half the scene's 128).
COUNT_GRID = 64


@pytest.fixture(scope="module")
def client():
    with TestClient(create_app(ServiceConfig(max_sessions=50, max_sessions_per_client=50, idle_ttl_s=600))) as c:
        yield c


def new(client, scene="dam_break2d", solver="mpm", **kw):
    r = client.post("/v1/sessions", json={"scene": scene, "solver": solver, "seed": 0, **kw})
    assert r.status_code == 201, r.text
    return r.json()


def field_of(r):
    assert r.status_code == 422, (r.status_code, r.text)
    return r.json()["detail"][0]["loc"][-1]


def occupied(pos: np.ndarray) -> int:
    """Cells of a ``COUNT_GRID`` grid that hold a particle (the water's area, in cells)."""
    return len({tuple(c) for c in np.floor(np.asarray(pos, np.float64) * COUNT_GRID).astype(int)})


def test_the_names_are_the_solvers():
    assert INTEGRATORS[0] == "explicit" and "projection" in INTEGRATORS


def test_a_projection_session_runs_the_projection_and_keeps_its_water(client):
    s = new(client, integrator="projection")
    assert s["integrator"] == "projection" and client.get(f"/v1/sessions/{s['id']}").json()["integrator"] == "projection"
    ref = make_simulator("dam_break2d", "mpm", seed=0, threads=1, integrator="projection")
    start = np.asarray(ref.frame.positions)
    want = rollout(ref, 40).positions[1:]
    got = step_binary(client, s["id"], 40)
    assert got.shape == want.shape and np.array_equal(got, np.asarray(want, np.float32)), "the session did not run the projection"
    assert client.get(f"/v1/sessions/{s['id']}").json()["frame"] == 40
    last = got[-1]
    assert np.isfinite(got).all() and (last > 0.0).all() and (last < 1.0).all()
    a0, a1 = occupied(start), occupied(last)
    assert abs(a1 - a0) <= 0.1 * a0, (a0, a1)  # incompressible: the water's area stays within 10 %
    assert last[:, 0].max() > start[:, 0].max() + 0.05  # and the dam broke: it flowed


def test_an_explicit_session_and_the_scenes_own_say_explicit(client):
    explicit = new(client, integrator="explicit")
    assert explicit["integrator"] == "explicit"
    a = step_binary(client, explicit["id"], 3)
    b = step_binary(client, new(client, integrator="projection")["id"], 3)
    assert not np.array_equal(a, b)  # another integrator, another run
    assert new(client)["integrator"] == "explicit"  # null: the scene's own
    assert new(client, solver="default")["integrator"] == "explicit"
    assert new(client, solver="hybrid")["integrator"] == "explicit"  # its MPM part runs the scene's


@pytest.mark.parametrize(
    "body",
    [
        {"scene": "water_sand2d", "solver": "mpm", "integrator": "projection"},  # sand
        {"scene": "dam_break2d", "solver": "mpm", "integrator": "bogus"},
        {"scene": "dam_break2d", "solver": "mpm", "integrator": 1},
        {"scene": "dam_break2d", "solver": "mpm", "integrator": ["projection"]},
        {"scene": "dam_break2d", "solver": "default", "integrator": "projection"},
        {"scene": "dam_break2d", "solver": "default", "integrator": "explicit"},
        {"scene": "dam_break2d", "solver": "hybrid", "integrator": "projection"},
        {"scene": "dam_break2d", "solver": "neural", "integrator": "explicit"},
    ],
)
def test_a_refused_integrator_is_a_422_naming_it(client, body):
    before = client.get("/healthz").json()["sessions"]
    assert field_of(client.post("/v1/sessions", json=body)) == "integrator", body
    assert client.get("/healthz").json()["sessions"] == before  # nothing was created


def test_a_scene_with_free_slip_obstacles_runs_on_the_projection(client):
    r = client.post("/v1/sessions", json={"scene": "water_ramps2d", "solver": "mpm", "integrator": "projection"})
    assert r.status_code == 201, r.text
    sid = r.json()["id"]
    assert r.json()["integrator"] == "projection"
    assert client.post(f"/v1/sessions/{sid}/step", json={"frames": 8}).status_code == 200
    client.delete(f"/v1/sessions/{sid}")


def test_the_schema_lists_the_integrators(client):
    prop = client.get("/openapi.json").json()["components"]["schemas"]["CreateSession"]["properties"]["integrator"]
    names = [n for option in prop["anyOf"] for n in option.get("enum", [])]
    assert names == list(INTEGRATORS)


def test_a_checkpoint_is_for_its_integrator(client):
    """A checkpoint's meta names the integrator asked: it restores onto a projection session, not an explicit one."""
    p, e = new(client, integrator="projection"), new(client, integrator="explicit")
    step_binary(client, p["id"], 4)
    blob = client.get(f"/v1/sessions/{p['id']}/checkpoint").content
    assert ckpt.loads(blob, 1 << 28)[1]["integrator"] == "projection"
    r = client.put(f"/v1/sessions/{e['id']}/checkpoint", content=blob, headers={"Content-Type": "application/octet-stream"})
    assert field_of(r) == "checkpoint" and "integrator" in r.json()["detail"][0]["msg"]
    step_binary(client, p["id"], 3)
    r = client.put(f"/v1/sessions/{p['id']}/checkpoint", content=blob, headers={"Content-Type": "application/octet-stream"})
    assert r.status_code == 200 and r.json()["frame"] == 4 and r.json()["integrator"] == "projection"


def test_a_projection_session_comes_back_from_the_store_as_one(tmp_path):
    ref = make_simulator("dam_break2d", "mpm", seed=0, threads=1, integrator="projection")
    rollout(ref, 5)
    expected = rollout(ref, 4).positions[1:]
    cfg = ServiceConfig(store=str(tmp_path / "store"), max_sessions=10, idle_ttl_s=600)
    with TestClient(create_app(cfg)) as c:
        sid = new(c, integrator="projection")["id"]
        step_binary(c, sid, 5)
    with TestClient(create_app(cfg)) as c:  # the first stopped (a clean stop saves every session)
        info = c.get(f"/v1/sessions/{sid}").json()
        assert info["restored_from_frame"] == 5 and info["integrator"] == "projection"
        # an explicit simulator refuses a projection state, so the rebuilt one runs the projection; it matches to
        # bitwise: a projection step reads nothing but the particles
        np.testing.assert_array_equal(step_binary(c, sid, 4), np.asarray(expected, np.float32))


def test_a_record_keeps_its_integrator_and_older_records_have_none():
    from hybridmpm.service.store import parse_record, rebuild, record_state

    sim = make_simulator("dam_break2d", "mpm", seed=2, threads=1, integrator="projection")
    rollout(sim, 3)
    meta = {"scene": "dam_break2d", "seed": 2, "solver": "mpm", "r_c": 0.8, "last_used_at": time.time(), "client": "", "integrator": "projection"}
    rec = parse_record("0" * 64, ckpt.dumps(record_state(sim), meta), 1 << 28)
    assert rec.integrator == "projection"
    back, _ = rebuild(rec)
    assert back.scene.params.integrator == "projection"
    np.testing.assert_array_equal(rollout(back, 3).positions, rollout(sim, 3).positions)  # bitwise
    old = {k: v for k, v in meta.items() if k != "integrator"}  # written before sessions had an integrator
    explicit = make_simulator("dam_break2d", "mpm", seed=2, threads=1)
    rec = parse_record("0" * 64, ckpt.dumps(record_state(explicit), old), 1 << 28)
    assert rec.integrator is None
    assert rebuild(rec)[0].scene.params.integrator == "explicit"
    for bad in ("bogus", 1, True):
        with pytest.raises(InvalidInputError, match="meta.integrator"):
            parse_record("0" * 64, ckpt.dumps(record_state(sim), {**meta, "integrator": bad}), 1 << 28)


def test_a_projection_session_takes_water_and_bodies_only(client):
    """What the projection cannot step (sand) is refused when it is added, naming the integrator, so the session
    is never left refusing every step; a rigid body joins (the projection couples it in its pressure solve, and
    the session's crates scene opens on it); water still pours in, and it steps on."""
    assert new(client, scene="crates2d", integrator="projection")["integrator"] == "projection"
    s = new(client, integrator="projection")
    sid = s["id"]
    r = client.post(f"/v1/sessions/{sid}/blocks", json={"material": "sand", "lo": [0.6, 0.1], "hi": [0.7, 0.2]})
    assert field_of(r) == "integrator"
    r = client.post(f"/v1/sessions/{sid}/bodies", json={"shape": "box", "center": [0.65, 0.65], "half_extents": [0.04, 0.03], "density": 500.0})
    assert r.status_code == 201, r.text
    info = client.get(f"/v1/sessions/{sid}").json()
    assert info["num_particles"] == s["num_particles"] and len(info["bodies"]) == 1 and info["integrator"] == "projection"
    r = client.post(f"/v1/sessions/{sid}/blocks", json={"material": "water", "lo": [0.6, 0.1], "hi": [0.7, 0.2]})
    assert r.status_code == 201 and r.json()["num_particles"] > s["num_particles"], r.text
    assert step_binary(client, sid, 2).shape[1] == r.json()["num_particles"]
    e = new(client, integrator="explicit")  # the explicit MPM takes both
    assert client.post(f"/v1/sessions/{e['id']}/blocks", json={"material": "sand", "lo": [0.6, 0.1], "hi": [0.7, 0.2]}).status_code == 201
