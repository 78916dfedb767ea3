"""Sessions on a Ray cluster (``hybridmpm serve --backend ray``): a local
cluster of two node processes (a head and a second node, on this machine's
loopback address, token authentication with a fresh token, Ray's files in a
temporary directory) and two front ends on one store. A session created
through one front end is stepped, controlled, checkpointed and streamed
through the other, bit for bit as one uninterrupted local run (a jelly
poured into it through one front end included); its actor's
process killed with SIGKILL, the next step resumes from its last save and
goes on bit for bit; the whole cluster and both front ends stopped and
started again on the same store, the session is back; the second node's
processes killed, its sessions come back on the head. The session cap holds
for the whole cluster. Settings that name no cluster, and the ray backend
without Ray installed, are refused naming the field.

The cluster is stopped by killing, by their process ids, the processes its
``ray start --block`` commands started (``ray stop`` would end every Ray
process of the machine's user, other clusters' too).
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import os
import secrets
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import httpx
import numpy as np
import pytest
import websockets

from hybridmpm.control import Controller, Sketch, control_episode
from hybridmpm.errors import InvalidInputError
from hybridmpm.service import decode_frame
from hybridmpm.service.config import ServiceConfig
from hybridmpm.service.store import SessionStore
from hybridmpm.service.testing import LiveServer, RayCluster, free_port, step_binary, wait_saved
from hybridmpm.sim import make_simulator, rollout
from hybridmpm.sim.pour import pour_block

OCTET = {"Accept": "application/octet-stream"}
#: Bounds on waiting (never a pass/fail threshold on time).
WAIT_S = 180.0
SCENE, SOLVER, SEED = "water2d", "mpm", 3
ARROW = {"kind": "arrow", "points": [[0.3, 0.3], [0.6, 0.4]]}
JELLY = {"material": "jello", "lo": [0.6, 0.75], "hi": [0.7, 0.85]}


@pytest.fixture(scope="module")
def cluster():
    root = Path(tempfile.mkdtemp(prefix="hmray", dir="/tmp"))  # short: Ray's socket paths live under it
    c = RayCluster(root, secrets.token_hex(16), nodes=2, num_cpus=1, timeout=WAIT_S)
    try:
        yield c.start()
    finally:
        c.stop()
        shutil.rmtree(root, ignore_errors=True)


def _front_end(cluster, store, log, max_sessions=10):
    args = ["--backend", "ray", "--ray-address", cluster.address, "--store", str(store), "--save-every", "0.3", "--log-level", "info"]
    return LiveServer(max_sessions=max_sessions, args=args, env={"RAY_AUTH_MODE": "token", "RAY_AUTH_TOKEN": cluster.token}, log=log)


def _start(*servers):
    for s in servers:
        s.start(timeout=WAIT_S)
    return servers


def _paused(c, sid):
    """The session's description once its frame stays put (the pause reached its actor)."""
    last = None
    deadline = time.monotonic() + WAIT_S
    while time.monotonic() < deadline:
        info = c.get(f"/v1/sessions/{sid}").json()
        if last is not None and info["frame"] == last["frame"]:
            return info
        last = info
        time.sleep(0.5)
    raise AssertionError("the session kept playing")


async def _watch(url):
    """The stream's meta and first frame, then the frames of a short play."""
    async with websockets.connect(url, max_size=None) as ws:
        meta = await asyncio.wait_for(ws.recv(), WAIT_S)
        first = await asyncio.wait_for(ws.recv(), WAIT_S)
        await ws.send('{"type": "play"}')
        frames = []
        while len(frames) < 3:
            m = await asyncio.wait_for(ws.recv(), WAIT_S)
            if isinstance(m, bytes):
                frames.append(decode_frame(m)[0].frame)
        await ws.send('{"type": "pause"}')
        return meta, first, frames


