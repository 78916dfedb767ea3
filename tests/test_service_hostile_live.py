"""Hostile clients against a real server (``hybridmpm serve`` on 127.0.0.1 in
a child process): heavy JSON steps do not stall the event loop, small PNGs
that decode big do not blow up the memory, session ids stay out of the
access log, forged Host headers are refused, slow headers are cut off, and a
control whose client leaves stops."""

from __future__ import annotations

import asyncio
import socket
import struct
import subprocess
import sys
import threading
import time
import zlib
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("fastapi")
httpx = pytest.importorskip("httpx")
websockets = pytest.importorskip("websockets")
ws_exceptions = pytest.importorskip("websockets.exceptions")

from hybridmpm.service.testing import LiveServer  # noqa: E402

ARROW = {"kind": "arrow", "points": [[0.2, 0.3], [0.5, 0.3]]}


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    log = tmp_path_factory.mktemp("hostile") / "server.log"
    env = {"HYBRIDMPM_HEADER_TIMEOUT_S": "1", "HYBRIDMPM_MAX_SESSIONS_PER_CLIENT": "40"}
    with LiveServer(max_sessions=40, env=env, log=log, args=["--log-level", "info"]) as s:
        s.log_path = log
        yield s


def vm(pid: int, key: str) -> int:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith(key + ":"):
            return int(line.split()[1]) * 1024
    raise KeyError(key)


PROBE = """
import sys, time, urllib.request
url, out = sys.argv[1], []
while True:
    t0 = time.perf_counter()
    with urllib.request.urlopen(url + "/healthz", timeout=30) as r:
        assert r.status == 200
    out.append(time.perf_counter() - t0)
    try:
        open(sys.argv[2]).close()
        break
    except OSError:
        time.sleep(0.02)
print(" ".join(f"{x:.6f}" for x in out))
"""


def probe_healthz(url: str, stop_file: Path) -> subprocess.Popen:
    """/healthz round trips [s] over fresh connections from another process
    (a client in this process would measure its own stalls parsing JSON)
    until ``stop_file`` exists; its stdout lists them."""
    return subprocess.Popen([sys.executable, "-c", PROBE, url, str(stop_file)], stdout=subprocess.PIPE, text=True)


def test_healthz_stays_fast_while_four_clients_pull_100_frame_json_steps(server, tmp_path):
    """Four clients each pull 100-frame JSON steps of dam_break2d (19 MB of
    JSON each) while another process polls /healthz: the JSON is encoded off
    the event loop, so /healthz answers fast throughout: p95 under 50 ms and
    every answer under 400 ms (on the old code, with the encoding on the
    loop, it waited up to seconds). Measured on a quiet 2-core machine: p95
    15-20 ms, max 98-197 ms (single scheduler or collector pauses), so a
    100 ms bound on the max failed there on unchanged code."""

    async def run() -> None:
        # one connection per request: a pooled connection left idle past the server's 5 s keep-alive
        # while the other clients' steps run can be closed as the next step is sent on it (an HTTP/1.1
        # race every client meets; seen here once as "Server disconnected without sending a response")
        no_reuse = httpx.Limits(max_keepalive_connections=0)
        async with httpx.AsyncClient(base_url=server.url, timeout=120, limits=no_reuse) as c:
            ids = []
            for _ in range(4):
                r = await c.post("/v1/sessions", json={"scene": "dam_break2d", "solver": "mpm"})
                assert r.status_code == 201, r.text
                ids.append(r.json()["id"])
            sizes: list[int] = []

            async def pull(sid: str) -> None:
                for _ in range(2):
                    r = await c.post(f"/v1/sessions/{sid}/step", json={"frames": 100})
                    assert r.status_code == 200, r.text[:200]
                    sizes.append(len(r.content))

            probe = probe_healthz(server.url, tmp_path / "stop")
            try:
                await asyncio.gather(*(pull(s) for s in ids))
            finally:
                (tmp_path / "stop").touch()
                lat_ms = np.array([float(x) for x in probe.communicate(timeout=60)[0].split()]) * 1e3
            for s in ids:
                await c.delete(f"/v1/sessions/{s}")
            assert min(sizes) > 10e6  # the heavy answers really were made
            print(f"/healthz under load: n={len(lat_ms)} p50 {np.median(lat_ms):.1f} p95 {np.percentile(lat_ms, 95):.1f} max {lat_ms.max():.1f} ms")
            assert len(lat_ms) >= 10
            assert np.percentile(lat_ms, 95) < 50, np.percentile(lat_ms, 95)
            assert lat_ms.max() < 400, lat_ms.max()

    asyncio.run(run())


