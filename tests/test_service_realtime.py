"""Real-time sessions over HTTP (``POST /v1/sessions`` with ``realtime``, ``serve --realtime``): a real-time
session runs the ``realtime`` solver and says what it does in its info, its stream's frames carry flag bit4
and the real-time factor at offset 26 (a plain session's bytes are as before), a change of rung is a
``realtime`` event, its checkpoint and its store record bring the rung back (bitwise), the refused
combinations answer 422 naming ``realtime``, and the server's default applies to sessions that leave the
field out. The rung changes are forced with a fake clock on the session's simulator (its ``clock`` hook):
nothing here asserts a speed."""

from __future__ import annotations

import argparse
import itertools
import json
import struct
import time

import numpy as np
import pytest

pytest.importorskip("fastapi")
pytest.importorskip("httpx")

from fastapi.testclient import TestClient  # noqa: E402

from hybridmpm.cli.serve import add_parsers  # noqa: E402
from hybridmpm.errors import InvalidInputError  # noqa: E402
from hybridmpm.scenes import DOMAINS  # noqa: E402
from hybridmpm.service import ServiceConfig, create_app, decode_frame  # noqa: E402
from hybridmpm.service import checkpoint as ckpt  # noqa: E402
from hybridmpm.service import core as core_module  # noqa: E402
from hybridmpm.service.core import PLAY_LAG_S, PLAY_TICK_S, REALTIME_LAG_S, Pacer  # noqa: E402
from hybridmpm.service.frames import FLAG_REALTIME, FLAGS_KNOWN, encode_frame, realtime_code  # noqa: E402
from hybridmpm.service.testing import step_binary  # noqa: E402
from hybridmpm.sim import SOLVERS, make_simulator, rollout  # noqa: E402
from hybridmpm.sim.realtime import MIN_SAMPLES, WARMUP_FRAMES  # noqa: E402

#: Frames after which a real-time session whose frames all run late moves down its ladder (its fake clock
#: makes each frame take a second): the untimed warm-up, then the samples a change needs.
FORCED_CHANGE_FRAMES = WARMUP_FRAMES + MIN_SAMPLES + 1
#: Fewer frames than any change of rung needs (a frame's timing never moves a session within them).
FEW_FRAMES = WARMUP_FRAMES + 3


@pytest.fixture(scope="module")
def client():
    with TestClient(create_app(ServiceConfig(max_sessions=50, max_sessions_per_client=50, idle_ttl_s=600))) as c:
        yield c


def new(client, scene="water2d", **kw):
    r = client.post("/v1/sessions", json={"scene": scene, "seed": 0, **kw})
    assert r.status_code == 201, r.text
    return r.json()


def field_of(r):
    assert r.status_code == 422, (r.status_code, r.text)
    return r.json()["detail"][0]["loc"][-1]


def late_clock(client, sid):
    """Every frame of session ``sid`` runs a second late from now on (its simulator's wall clock, the one it
    times its frames with, moves a second a reading): its next timed frames ask to move down the ladder."""
    sim = client.app.state.manager.sessions[sid].core.sim
    ticks = itertools.count(time.perf_counter(), 1.0)
    sim._clock = lambda: next(ticks)


def events_until(ws, kind, most=500):
    """The stream's JSON messages up to the first of ``type`` ``kind`` (binary frames skipped); that one last."""
    seen = []
    for _ in range(most):
        m = ws.receive()
        if m.get("text"):
            seen.append(json.loads(m["text"]))
            if seen[-1]["type"] == kind:
                return seen
    raise AssertionError(f"no {kind} event in {most} messages: {seen}")


def first_frame(client, sid):
    """The raw binary frame a new viewer of ``sid`` gets first, and its ``meta`` message."""
    with client.websocket_connect(f"/v1/sessions/{sid}/stream") as ws:
        meta = ws.receive_json()
        return ws.receive_bytes(), meta


