"""Durable sessions (``hybridmpm serve --store``): a real server killed with
SIGKILL and started again on the same store brings its sessions back under
the same ids, and stepping on from the restored frame matches an
uninterrupted run bit for bit; a save torn by a crash leaves the previous
save; the fsspec layout (numbered objects and a pointer) falls back past a
bad object; malformed records and unwritable stores give errors naming the field."""

from __future__ import annotations

import asyncio
import logging
import os
import time
import uuid
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("fastapi")
httpx = pytest.importorskip("httpx")

from hybridmpm.errors import CheckpointError, InvalidInputError  # noqa: E402
from hybridmpm.service import checkpoint as ckpt  # noqa: E402
from hybridmpm.service.config import ServiceConfig  # noqa: E402
from hybridmpm.service.sessions import SessionManager  # noqa: E402
from hybridmpm.service.store import TEAR_ENV, SessionStore, session_key  # noqa: E402
from hybridmpm.service.testing import LiveServer, step_binary, wait_saved  # noqa: E402
from hybridmpm.sim import make_simulator, rollout  # noqa: E402

#: Bounds on waiting (never a pass/fail threshold on time).
WAIT_S = 60.0


def _server(store, tmp_path, name, env=None):
    return LiveServer(args=["--store", str(store), "--save-every", "0.2", "--log-level", "info"], env=env, log=tmp_path / f"{name}.log")


def _uninterrupted(scene, solver, seed, first, then):
    """Positions of the steps after the first ``first`` frames, in one process, never stopped."""
    sim = make_simulator(scene, solver, seed=seed, threads=1, nn_threads=1)
    rollout(sim, first)
    return rollout(sim, then).positions[1:]


def _kill(server):
    server.proc.kill()  # SIGKILL: no shutdown, no final save
    server.proc.wait(WAIT_S)
    server.stop()


def test_sigkill_restart_restores_sessions_bitwise(tmp_path):
    store = tmp_path / "store"
    specs = {"a": ("water2d", "mpm", 3, 7), "b": ("dam_break2d", "hybrid", 1, 8)}
    ids, saved = {}, {}
    server = _server(store, tmp_path, "first").start()
    try:
        with httpx.Client(base_url=server.url, timeout=WAIT_S) as c:
            for name, (scene, solver, seed, frames) in specs.items():
                r = c.post("/v1/sessions", json={"scene": scene, "solver": solver, "seed": seed})
                assert r.status_code == 201, r.text
                ids[name] = r.json()["id"]
                assert r.json()["saved_frame"] == 0 and r.json()["restored_from_frame"] is None
                step_binary(c, ids[name], frames)
                saved[name] = wait_saved(c, ids[name], WAIT_S)
            gone = c.post("/v1/sessions", json={"scene": "water2d", "seed": 9}).json()["id"]
            assert c.delete(f"/v1/sessions/{gone}").status_code == 204
        # the store holds no session id, only their hashes (and the server's claim, .lock, holding its pid)
        names = sorted(n for n in os.listdir(store) if n != ".lock")
        assert names == sorted(session_key(sid) + ".npz" for sid in ids.values())
        assert not any(sid.encode() in (store / n).read_bytes() for n in names for sid in ids.values())
    finally:
        _kill(server)
    with _server(store, tmp_path, "second") as server, httpx.Client(base_url=server.url, timeout=WAIT_S) as c:
        assert c.get("/healthz").json()["sessions"] == 2
        assert c.get(f"/v1/sessions/{gone}").status_code == 404
        assert c.get(f"/v1/sessions/{session_key(ids['a'])}").status_code == 404  # the key is no credential
        for name, (scene, solver, seed, frames) in specs.items():
            info = c.get(f"/v1/sessions/{ids[name]}").json()
            assert info["frame"] == saved[name] == info["restored_from_frame"] and info["id"] == ids[name]
            after = step_binary(c, ids[name], 8)
            assert np.array_equal(after, _uninterrupted(scene, solver, seed, frames, 8)), f"{scene} {solver}: the restored run differs"


def test_torn_save_leaves_the_previous_one(tmp_path):
    store = tmp_path / "store"
    # save 1: the session's creation (frame 0); save 2 (after the step) is torn: the process dies in it
    server = _server(store, tmp_path, "torn", env={TEAR_ENV: "2"}).start()
    try:
        with httpx.Client(base_url=server.url, timeout=WAIT_S) as c:
            sid = c.post("/v1/sessions", json={"scene": "water2d", "solver": "mpm", "seed": 4}).json()["id"]
            try:
                step_binary(c, sid, 5)
            except httpx.RemoteProtocolError:
                pass  # the saver runs beside the request: on a loaded machine the process may die before its answer goes out
        assert server.proc.wait(WAIT_S) == -9
    finally:
        server.stop()
    torn = [n for n in os.listdir(store) if n.endswith(".tmp")]
    assert len(torn) == 1 and (store / torn[0]).stat().st_size > 0
    with _server(store, tmp_path, "after") as server, httpx.Client(base_url=server.url, timeout=WAIT_S) as c:
        info = c.get(f"/v1/sessions/{sid}").json()
        assert info["restored_from_frame"] == 0 and info["frame"] == 0
        assert np.array_equal(step_binary(c, sid, 3), _uninterrupted("water2d", "mpm", 4, 0, 3))
    assert not [n for n in os.listdir(store) if n.endswith(".tmp")]


