"""A poured session is durable and its checkpoints are its states: a session
poured into and saved comes back after a SIGKILL with its poured particles
and steps on bit for bit; a checkpoint taken before a pour brings the session
back to that state (the scene's particles alone) and one taken after it brings
the block back; a checkpoint that is not this scene's particles plus blocks is
a 422 naming ``checkpoint`` and leaves the session as it was."""

from __future__ import annotations

import json
import struct
import time

import numpy as np
import pytest

pytest.importorskip("fastapi")
httpx = pytest.importorskip("httpx")

from fastapi.testclient import TestClient  # noqa: E402

from hybridmpm.conventions import GNS_ELASTIC, GNS_WATER  # noqa: E402
from hybridmpm.errors import InvalidInputError  # noqa: E402
from hybridmpm.service import ServiceConfig, create_app  # noqa: E402
from hybridmpm.service import checkpoint as ckpt  # noqa: E402
from hybridmpm.service.store import parse_record, rebuild, record_state  # noqa: E402
from hybridmpm.service.testing import LiveServer, get_checkpoint, new_session, step_binary, wait_saved  # noqa: E402
from hybridmpm.sim import make_simulator, rollout  # noqa: E402
from hybridmpm.sim import pour as pour_module  # noqa: E402
from hybridmpm.sim.pour import pour_block  # noqa: E402

JELLY = {"material": "jello", "lo": [0.6, 0.6], "hi": [0.7, 0.7]}
#: The jelly's lattice: 0.1 m / (dx/2 = 1/256 m) -> 26 particles a side.
JELLY_N = 26 * 26
WAIT_S = 60.0


def _reference(first: int, then: int, after: int):
    """Positions of the ``after`` steps that follow ``first`` frames, the jelly poured, ``then`` frames: one process, never stopped."""
    sim = make_simulator("dam_break2d", "mpm", seed=0, threads=1)
    rollout(sim, first)
    pour_block(sim, JELLY)
    rollout(sim, then)
    return rollout(sim, after).positions[1:]


def _meta(sim):
    return {"scene": "dam_break2d", "seed": 0, "solver": "mpm", "r_c": 0.0, "last_used_at": time.time(), "client": ""}


def test_a_record_of_a_poured_session_rebuilds_with_its_block():
    sim = make_simulator("dam_break2d", "mpm", seed=0, threads=1)
    n0 = sim.solver.num_particles
    rollout(sim, 3)
    pour_block(sim, JELLY)
    rollout(sim, 3)
    rec = parse_record("0" * 64, ckpt.dumps(record_state(sim), _meta(sim)), 1 << 28)
    back, initial = rebuild(rec, threads=2)  # another thread count: the engine's bits are the same
    assert back.solver.num_particles == n0 + JELLY_N and back.poured_particles == JELLY_N
    assert np.count_nonzero(back.particles.particle_type == GNS_ELASTIC) == JELLY_N
    assert np.array_equal(rollout(back, 6).positions, rollout(sim, 6).positions)
    # its reset state is the scene's own
    back.restore(initial)
    assert back.solver.num_particles == n0 and back.poured_particles == 0


def test_a_poured_session_comes_back_after_a_restart(tmp_path):
    store = tmp_path / "store"
    args = ["--store", str(store), "--save-every", "0.2", "--log-level", "info"]
    server = LiveServer(args=args, log=tmp_path / "first.log").start()
    try:
        with httpx.Client(base_url=server.url, timeout=WAIT_S) as c:
            r = c.post("/v1/sessions", json={"scene": "dam_break2d", "solver": "mpm", "seed": 0})
            assert r.status_code == 201, r.text
            sid, n0 = r.json()["id"], r.json()["num_particles"]
            step_binary(c, sid, 3)
            r = c.post(f"/v1/sessions/{sid}/blocks", json=JELLY)
            assert r.status_code == 201, r.text
            assert r.json()["added"] == JELLY_N
            step_binary(c, sid, 3)
            saved = wait_saved(c, sid, WAIT_S)
    finally:
        server.proc.kill()  # SIGKILL: no shutdown, no final save
        server.proc.wait(WAIT_S)
        server.stop()
    with LiveServer(args=args, log=tmp_path / "second.log") as server, httpx.Client(base_url=server.url, timeout=WAIT_S) as c:
        info = c.get(f"/v1/sessions/{sid}").json()
        assert info["frame"] == saved == 6 and info["restored_from_frame"] == 6
        assert info["num_particles"] == n0 + JELLY_N
        types = np.array(info["particle_type"])
        assert np.count_nonzero(types == GNS_ELASTIC) == JELLY_N and np.count_nonzero(types == GNS_WATER) == n0
        assert np.array_equal(step_binary(c, sid, 8), _reference(3, 3, 8)), "the restored poured session steps on differently"


@pytest.fixture(scope="module")
def client():
    with TestClient(create_app(ServiceConfig(max_sessions=50, max_sessions_per_client=50, idle_ttl_s=600))) as c:
        yield c


