"""Hostile and careless clients against the service (test client, in process):
a refused checkpoint leaves the session exactly as it was, deep or huge
inputs answer 4xx (never 500), loose types are refused, error messages stay
short and carry no object reprs, forged Host headers are refused, the
per-client session quota and the process memory budget hold, and the smaller
protocol details (binary WebSocket messages, OPTIONS) answer properly.

The live-server parts (latency of /healthz under heavy JSON steps, PNG
memory, access logs, header timeout, a control whose client leaves) are in
``tests/test_service_hostile_live.py``."""

from __future__ import annotations

import io
import json
import math
import struct
import time

import numpy as np
import pytest

pytest.importorskip("fastapi")
pytest.importorskip("httpx")

from fastapi.testclient import TestClient  # noqa: E402
from starlette.websockets import WebSocketDisconnect  # noqa: E402

from hybridmpm.service import ServiceConfig, create_app  # noqa: E402
from hybridmpm.service import checkpoint as ckpt  # noqa: E402

OCTET = {"Accept": "application/octet-stream"}
HOST = ("testserver",)
# the Rust solver's checkpoint: magic, u32 D, u64 N, f64 time, u64 frame, then fixed-size records
CORE_HEADER = 36


@pytest.fixture(scope="module")
def client():
    app = create_app(ServiceConfig(max_sessions=60, max_sessions_per_client=60, allowed_hosts=HOST))
    with TestClient(app) as c:
        yield c


def new(client, scene="dam_break2d", solver="hybrid", seed=0):
    r = client.post("/v1/sessions", json={"scene": scene, "solver": solver, "seed": seed})
    assert r.status_code == 201, r.text
    return r.json()["id"]


def snapshot(client, sid):
    r = client.get(f"/v1/sessions/{sid}/checkpoint")
    assert r.status_code == 200, r.text
    return ckpt.loads(r.content, 1 << 30)


def same(a, b, path="state"):
    """Exact equality of two state trees (arrays bytewise, NaN equal to NaN)."""
    assert type(a) is type(b), (path, type(a), type(b))
    if isinstance(a, dict):
        assert a.keys() == b.keys(), path
        for k in a:
            same(a[k], b[k], f"{path}.{k}")
    elif isinstance(a, list):
        assert len(a) == len(b), path
        for i, (x, y) in enumerate(zip(a, b)):
            same(x, y, f"{path}[{i}]")
    elif isinstance(a, np.ndarray):
        assert a.dtype == b.dtype and a.shape == b.shape and a.tobytes() == b.tobytes(), path
    elif isinstance(a, float) and math.isnan(a):
        assert math.isnan(b), path
    else:
        assert a == b, (path, a, b)


def split_blob(blob):
    """An MpmSolver checkpoint → (parameter header, core header, records [N, per] uint8)."""
    (n_head,) = struct.unpack("<Q", blob[8:16])
    head, core = blob[: 16 + n_head], blob[16 + n_head :]
    d = struct.unpack("<I", core[8:12])[0]
    (n,) = struct.unpack("<Q", core[12:20])
    records = np.frombuffer(core[CORE_HEADER:], np.uint8).reshape(n, -1)
    assert records.shape[1] == 4 * (3 * d + 3 * d * d + 4) + 3  # f32 fields, material (u8), parameter set (u16)
    return head, core[:CORE_HEADER], records


def join_blob(head, core_head, records):
    core_head = core_head[:12] + struct.pack("<Q", len(records)) + core_head[20:]
    return head + core_head + records.tobytes()


def mpm_blob_of(state):
    return state["mpm"]["solver"] if state["kind"] == "hybrid" else state["solver"]


def with_mpm_blob(state, blob):
    out = json.loads(json.dumps({}))  # a fresh dict
    out.update(state)
    if state["kind"] == "hybrid":
        out["mpm"] = {**state["mpm"], "solver": blob}
    else:
        out["solver"] = blob
    return out


def ten_particles(state, _):
    head, ch, rec = split_blob(mpm_blob_of(state))
    return with_mpm_blob(state, join_blob(head, ch, rec[:10]))