def png_16bit_rgba(size: int = 2048, colour: tuple[int, int, int, int] = (1000, 40000, 20000, 65535)) -> bytes:
    """A one-colour 16-bit RGBA PNG: about 32 KB on the wire, 2048² pixels once decoded."""
    row = b"\x01" + struct.pack(">4H", *colour) + bytes(8 * (size - 1))  # filter "Sub": each pixel as the difference to the one before
    raw = zlib.compress(row * size, 9)

    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF)

    ihdr = struct.pack(">IIBBBBB", size, size, 16, 6, 0, 0, 0)
    return b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IDAT", raw) + chunk(b"IEND", b"")


def test_ten_small_pngs_that_decode_big_stay_within_200_mb(server):
    png = png_16bit_rgba()
    assert len(png) < 40_000  # within the raw PNG body cap

    peak: list[int] = []

    async def run() -> list[int]:
        async with httpx.AsyncClient(base_url=server.url, timeout=120) as c:
            r = await c.post("/v1/sessions", json={"scene": "water2d", "solver": "mpm"})
            sid = r.json()["id"]
            url = f"/v1/sessions/{sid}/controls/png?frames=4"
            await c.post(url, content=png, headers={"Content-Type": "image/png"})  # the modules it needs are loaded
            peak.append(vm(server.proc.pid, "VmHWM"))
            rs = await asyncio.gather(*(c.post(url, content=png, headers={"Content-Type": "image/png"}) for _ in range(10)))
            await c.delete(f"/v1/sessions/{sid}")
            return [x.status_code for x in rs]

    t0 = time.perf_counter()
    codes = asyncio.run(run())
    wall = time.perf_counter() - t0
    growth = vm(server.proc.pid, "VmHWM") - peak[0]
    print(f"ten 2048² 16-bit PNGs: {wall:.2f} s, peak RSS growth {growth / 2**20:.0f} MiB, answers {codes}")
    assert set(codes) <= {422, 503}, codes  # one colour: no stroke in it
    assert growth < 200 * 2**20


def test_no_full_session_id_in_the_logs(server):
    with httpx.Client(base_url=server.url, timeout=60) as c:
        sid = c.post("/v1/sessions", json={"scene": "water2d", "solver": "mpm"}).json()["id"]
        assert c.post(f"/v1/sessions/{sid}/step", json={"frames": 2}).status_code == 200
        assert c.get(f"/v1/sessions/{sid}/checkpoint").status_code == 200
        assert c.post(f"/v1/sessions/{sid}/step", json={"frames": "x"}).status_code == 422
        assert c.get(f"/v1/sessions/{sid}/controls/nope").status_code == 404

        async def ws() -> None:
            async with websockets.connect(f"{server.ws_url}/v1/sessions/{sid}/stream") as w:
                await w.recv()

        asyncio.run(ws())
        assert c.delete(f"/v1/sessions/{sid}").status_code == 204
    deadline = time.monotonic() + 30  # the access log is written as requests end: wait for the delete's line
    while f"DELETE /v1/sessions/{sid[:6]}…" not in server.log_path.read_text(errors="replace") and time.monotonic() < deadline:
        time.sleep(0.05)
    text = server.log_path.read_text(errors="replace")
    assert f"/v1/sessions/{sid[:6]}…/step" in text  # the access log is on, and shows the prefix
    assert sid not in text and sid[6:] not in text


def test_forged_host_is_refused_on_a_loopback_server(server):
    with httpx.Client(base_url=server.url, timeout=30) as c:
        assert c.get("/healthz").status_code == 200
        assert c.get("/healthz", headers={"Host": f"localhost:{server.port}"}).status_code == 200
        assert c.get("/healthz", headers={"Host": "evil.example"}).status_code == 400
        sid = c.post("/v1/sessions", json={"scene": "water2d", "solver": "mpm"}).json()["id"]

    async def ws() -> None:
        hdrs = {"Host": "evil.example", "Origin": "http://evil.example"}
        with pytest.raises(ws_exceptions.InvalidStatus) as e:
            async with websockets.connect(f"{server.ws_url}/v1/sessions/{sid}/stream", additional_headers=hdrs) as w:
                await w.recv()
        assert e.value.response.status_code == 400

    asyncio.run(ws())