def test_two_front_ends_serve_one_session_bitwise_and_survive_its_killed_actor(cluster, tmp_path):
    store = tmp_path / "store"
    ref = make_simulator(SCENE, SOLVER, seed=SEED, threads=1, nn_threads=1)
    a, b = _front_end(cluster, store, tmp_path / "a.log", max_sessions=3), _front_end(cluster, store, tmp_path / "b.log", max_sessions=3)
    try:
        _start(a, b)
        with httpx.Client(base_url=a.url, timeout=WAIT_S) as ca, httpx.Client(base_url=b.url, timeout=WAIT_S) as cb:
            r = ca.post("/v1/sessions", json={"scene": SCENE, "solver": SOLVER, "seed": SEED})
            assert r.status_code == 201, r.text
            sid = r.json()["id"]
            assert r.json()["saved_frame"] == 0 and r.json()["restored_from_frame"] is None
            # stepped through B, then A: one uninterrupted run
            assert np.array_equal(step_binary(cb, sid, 5), rollout(ref, 5).positions[1:])
            assert np.array_equal(step_binary(ca, sid, 3), rollout(ref, 3).positions[1:])
            # a jelly poured through A: B's facts and frames hold it, and the run goes on as a local one poured alike
            r = ca.post(f"/v1/sessions/{sid}/blocks", json=JELLY)
            assert r.status_code == 201, r.text
            n = pour_block(ref, JELLY)
            assert r.json()["num_particles"] == n and cb.get(f"/v1/sessions/{sid}").json()["num_particles"] == n
            # controlled through B, its trajectory fetched through A
            r = cb.post(f"/v1/sessions/{sid}/controls", json={"sketch": ARROW, "method": "constant", "frames": 20})
            assert r.status_code == 200, r.text
            ep = control_episode(ref, Sketch.from_json(ARROW), Controller.for_scene(SCENE, "constant", frames=20))
            t = ca.get(r.json()["trajectory"], headers=OCTET)
            assert t.status_code == 200 and np.array_equal(np.frombuffer(t.content, "<f4").reshape(ep.rollout.positions.shape), ep.rollout.positions)
            # checkpointed through B, restored through A
            blob = cb.get(f"/v1/sessions/{sid}/checkpoint")
            assert blob.status_code == 200
            assert ca.put(f"/v1/sessions/{sid}/checkpoint", content=blob.content).json()["frame"] == 28
            # streamed through B (its meta names the session; frames come from the actor)
            meta, first, played = asyncio.run(_watch(f"{b.ws_url}/v1/sessions/{sid}/stream"))
            assert '"meta"' in meta and sid in meta and decode_frame(first)[0].frame == 28 and played == sorted(played)
            info = _paused(ca, sid)
            # its recent trajectory (kept by the actor) through A: the frames played through B
            t = ca.get(f"/v1/sessions/{sid}/trajectory", params={"frames": 3})
            assert t.status_code == 200 and int(t.headers["x-frames"].split(",")[1]) == info["frame"], t.text[:200]
            assert info["frame"] == played[-1] or info["frame"] > played[-1]
            ref = make_simulator(SCENE, SOLVER, seed=SEED, threads=1, nn_threads=1)
            rollout(ref, 8)
            pour_block(ref, JELLY)
            control_episode(ref, Sketch.from_json(ARROW), Controller.for_scene(SCENE, "constant", frames=20))
            rollout(ref, info["frame"] - 28)
            # its actor's process killed: the next request waits for it, resumed from the last save
            saved = wait_saved(ca, sid, WAIT_S)
            assert saved == info["frame"] or saved > info["frame"]
            rollout(ref, saved - info["frame"])
            pids = cluster.actor_pids()
            assert len(pids) == 1, pids
            os.kill(pids[0], signal.SIGKILL)
            t0 = time.monotonic()
            after = step_binary(ca, sid, 4)
            back_s = time.monotonic() - t0
            assert len(after) == 4 and np.array_equal(after, rollout(ref, 4).positions[1:]), "the restored run differs"  # the jelly in it
            info = cb.get(f"/v1/sessions/{sid}").json()
            assert info["restored_from_frame"] == saved and info["frame"] == saved + 4
            assert cluster.actor_pids() != pids
            print(f"session back {back_s:.2f} s after its actor was killed")
            # a bad setting is refused as with one process (its actor goes)
            r = cb.post("/v1/sessions", json={"scene": "water_columns2d", "solver": "hybrid"})
            assert r.status_code == 422, r.text
            assert ca.get("/healthz").json()["sessions"] == 1
            # the cap counts the cluster: 3 sessions through A and B, a 4th refused through either
            more = [c.post("/v1/sessions", json={"scene": SCENE, "solver": SOLVER}) for c in (ca, cb)]
            assert [m.status_code for m in more] == [201, 201]
            assert ca.get("/healthz").json()["sessions"] == cb.get("/healthz").json()["sessions"] == 3
            r = cb.post("/v1/sessions", json={"scene": SCENE, "solver": SOLVER})
            assert r.status_code == 503 and r.headers["retry-after"]
            for m in more:  # deleted through the other front end
                assert (cb if m is more[0] else ca).delete(f"/v1/sessions/{m.json()['id']}").status_code == 204
                assert ca.get(f"/v1/sessions/{m.json()['id']}").status_code == 404
            assert ca.get("/healthz").json()["sessions"] == 1
    finally:
        a.stop()
        b.stop()