def _state_and_meta(frames=2):
    sim = make_simulator("water2d", "mpm", seed=2, threads=1)
    rollout(sim, frames)
    meta = {"scene": "water2d", "seed": 2, "solver": "mpm", "r_c": 0.0, "last_used_at": time.time(), "client": "127.0.0.1"}
    return sim.state(), meta


def test_fsspec_store_falls_back_past_a_bad_object():
    url = f"memory://hmpm-{uuid.uuid4().hex}"
    st = SessionStore(url).open()
    key = session_key("some-session")
    state, meta = _state_and_meta()
    st.write(key, ckpt.dumps(state, {**meta, "seed": 2}))
    st.write(key, ckpt.dumps(state, {**meta, "seed": 5}))
    assert st.keys() == [key] and st.load(key, 1 << 30).seed == 5
    # the newest object, torn: the previous one is used
    head = st.fs.cat_file(f"{st.root}/{key}/HEAD").decode()
    st.fs.pipe_file(f"{st.root}/{key}/{head}", b"PK\x03\x04 torn")
    assert st.load(key, 1 << 30).seed == 2
    st.write(key, ckpt.dumps(state, {**meta, "seed": 7}))  # writes go on past it
    assert st.load(key, 1 << 30).seed == 7
    st.delete(key)
    assert st.keys() == []


def test_bad_records_and_unwritable_store(tmp_path, caplog):
    (tmp_path / "file").write_text("x")
    with pytest.raises(InvalidInputError) as e:
        SessionStore(str(tmp_path / "file" / "sub")).open()  # a path under a file: not writable
    assert e.value.field == "store" and "cannot write" in str(e.value)
    store = tmp_path / "store"
    st = SessionStore(str(store)).open()
    state, meta = _state_and_meta()
    good, garbage, badmeta = (session_key(x) for x in ("good", "garbage", "badmeta"))
    st.write(good, ckpt.dumps(state, meta))
    (store / f"{garbage}.npz").write_bytes(b"not a zip")
    st.write(badmeta, ckpt.dumps(state, {**meta, "seed": "two"}))
    mgr = SessionManager(ServiceConfig(store=str(store), max_sessions=10))
    with caplog.at_level(logging.WARNING, logger="hybridmpm.service"):
        assert asyncio.run(mgr.restore_all()) == 1
    text = caplog.text
    assert "meta.seed" in text and "checkpoint: not an npz archive" in text
    assert mgr.get("good") is not None and mgr.get("good").core.restored_from_frame == 2
    assert mgr.get("garbage") is None and mgr.get("badmeta") is None
    # an expired record is removed at start
    old = session_key("old")
    st.write(old, ckpt.dumps(state, {**meta, "last_used_at": time.time() - 10_000}))
    mgr = SessionManager(ServiceConfig(store=str(store), max_sessions=10, idle_ttl_s=600))
    asyncio.run(mgr.restore_all())
    assert not (store / f"{old}.npz").exists() and mgr.get("old") is None


def test_a_restored_session_rebuilds_its_scene_without_the_k_means(tmp_path):
    """A record of a session at r_p < 1 holds its clusters: a fresh process
    rebuilds the session from it without importing scikit-learn (the k-means
    costs about 3 s of a crash's recovery), and steps on bit for bit; a
    record whose clusters do not fit its scene is refused naming the field."""
    import subprocess
    import sys

    from hybridmpm.service.store import CLUSTERS_KEY, parse_record, rebuild, record_state

    sim = make_simulator("dam_break2d", "hybrid", seed=2, threads=1, nn_threads=1)
    rollout(sim, 8)
    state = record_state(sim)
    assert CLUSTERS_KEY in state
    meta = {"scene": "dam_break2d", "seed": 2, "solver": "hybrid", "r_c": sim.r_c, "last_used_at": time.time(), "client": ""}
    path = tmp_path / "record.npz"
    path.write_bytes(ckpt.dumps(state, meta))
    want = rollout(sim, 8).positions[1:]
    code = (
        "import sys, numpy as np\n"
        "from hybridmpm.service.store import parse_record, rebuild\n"
        "from hybridmpm.sim import rollout\n"
        f"rec = parse_record('0' * 64, open({str(path)!r}, 'rb').read(), 1 << 28)\n"
        "sim, _ = rebuild(rec)\n"
        "assert 'sklearn' not in sys.modules, 'the rebuild clustered again'\n"
        f"np.save({str(tmp_path / 'after.npy')!r}, rollout(sim, 8).positions[1:])\n"
    )
    subprocess.run([sys.executable, "-c", code], check=True, timeout=WAIT_S)
    assert np.array_equal(np.load(tmp_path / "after.npy"), want)
    # clusters of another scene: refused, naming the field
    state[CLUSTERS_KEY] = {"labels": state[CLUSTERS_KEY]["labels"][:-1], "boundary_labels": state[CLUSTERS_KEY]["boundary_labels"]}
    rec = parse_record("0" * 64, ckpt.dumps(state, meta), 1 << 28)
    with pytest.raises(InvalidInputError) as e:
        rebuild(rec)
    assert e.value.field == "clusters.labels"