def twice_the_particles(state, _):
    head, ch, rec = split_blob(mpm_blob_of(state))
    return with_mpm_blob(state, join_blob(head, ch, np.concatenate([rec, rec])))


def other_scenes_particles(state, client):
    """water2d's particles (same solver parameters as dam_break2d) in place of the session's."""
    other = new(client, "water2d", "mpm", seed=1)
    foreign, _ = snapshot(client, other)
    client.delete(f"/v1/sessions/{other}")
    return with_mpm_blob(state, foreign["solver"])


def nan_buffer(state, _):
    buf = state["buffer"].copy()
    buf[-1, 0, 0] = np.nan
    return {**state, "buffer": buf}


def nan_frame_positions(state, _):
    if state["kind"] == "hybrid":
        return {**state, "neural": nan_frame_positions(state["neural"], None)}
    fp = state["frame_positions"].copy()
    fp[3, 1] = np.nan
    return {**state, "frame_positions": fp}


def huge_step_index(state, _):
    return {**state, "step_index": 10**30}


def huge_inner_step_index(state, _):
    return {**state, "mpm": {**state["mpm"], "step_index": 10**30}}


def huge_counter(state, _):
    return {**state, "calm": 10**30}


def string_counter(state, _):
    return {**state, "strikes": "3"}


def float_step_index(state, _):
    return {**state, "step_index": 8.5}


def nan_score(state, _):
    return {**state, "last_score": "nan"}


CASES = [
    ("hybrid", ten_particles),
    ("hybrid", twice_the_particles),
    ("mpm", ten_particles),
    ("mpm", twice_the_particles),
    ("mpm", other_scenes_particles),
    ("hybrid", other_scenes_particles),
    ("hybrid", nan_buffer),
    ("hybrid", nan_frame_positions),
    ("neural", nan_frame_positions),
    ("hybrid", huge_step_index),
    ("mpm", huge_step_index),
    ("neural", huge_step_index),
    ("hybrid", huge_inner_step_index),
    ("hybrid", huge_counter),
    ("hybrid", string_counter),
    ("mpm", float_step_index),
    ("hybrid", nan_score),
]


@pytest.mark.parametrize("solver,mutate", CASES, ids=[f"{s}-{m.__name__}" for s, m in CASES])
def test_refused_checkpoint_leaves_the_session_unchanged(client, solver, mutate):
    sid = new(client, solver=solver)
    assert client.post(f"/v1/sessions/{sid}/step", json={"frames": 8}).status_code == 200
    state, meta = snapshot(client, sid)
    bad = mutate(state, client)
    r = client.put(f"/v1/sessions/{sid}/checkpoint", content=ckpt.dumps(bad, meta))
    assert r.status_code == 422, r.text
    assert r.json()["detail"][0]["loc"] == ["body", "checkpoint"]
    after, meta_after = snapshot(client, sid)
    same(state, after)
    assert meta_after == meta
    # and the session goes on as if nothing had happened: the same frames as a twin restored from the good state
    twin = new(client, solver=solver)
    assert client.put(f"/v1/sessions/{twin}/checkpoint", content=ckpt.dumps(state, meta)).status_code == 200
    a = client.post(f"/v1/sessions/{sid}/step", json={"frames": 6}, headers=OCTET)
    b = client.post(f"/v1/sessions/{twin}/step", json={"frames": 6}, headers=OCTET)
    assert a.status_code == b.status_code == 200, a.text
    assert a.content == b.content and a.headers["x-solvers"] == b.headers["x-solvers"]
    for s in (sid, twin):
        client.delete(f"/v1/sessions/{s}")


def raw_checkpoint(tree_json: bytes, **arrays) -> bytes:
    buf = io.BytesIO()
    np.savez(buf, __tree__=np.frombuffer(tree_json, np.uint8), **arrays)
    return buf.getvalue()


META = b'{"scene": "dam_break2d", "seed": 0, "solver": "mpm", "r_c": 0.1}'