async def _opened(ws) -> dict[str, Any]:
    """Read a stream's opening messages: its ``meta`` (returned), then up to the current frame. What a viewer can
    rely on: once they are read, every later event of the session reaches it."""
    meta = json.loads(await asyncio.wait_for(ws.recv(), WAIT_S))
    assert meta["type"] == "meta", meta
    while not isinstance(await asyncio.wait_for(ws.recv(), WAIT_S), bytes):
        pass
    return meta


def _controls(events: list[str]) -> list[dict[str, Any]]:
    return [m for m in map(json.loads, events) if m.get("type") == "control"]


async def _told_of(ws, control: dict[str, Any]) -> dict[str, Any]:
    """What a viewer that joins while ``control`` (its ``running`` event) runs learns from its opening messages and
    the events after them: ``{"meta": the meta's control, "plan": the plan (the meta's or a plan event's), "ended":
    the control event that ended it, "frame": the meta's frame}``."""
    meta = json.loads(await asyncio.wait_for(ws.recv(), WAIT_S))
    assert meta["type"] == "meta", meta
    told: dict[str, Any] = {"meta": meta.get("control"), "frame": meta["frame"], "plan": (meta.get("control") or {}).get("plan"), "ended": None}
    deadline = time.monotonic() + WAIT_S
    while told["ended"] is None and time.monotonic() < deadline:
        m = await asyncio.wait_for(ws.recv(), WAIT_S)
        if isinstance(m, str):
            e = json.loads(m)
            if e.get("type") == "plan" and e.get("id") == control["id"]:
                told["plan"] = told["plan"] or e
            elif e.get("type") == "control" and e.get("id") == control["id"] and e["status"] != "running":
                told["ended"] = e
    return told


def _check_told(told: dict[str, Any], control: dict[str, Any], start: int, frames: int) -> None:
    """A viewer that joined before ``control`` (``frames`` frames from frame ``start``) ended (its meta's frame short
    of the control's end) was told it runs, with its sketch, and got its plan and its end."""
    assert told["ended"] is not None and told["ended"]["status"] == "done", told
    if told["frame"] < start + frames:
        c = told["meta"]
        assert c is not None and c["status"] == "running" and c["id"] == control["id"] and c["method"] == "constant", told
        assert c["sketch"]["kind"] == ARROW["kind"] and np.allclose(c["sketch"]["points"], ARROW["points"]), c
        assert c["frames"] == frames and c["start_frame"] == start
        plan = told["plan"]
        assert plan is not None and plan["frames"] == frames and len(plan["centroid_path"]) >= 2, told