def test_a_realtime_session_runs_the_realtime_solver_and_says_so(client):
    s = new(client, realtime=True)
    rt = s["realtime"]
    assert s["solver"] == "realtime" and rt["rung"] in rt["ladder"] and rt["rung"] == rt["ladder"][0]
    assert rt["label"].startswith("MPM ") and rt["changes"] == 0 and rt["frame_ms"] is None and rt["realtime_factor"] is None
    assert rt["budget_ms"] > 0 and len(rt["ladder"]) >= 2
    assert set(rt) >= {"rung", "label", "frame_ms", "budget_ms", "realtime_factor", "changes", "ladder"}
    assert client.get(f"/v1/sessions/{s['id']}").json()["realtime"] == rt
    assert new(client, solver="realtime")["solver"] == "realtime"  # the solver named directly
    plain = new(client, solver="mpm")
    assert plain["solver"] == "mpm" and plain["realtime"] is None
    assert new(client)["realtime"] is None  # the default solver, without --realtime


def test_the_solver_lists_offer_realtime(client):
    h = client.get("/healthz").json()
    assert h["solvers"] == list(SOLVERS) and "realtime" in h["solvers"] and h["realtime_default"] is False
    scenes = client.get("/v1/scenes").json()
    assert {s["name"] for s in scenes} == set(DOMAINS)
    for s in scenes:  # every scene runs MPM, so every one takes real-time mode
        assert s["solvers"][0] == "default" and "mpm" in s["solvers"] and "realtime" in s["solvers"], s
    prop = client.get("/openapi.json").json()["components"]["schemas"]["CreateSession"]["properties"]
    assert prop["solver"]["enum"] == list(SOLVERS)


def test_a_realtime_sessions_frames_carry_the_flag_and_its_factor(client):
    s = new(client, realtime=True)
    sid = s["id"]
    data, meta = first_frame(client, sid)
    h, _ = decode_frame(data)
    assert data[7] & FLAG_REALTIME and h.realtime and h.realtime_factor is None  # not measured yet: 0 at offset 26
    assert data[26:28] == b"\0\0" and meta["realtime"]["realtime_factor"] is None
    pos = step_binary(client, sid, FEW_FRAMES)
    assert pos.shape == (FEW_FRAMES, s["num_particles"], 2) and np.isfinite(pos).all()
    data, meta = first_frame(client, sid)
    h, pos = decode_frame(data)
    factor = meta["realtime"]["realtime_factor"]
    assert h.frame == FEW_FRAMES and h.realtime and h.solver == "mpm"
    assert factor is not None and factor >= 0 and h.realtime_factor is not None and h.realtime_factor > 0
    (code,) = struct.unpack_from("<H", data, 26)
    assert code == realtime_code(factor) and 1 <= code <= 0xFFFF and h.realtime_factor == code / 1000
    info = client.get(f"/v1/sessions/{sid}").json()["realtime"]
    assert info["frame_ms"] is not None and info["frame_ms"] > 0 and info["changes"] == 0


def test_a_playing_realtime_session_streams_flagged_frames(client):
    sid = new(client, realtime=True)["id"]
    with client.websocket_connect(f"/v1/sessions/{sid}/stream") as ws:
        ws.receive_json()
        assert decode_frame(ws.receive_bytes())[0].realtime
        ws.send_json({"type": "play"})
        heads = []
        while len(heads) < 3:
            m = ws.receive()
            if m.get("bytes"):
                heads.append(decode_frame(m["bytes"])[0])
        ws.send_json({"type": "pause"})
    assert all(h.realtime for h in heads) and all(b.frame > a.frame for a, b in zip(heads, heads[1:]))


def test_a_plain_sessions_header_is_as_before(client):
    for body in ({"solver": "mpm"}, {"solver": "default"}, {"solver": "default", "realtime": False}):
        s = new(client, **body)
        step_binary(client, s["id"], 2)
        data, meta = first_frame(client, s["id"])
        h, _ = decode_frame(data)
        assert not data[7] & FLAG_REALTIME and data[26:28] == b"\0\0", body
        assert not h.realtime and h.realtime_factor is None and meta["realtime"] is None and s["realtime"] is None