def test_partial_headers_are_cut_off(server):
    """A client that sends half a request line and then nothing is
    disconnected after the header timeout (1 s here), not held forever."""
    with socket.create_connection(("127.0.0.1", server.port), timeout=10) as s:
        s.sendall(b"GET /healthz HTTP/1.1\r\nHost: 127.0.0.1\r\nX-Slow: ")
        t0 = time.monotonic()
        s.settimeout(10)
        data = s.recv(100)  # b"" when the server closes
        waited = time.monotonic() - t0
    assert data == b"" and waited < 5, (data, waited)
    # a complete request on a fresh connection is served as usual
    with httpx.Client(base_url=server.url) as c:
        assert c.get("/healthz").status_code == 200


def test_a_control_whose_client_leaves_is_cancelled(server):
    """A 1000-frame control takes seconds; its client gives up after 0.5 s.
    The control stops (its session slot frees with the session short of
    1000 frames) instead of running on to the end."""
    with httpx.Client(base_url=server.url, timeout=60) as c:
        sid = c.post("/v1/sessions", json={"scene": "dam_break2d", "solver": "mpm"}).json()["id"]
        with pytest.raises(httpx.TimeoutException):
            c.post(f"/v1/sessions/{sid}/controls", json={"sketch": ARROW, "frames": 1000}, timeout=0.5)
        t0 = time.monotonic()
        while time.monotonic() - t0 < 60:
            r = c.post(f"/v1/sessions/{sid}/controls", json={"sketch": ARROW, "frames": 2})
            if r.status_code != 409:
                break
            time.sleep(0.1)
        freed = time.monotonic() - t0
        assert r.status_code == 200, r.text
        frame = c.get(f"/v1/sessions/{sid}").json()["frame"]
        print(f"slot free {freed:.2f} s after the client left; session at frame {frame}")
        assert frame < 1000  # run to its end, the control would have left it at frame 1000 + 2
        c.delete(f"/v1/sessions/{sid}")


def test_a_session_deleted_during_its_control_stops_it_and_returns_every_byte(server):
    """Sessions deleted 0.3 s into a 1000-frame control: each control stops within a frame and answers 404
    (not 200 after running to its end), and the memory budget goes back to what it was before the sessions
    (the control's frames used to be recorded into the budget again after the delete had given it back)."""

    async def go() -> None:
        async with httpx.AsyncClient(base_url=server.url, timeout=120) as c:
            base = (await c.get("/healthz")).json()["memory_used"]
            sids = [(await c.post("/v1/sessions", json={"scene": "dam_break2d", "solver": "mpm", "seed": i})).json()["id"] for i in range(4)]
            t0 = time.monotonic()
            controls = [asyncio.create_task(c.post(f"/v1/sessions/{sid}/controls", json={"sketch": ARROW, "frames": 1000})) for sid in sids]
            deadline = time.monotonic() + 60  # deleted once a control runs (two run at once on the two compute slots)
            while time.monotonic() < deadline and not any([(await c.get(f"/v1/sessions/{sid}")).json().get("control") for sid in sids]):
                await asyncio.sleep(0.02)
            for sid in sids:
                assert (await c.delete(f"/v1/sessions/{sid}")).status_code == 204
            answers = await asyncio.gather(*controls)
            took = time.monotonic() - t0
            assert [r.status_code for r in answers] == [404] * 4, [r.text[:80] for r in answers]
            deadline = time.monotonic() + 30  # a deleted session's record goes off the event loop: wait for it
            while (h := (await c.get("/healthz")).json())["memory_used"] != base and time.monotonic() < deadline:
                await asyncio.sleep(0.05)
            assert h["memory_used"] == base, (h["memory_used"], base)
            print(f"4 controls stopped {took:.2f} s after they started")

    asyncio.run(go())


def test_a_binary_websocket_message_gets_a_close_frame(server):
    """Binary messages are not part of the protocol: the server closes with
    1003 and a close frame (not a dropped connection, 1006)."""
    with httpx.Client(base_url=server.url, timeout=30) as c:
        sid = c.post("/v1/sessions", json={"scene": "water2d", "solver": "mpm"}).json()["id"]

    async def run() -> None:
        async with websockets.connect(f"{server.ws_url}/v1/sessions/{sid}/stream") as w:
            await w.recv()
            await w.send(b"\x00\x01")
            with pytest.raises(ws_exceptions.ConnectionClosed) as e:
                for _ in range(100):
                    await asyncio.wait_for(w.recv(), 10)
            assert e.value.rcvd is not None and e.value.rcvd.code == 1003, e.value

    asyncio.run(run())