def test_a_refused_control_tells_no_viewer_it_is_running(cluster, tmp_path):
    """A control runs through front end A; a second one sent through B is refused (409 from the actor). A viewer
    on B, attached before it (its opening messages read), sees one "running" event (A's, emitted by the actor
    once it starts) and then its end: none for the refused one (B announced every control before the actor
    accepted it). Viewers that join while it runs, on A (whose stream starts its feeder then) and on B (whose
    feeder runs), are told by their opening messages that it runs, with its sketch and plan, and see it end."""
    a, b = _front_end(cluster, tmp_path / "store", tmp_path / "a.log"), _front_end(cluster, tmp_path / "store", tmp_path / "b.log")

    async def go(sid: str) -> tuple[list[str], list[dict[str, Any]], dict[str, Any], int]:
        events: list[str] = []

        async def read(ws) -> None:  # read on throughout (a client that stops reading stalls its socket, pongs too)
            while not any(e["status"] == "done" for e in _controls(events)):
                m = await asyncio.wait_for(ws.recv(), WAIT_S)
                if isinstance(m, str):
                    events.append(m)

        async with websockets.connect(f"{b.ws_url}/v1/sessions/{sid}/stream", max_size=None) as ws, httpx.AsyncClient(timeout=WAIT_S) as c:
            start = int((await _opened(ws))["frame"])
            long = asyncio.create_task(c.post(f"{a.url}/v1/sessions/{sid}/controls", json={"sketch": ARROW, "method": "constant", "frames": 1000}))
            reader = asyncio.create_task(read(ws))
            deadline = time.monotonic() + WAIT_S
            while not _controls(events) and not reader.done() and time.monotonic() < deadline:
                await asyncio.sleep(0.01)
            running = _controls(events)[0]
            assert running["status"] == "running", running
            # late viewers, joined mid-control
            async with (
                websockets.connect(f"{a.ws_url}/v1/sessions/{sid}/stream", max_size=None) as la,
                websockets.connect(f"{b.ws_url}/v1/sessions/{sid}/stream", max_size=None) as lb,
            ):
                late = [asyncio.create_task(_told_of(w, running)) for w in (la, lb)]
                refused = [await c.post(f"{b.url}/v1/sessions/{sid}/controls", json={"sketch": ARROW, "method": "constant", "frames": 5}) for _ in range(3)]
                assert [r.status_code for r in refused] == [409] * 3, [r.text[:80] for r in refused]
                assert (await long).status_code == 200
                await reader
                told = [await t for t in late]
        return events, told, running, start

    try:
        _start(a, b)
        with httpx.Client(base_url=a.url, timeout=WAIT_S) as ca:
            sid = ca.post("/v1/sessions", json={"scene": SCENE, "solver": SOLVER, "seed": SEED}).json()["id"]
            events, told, running, start = asyncio.run(go(sid))
            for t in told:
                _check_told(t, running, start, 1000)
            assert [e["status"] for e in _controls(events)] == ["running", "done"], _controls(events)
            ca.delete(f"/v1/sessions/{sid}")
    finally:
        a.stop()
        b.stop()


def test_cluster_and_front_ends_restarted_on_the_store_bring_the_session_back(cluster, tmp_path):
    store = tmp_path / "store"
    a = _front_end(cluster, store, tmp_path / "a.log")
    try:
        _start(a)
        with httpx.Client(base_url=a.url, timeout=WAIT_S) as c:
            sid = c.post("/v1/sessions", json={"scene": SCENE, "solver": SOLVER, "seed": 4}).json()["id"]
            step_binary(c, sid, 6)
            saved = wait_saved(c, sid, WAIT_S)
    finally:
        a.stop()
    cluster.stop()
    cluster.start()
    a, b = _front_end(cluster, store, tmp_path / "a2.log"), _front_end(cluster, store, tmp_path / "b2.log")
    try:
        _start(a, b)
        with httpx.Client(base_url=b.url, timeout=WAIT_S) as c:
            info = c.get(f"/v1/sessions/{sid}").json()
            assert info["frame"] == info["restored_from_frame"] == saved == 6
            ref = make_simulator(SCENE, SOLVER, seed=4, threads=1, nn_threads=1)
            rollout(ref, saved)
            assert np.array_equal(step_binary(c, sid, 3), rollout(ref, 3).positions[1:])
            assert c.get("/healthz").json()["sessions"] == 1
    finally:
        a.stop()
        b.stop()


