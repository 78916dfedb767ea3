"""POST /v1/sessions/{id}/bodies and DELETE .../bodies/{index}: rigid bodies
added to and removed from an MPM session between frames (test client). The
viewers get a ``bodies`` event, the session's description lists them, JSON
frames of a step carry their poses, every refusal names the field and
leaves the session bit for bit as it was (its checkpoint bytes), and a
session with bodies survives a checkpoint round trip and a restart on its
store."""

from __future__ import annotations

import json

import numpy as np
import pytest

pytest.importorskip("fastapi")
pytest.importorskip("httpx")

from fastapi.testclient import TestClient  # noqa: E402

from hybridmpm.service import ServiceConfig, create_app  # noqa: E402
from hybridmpm.service.testing import get_checkpoint, new_session  # noqa: E402
from hybridmpm.sim import make_simulator, rollout  # noqa: E402

#: A 500 kg/m³ box in the air above dam_break2d's water column (its grid: 128², a cell 1/128 m).
BOX = {"shape": "box", "center": [0.65, 0.65], "half_extents": [0.04, 0.03], "density": 500.0}
BALL = {"shape": "circle", "center": [0.4, 0.8], "radius": 0.03, "mass": 1.5}


@pytest.fixture(scope="module")
def client():
    with TestClient(create_app(ServiceConfig(max_sessions=50, max_sessions_per_client=50, idle_ttl_s=600))) as c:
        yield c


def _step(client, sid, frames):
    r = client.post(f"/v1/sessions/{sid}/step", json={"frames": frames})
    assert r.status_code == 200, r.text
    return r.json()["frames"]


def _event(ws, kind):
    while True:
        m = ws.receive()
        if m.get("text") and json.loads(m["text"]).get("type") == kind:
            return json.loads(m["text"])


def test_a_body_joins_the_run_viewers_hear_of_it_and_frames_carry_its_pose(client):
    sid = new_session(client)["id"]
    assert client.get(f"/v1/sessions/{sid}").json()["bodies"] == []
    assert "bodies" not in _step(client, sid, 2)[-1]  # no bodies: the frames old clients know
    with client.websocket_connect(f"/v1/sessions/{sid}/stream") as ws:
        assert json.loads(ws.receive_text())["type"] == "meta"
        r = client.post(f"/v1/sessions/{sid}/bodies", json=BOX)
        assert r.status_code == 201, r.text
        assert r.json() == {"index": 0, "num_bodies": 1, "frame": 2}
        event = _event(ws, "bodies")
        assert event["frame"] == 2 and event["bodies"] == [BOX]
        r = client.post(f"/v1/sessions/{sid}/bodies", json=BALL)
        assert r.json() == {"index": 1, "num_bodies": 2, "frame": 2}, r.text
        assert _event(ws, "bodies")["bodies"] == [BOX, BALL]
    info = client.get(f"/v1/sessions/{sid}").json()
    box, ball = info["bodies"]
    assert box["shape"] == "box" and box["half_extents"] == BOX["half_extents"] and "radius" not in box
    assert box["mass"] == pytest.approx(500.0 * 0.08 * 0.06, rel=1e-5)  # per unit depth in 2D
    assert ball["radius"] == BALL["radius"] and ball["mass"] == pytest.approx(1.5)
    np.testing.assert_allclose(box["center"], BOX["center"], atol=1e-6)
    np.testing.assert_allclose(box["rotation"], np.eye(2), atol=1e-6)
    assert box["velocity"] == [0.0, 0.0] and box["angular_velocity"] == 0.0
    # it runs: both fall freely through the air, g t^2 / 2, and every JSON frame carries their poses
    frames = _step(client, sid, 20)
    assert all(len(f["bodies"]) == 2 and set(f["bodies"][0]) == {"center", "rotation"} for f in frames)
    t = 20 * info["dt_frame"]
    for k, given in enumerate((BOX, BALL)):
        assert frames[-1]["bodies"][k]["center"][1] == pytest.approx(given["center"][1] - 9.8 * t * t / 2, abs=2e-3)
        assert frames[-1]["bodies"][k]["center"][0] == pytest.approx(given["center"][0], abs=1e-6)
    now = client.get(f"/v1/sessions/{sid}").json()["bodies"]
    assert now[0]["center"] == pytest.approx(frames[-1]["bodies"][0]["center"], abs=1e-7) and now[0]["velocity"][1] < -0.4
    # the binary step is the positions alone, as before
    r = client.post(f"/v1/sessions/{sid}/step", json={"frames": 1}, headers={"Accept": "application/octet-stream"})
    assert r.status_code == 200 and len(r.content) == 4 * info["num_particles"] * 2
    # removed: the later one moves down, the viewers hear of it, frames without bodies again once none is left
    with client.websocket_connect(f"/v1/sessions/{sid}/stream") as ws:
        assert json.loads(ws.receive_text())["bodies"][1]["shape"] == "circle"  # a new viewer's meta lists them
        r = client.delete(f"/v1/sessions/{sid}/bodies/0")
        assert r.status_code == 200 and r.json() == {"index": 0, "num_bodies": 1, "frame": 23}, r.text
        assert _event(ws, "bodies")["bodies"] == [BALL]
    assert [b["shape"] for b in client.get(f"/v1/sessions/{sid}").json()["bodies"]] == ["circle"]
    assert client.delete(f"/v1/sessions/{sid}/bodies/0").json()["num_bodies"] == 0
    assert "bodies" not in _step(client, sid, 1)[-1]