@pytest.mark.parametrize(
    "tree",
    [
        b'{"format": "hybridmpm-checkpoint", "version": 1, "meta": ' + META + b', "state": ' + b"[" * 100_000 + b"]" * 100_000 + b"}",
        b'{"format": "hybridmpm-checkpoint", "version": 1, "meta": ' + META + b', "state": ' + b'{"a":' * 50_000 + b"1" + b"}" * 50_000 + b"}",
        b'{"format": "hybridmpm-checkpoint", "version": 1, "meta": {"scene": ' + b"[" * 900 + b"]" * 900 + b'}, "state": {}}',
        b'{"format": "hybridmpm-checkpoint", "version": 1, "meta": {"scene": "]]]]]]]]]]]]]]", "x": ' + b"[" * 5000 + b"]" * 5000 + b'}, "state": {}}',
        b'{"format": "hybridmpm-checkpoint", "version": 1, "meta": {"scene": "' + b"A" * (8 << 20) + b'"}, "state": {}}',
    ],
    ids=["deep-state-lists", "deep-state-objects", "deep-meta", "brackets-in-strings", "huge-meta-string"],
)
def test_deep_or_huge_checkpoint_trees_are_422_with_a_short_message(client, tree):
    sid = new(client, solver="mpm")
    before = snapshot(client, sid)
    r = client.put(f"/v1/sessions/{sid}/checkpoint", content=raw_checkpoint(tree))
    assert r.status_code == 422, r.text[:300]
    assert r.json()["detail"][0]["loc"] == ["body", "checkpoint"]
    assert len(r.content) < 2000
    same(before[0], snapshot(client, sid)[0])
    # the connection stays usable (a 500 closed it under the client)
    assert client.get(f"/v1/sessions/{sid}").status_code == 200


def test_error_messages_are_short_and_carry_no_object_repr(client):
    sid = new(client, solver="mpm")
    state, meta = snapshot(client, sid)
    cases = [
        raw_checkpoint(b"{}", a0=np.zeros(3)).replace(b"__tree__.npy", b"__tree__.np_"),  # a member that is no array
        b"PK\x03\x04" + b"\x00" * 100,
        raw_checkpoint(b"\x00\xff not json"),
        ckpt.dumps(state, {**meta, "scene": "x" * 100_000}),
        ckpt.dumps({**state, "stats": {"steps": "x" * 100_000}}, meta),
        ckpt.dumps({**state, "step_index": "x" * 100_000}, meta),
        ckpt.dumps({**state, "forcing": np.zeros((5, 7))}, meta),
    ]
    for body in cases:
        r = client.put(f"/v1/sessions/{sid}/checkpoint", content=body)
        assert r.status_code == 422, r.text[:300]
        msg = r.json()["detail"][0]["msg"]
        assert " at 0x" not in msg and "object at" not in msg, msg
        assert len(msg) <= 600, len(msg)


@pytest.mark.parametrize(
    "route,body,field",
    [
        ("/v1/sessions", {"scene": "water2d", "seed": True}, "seed"),
        ("/v1/sessions", {"scene": "water2d", "seed": 1.0}, "seed"),
        ("/v1/sessions", {"scene": "water2d", "seed": "3"}, "seed"),
        ("/v1/sessions", {"scene": "water2d", "r_c": False}, "r_c"),
        ("/v1/sessions", {"scene": "water2d", "r_c": "0.1"}, "r_c"),
        ("step", {"frames": "10"}, "frames"),
        ("step", {"frames": True}, "frames"),
        ("step", {"frames": 10.0}, "frames"),
        ("controls", {"sketch": {"kind": "arrow", "points": [[0.2, 0.3], [0.5, 0.3]]}, "frames": "10"}, "frames"),
        ("controls", {"sketch": {"kind": "arrow", "points": [[0.2, 0.3], [0.5, "0.3"]]}}, "1"),
        ("controls", {"sketch": {"kind": "arrow", "points": [[0.2, 0.3], [0.5, True]]}}, "1"),
    ],
)
def test_loose_types_are_refused(client, route, body, field):
    if route != "/v1/sessions":
        route = f"/v1/sessions/{new(client, solver='mpm')}/{route}"
    r = client.post(route, json=body)
    assert r.status_code == 422, r.text
    assert r.json()["detail"][0]["loc"][-1] == field