def test_an_actor_killed_during_a_control_keeps_the_steps_answered_before_it(cluster, tmp_path):
    """Steps answered just before a control are durable (the actor saves when the control starts, while its
    lock is held for the whole control): its process killed mid-control (SIGKILL), the session comes back at
    the control's start frame, not at an older periodic save; the control answers 503 and a viewer sees it
    end (not "running" forever while the frame jumps back)."""
    a = _front_end(cluster, tmp_path / "store", tmp_path / "a.log")

    async def go(sid: str, victim_of: Callable[[], int]) -> tuple[list[dict[str, Any]], int]:
        events: list[dict[str, Any]] = []
        async with websockets.connect(f"{a.ws_url}/v1/sessions/{sid}/stream", max_size=None) as ws, httpx.AsyncClient(timeout=WAIT_S) as c:
            # attached first (the stream's meta, then the current frame): a control started before the viewer is
            # attached sends its "running" event to nobody (seen under load on two test workers)
            while not isinstance(await asyncio.wait_for(ws.recv(), WAIT_S), bytes):
                pass
            long = asyncio.create_task(c.post(f"{a.url}/v1/sessions/{sid}/controls", json={"sketch": ARROW, "method": "constant", "frames": 1000}))
            deadline = time.monotonic() + WAIT_S
            while not any(e.get("status") == "running" for e in events) and time.monotonic() < deadline:
                m = await asyncio.wait_for(ws.recv(), WAIT_S)
                if isinstance(m, str) and '"control"' in m:
                    events.append(json.loads(m))
            os.kill(victim_of(), signal.SIGKILL)
            answer = await long
            with contextlib.suppress(websockets.exceptions.ConnectionClosed, TimeoutError):  # the end event comes before any close
                while not any(e.get("status") != "running" for e in events) and time.monotonic() < deadline:
                    m = await asyncio.wait_for(ws.recv(), 30)
                    if isinstance(m, str) and '"control"' in m:
                        events.append(json.loads(m))
        return events, answer.status_code

    try:
        _start(a)
        with httpx.Client(base_url=a.url, timeout=WAIT_S) as c:
            before = set(cluster.actor_pids())
            sid = c.post("/v1/sessions", json={"scene": SCENE, "solver": SOLVER, "seed": SEED}).json()["id"]
            mine = set(cluster.actor_pids()) - before
            assert len(mine) == 1, mine
            step_binary(c, sid, 40)  # answered; the periodic save (every 0.3 s) may not have caught it yet
            events, status = asyncio.run(go(sid, lambda: next(iter(mine))))
            assert status == 503, status
            assert [e["status"] for e in events][:1] == ["running"] and len(events) >= 2 and events[-1]["status"] != "running", events
            info = c.get(f"/v1/sessions/{sid}").json()
            assert info["restored_from_frame"] == 40 and info["frame"] == 40, info
            c.delete(f"/v1/sessions/{sid}")
    finally:
        a.stop()


def test_a_dead_node_s_sessions_come_back_on_a_live_node(cluster, tmp_path):
    """The second node's processes killed (its raylet, its workers: a machine
    lost): its session's actor is rebuilt on the head from the last save and
    goes on bit for bit; the head's session is untouched."""
    from hybridmpm.service.testing import descendants

    store = tmp_path / "store"
    a = _front_end(cluster, store, tmp_path / "a.log")
    try:
        _start(a)
        with httpx.Client(base_url=a.url, timeout=WAIT_S) as c:
            others = set(cluster.actor_pids())  # earlier tests' sessions live on in the cluster
            sessions = {}  # id -> seed
            for seed in range(10, 14):  # placed by SPREAD: until one lands on the second node
                r = c.post("/v1/sessions", json={"scene": SCENE, "solver": SOLVER, "seed": seed})
                assert r.status_code == 201, r.text
                sessions[r.json()["id"]] = seed
                node1 = set(descendants([cluster.procs[1].pid])) - others
                if len(sessions) >= 2 and node1 & set(cluster.actor_pids()):
                    break
            assert node1 & set(cluster.actor_pids()), "no session's actor was placed on the second node"
            on_node1 = len(node1 & set(cluster.actor_pids()))
            saved = {}
            for sid in sessions:
                step_binary(c, sid, 5)
                saved[sid] = wait_saved(c, sid, WAIT_S)
            for pid in reversed(descendants([cluster.procs[1].pid])):
                with contextlib.suppress(ProcessLookupError):
                    os.kill(pid, signal.SIGKILL)
            cluster.procs[1].wait(WAIT_S)
            restored = 0
            for sid, seed in sessions.items():
                ref = make_simulator(SCENE, SOLVER, seed=seed, threads=1, nn_threads=1)
                rollout(ref, saved[sid])
                assert np.array_equal(step_binary(c, sid, 3), rollout(ref, 3).positions[1:]), "a session differs after its node died"
                info = c.get(f"/v1/sessions/{sid}").json()
                restored += info["restored_from_frame"] == saved[sid]
            assert restored == on_node1  # the dead node's sessions were restored, the head's were not
            head = set(descendants([cluster.procs[0].pid]))
            assert set(cluster.actor_pids()) <= head
    finally:
        a.stop()
        cluster.stop()  # the next test that needs it starts it again
        cluster.start()


