"""A session's saves as the core writes them for both backends
(hybridmpm.service.core): two saves that cross keep the newer snapshot, a
closed session writes no record, and a control is saved before it answers
on the local backend as in a Ray actor (the core's save policy). Each record
is read back through the store and rebuilt (SessionCore.load), so the frame
it holds is the one the session was at, not a flag the core keeps."""

from __future__ import annotations

import asyncio
import threading

import pytest

pytest.importorskip("fastapi", reason="the service extra")  # the local backend's manager imports the web stack

from hybridmpm.control import Sketch  # noqa: E402
from hybridmpm.service.budget import MemoryBudget  # noqa: E402
from hybridmpm.service.config import ServiceConfig  # noqa: E402
from hybridmpm.service.core import SessionCore  # noqa: E402
from hybridmpm.service.facts import SessionSettings  # noqa: E402
from hybridmpm.service.sessions import SessionManager  # noqa: E402
from hybridmpm.service.store import SessionStore, session_key  # noqa: E402

BIG = 1 << 30
ARROW = {"kind": "arrow", "points": [[0.3, 0.3], [0.6, 0.4]]}


def stored_frame(store: SessionStore, key: str) -> int:
    """The frame of ``key``'s record, rebuilt from the store."""
    return SessionCore.load(store.load(key, BIG), MemoryBudget(BIG)).frame_index


def new_core(budget: MemoryBudget) -> SessionCore:
    return SessionCore.build(session_key("a session"), SessionSettings("water2d", 3, "mpm", 0.8), "127.0.0.1", budget)


def test_two_saves_that_cross_keep_the_newer_snapshot(tmp_path):
    # the periodic saver's snapshot taken, then a control's save of a later frame written first: the older one must not
    # overwrite it (the record would go back in time while the session is marked saved)
    store = SessionStore(str(tmp_path / "store")).open()
    core = new_core(MemoryBudget(BIG))
    core.dirty = True
    older = core.snapshot()
    core.rollout(3)
    newer = core.snapshot()
    assert older is not None and newer is not None and newer[1] == older[1] + 3
    assert core.write(store, *newer)
    assert core.write(store, *older)  # nothing to do: a newer one is written
    assert stored_frame(store, core.key) == newer[1]
    core.rollout(1)
    assert core.save(store) and stored_frame(store, core.key) == newer[1] + 1  # the next save goes on


def test_a_closed_session_writes_no_record(tmp_path):
    # a save whose snapshot was taken before a delete must not write the record back after the delete removed it
    store = SessionStore(str(tmp_path / "store")).open()
    core = new_core(MemoryBudget(BIG))
    core.dirty = True
    snap = core.snapshot()
    assert snap is not None
    core.close(store)
    assert core.write(store, *snap)
    assert not store.has(core.key)


def test_a_control_is_saved_before_it_answers_on_the_local_backend(tmp_path):
    # the core's save policy: the steps before the control are saved before it runs, the control's end before it answers;
    # nothing else saves (no periodic saver runs: the manager is not started)
    async def go() -> tuple[int, int, int]:
        m = SessionManager(ServiceConfig(store=str(tmp_path / "store"), max_sessions=2, compute_threads=1))
        s = await m.create("water2d", 3, "mpm", 0.8)
        assert m.store is not None and stored_frame(m.store, s.key) == 0  # a 201 is durable
        await m.rollout(s, 4)
        events: list[int] = []
        core = m.core_of(s)
        announce = core.on_event

        def seen(msg: dict) -> None:  # the frame of the record when the control announces itself (in the worker, before it runs)
            if msg.get("status") == "running":
                events.append(stored_frame(m.store, s.key))
            announce(msg)

        core.on_event = seen
        await m.run_control(s, Sketch.from_json(ARROW), "constant", 10, threading.Event(), [], "c1")
        frame = m.core_of(s).frame_index
        record = stored_frame(m.store, s.key)
        await m.stop()
        return events[0] if events else -1, record, frame

    before, after, frame = asyncio.run(go())
    assert before == 4  # the steps answered before the control were durable when it started
    assert after == frame and frame >= 4 + 10  # and the control's end before it answered