@pytest.mark.parametrize(
    ("change", "field"),
    [
        ({"density": 0.0}, "density"),
        ({"density": -500.0}, "density"),
        ({"density": "heavy"}, "density"),
        ({"half_extents": [0.001, 0.03]}, "half_extents"),  # thinner than a cell
        ({"half_extents": [0.04, 0.03, 0.03]}, "half_extents"),  # 3 numbers in 2D
        ({"center": [0.01, 0.5]}, "center"),  # in the wall band
        ({"center": [0.5, 0.5, 0.5]}, "center"),
        ({"center": None}, "center"),
        ({"shape": "cylinder"}, "shape"),  # no such shape
        ({"colour": "red"}, "colour"),
        ({"velocity": [1.0]}, "velocity"),
    ],
)
def test_refusals_name_the_field_and_change_nothing(client, change, field):
    sid = new_session(client)["id"]
    before = get_checkpoint(client, sid)
    body = {k: v for k, v in {**BOX, **change}.items() if v is not None}
    r = client.post(f"/v1/sessions/{sid}/bodies", json=body)
    assert r.status_code == 422, r.text
    assert r.json()["detail"][0]["loc"][-1] == field, r.text
    assert get_checkpoint(client, sid) == before


def test_nan_too_many_a_missing_index_and_the_wrong_session_are_refused(client):
    from hybridmpm.mpm.bodies import MAX_BODIES

    sid = new_session(client)["id"]
    for k in range(MAX_BODIES):  # 8 × 8 apart: a body overlapping another is refused
        assert client.post(f"/v1/sessions/{sid}/bodies", json={**BALL, "center": [0.12 + 0.1 * (k % 8), 0.12 + 0.1 * (k // 8)]}).status_code == 201
    before = get_checkpoint(client, sid)
    r = client.post(f"/v1/sessions/{sid}/bodies", json=BALL)
    assert r.status_code == 422 and r.json()["detail"][0]["loc"][-1] == "bodies", r.text
    r = client.post(f"/v1/sessions/{sid}/bodies", content=json.dumps(BOX)[:-1] + ', "mass": NaN}', headers={"Content-Type": "application/json"})
    assert r.status_code == 422 and r.json()["detail"][0]["loc"][-1] == "mass", r.text
    r = client.delete(f"/v1/sessions/{sid}/bodies/{MAX_BODIES}")
    assert r.status_code == 404 and r.json()["detail"][0]["loc"] == ["path", "index"], r.text
    assert get_checkpoint(client, sid) == before
    # a running control, a learned simulator: 409; a missing or deleted session: 404
    manager = client.app.state.manager
    manager.sessions[sid].controlling = True
    assert client.post(f"/v1/sessions/{sid}/bodies", json=BOX).status_code == 409
    assert client.delete(f"/v1/sessions/{sid}/bodies/0").status_code == 409
    manager.sessions[sid].controlling = False
    neural = new_session(client, scene="water2d", solver="neural")["id"]
    assert client.post(f"/v1/sessions/{neural}/bodies", json=BOX).status_code == 409
    assert client.post("/v1/sessions/" + "x" * 32 + "/bodies", json=BOX).status_code == 404
    assert client.delete(f"/v1/sessions/{sid}").status_code == 204
    assert client.post(f"/v1/sessions/{sid}/bodies", json=BOX).status_code == 404
    assert client.delete(f"/v1/sessions/{sid}/bodies/0").status_code == 404


def test_a_session_with_bodies_survives_a_checkpoint_round_trip_and_a_reset(client):
    sid = new_session(client)["id"]
    bare = get_checkpoint(client, sid)
    assert client.post(f"/v1/sessions/{sid}/bodies", json=BOX).status_code == 201
    _step(client, sid, 5)
    saved = get_checkpoint(client, sid)
    ahead = _step(client, sid, 6)
    # back to a state before the body: none, and the viewers hear of it
    with client.websocket_connect(f"/v1/sessions/{sid}/stream") as ws:
        assert json.loads(ws.receive_text())["type"] == "meta"
        assert client.put(f"/v1/sessions/{sid}/checkpoint", content=bare).status_code == 200
        assert _event(ws, "bodies")["bodies"] == []
    assert client.get(f"/v1/sessions/{sid}").json()["bodies"] == []
    # forward to the state with it: the same bits as a run that never went back
    assert client.put(f"/v1/sessions/{sid}/checkpoint", content=saved).status_code == 200
    assert client.get(f"/v1/sessions/{sid}").json()["frame"] == 5
    again = _step(client, sid, 6)
    assert again[-1]["bodies"] == ahead[-1]["bodies"] and again[-1]["positions"] == ahead[-1]["positions"]
    # a reset: the scene's own bodies (none)
    with client.websocket_connect(f"/v1/sessions/{sid}/stream") as ws:
        assert json.loads(ws.receive_text())["type"] == "meta"
        ws.send_text(json.dumps({"type": "reset"}))
        assert _event(ws, "bodies")["bodies"] == []
    assert client.get(f"/v1/sessions/{sid}").json()["bodies"] == []


def test_a_session_with_bodies_comes_back_after_a_restart_on_its_store(tmp_path):
    reference = make_simulator("dam_break2d", "mpm", seed=0, threads=1)
    rollout(reference, 3)
    reference.add_body(BOX)
    rollout(reference, 4)
    expected = rollout(reference, 5)
    cfg = ServiceConfig(store=str(tmp_path / "store"), max_sessions=10, idle_ttl_s=600)
    with TestClient(create_app(cfg)) as c:
        sid = new_session(c)["id"]
        _step(c, sid, 3)
        assert c.post(f"/v1/sessions/{sid}/bodies", json=BOX).status_code == 201
        _step(c, sid, 4)
    with TestClient(create_app(cfg)) as c:  # the first stopped (a clean stop saves every session)
        info = c.get(f"/v1/sessions/{sid}").json()
        assert info["frame"] == 7 and info["restored_from_frame"] == 7
        assert [b["shape"] for b in info["bodies"]] == ["box"] and info["bodies"][0]["mass"] == pytest.approx(2.4, rel=1e-5)
        frames = _step(c, sid, 5)
    np.testing.assert_array_equal(np.asarray(frames[-1]["bodies"][0]["center"]), expected.body_center[-1, 0])
    np.testing.assert_array_equal(np.asarray(frames[-1]["positions"], np.float32), np.asarray(expected.positions[-1], np.float32))


def test_a_scene_with_bodies_lists_them_and_takes_more_on_its_default_solver(client):
    s = new_session(client, scene="crates2d", solver="default")  # no shipped model: the default runs MPM
    assert [b["shape"] for b in s["bodies"]] == ["box"] * 4
    r = client.post(f"/v1/sessions/{s['id']}/bodies", json={**BOX, "center": [0.5, 0.8]})
    assert r.status_code == 201 and r.json()["index"] == 4, r.text
    assert len(_step(client, s["id"], 1)[-1]["bodies"]) == 5


def test_the_trajectory_download_carries_the_bodies_of_the_frames_that_share_them(client, tmp_path):
    """GET .../trajectory: the npz holds body_center / body_rotation / body_mass equal to a local rollout of the same
    scene (MPM, bit for bit) over the frames whose bodies were the same; frames across an added body have none; the
    mesh zip holds each body at each frame, at its pose (body_surface of the pose the npz gives)."""
    import io
    import zipfile

    import trimesh

    from hybridmpm.render.bodies import body_surface

    sid = new_session(client, "crates2d")["id"]
    _step(client, sid, 6)
    t = client.get(f"/v1/sessions/{sid}/trajectory?frames=6")
    assert t.status_code == 200
    with np.load(io.BytesIO(t.content), allow_pickle=False) as z:
        center, rotation, mass = z["body_center"], z["body_rotation"], z["body_mass"]
    sim = make_simulator("crates2d", "mpm", seed=0, threads=1)
    ro = rollout(sim, 6)
    assert center.shape == (6, len(sim.bodies), 2) and rotation.shape == (6, len(sim.bodies), 2, 2)
    assert np.array_equal(center, ro.body_center[1:]) and np.array_equal(rotation, ro.body_rotation[1:]) and np.array_equal(mass, ro.body_mass)

    z = zipfile.ZipFile(io.BytesIO(client.get(f"/v1/sessions/{sid}/trajectory?frames=2&format=mesh").content))
    names = z.namelist()
    assert {f"body_{i}_{k:05d}.ply" for i in range(len(sim.bodies)) for k in range(2)} <= set(names)
    got = trimesh.load(io.BytesIO(z.read("body_1_00001.ply")), file_type="ply", process=False)
    want = body_surface(sim.solver.params.bodies[1], center[-1, 1], rotation[-1, 1])
    ring = np.concatenate([loop[:-1] for loop in want.loops])  # the outline's points (its last repeats its first)
    v = np.asarray(got.vertices)[:, :2]
    assert len(v) == len(ring) and np.abs(v[:, None] - ring[None]).max(-1).min(1).max() < 1e-6

    # a body added: the frames before it and after it do not share their bodies
    assert client.post(f"/v1/sessions/{sid}/bodies", json=BALL | {"center": [0.5, 0.8]}).status_code == 201
    _step(client, sid, 2)
    with np.load(io.BytesIO(client.get(f"/v1/sessions/{sid}/trajectory?frames=4").content), allow_pickle=False) as z:
        assert "body_center" not in z.files and z["positions"].shape[0] == 4
    with np.load(io.BytesIO(client.get(f"/v1/sessions/{sid}/trajectory?frames=2").content), allow_pickle=False) as z:
        assert z["body_center"].shape == (2, len(sim.bodies) + 1, 2)
    names = zipfile.ZipFile(io.BytesIO(client.get(f"/v1/sessions/{sid}/trajectory?frames=4&format=mesh").content)).namelist()
    assert not [n for n in names if n.startswith("body_")] and [n for n in names if n.startswith("water_")]