def test_node_loads_count_the_fresh_reports_of_a_node_and_expire_the_silent_ones():
    from hybridmpm.service.ray_backend.shares import NodeLoads

    now = [0.0]
    loads = NodeLoads(clock=lambda: now[0], expire_s=3.0)
    assert loads.report("n1", "a", 1) == 1 and loads.report("n1", "b", 2) == 3 and loads.report("n2", "c", 1) == 1
    now[0] = 2.0
    assert loads.report("n1", "a", 1) == 3  # b's report is 2 s old: it counts
    now[0] = 4.0
    assert loads.report("n1", "a", 1) == 1  # b's is 4 s old (its actor died): gone; a's renewed at 2 s counts
    assert loads.report("n1", "a", 0) == 0 and "n1" not in loads.nodes  # a stopped
    assert loads.report("n2", "d", 1) == 1 and "c" not in loads.nodes["n2"]  # c's (at 0 s) expired meanwhile
    loads.drop("d")  # deleted: gone from its node at once
    assert loads.nodes == {}


def test_a_share_reporter_never_waits_and_reports_at_most_every_refresh():
    from concurrent.futures import Future

    from hybridmpm.service.capacity import share_of
    from hybridmpm.service.ray_backend.shares import SHARE_REFRESH_S, ShareReporter

    sent: list[tuple[str, str, int]] = []
    futures: list[Future] = []

    class Call:
        def remote(self, *args):
            sent.append(args)
            f: Future = Future()
            futures.append(f)
            return type("Ref", (), {"future": lambda _: f})()

    registry = type("Registry", (), {"realtime": Call()})()
    now, shares = [0.0], []
    r = ShareReporter(registry, "n1", "k" * 64, 1, shares.append, clock=lambda: now[0])
    r.tick()
    r.tick()  # unanswered and too soon: nothing sent
    assert sent == [("n1", "k" * 64, 1)] and shares == []
    now[0] = 2 * SHARE_REFRESH_S
    r.tick()  # still unanswered: no second report piles up
    assert len(sent) == 1
    futures[0].set_result((4, 2.0))  # 4 threads play on a node of 2 CPUs
    assert shares == [share_of(4, 2.0)]
    r.tick()
    futures[1].set_result((1, None))  # a node the cluster does not know: the share stays
    now[0] += SHARE_REFRESH_S / 2
    r.tick()
    assert len(sent) == 2 and shares == [share_of(4, 2.0)]
    r.stop()
    assert sent[-1] == ("n1", "k" * 64, 0)


# Stands in for an environment without Ray: the local backend needs none, the ray backend says what is missing.
_NO_RAY = """
import sys
from importlib.abc import MetaPathFinder

class NoRay(MetaPathFinder):
    def find_spec(self, name, path=None, target=None):
        if name.split(".")[0] == "ray":
            raise ImportError(f"{name} is not installed (the cluster extra)")
        return None

sys.meta_path.insert(0, NoRay())
from hybridmpm.errors import InvalidInputError
from hybridmpm.service import ServiceConfig, create_app
create_app(ServiceConfig(max_sessions=2))
assert not [m for m in sys.modules if m.split(".")[0] == "ray"]
try:
    create_app(ServiceConfig(backend="ray"))
except InvalidInputError as e:
    assert "hybridmpm[cluster]" in str(e), e
    print(e.field)
"""