def test_whole_numbers_still_pass_as_floats(client):
    r = client.post("/v1/sessions", json={"scene": "water2d", "solver": "mpm", "r_c": 0})
    assert r.status_code == 201, r.text
    assert r.json()["r_c"] == 0.0


def test_forged_host_is_refused():
    # by default, a connection to a loopback address serves the loopback names only
    with TestClient(create_app(ServiceConfig(max_sessions=4)), base_url="http://127.0.0.1:8000") as c:
        assert c.get("/healthz").status_code == 200
        assert c.get("/healthz", headers={"Host": "localhost:8000"}).status_code == 200
        assert c.get("/healthz", headers={"Host": "[::1]:8000"}).status_code == 200
        r = c.get("/healthz", headers={"Host": "evil.example"})
        assert r.status_code == 400
        assert c.post("/v1/sessions", json={"scene": "water2d", "solver": "mpm"}, headers={"Host": "evil.example:8000"}).status_code == 400
    # DNS rebinding: the attacker's page, with its own origin and host, reaches the stream no more
    # (the test client's WebSockets always connect to "testserver": the hosts are given)
    with TestClient(create_app(ServiceConfig(max_sessions=4, allowed_hosts=("localhost", "127.0.0.1")))) as c:
        sid = c.post("/v1/sessions", json={"scene": "water2d", "solver": "mpm"}, headers={"Host": "localhost"}).json()["id"]
        with pytest.raises(WebSocketDisconnect):
            with c.websocket_connect(f"/v1/sessions/{sid}/stream", headers={"Host": "evil.example", "Origin": "http://evil.example"}) as ws:
                ws.receive_json()
        with c.websocket_connect(f"/v1/sessions/{sid}/stream", headers={"Host": "localhost", "Origin": "http://localhost"}) as ws:
            assert ws.receive_json()["type"] == "meta"


def test_per_client_session_quota():
    app = create_app(ServiceConfig(max_sessions=10, max_sessions_per_client=2, allowed_hosts=HOST))
    with TestClient(app) as c:
        ids = [c.post("/v1/sessions", json={"scene": "water2d", "solver": "mpm"}) for _ in range(3)]
        assert [r.status_code for r in ids] == [201, 201, 429]
        assert int(ids[2].headers["retry-after"]) > 0 and "per client" in ids[2].text
        assert c.delete(f"/v1/sessions/{ids[0].json()['id']}").status_code == 204
        assert c.post("/v1/sessions", json={"scene": "water2d", "solver": "mpm"}).status_code == 201


def test_memory_budget_refuses_with_503_and_counts_kept_controls():
    # one water2d session (about 4 MiB with its overhead) fits; a 1000-frame control (3 copies of 3 MiB of trajectory) does not
    app = create_app(ServiceConfig(max_sessions=10, memory_budget="12M", allowed_hosts=HOST))
    with TestClient(app) as c:
        r = c.post("/v1/sessions", json={"scene": "water2d", "solver": "mpm"})
        assert r.status_code == 201, r.text
        sid = r.json()["id"]
        h = c.get("/healthz").json()
        assert 0 < h["memory_used"] <= h["memory_budget"] == 12 << 20
        body = {"sketch": {"kind": "arrow", "points": [[0.2, 0.3], [0.5, 0.3]]}, "frames": 1000}
        before = snapshot(c, sid)
        r = c.post(f"/v1/sessions/{sid}/controls", json=body)
        assert r.status_code == 503 and int(r.headers["retry-after"]) > 0, r.text
        same(before[0], snapshot(c, sid)[0])
        # a short control fits and is kept; its trajectory counts until it is dropped with the session
        r = c.post(f"/v1/sessions/{sid}/controls", json={**body, "frames": 20})
        assert r.status_code == 200, r.text
        used = c.get("/healthz").json()["memory_used"]
        assert used > h["memory_used"]
        # sessions are refused once the budget is spent
        more = [c.post("/v1/sessions", json={"scene": "dam_break2d", "solver": "mpm"}) for _ in range(4)]
        assert [r.status_code for r in more][-1] == 503 and "memory budget" in more[-1].text
        h2 = c.get("/healthz").json()
        assert h2["memory_used"] <= h2["memory_budget"]
        # everything given back once the sessions are gone
        for sid_ in [sid] + [r.json()["id"] for r in more if r.status_code == 201]:
            assert c.delete(f"/v1/sessions/{sid_}").status_code == 204
        assert c.get("/healthz").json()["memory_used"] == 0