def test_the_header_bytes():
    pos = np.zeros((3, 2), np.float32)
    plain = encode_frame(pos, 5, 0.0125, "mpm")
    assert encode_frame(pos, 5, 0.0125, "mpm", realtime_factor=2.5) == plain  # a factor without the flag: nothing
    for factor, code in ((None, 0), (0.0, 1), (0.0004, 1), (1.0, 1000), (2.3456, 2346), (1e9, 0xFFFF)):
        data = encode_frame(pos, 5, 0.0125, "mpm", realtime=True, realtime_factor=factor)
        assert data[7] == FLAG_REALTIME and struct.unpack_from("<H", data, 26) == (code,), factor
        assert data[:7] == plain[:7] and data[8:26] == plain[8:26] and data[28:] == plain[28:]  # nothing else moves
        h, _ = decode_frame(data)
        assert h.realtime and h.realtime_factor == (None if code == 0 else code / 1000)
    assert FLAGS_KNOWN & FLAG_REALTIME and FLAG_REALTIME == 16


def test_a_change_of_rung_is_an_event(client):
    s = new(client, scene="dam_break2d", realtime=True)
    sid, start = s["id"], s["realtime"]["rung"]
    late_clock(client, sid)
    with client.websocket_connect(f"/v1/sessions/{sid}/stream") as ws:
        ws.receive_json()
        step_binary(client, sid, FORCED_CHANGE_FRAMES)
        msg = events_until(ws, "realtime")[-1]
    info = client.get(f"/v1/sessions/{sid}").json()
    assert msg["rung"] != start and msg["rung"] in msg["ladder"] and msg["changes"] == 1
    assert info["realtime"]["rung"] == msg["rung"] and info["realtime"]["changes"] == 1 and info["frame"] == FORCED_CHANGE_FRAMES
    assert {k: msg[k] for k in ("rung", "label", "budget_ms", "ladder")} == {k: info["realtime"][k] for k in ("rung", "label", "budget_ms", "ladder")}
    pos = step_binary(client, sid, 2)  # it steps on, on its new rung
    assert np.isfinite(pos).all() and client.get(f"/v1/sessions/{sid}").json()["realtime"]["rung"] == msg["rung"]


def moved(client):
    """A real-time session that moved down its ladder (:func:`late_clock`): its id and its rung."""
    s = new(client, realtime=True)
    late_clock(client, s["id"])
    step_binary(client, s["id"], FORCED_CHANGE_FRAMES)
    rung = client.get(f"/v1/sessions/{s['id']}").json()["realtime"]["rung"]
    assert rung != s["realtime"]["rung"]
    return s["id"], rung


def test_a_checkpoint_brings_the_rung_back_bitwise(client):
    sid, rung = moved(client)
    blob = client.get(f"/v1/sessions/{sid}/checkpoint").content
    state, meta = ckpt.loads(blob, 1 << 28)
    assert meta["solver"] == "realtime" and state["rung"] == rung
    other = new(client, realtime=True)["id"]  # a fresh one, on its ladder's first rung
    octet = {"Content-Type": "application/octet-stream"}
    with client.websocket_connect(f"/v1/sessions/{other}/stream") as ws:
        ws.receive_json()
        r = client.put(f"/v1/sessions/{other}/checkpoint", content=blob, headers=octet)
        assert r.status_code == 200 and r.json()["realtime"]["rung"] == rung and r.json()["frame"] == FORCED_CHANGE_FRAMES, r.text
        assert events_until(ws, "realtime")[-1]["rung"] == rung  # the restore moved it: the viewers are told
    step_binary(client, sid, 3)
    r = client.put(f"/v1/sessions/{sid}/checkpoint", content=blob, headers=octet)
    assert r.status_code == 200 and r.json()["realtime"]["rung"] == rung
    np.testing.assert_array_equal(step_binary(client, sid, 3), step_binary(client, other, 3))  # the same state, the same rung: bitwise
    plain = new(client, solver="mpm")["id"]
    assert field_of(client.put(f"/v1/sessions/{plain}/checkpoint", content=blob, headers=octet)) == "checkpoint"  # another solver's