def test_settings_that_name_no_cluster_are_refused_naming_the_field(tmp_path):
    for kw, name in [
        ({"backend": "grid"}, "backend"),
        ({"backend": "ray", "ray_address": "10.0.0.5"}, "ray_address"),
        ({"backend": "ray", "ray_address": "10.0.0.5:99999"}, "ray_address"),
        ({"backend": "ray", "ray_num_cpus": 0}, "ray_num_cpus"),
        ({"backend": "ray", "store": "memory://sessions"}, "store"),
    ]:
        with pytest.raises(InvalidInputError) as e:
            ServiceConfig(**kw)
        assert e.value.field == name, (kw, e.value)
    out = subprocess.run([sys.executable, "-c", _NO_RAY], capture_output=True, text=True, timeout=WAIT_S)
    assert out.returncode == 0 and out.stdout.strip() == "backend", out.stderr[-1000:]
    out = subprocess.run(
        [sys.executable, "-m", "hybridmpm", "serve", "--backend", "ray", "--ray-address", f"127.0.0.1:{free_port()}", "--port", "0"],
        capture_output=True,
        text=True,
        timeout=WAIT_S,
    )
    assert out.returncode == 2 and "ray_address" in out.stderr, out.stderr[-500:]


def test_the_registry_holds_the_store_so_a_plain_server_is_refused_on_it(cluster, tmp_path):
    """One writer per store on a cluster too: the namespace's registry holds the store's lock for every front
    end, so a plain server started on that store is refused (exit 2, naming the store and the registry), even
    after the front ends stopped (the sessions' actors live on and save into it)."""
    store = tmp_path / "store"
    with _front_end(cluster, store, tmp_path / "a.log") as a:
        with httpx.Client(base_url=a.url, timeout=WAIT_S) as c:
            r = c.post("/v1/sessions", json={"scene": SCENE, "solver": SOLVER, "seed": SEED})
            assert r.status_code == 201
            # an obstacle move goes through the actor too (this scene has none: 422 naming the index)
            moved = c.put(f"/v1/sessions/{r.json()['id']}/obstacles/0", json={"center": [0.5, 0.5]})
            assert moved.status_code == 422 and moved.json()["detail"][0]["loc"] == ["path", "index"], moved.text
        with pytest.raises(InvalidInputError) as e:
            SessionStore(str(store)).claim()
        assert e.value.field == "store" and "Ray registry" in str(e.value), e.value
    out = subprocess.run([sys.executable, "-m", "hybridmpm", "serve", "--store", str(store), "--port", "0"], capture_output=True, text=True, timeout=WAIT_S)
    assert out.returncode == 2 and "store" in out.stderr and "Ray registry" in out.stderr, out.stderr[-500:]


def test_bodies_added_and_removed_through_two_front_ends_survive_a_killed_actor(cluster, tmp_path):
    # crates2d's four boxes, a ball added through A and the first box removed through B: the session's bodies and frames
    # are a local run's with the same changes, bit for bit, before and after its actor is killed (restored from the store)
    store = tmp_path / "store"
    ball = {"shape": "circle", "center": [0.3, 0.7], "radius": 0.04, "density": 700.0, "velocity": [0.5, 0.0]}
    ref = make_simulator("crates2d", "mpm", seed=1, threads=1)
    a, b = _front_end(cluster, store, tmp_path / "a.log"), _front_end(cluster, store, tmp_path / "b.log")
    try:
        _start(a, b)
        with httpx.Client(base_url=a.url, timeout=WAIT_S) as ca, httpx.Client(base_url=b.url, timeout=WAIT_S) as cb:
            before = set(cluster.actor_pids())  # earlier tests' sessions live on in the cluster
            r = ca.post("/v1/sessions", json={"scene": "crates2d", "solver": "mpm", "seed": 1})
            assert r.status_code == 201, r.text
            sid = r.json()["id"]
            mine = set(cluster.actor_pids()) - before
            assert len(mine) == 1, (before, mine)
            assert np.array_equal(step_binary(cb, sid, 3), rollout(ref, 3).positions[1:])
            r = ca.post(f"/v1/sessions/{sid}/bodies", json=ball)
            assert r.status_code == 201 and r.json()["index"] == 4 and r.json()["num_bodies"] == 5, r.text
            assert ref.add_body(ball) == 4
            r = cb.delete(f"/v1/sessions/{sid}/bodies/0")
            assert r.status_code == 200 and r.json()["num_bodies"] == 4, r.text
            ref.remove_body(0)
            assert np.array_equal(step_binary(ca, sid, 4), rollout(ref, 4).positions[1:])
            info = cb.get(f"/v1/sessions/{sid}").json()
            assert [x["shape"] for x in info["bodies"]] == ["box", "box", "box", "circle"], info["bodies"]
            assert np.array_equal(np.array([x["center"] for x in info["bodies"]]), ref.bodies.center)
            saved = wait_saved(ca, sid, WAIT_S)
            rollout(ref, saved - info["frame"])
            os.kill(mine.pop(), signal.SIGKILL)
            after = step_binary(cb, sid, 3)
            assert np.array_equal(after, rollout(ref, 3).positions[1:]), "the restored run differs"
            info = ca.get(f"/v1/sessions/{sid}").json()
            assert info["restored_from_frame"] == saved and len(info["bodies"]) == 4
            assert np.array_equal(np.array([x["center"] for x in info["bodies"]]), ref.bodies.center)
    finally:
        a.stop()
        b.stop()