def test_a_record_keeps_its_sessions_grid():
    """A session on a coarser grid is saved with its grid (meta.n_grid) and rebuilt on it, bit for bit; older records without it rebuild on the scene's grid."""
    from hybridmpm.service.store import parse_record, rebuild, record_state

    sim = make_simulator("sand2d", "mpm", seed=4, threads=1, n_grid=64)
    rollout(sim, 6)
    meta = {"scene": "sand2d", "seed": 4, "solver": "mpm", "r_c": 0.8, "last_used_at": time.time(), "client": "", "n_grid": 64}
    blob = ckpt.dumps(record_state(sim), meta)
    back, _ = rebuild(parse_record("0" * 64, blob, 1 << 28))
    assert back.scene.params.resolved_n_grid() == 64
    assert np.array_equal(rollout(back, 6).positions, rollout(sim, 6).positions)
    for bad in (64.5, "64", True, 8, 10**6):
        with pytest.raises(InvalidInputError, match="meta.n_grid"):
            parse_record("0" * 64, ckpt.dumps(record_state(sim), {**meta, "n_grid": bad}), 1 << 28)
    old = {k: v for k, v in meta.items() if k != "n_grid"}
    with pytest.raises((InvalidInputError, CheckpointError)):  # the scene's own grid: another solver's particles
        rebuild(parse_record("0" * 64, ckpt.dumps(record_state(sim), old), 1 << 28))


def test_the_periodic_saver_never_waits_for_a_control(tmp_path):
    """A control holds its session's lock for its whole run: a round of the periodic saver saves every other
    session at once instead of queueing behind it, and that session's own save waits for the control's end
    (a snapshot at its step boundary), then runs without another round."""

    async def go() -> None:
        mgr = SessionManager(ServiceConfig(store=str(tmp_path / "store"), max_sessions=10))
        a = await mgr.create("water2d", 0, "mpm", 0.8)
        b = await mgr.create("water2d", 1, "mpm", 0.8)
        root = Path(mgr.store.root)
        for s in (a, b):  # both step on after their first save
            s.core.sim.advance()
            s.core.dirty = True
        a_before, b_before = (root / f"{a.key}.npz").read_bytes(), (root / f"{b.key}.npz").read_bytes()
        async with a.lock:  # a control (or a long step) running on a
            mgr.save_round()
            deadline = time.monotonic() + 10
            while (b.core.dirty or b.key in mgr._saving) and time.monotonic() < deadline:
                await asyncio.sleep(0.01)
            assert not b.core.dirty and (root / f"{b.key}.npz").read_bytes() != b_before
            assert a.core.dirty and (root / f"{a.key}.npz").read_bytes() == a_before
            mgr.save_round()  # a's save is already waiting: no second one
            assert list(mgr._saving) == [a.key]
            a.core.sim.advance()  # the control's last step, before its lock goes
        await asyncio.wait_for(mgr._saving[a.key], 10)
        assert not a.core.dirty and (root / f"{a.key}.npz").read_bytes() != a_before
        assert a.core.saved_frame == a.core.frame_index

    asyncio.run(go())


def test_one_server_per_store(tmp_path):
    """A second server on a store another one holds is refused at start, naming the store and the holder's pid;
    once the first stops (or dies: the OS drops the lock), a server starts on it again."""
    from fastapi.testclient import TestClient

    from hybridmpm.service import create_app

    cfg = ServiceConfig(store=str(tmp_path / "store"), allowed_hosts=("testserver",))
    first = create_app(cfg)
    with pytest.raises(InvalidInputError) as e:
        create_app(cfg)
    assert e.value.field == "store" and f"pid {os.getpid()}" in str(e.value)
    with TestClient(first) as c:
        assert c.get("/healthz").status_code == 200
    with TestClient(create_app(cfg)) as c:  # the first stopped: its claim went with it
        assert c.get("/healthz").status_code == 200
