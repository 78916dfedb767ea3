"""Obstacle moves pending for the next step are part of a session's state:
they survive the checkpoint's JSON (where integer keys would become
strings), a clean stop (SIGTERM), a SIGKILL of the server and a killed Ray
actor, and the restored session steps to the same bits as one never saved.
States written before (the moves as a mapping with integer or string keys)
still restore."""

from __future__ import annotations

import json
import os
import secrets
import shutil
import signal
import tempfile
import time
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("fastapi")
httpx = pytest.importorskip("httpx")

from fastapi.testclient import TestClient  # noqa: E402

from hybridmpm.errors import InvalidInputError  # noqa: E402
from hybridmpm.service import ServiceConfig, create_app  # noqa: E402
from hybridmpm.service import checkpoint as ckpt  # noqa: E402
from hybridmpm.service.store import SessionStore, session_key  # noqa: E402
from hybridmpm.service.testing import LiveServer, RayCluster, step_binary  # noqa: E402
from hybridmpm.sim import make_simulator, rollout  # noqa: E402

#: Bounds on waiting (never a pass/fail threshold on time).
WAIT_S = 120.0
#: (scene, solver, seed) with a movable obstacle, 2D and 3D.
CASES = [("water_ramps2d", "mpm", 1), ("paddle3d", "mpm", 0), ("water_ramps2d", "hybrid", 2)]


def _target(sim, dx=0.01):
    c = sim.obstacle_centers[0].copy()
    c[0] += dx
    return c.tolist()


def _reference(scene, solver, seed, before, after, velocity=None):
    """Positions of ``after`` frames stepped after ``before`` frames and a move of obstacle 0, never saved."""
    sim = make_simulator(scene, solver, seed=seed, threads=1, nn_threads=1)
    rollout(sim, before)
    target = _target(sim)
    sim.move_obstacle(0, target, velocity)
    return target, rollout(sim, after).positions[1:]


@pytest.mark.parametrize("scene,solver,seed", CASES)
def test_a_pending_move_survives_the_checkpoint_json_bitwise(scene, solver, seed):
    velocity = [0.5] + [0.0] * (2 if scene.endswith("3d") else 1)
    for v in (None, velocity):
        target, ref = _reference(scene, solver, seed, 2, 3, v)
        sim = make_simulator(scene, solver, seed=seed, threads=1, nn_threads=1)
        rollout(sim, 2)
        sim.move_obstacle(0, target, v)
        state, _ = ckpt.loads(ckpt.dumps(sim.state(), {}), 1 << 30)  # the service's checkpoint: JSON + arrays
        fresh = make_simulator(scene, solver, seed=seed, threads=1, nn_threads=1)
        fresh.restore(state)
        assert getattr(fresh, "mpm", fresh).obstacles_moving  # the hybrid's MPM holds the move
        assert np.array_equal(rollout(fresh, 3).positions[1:], ref), (scene, solver, v)


def test_states_written_before_still_restore_and_bad_moves_are_refused():
    """The moves as a mapping of obstacle index (an int, or its string after a JSON round trip) to (centre,
    velocity): what stores written before hold. A bad record is refused naming the field, the simulator unchanged."""
    target, ref = _reference("water_ramps2d", "mpm", 1, 2, 3)
    sim = make_simulator("water_ramps2d", "mpm", seed=1, threads=1)
    rollout(sim, 2)
    base = sim.state()
    for old in ({0: (target, None)}, {"0": [target, None]}):
        fresh = make_simulator("water_ramps2d", "mpm", seed=1, threads=1)
        fresh.restore({**base, "obstacle_moves": old})
        assert np.array_equal(rollout(fresh, 3).positions[1:], ref)
    for bad in (
        {"7": [target, None]},
        {"x": [target, None]},
        [{"index": 0, "center": target, "velocity": None}, {"index": 0, "center": target, "velocity": None}],
        [{"index": 0, "center": [np.nan, 0.3], "velocity": None}],
        [{"index": 0, "center": target}],
        [{"index": True, "center": target, "velocity": None}],
        [[0, target, None]],
        "0",
    ):
        fresh = make_simulator("water_ramps2d", "mpm", seed=1, threads=1)
        before = fresh.state()
        with pytest.raises(InvalidInputError) as e:
            fresh.restore({**base, "obstacle_moves": bad})
        assert e.value.field == "state" and str(e.value).startswith("state.obstacle_moves"), bad
        assert fresh.state()["step_index"] == before["step_index"] and not fresh.obstacles_moving


def test_put_back_the_checkpoint_of_a_session_with_a_pending_move():
    """GET the checkpoint while a move is pending, PUT it back: 200, and the session steps as one never saved."""
    target, ref = _reference("water_ramps2d", "mpm", 1, 2, 3)
    with TestClient(create_app(ServiceConfig(max_sessions=4, max_sessions_per_client=4))) as c:
        sid = c.post("/v1/sessions", json={"scene": "water_ramps2d", "solver": "mpm", "seed": 1}).json()["id"]
        step_binary(c, sid, 2)
        assert c.put(f"/v1/sessions/{sid}/obstacles/0", json={"center": target}).status_code == 200
        blob = c.get(f"/v1/sessions/{sid}/checkpoint")
        assert blob.status_code == 200
        step_binary(c, sid, 5)  # elsewhere meanwhile
        r = c.put(f"/v1/sessions/{sid}/checkpoint", content=blob.content, headers={"Content-Type": "application/octet-stream"})
        assert r.status_code == 200, r.text
        assert np.array_equal(step_binary(c, sid, 3), ref)