def test_real_time_actors_share_their_node_s_cpus_by_the_local_rule(cluster, tmp_path):
    """Three real-time sessions play, one viewer each: each actor's share (its description's ``realtime.share``)
    is the local backend's rule for the real-time sessions playing on its node (``share_of(k, 1)``: each node
    offers one CPU). One session of the fullest node left playing alone (one paused, one deleted), its share is
    the rule's for one alone."""
    from hybridmpm.service.capacity import share_of
    from hybridmpm.service.testing import descendants

    a = _front_end(cluster, tmp_path / "store", tmp_path / "a.log")

    async def shares_become(c: httpx.AsyncClient, want: dict[str, float]) -> None:
        got: dict[str, float] = {}
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline:
            got = {sid: (await c.get(f"{a.url}/v1/sessions/{sid}")).json()["realtime"]["share"] for sid in want}
            if all(got[sid] == pytest.approx(v, abs=1e-3) for sid, v in want.items()):
                return
            await asyncio.sleep(0.2)
        raise AssertionError(f"shares {got}, the rule's {want}")

    async def go(node_of: dict[str, int]) -> None:
        async def drain(ws) -> None:  # a viewer that stops reading stalls its socket
            with contextlib.suppress(websockets.exceptions.ConnectionClosed):
                while True:
                    await ws.recv()

        async with contextlib.AsyncExitStack() as stack, httpx.AsyncClient(timeout=WAIT_S) as c:
            socks = {}
            for sid in node_of:
                ws = socks[sid] = await stack.enter_async_context(websockets.connect(f"{a.ws_url}/v1/sessions/{sid}/stream", max_size=None))
                await _opened(ws)
                await ws.send('{"type": "play"}')
            readers = [asyncio.create_task(drain(ws)) for ws in socks.values()]
            on = {n: [s for s in node_of if node_of[s] == n] for n in set(node_of.values())}
            await shares_become(c, {sid: share_of(len(on[n]), 1) for sid, n in node_of.items()})
            alone, *others = max(on.values(), key=len)  # at least two: three sessions on two nodes
            await socks[others[0]].send('{"type": "pause"}')
            for sid in [*others[1:], *(s for s in node_of if node_of[s] != node_of[alone])]:
                assert (await c.delete(f"{a.url}/v1/sessions/{sid}")).status_code == 204
            await shares_become(c, {alone: share_of(1, 1)})
            for t in readers:
                t.cancel()

    try:
        _start(a)
        with httpx.Client(base_url=a.url, timeout=WAIT_S) as c:
            node_of = {}  # session id -> the node its actor runs on
            for seed in range(3):
                before = set(cluster.actor_pids())
                r = c.post("/v1/sessions", json={"scene": SCENE, "realtime": True, "seed": seed})
                assert r.status_code == 201, r.text
                (pid,) = set(cluster.actor_pids()) - before
                node_of[r.json()["id"]] = next(i for i, p in enumerate(cluster.procs) if pid in descendants([p.pid]))
            asyncio.run(go(node_of))
    finally:
        a.stop()
