"""The capacity benchmark (benchmarks/bench_capacity.py): its arithmetic on
hand-made records, and a ``--quick`` run against a real server whose
per-session rates must stay under what the play loop's pacing allows (an
unpaced loop steps water2d thousands of frames a second) and whose reported
capacity must agree with its rows."""

from __future__ import annotations

import importlib.util
import json
from pathlib import Path

import pytest

pytest.importorskip("fastapi")
pytest.importorskip("httpx")
pytest.importorskip("websockets")

SCRIPT = Path(__file__).resolve().parents[1] / "benchmarks" / "bench_capacity.py"


@pytest.fixture(scope="module")
def cap():
    spec = importlib.util.spec_from_file_location("bench_capacity_script", SCRIPT)
    assert spec is not None and spec.loader is not None
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_ladder_and_capacity_on_hand_made_rows(cap):
    assert cap.ladder(12) == [1, 2, 4, 6, 8, 10, 12]
    assert cap.ladder(3) == [1, 2]
    rows = [{"sessions": n, "all_real_time": ok} for n, ok in [(1, True), (2, True), (4, True), (6, False), (8, True)]]
    assert cap.capacity(rows) == 4  # the first failing rung ends it, a later pass does not count
    assert cap.capacity([{"sessions": 1, "all_real_time": False}]) == 0
    # the fill-in after a failing rung comes after it in the rows: 6 failed, then 5 held
    filled = [{"sessions": n, "all_real_time": ok} for n, ok in [(1, True), (2, True), (4, True), (6, False), (5, True)]]
    assert cap.capacity(filled) == 5


def test_engine_bound_counts_the_seeds_whose_engine_work_fits_the_cores(cap):
    # 1 ms a frame at 400 frames/s is 0.4 of a core: five such sessions fit on 2 cores, not six
    assert cap.engine_bound([1.0] * 8, 0.0025, 2.0) == 5
    assert cap.engine_bound([0.25, 1.6, 1.2], 0.0025, 2.0) == 3  # 0.1 + 0.64 + 0.48 cores
    assert cap.engine_bound([6.0], 0.0025, 2.0) == 0  # one session alone needs 2.4 cores
    assert cap.engine_bound([0.5, 6.0, 0.1], 0.0025, 2.0) == 1  # seeds are taken in order: a heavy seed ends the count
    assert cap.engine_bound([], 0.0025, 2.0) == 0


def test_stream_rate_reads_the_window_of_frame_numbers(cap):
    # a session at exactly 400 frames/s seen 60 times a second from t = 0; the window [1, 3] s
    seen = [(k / 60, int(400 * k / 60)) for k in range(240)]
    r = cap.stream_rate(seen, 1.0, 3.0)
    assert r == pytest.approx(400, rel=0.01)
    assert cap.holds(r, 0.0025) and not cap.holds(0.9 * 400, 0.0025)
    assert cap.stream_rate(seen[:1], 0.0, 10.0) == 0.0
    assert cap.stream_rate(seen, 10.0, 11.0) == 0.0


def test_rate_bound_admits_real_time_and_refuses_an_unpaced_loop(cap):
    b = cap.rate_bound(0.0025, 1, 4.0)
    assert 400 < b < 400 * 1.1  # 4 s window: catch-up 0.25 s, two send gaps, one step
    assert cap.rate_bound(0.0025, 1, 1.0) > cap.rate_bound(0.0025, 1, 4.0)  # a shorter window admits more catch-up per second


def test_quick_run_against_a_real_server(cap, tmp_path: Path):
    doc = cap.main(["--quick", "--out-dir", str(tmp_path), "--server-log", str(tmp_path / "server.log")])
    rows = doc["rows"]
    assert [r["sessions"] for r in rows] == cap.ladder(2)[: len(rows)]
    assert doc["capacity"] == cap.capacity(rows)
    assert all(r["all_real_time"] for r in rows[:-1])  # the ladder stops at the first failing rung
    for r in rows:
        assert r["solver"] == "default" and r["dt_frame"] == pytest.approx(0.0025)
        assert len(r["rates"]) == r["sessions"]
        bound = cap.rate_bound(r["dt_frame"], r["r_t"], r["window_s"])
        assert 0 < min(r["rates"]) and max(r["rates"]) <= bound, (r["rates"], bound)  # the play loop paces every session
        assert r["all_real_time"] == all(cap.holds(x, r["dt_frame"]) for x in r["rates"])
        assert r["probe_steps"] >= 1 and r["step_p95_ms"] >= r["step_p50_ms"] > 0
        assert len(r["particles"]) == len(r["engine_ms_per_frame"]) == r["sessions"]
        assert r["engine_cores"] == pytest.approx(sum(r["engine_ms_per_frame"]) / 1e3 / r["dt_frame"])
    cost = doc["engine_ms_by_seed"]
    assert len(cost) >= max(r["sessions"] for r in rows) and doc["engine_bound"] == cap.engine_bound(cost, rows[0]["dt_frame"], doc["cores"])
    saved = json.loads((tmp_path / "capacity.json").read_text())
    assert saved["capacity"] == doc["capacity"] and "provenance" in saved
    assert f"Sessions held at real time: {doc['capacity']}" in (tmp_path / "capacity.md").read_text()
    assert f"The engine alone bounds it at {doc['engine_bound']} sessions" in (tmp_path / "capacity.md").read_text()