def peak_budget_during(url: str, request: Callable[[], httpx.Response]) -> tuple[httpx.Response, int]:
    """``request()``'s answer and the most bytes of the memory budget held while it ran (/healthz polled every 20 ms)."""
    peak, done = [0], threading.Event()

    def poll() -> None:
        with httpx.Client(base_url=url, timeout=30) as c2:
            while not done.is_set():
                peak[0] = max(peak[0], c2.get("/healthz").json()["memory_used"])
                time.sleep(0.02)

    watcher = threading.Thread(target=poll)
    watcher.start()
    try:
        return request(), peak[0]
    finally:
        done.set()
        watcher.join()


# alone: a peak of the server's resident memory reads the machine's load too (the same control grew it 1.05-1.11x
# its reservation on a quiet machine, 1.50x beside the parallel phase's other tests). Even alone, a clean-clone run
# once read 1.50x (+15 MB over its usual 1.07x; three runs alone here read 1.06-1.08x), so a reading past
# the bound is taken once more on the same server; the 3.4x this test was written against fails both.
@pytest.mark.alone
def test_peak_rss_of_the_largest_control_stays_within_1_5x_of_what_the_budget_reserved():
    """The memory budget counts a control's real peak: for the largest control a request may ask (1000 frames,
    the diffusion controller, on 3D sessions: hybrid, whose network runs at r_p, and plain MPM at full
    resolution), the server's peak resident memory grows by at most 1.5x what the budget reserved at its peak
    (a fresh server; the controllers are loaded by two short controls first, so their one-off model and
    arena memory is not counted). It used to grow 3.4x the reservation."""
    with LiveServer(max_sessions=4) as srv, httpx.Client(base_url=srv.url, timeout=300) as c:
        for solver in ("hybrid", "mpm"):
            sid = c.post("/v1/sessions", json={"scene": "water3d", "solver": solver}).json()["id"]
            body = {"method": "diffusion", "sketch": ARROW, "frames": 30}
            for _ in range(2):
                assert c.post(f"/v1/sessions/{sid}/controls", json=body).status_code == 200
            for _ in range(2):  # a second reading only where the first is past the bound (see below)
                base_rss = vm(srv.proc.pid, "VmRSS")
                Path(f"/proc/{srv.proc.pid}/clear_refs").write_text("5")  # VmHWM from here
                base_used = c.get("/healthz").json()["memory_used"]
                r, peak_used = peak_budget_during(srv.url, lambda sid=sid, body=body: c.post(f"/v1/sessions/{sid}/controls", json={**body, "frames": 1000}))
                assert r.status_code == 200, r.text[:200]
                grew, reserved = vm(srv.proc.pid, "VmHWM") - base_rss, peak_used - base_used
                print(f"water3d {solver}: peak RSS +{grew / 1e6:.1f} MB, reserved +{reserved / 1e6:.1f} MB ({grew / reserved:.2f}x)")
                if reserved > 0 and grew <= 1.5 * reserved:
                    break
            assert reserved > 0 and grew <= 1.5 * reserved, (grew, reserved)
            assert c.delete(f"/v1/sessions/{sid}").status_code == 204


def test_a_soak_of_16_mixed_sessions_with_deletes_during_controls(tmp_path):
    """16 mixed sessions (2D and 3D, every solver) driven by 6 clients for 20 s with steps, controls of every
    method, checkpoint round trips, downloads, stream views and deletes during 1000-frame controls, on a durable
    server saving every 0.5 s: no answer is 5xx, every control whose session was deleted answers 404, the ledger
    is back at its start once the sessions are gone, and a witness session stepped in random chunks through it
    all equals an uninterrupted run bit for bit. (``benchmarks/bench_soak.py`` runs it for minutes, and on Ray.)"""
    from hybridmpm.service.testing import SOAK_WITNESS, soak
    from hybridmpm.sim import make_simulator, rollout

    args = ["--store", str(tmp_path / "store"), "--save-every", "0.5"]
    with LiveServer(max_sessions=40, args=args, log=tmp_path / "server.log") as srv:
        seed = int(time.time())  # a fresh mix each run, printed
        rep = asyncio.run(soak(srv.url, 20.0, sessions=16, workers=6, seed=seed))
    codes = rep["statuses"]
    print(f"seed {seed}: {rep['ops']} operations: {dict(sorted(codes.items()))}; witness {len(rep['witness'])} frames")
    assert not any(code >= 500 for code in codes), (codes, (tmp_path / "server.log").read_text()[-3000:])
    assert all(code == 404 for code in rep["deleted_controls"]), rep["deleted_controls"]
    assert rep["memory_used_end"] == rep["memory_used_start"], rep
    scene, solver, seed = SOAK_WITNESS
    assert len(rep["witness"]) > 0
    ref = rollout(make_simulator(scene, solver, seed=seed, threads=1, nn_threads=1), len(rep["witness"])).positions[1:]
    assert np.array_equal(ref, rep["witness"]), "the witness session differs from an uninterrupted run"


