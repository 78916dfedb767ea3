"""Real-time capacity (hybridmpm.service.capacity): a new real-time session is admitted at its most accurate rung
while the playing ones leave room, at a coarser rung when it asks (``when_full: "coarser"``) and one fits, and
refused with a 503 saying how many play and at what cost otherwise. The playing sessions' load is set through
their measured frame time (nothing here asserts a speed)."""

from __future__ import annotations

import pytest

pytest.importorskip("fastapi")
pytest.importorskip("httpx")

from fastapi.testclient import TestClient  # noqa: E402

from hybridmpm.service import ServiceConfig, create_app  # noqa: E402
from hybridmpm.service.capacity import REALTIME_SHARE, Playing, RealtimeFullError, admit  # noqa: E402
from hybridmpm.service.testing import step_binary  # noqa: E402
from hybridmpm.sim import RealtimeSimulator  # noqa: E402

DT_MS = 2.5


def _chart_ms(sim: RealtimeSimulator) -> dict[str, float]:
    assert sim.chart, "water2d ships a real-time chart"
    return {r["key"]: float(r["ms"]) for r in sim.chart["rungs"]}


def test_admit_takes_the_most_accurate_rung_that_fits_what_the_playing_sessions_leave() -> None:
    sim = RealtimeSimulator("water2d")
    ms = _chart_ms(sim)
    best, coarsest = sim.ladder[0].key, sim.ladder[-1].key
    need = {k: v / DT_MS for k, v in ms.items()}  # one thread, this chart's pace
    capacity = REALTIME_SHARE * 2
    assert admit(sim, 1, [], 2, "refuse") == best
    # the others leave less than the best rung needs but more than the coarsest: refused, or coarser on request
    used = capacity - (need[best] + need[coarsest]) / 2
    others = [Playing(used / 2, 1.0), Playing(used / 2, 1.0)]
    with pytest.raises(RealtimeFullError, match=r"2 real-time sessions play, using .* cores"):
        admit(sim, 1, others, 2, "refuse")
    got = admit(sim, 1, others, 2, "coarser")
    assert got != best and used + need[got] <= capacity
    assert all(used + need[r.key] > capacity for r in sim.ladder[: [r.key for r in sim.ladder].index(got)])  # the most accurate that fits
    # this machine twice as slow as the chart's (the playing sessions' pace): every need doubles
    slow = [Playing(used / 2, 2.0), Playing(used / 2, 2.0)]
    fits_slow = [r.key for r in sim.ladder if used + 2 * need[r.key] <= capacity]
    if fits_slow:
        assert admit(sim, 1, slow, 2, "coarser") == fits_slow[0]
    else:
        with pytest.raises(RealtimeFullError):
            admit(sim, 1, slow, 2, "coarser")
    with pytest.raises(RealtimeFullError, match="retry later"):
        admit(sim, 1, [Playing(capacity, 1.0)], 2, "coarser")  # nothing fits
    # alone, a session is admitted at its best even where its best cannot keep real time here
    assert admit(sim, 2, [], 1, "refuse") == best


def test_a_server_refuses_or_coarsens_a_realtime_session_once_the_playing_ones_fill_its_cores() -> None:
    with TestClient(create_app(ServiceConfig(max_sessions=10, max_sessions_per_client=10, compute_threads=1))) as client:
        manager = client.app.state.manager

        def new(**kw):
            return client.post("/v1/sessions", json={"scene": "water2d", "realtime": True, **kw})

        a = new().json()
        step_binary(client, a["id"], 2)
        core = manager.sessions[a["id"]].core
        sim = core.sim
        ms = _chart_ms(sim)
        best = sim.ladder[0].key
        assert sim.rung == best
        ratio = {r.key: ms[r.key] / ms[best] for r in sim.ladder}  # b's needs over a's: both on this machine's pace
        capacity = REALTIME_SHARE * 1
        # a's cores u: too many for b at its best rung (u + u > capacity), room for b at its coarsest
        u = (capacity / 2 + capacity / (1 + min(ratio.values()))) / 2
        sim._ema, sim._samples = u * DT_MS * 1e-3, 1  # its measured frame [s]
        core.playing, watched = True, core.has_viewers
        core.has_viewers = lambda: True  # a viewer watches it play (its play loop runs only then)
        r = new()
        assert r.status_code == 503, r.text
        assert "1 real-time sessions play" in r.json()["detail"] and r.headers.get("retry-after")
        assert len(manager.sessions) == 1  # nothing was created
        r = new(when_full="coarser")
        assert r.status_code == 201, r.text
        expect = next(r.key for r in sim.ladder if u * (1 + ratio[r.key]) <= capacity + 1e-9)
        assert r.json()["realtime"]["rung"] == expect != best
        core.has_viewers = watched  # nobody watches: its play loop waits and takes no cores, the next starts at its best
        assert new().json()["realtime"]["rung"] == best


def test_the_playing_real_time_sessions_share_the_real_time_capacity() -> None:
    from types import SimpleNamespace
    from typing import Any

    from hybridmpm.service.capacity import REALTIME_SHARE, realtime_share

    rt_sim = RealtimeSimulator("water2d")

    def core(playing: bool = True, viewers: bool = True, threads: int = 1, sim: Any = rt_sim) -> Any:
        return SimpleNamespace(sim=sim, playing=playing, has_viewers=lambda: viewers, threads=threads)

    assert realtime_share([], 2) == 1.0
    assert realtime_share([core()], 2) == 1.0  # alone: all of its thread
    assert realtime_share([core(), core()], 2) == pytest.approx(REALTIME_SHARE)  # real time takes 90 % of the threads
    assert realtime_share([core() for _ in range(8)], 2) == pytest.approx(REALTIME_SHARE * 2 / 8)
    assert realtime_share([core(threads=2) for _ in range(3)], 2) == pytest.approx(REALTIME_SHARE * 2 / 6)
    # paused, unwatched and plain sessions take no share
    idle = [core(playing=False), core(viewers=False), core(sim=object())]
    assert realtime_share([core() for _ in range(4)] + idle, 2) == pytest.approx(REALTIME_SHARE * 2 / 4)


def test_the_share_rule_is_a_function_of_the_playing_threads_and_the_compute_threads() -> None:
    # the one rule of both backends: the local server's sessions, a Ray node's actors
    from hybridmpm.service.capacity import share_of

    assert share_of(0, 2) == share_of(-1, 2) == 1.0  # none plays
    assert share_of(1, 2) == 1.0 and share_of(2, 2) == pytest.approx(REALTIME_SHARE)
    assert share_of(17, 2) == pytest.approx(REALTIME_SHARE * 2 / 17)
    assert share_of(1, 1) == pytest.approx(REALTIME_SHARE)  # a node of one CPU keeps a tenth back even for one
    assert share_of(3, 0.5) == pytest.approx(REALTIME_SHARE * 0.5 / 3)
    for bad in (0, -1.0):
        with pytest.raises(ValueError, match="compute_threads"):
            share_of(1, bad)
