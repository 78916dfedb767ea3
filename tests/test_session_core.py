"""The session core (hybridmpm.service.core) as the local backend runs it:
how many MPM threads a session steps on, the compute tokens it holds while it
does, and that wide and narrow sessions stepping at once neither deadlock nor
change a bit (checked against the same scenes run alone through
hybridmpm.sim, one thread)."""

from __future__ import annotations

import asyncio

import numpy as np
import pytest

pytest.importorskip("fastapi", reason="the service extra")  # the local backend's manager imports the web stack

from hybridmpm.service.config import ServiceConfig  # noqa: E402
from hybridmpm.service.core import WIDE_SESSION_PARTICLES, session_threads  # noqa: E402
from hybridmpm.service.facts import SessionSettings  # noqa: E402
from hybridmpm.service.sessions import SessionManager  # noqa: E402
from hybridmpm.sim import make_simulator, rollout  # noqa: E402


def test_a_large_scene_steps_on_two_threads_where_two_are_granted():
    big, small = SessionSettings("dam_break3d", 0, "mpm", 0.8), SessionSettings("water2d", 0, "mpm", 0.8)
    assert make_simulator("dam_break3d", "mpm", seed=0, threads=1).particles.num_total >= WIDE_SESSION_PARTICLES
    assert session_threads(big, 2) == 2 and session_threads(big, 16) == 2
    assert session_threads(big, 1) == 1 and session_threads(small, 2) == 1
    assert session_threads(SessionSettings("dam_break3d", 0, "mpm", 0.8, n_grid=24), 2) == 1  # fewer particles on a coarser grid


def test_a_wide_call_holds_as_many_tokens_as_threads():
    async def go() -> tuple[int, int]:
        m = SessionManager(ServiceConfig(compute_threads=2, max_sessions=4))
        wide = await m.compute_wide(2, lambda: m.limiter.borrowed_tokens)
        narrow = await m.compute_wide(1, lambda: m.limiter.borrowed_tokens)
        assert m.limiter.borrowed_tokens == 0
        return wide, narrow

    assert asyncio.run(go()) == (2, 1)


def test_a_wide_call_cancelled_while_it_takes_its_tokens_leaves_none_taken():
    # a session deleted while its play loop waits for its second token (its task is cancelled there) must not keep
    # the first: a leaked token leaves every later two-thread session waiting for ever (a 3D session that never plays)
    async def go() -> tuple[int, int]:
        m = SessionManager(ServiceConfig(compute_threads=2, max_sessions=4))
        other = object()
        await m.limiter.acquire_on_behalf_of(other)  # a narrow call holds one of the two tokens
        wide = asyncio.ensure_future(m.compute_wide(2, lambda: None))
        for _ in range(20):  # the wide call takes the free token and waits for the other
            await asyncio.sleep(0)
        waiting = m.limiter.borrowed_tokens
        wide.cancel()
        with pytest.raises(asyncio.CancelledError):
            await wide
        m.limiter.release_on_behalf_of(other)
        left = m.limiter.borrowed_tokens
        await asyncio.wait_for(m.compute_wide(2, lambda: None), 5)  # a later wide call gets both
        return waiting, left

    assert asyncio.run(go()) == (2, 0)


def test_wide_and_narrow_sessions_step_at_once_without_deadlock_and_bit_for_bit():
    frames = 6
    specs = [("dam_break3d", 1), ("dam_break3d", 2), ("water2d", 3), ("sand2d", 4)]

    async def go() -> list[np.ndarray]:
        m = SessionManager(ServiceConfig(compute_threads=2, max_sessions=8))
        sessions = [await m.create(scene, seed, "mpm", 0.8) for scene, seed in specs]
        assert [m.core_of(s).threads for s in sessions] == [2, 2, 1, 1]

        async def steps(s):  # three requests each, all sessions at once
            out = [await m.rollout(s, frames // 3) for _ in range(3)]
            return np.concatenate([ro.positions[1:] for ro in out])

        got = await asyncio.wait_for(asyncio.gather(*(steps(s) for s in sessions)), 300)
        assert m.limiter.borrowed_tokens == 0
        return got

    got = asyncio.run(go())
    for (scene, seed), pos in zip(specs, got):
        alone = rollout(make_simulator(scene, "mpm", seed=seed, threads=1), frames).positions[1:]
        assert np.array_equal(pos, alone), f"{scene} seed {seed} differs from a one-thread run alone"


def test_an_mpc_plan_stops_within_two_seconds_of_a_cancel():
    """The core a Ray actor runs: a 1000-frame MPC control on dam_break3d plans for many seconds; setting its
    ``cancel`` (the actor's ``cancel_control``: its client left) 0.5 s in stops the plan between its model
    rollouts' frames: the control returns a rollout of no frame (the session's state untouched) within 2 s."""
    import threading
    import time

    from hybridmpm.control import Sketch
    from hybridmpm.service.budget import MemoryBudget
    from hybridmpm.service.core import SessionCore

    core = SessionCore.build("k", SessionSettings("dam_break3d", 0, "mpm", 0.8), "test", MemoryBudget(1 << 30), threads=1)
    p0, f0 = np.array(core.sim.positions), core.frame_index
    sketch = Sketch.from_json({"kind": "arrow", "points": [[0.2, 0.3], [0.5, 0.3]]})
    out: list[object] = []
    worker = threading.Thread(target=lambda: out.append(core.control("mpc", 1000, sketch, "c1")))
    worker.start()
    time.sleep(0.5)  # into the plan (it runs for many seconds): what is measured is the time from the cancel on
    t0 = time.monotonic()
    core.cancel.set()
    worker.join(60)
    took = time.monotonic() - t0
    assert not worker.is_alive() and took < 2.0, took
    ro, metrics, plan, first = out[0]  # type: ignore[misc]
    assert ro.frames_done == 0 and metrics["failure"] == "cancelled while planning" and plan is None and first is None
    assert np.array_equal(core.sim.positions, p0) and core.frame_index == f0
    assert core.control_state() is None and not core.controlling