def test_an_mpc_control_shares_the_compute_and_stops_when_its_session_or_client_goes(server):
    """A 1000-frame MPC control on dam_break3d (the longest the API allows) plans for about 17 s here on both
    compute slots (the scene steps on two threads). Meanwhile another session's 1-frame steps answer within 2 s
    (the control hands its compute to waiting work between its model rollouts' frames; it used to hold it for the
    whole plan: 22.5 s for a 4 ms step); a DELETE ends the plan within 2 s (the control answers 404), and so does
    a client that leaves (the session's control slot is free again)."""

    async def started(c: httpx.AsyncClient, sid: str, body: dict) -> asyncio.Task:
        """The control posted once a viewer is attached, returned once the viewer hears it runs (it is planning)."""
        async with websockets.connect(f"{server.ws_url}/v1/sessions/{sid}/stream", max_size=None) as ws:
            while not isinstance(await asyncio.wait_for(ws.recv(), 60), bytes):  # attached: the meta, then the frame
                pass
            control = asyncio.create_task(c.post(f"/v1/sessions/{sid}/controls", json=body))
            while not ((m := await asyncio.wait_for(ws.recv(), 120)) and isinstance(m, str) and '"running"' in m):
                pass
        return control

    async def go() -> tuple[list[float], float, float]:
        async with httpx.AsyncClient(base_url=server.url, timeout=120) as c:
            small = (await c.post("/v1/sessions", json={"scene": "water2d", "solver": "mpm"})).json()["id"]
            assert (await c.post(f"/v1/sessions/{small}/step", json={"frames": 1})).status_code == 200
            big = (await c.post("/v1/sessions", json={"scene": "dam_break3d", "solver": "mpm"})).json()["id"]
            body = {"sketch": ARROW, "method": "mpc", "frames": 1000}
            control = await started(c, big, body)
            waits = []
            for _ in range(8):
                t0 = time.monotonic()
                assert (await c.post(f"/v1/sessions/{small}/step", json={"frames": 1})).status_code == 200
                waits.append(time.monotonic() - t0)
            assert max(waits) < 2.0, f"another session's 1-frame steps waited {max(waits):.1f} s for the plan"
            assert not control.done(), "the plan ended before the steps: nothing was measured"
            t0 = time.monotonic()
            assert (await c.delete(f"/v1/sessions/{big}")).status_code == 204
            r = await control
            deleted = time.monotonic() - t0
            assert r.status_code == 404, r.text[:200]
            # its client leaves 1 s in: the plan stops and the session's control slot frees
            big = (await c.post("/v1/sessions", json={"scene": "dam_break3d", "solver": "mpm"})).json()["id"]
            with pytest.raises(httpx.TimeoutException):
                await c.post(f"/v1/sessions/{big}/controls", json=body, timeout=1.0)
            t0 = time.monotonic()
            while time.monotonic() - t0 < 60:
                r = await c.post(f"/v1/sessions/{big}/controls", json={"sketch": ARROW, "method": "constant", "frames": 1})
                if r.status_code != 409:
                    break
                await asyncio.sleep(0.05)
            left = time.monotonic() - t0
            assert r.status_code == 200, r.text[:200]
            for sid in (small, big):
                assert (await c.delete(f"/v1/sessions/{sid}")).status_code == 204
            return waits, deleted, left

    waits, deleted, left = asyncio.run(go())
    print(f"steps during the plan: {max(waits):.3f} s at most; plan ended {deleted:.2f} s after the DELETE, {left:.2f} s after its client left")
    assert deleted < 2.0 and left < 2.0, (deleted, left)