def test_a_realtime_session_comes_back_from_the_store_on_its_rung(tmp_path):
    cfg = ServiceConfig(store=str(tmp_path / "store"), max_sessions=10, idle_ttl_s=600)
    with TestClient(create_app(cfg)) as c:
        sid, rung = moved(c)
        blob = c.get(f"/v1/sessions/{sid}/checkpoint").content
    with TestClient(create_app(cfg)) as c:  # the first stopped (a clean stop saves every session)
        info = c.get(f"/v1/sessions/{sid}").json()
        assert info["restored_from_frame"] == FORCED_CHANGE_FRAMES and info["solver"] == "realtime" and info["realtime"]["rung"] == rung
        got = step_binary(c, sid, 3)
        ref = make_simulator("water2d", "realtime", seed=0, threads=1)
        ref.restore(ckpt.loads(blob, 1 << 28)[0])
        assert ref.rung == rung
        np.testing.assert_array_equal(got, np.asarray(rollout(ref, 3).positions[1:], np.float32))  # an independent path, bitwise
        with c.websocket_connect(f"/v1/sessions/{sid}/stream") as ws:  # a reset: its initial state, on the ladder's first rung
            ws.receive_json()
            ws.send_json({"type": "reset"})
            seen = events_until(ws, "reset")
        back = c.get(f"/v1/sessions/{sid}").json()
        assert back["frame"] == 0 and back["solver"] == "realtime" and back["realtime"]["rung"] == back["realtime"]["ladder"][0]
        assert [m["rung"] for m in seen if m["type"] == "realtime"] == [back["realtime"]["rung"]]


@pytest.mark.parametrize(
    "body",
    [
        {"realtime": True, "solver": "mpm"},
        {"realtime": True, "solver": "hybrid"},
        {"realtime": True, "solver": "neural"},
        {"realtime": True, "n_grid": 64},
        {"realtime": True, "solver": "realtime", "n_grid": 64},
        {"realtime": True, "integrator": "projection"},
        {"realtime": True, "integrator": "explicit"},
        {"realtime": True, "solver": "mpm", "integrator": "projection"},
        {"realtime": False, "solver": "realtime"},
        {"realtime": 1},
        {"realtime": "true"},
        {"realtime": [True]},
    ],
)
def test_a_refused_realtime_is_a_422_naming_it(client, body):
    before = client.get("/healthz").json()["sessions"]
    r = client.post("/v1/sessions", json={"scene": "water2d", **body})
    assert field_of(r) == "realtime", body
    assert "realtime" in r.json()["detail"][0]["msg"] or r.json()["detail"][0]["type"] != "value_error"
    assert client.get("/healthz").json()["sessions"] == before  # nothing was created


@pytest.mark.parametrize("body, field", [({"solver": "realtime", "n_grid": 64}, "n_grid"), ({"solver": "realtime", "integrator": "projection"}, "integrator")])
def test_the_realtime_solver_refuses_a_grid_or_an_integrator(client, body, field):
    r = client.post("/v1/sessions", json={"scene": "water2d", **body})
    assert field_of(r) == field and "realtime" in r.json()["detail"][0]["msg"]


def test_serve_realtime_makes_sessions_realtime_by_default():
    with TestClient(create_app(ServiceConfig(realtime=True, max_sessions=10, max_sessions_per_client=10))) as c:
        assert c.get("/healthz").json()["realtime_default"] is True
        a = new(c)  # no realtime: the server's default
        assert a["solver"] == "realtime" and a["realtime"]["rung"] in a["realtime"]["ladder"]
        data, _ = first_frame(c, a["id"])
        assert decode_frame(data)[0].realtime
        b = new(c, realtime=False)
        assert b["solver"] == "default" and b["realtime"] is None and not decode_frame(first_frame(c, b["id"])[0])[0].realtime
        assert new(c, realtime=None)["solver"] == "realtime"
        assert new(c, solver="mpm")["solver"] == "mpm"  # a solver named runs as named
        assert new(c, solver="mpm", n_grid=64)["realtime"] is None
        assert new(c, realtime=True)["solver"] == "realtime"