def _server(store, log):
    return LiveServer(args=["--store", str(store), "--save-every", "0.2", "--log-level", "info"], log=log)


def _stored_moves(store, sid):
    """The pending moves of ``sid``'s record in the local store ``store`` (None while it has no loadable record)."""
    try:
        rec = SessionStore(str(store)).load(session_key(sid), 1 << 30)
    except InvalidInputError:
        return None
    return rec.state.get("obstacle_moves")


def _wait_stored_move(store, sid):
    deadline = time.monotonic() + WAIT_S
    while time.monotonic() < deadline:
        if _stored_moves(store, sid):
            return
        time.sleep(0.05)
    raise AssertionError("the pending move never reached the store")


@pytest.mark.parametrize("how", ["sigterm", "sigkill"])
def test_a_pending_move_survives_a_restart_of_the_server(tmp_path, how):
    """A move pending when the server stops (SIGTERM: a clean stop; SIGKILL once the store holds it): the
    restarted server has the session, which steps to the same bits as one never stopped."""
    store = tmp_path / "store"
    cases = [("water_ramps2d", "mpm", 1), ("paddle3d", "mpm", 0)]
    refs = {scene: _reference(scene, solver, seed, 2, 3) for scene, solver, seed in cases}
    ids = {}
    server = _server(store, tmp_path / "first.log").start()
    try:
        with httpx.Client(base_url=server.url, timeout=WAIT_S) as c:
            for scene, solver, seed in cases:
                r = c.post("/v1/sessions", json={"scene": scene, "solver": solver, "seed": seed})
                assert r.status_code == 201, r.text
                ids[scene] = r.json()["id"]
                step_binary(c, ids[scene], 2)
                assert c.put(f"/v1/sessions/{ids[scene]}/obstacles/0", json={"center": refs[scene][0]}).status_code == 200
        if how == "sigkill":
            for sid in ids.values():
                _wait_stored_move(store, sid)
            server.proc.send_signal(signal.SIGKILL)
            server.proc.wait(WAIT_S)
    finally:
        server.stop()  # SIGTERM: a clean stop saves every changed session first
    assert how == "sigkill" or all(_stored_moves(store, sid) for sid in ids.values())
    with _server(store, tmp_path / "second.log") as server, httpx.Client(base_url=server.url, timeout=WAIT_S) as c:
        assert c.get("/healthz").json()["sessions"] == len(cases)
        for scene, sid in ids.items():
            info = c.get(f"/v1/sessions/{sid}")
            assert info.status_code == 200, (scene, info.text)
            assert info.json()["restored_from_frame"] == 2
            assert np.array_equal(step_binary(c, sid, 3), refs[scene][1]), scene


def test_a_pending_move_survives_a_killed_ray_actor(tmp_path):
    """On a one-node Ray cluster: the session's actor killed (SIGKILL) once its record holds the move; the
    next request builds it again from the store and it steps to the same bits as one never killed."""
    pytest.importorskip("ray")
    root = Path(tempfile.mkdtemp(prefix="hmmv", dir="/tmp"))  # short: Ray's socket paths live under it
    cluster = RayCluster(root, secrets.token_hex(16), nodes=1, num_cpus=1, timeout=WAIT_S)
    store = tmp_path / "store"
    target, ref = _reference("water_ramps2d", "mpm", 1, 2, 3)
    try:
        cluster.start()
        args = ["--backend", "ray", "--ray-address", cluster.address, "--store", str(store), "--save-every", "0.2", "--log-level", "info"]
        env = {"RAY_AUTH_MODE": "token", "RAY_AUTH_TOKEN": cluster.token}
        server = LiveServer(max_sessions=2, args=args, env=env, log=tmp_path / "front.log")
        try:
            server.start(timeout=WAIT_S)
            with httpx.Client(base_url=server.url, timeout=WAIT_S) as c:
                r = c.post("/v1/sessions", json={"scene": "water_ramps2d", "solver": "mpm", "seed": 1})
                assert r.status_code == 201, r.text
                sid = r.json()["id"]
                step_binary(c, sid, 2)
                assert c.put(f"/v1/sessions/{sid}/obstacles/0", json={"center": target}).status_code == 200
                _wait_stored_move(store, sid)
                pids = cluster.actor_pids()
                assert len(pids) == 1, pids
                os.kill(pids[0], signal.SIGKILL)
                after = step_binary(c, sid, 3)
                info = c.get(f"/v1/sessions/{sid}").json()
                assert info["restored_from_frame"] == 2, json.dumps(info)[:300]
                assert np.array_equal(after, ref)
        finally:
            server.stop()
    finally:
        cluster.stop()
        shutil.rmtree(root, ignore_errors=True)