def _step(client, sid, frames):
    r = client.post(f"/v1/sessions/{sid}/step", json={"frames": frames})
    assert r.status_code == 200, r.text
    return np.asarray(r.json()["frames"][-1]["positions"])


def _put(client, sid, data):
    return client.put(f"/v1/sessions/{sid}/checkpoint", content=data, headers={"content-type": "application/octet-stream"})


def test_checkpoints_before_and_after_a_pour_restore_their_own_particles(client):
    s = new_session(client)
    sid, n0 = s["id"], s["num_particles"]
    _step(client, sid, 3)
    before = get_checkpoint(client, sid)
    assert client.post(f"/v1/sessions/{sid}/blocks", json=JELLY).status_code == 201
    _step(client, sid, 3)
    after = get_checkpoint(client, sid)
    with client.websocket_connect(f"/v1/sessions/{sid}/stream") as ws:
        assert json.loads(ws.receive_text())["type"] == "meta"
        r = _put(client, sid, before)
        assert r.status_code == 200, r.text
        assert r.json()["num_particles"] == n0 and r.json()["frame"] == 3 and set(r.json()["particle_type"]) == {GNS_WATER}
        event = None
        while event is None:
            m = ws.receive()
            if m.get("text") and json.loads(m["text"]).get("type") == "particles":
                event = json.loads(m["text"])
        assert event["num_particles"] == n0 and event["particle_type"].count(GNS_ELASTIC) == 0
    # the session is the unpoured run again: the same positions as a session never poured into
    other = new_session(client)["id"]
    _step(client, other, 3)
    assert np.array_equal(_step(client, sid, 5), _step(client, other, 5))
    # the checkpoint after the pour brings the block back, and the run on from it
    r = _put(client, sid, after)
    assert r.status_code == 200, r.text
    assert r.json()["num_particles"] == n0 + JELLY_N and r.json()["particle_type"].count(GNS_ELASTIC) == JELLY_N
    assert np.allclose(_step(client, sid, 4), _reference(3, 3, 4)[-1], rtol=0, atol=1e-6), "the restored poured run differs"


def _with_header(data: bytes, **changes) -> bytes:
    """``data`` (a checkpoint) with its solver's parameter header changed."""
    state, meta = ckpt.loads(data, 1 << 28)
    blob = state["solver"]
    (n,) = struct.unpack("<Q", blob[8:16])
    head = {**json.loads(blob[16 : 16 + n]), **changes}
    header = json.dumps(head).encode()
    state["solver"] = blob[:8] + struct.pack("<Q", len(header)) + header + blob[16 + n :]
    return ckpt.dumps(state, meta)


def _with_state(data: bytes, **changes) -> bytes:
    """``data`` (a checkpoint) with keys of its simulator's state changed."""
    state, meta = ckpt.loads(data, 1 << 28)
    return ckpt.dumps({**state, **changes}, meta)


def test_a_checkpoint_that_is_not_this_scene_plus_blocks_is_refused(client, monkeypatch):
    s = new_session(client)
    sid, n0 = s["id"], s["num_particles"]
    assert client.post(f"/v1/sessions/{sid}/blocks", json=JELLY).status_code == 201
    poured = get_checkpoint(client, sid)
    _step(client, sid, 2)
    now = get_checkpoint(client, sid)
    state, _ = ckpt.loads(poured, 1 << 28)
    gravity = json.loads(state["solver"][16 : 16 + struct.unpack("<Q", state["solver"][8:16])[0]])["gravity"]
    bad = {
        "other physics": _with_header(poured, gravity=[g * 2 for g in gravity]),
        "other parameter sets": _with_header(poured, sets=[]),
        "a record of the block one particle short": _with_state(poured, poured=[JELLY_N - 1]),
        "no record of the block": _with_state(poured, poured=[]),
        "a record that is not a list": _with_state(poured, poured={"0": JELLY_N}),
    }
    for why, data in bad.items():
        r = _put(client, sid, data)
        assert r.status_code == 422, (why, r.text[:300])
        assert r.json()["detail"][0]["loc"][-1] == "checkpoint", (why, r.text[:300])
        assert get_checkpoint(client, sid) == now, f"{why}: the session changed"
    # more particles than a session may hold with poured blocks (into a session of the scene's particles)
    fresh = new_session(client)["id"]
    mine = get_checkpoint(client, fresh)
    monkeypatch.setattr(pour_module, "MAX_POURED_TOTAL", n0 + JELLY_N - 1)
    r = _put(client, fresh, poured)
    assert r.status_code == 422 and r.json()["detail"][0]["loc"][-1] == "checkpoint" and str(n0 + JELLY_N) in r.text, r.text[:300]
    assert get_checkpoint(client, fresh) == mine
    # the simulator's own refusal: the scene's particles must come first
    sim = make_simulator("dam_break2d", "mpm", seed=0, threads=1)
    other = make_simulator("water2d", "mpm", seed=0, threads=1)
    with pytest.raises(InvalidInputError, match="fewer than the 4608"):
        sim.restore(other.state())