def test_the_realtime_setting_comes_from_the_environment_and_the_command_line(monkeypatch):
    assert ServiceConfig().realtime is False
    for raw, want in (("1", True), ("true", True), ("ON", True), ("0", False), ("no", False)):
        monkeypatch.setenv("HYBRIDMPM_REALTIME", raw)
        assert ServiceConfig.from_env().realtime is want, raw
    monkeypatch.setenv("HYBRIDMPM_REALTIME", "maybe")
    with pytest.raises(InvalidInputError) as e:
        ServiceConfig.from_env()
    assert e.value.field == "realtime"
    monkeypatch.setenv("HYBRIDMPM_REALTIME", "0")
    assert ServiceConfig.from_env(realtime=True).realtime is True  # the command line over the environment
    with pytest.raises(InvalidInputError) as e:
        ServiceConfig(realtime="yes")  # type: ignore[arg-type]
    assert e.value.field == "realtime"
    ap = argparse.ArgumentParser()
    add_parsers(ap.add_subparsers())
    assert ap.parse_args(["serve", "--realtime"]).realtime is True
    assert ap.parse_args(["serve"]).realtime is None  # absent: the environment's, else off


def test_a_realtime_session_steps_what_fell_due_in_a_tick_and_owes_nothing_older(client, monkeypatch):
    """The play loop sleeps out a tick (``PLAY_TICK_S``) between its calls: a real-time session steps on waking the
    frames that fell due meanwhile (so it can play at 1/dt_frame, as water2d's 400 frames/s), but a frame later than
    ``REALTIME_LAG_S`` (two ticks) is not owed; a plain session catches up ``PLAY_LAG_S``. A clock of our own."""
    rt, plain = new(client, realtime=True)["id"], new(client, solver="mpm")["id"]
    sessions = client.app.state.manager.sessions
    assert sessions[rt].core.pacer().lag == REALTIME_LAG_S and sessions[plain].core.pacer().lag == PLAY_LAG_S
    assert PLAY_TICK_S < REALTIME_LAG_S < PLAY_LAG_S
    now = [1000.0]
    monkeypatch.setattr(core_module.time, "monotonic", lambda: now[0])
    period = 0.0025

    def steps_on_waking(lag: float, late: float) -> int:  # a frame stepped at t, the loop wakes `late` s on and steps
        p = Pacer(period, lag=lag)
        assert p.delay() == pytest.approx(period)  # on time: the next frame a period on
        now[0] += late
        n = 1  # on waking it steps; then again while the next one is due (no wait)
        while p.delay() == 0.0:
            n += 1
        return n

    tick = round(PLAY_TICK_S / period)  # 4 frames of 2.5 ms in a tick
    assert steps_on_waking(REALTIME_LAG_S, PLAY_TICK_S + period / 2) == tick  # the frames of a tick's sleep
    assert steps_on_waking(REALTIME_LAG_S, PLAY_TICK_S + period * 1.5) == tick + 1  # and of the timer's lateness
    assert steps_on_waking(0.0, PLAY_TICK_S + period / 2) == 2  # with no lag, two of the four: 200 frames/s at best
    for lag in (REALTIME_LAG_S, PLAY_LAG_S):  # a 100 s stall: a real-time session owes two ticks, a plain one 0.25 s
        assert lag / period <= steps_on_waking(lag, 100.0) <= lag / period + 2


def test_a_realtime_session_takes_a_poured_block_and_an_added_body_and_steps_on(client):
    """A block or a body joins a real-time session as it joins an MPM one; a sand block moves a projection rung
    to the explicit step (the projection steps water only) and its ladder keeps the projection off while the
    sand is in; the body joins whatever runs."""
    s = new(client, realtime=True)
    sid = s["id"]
    r = client.post(f"/v1/sessions/{sid}/blocks", json={"material": "sand", "lo": [0.6, 0.1], "hi": [0.7, 0.2]})
    assert r.status_code == 201, r.text
    r = client.post(f"/v1/sessions/{sid}/bodies", json={"shape": "box", "center": [0.65, 0.65], "half_extents": [0.04, 0.03], "density": 500.0})
    assert r.status_code == 201, r.text
    info = client.get(f"/v1/sessions/{sid}").json()
    assert info["num_particles"] > s["num_particles"] and len(info["bodies"]) == 1
    assert info["realtime"]["rung"].endswith("explicit")
    assert step_binary(client, sid, 2).shape == (2, info["num_particles"], 2)