def test_a_large_png_sketch_is_read_at_reduced_size(client):
    """A 2048² canvas export of a thin arrow (read as its ink, max-pooled to
    512²) gives the arrow, pointing the right way."""
    from PIL import Image

    from hybridmpm.control import Sketch, render_sketch

    img = 255 - render_sketch(Sketch.arrow([0.2, 0.4], [0.7, 0.4], width=0.004), size=1024).max(-1)  # dark ink on white
    big = Image.fromarray(img).resize((2048, 2048), Image.NEAREST)
    buf = io.BytesIO()
    big.save(buf, format="PNG")
    sid = new(client, "water2d", "mpm")
    r = client.post(f"/v1/sessions/{sid}/controls/png?method=constant&frames=4", content=buf.getvalue(), headers={"Content-Type": "image/png"})
    assert r.status_code == 200, r.text
    pts = np.array(r.json()["sketch"]["points"])
    assert r.json()["sketch"]["kind"] == "arrow"
    np.testing.assert_allclose(pts[0], [0.2, 0.4], atol=0.02)
    np.testing.assert_allclose(pts[-1], [0.7, 0.4], atol=0.02)


def test_options_answers_405_with_allow(client):
    r = client.options("/v1/sessions")
    assert r.status_code == 405 and set(r.headers["allow"].replace(" ", "").split(",")) == {"POST"}
    sid = new(client, solver="mpm")
    r = client.options(f"/v1/sessions/{sid}/checkpoint")
    assert r.status_code == 405 and set(r.headers["allow"].replace(" ", "").split(",")) == {"GET", "PUT"}


def test_schema_states_192_bit_ids(client):
    schema = client.get("/openapi.json").json()
    desc = schema["components"]["schemas"]["SessionInfo"]["properties"]["id"]["description"]
    assert "192 bits" in desc and "128" not in desc


def test_the_ledger_returns_to_its_start_after_every_way_a_session_ends():
    """The memory budget is one ledger: whatever a session took — its state, its recording, a kept control, a
    download — comes back when it ends, by DELETE or by expiry, and a refused request takes nothing."""
    app = create_app(ServiceConfig(allowed_hosts=HOST, idle_ttl_s=1.0, reap_interval_s=0.2))
    arrow = {"kind": "arrow", "points": [[0.2, 0.3], [0.5, 0.3]]}
    with TestClient(app) as c:
        base = c.get("/healthz").json()["memory_used"]

        def used_every_way() -> str:
            sid = new(c, scene="water2d", solver="mpm")
            assert c.post(f"/v1/sessions/{sid}/step", json={"frames": 30}).status_code == 200
            r = c.post(f"/v1/sessions/{sid}/controls", json={"sketch": arrow, "frames": 40})
            assert r.status_code == 200, r.text
            assert c.get(r.json()["trajectory"], headers=OCTET).status_code == 200
            assert c.get(f"/v1/sessions/{sid}/trajectory", params={"frames": 10}).status_code == 200
            before = c.get("/healthz").json()["memory_used"]
            assert c.put(f"/v1/sessions/{sid}/checkpoint", content=b"not a checkpoint").status_code == 422
            assert c.get("/healthz").json()["memory_used"] == before  # refused: nothing taken
            assert before > base
            return sid

        sid = used_every_way()
        assert c.delete(f"/v1/sessions/{sid}").status_code == 204
        assert c.get("/healthz").json()["memory_used"] == base
        used_every_way()  # left to expire
        deadline = time.monotonic() + 30
        while c.get("/healthz").json()["sessions"] and time.monotonic() < deadline:
            time.sleep(0.2)
        h = c.get("/healthz").json()
        assert h["sessions"] == 0 and h["memory_used"] == base, h
