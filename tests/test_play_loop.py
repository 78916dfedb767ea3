"""The play loop (SessionCore.play), run as a backend runs it (sleeping what
it yields): it holds real time, wakes at most once per tick (PLAY_TICK_S)
and steps the frames due in one call, records every step, shows its viewers
the last step of each call, and shows the last step before a pause or a
failure. The old loop woke once per frame (400 times a second on water2d)."""

from __future__ import annotations

import time

import pytest

from hybridmpm.service.budget import MemoryBudget
from hybridmpm.service.core import PLAY_LAG_S, PLAY_TICK_S, RECORD_STEPS, SessionCore
from hybridmpm.service.facts import SessionSettings
from hybridmpm.service.store import session_key

BIG = 1 << 30


def playing_core() -> tuple[SessionCore, list[int]]:
    """water2d seed 0 (224 particles, ~0.3 ms a frame) on MPM, playing, with a viewer; the frame numbers shown."""
    core = SessionCore.build(session_key("play"), SessionSettings("water2d", 0, "mpm", 0.8), "127.0.0.1", MemoryBudget(BIG))
    shown: list[int] = []
    core.on_frame = lambda fr, _c: shown.append(int(fr.frame_index))
    core.has_viewers = lambda: True
    core.playing = True
    return core, shown


def play_for(core: SessionCore, seconds: float) -> tuple[int, float]:
    """Run the play loop for ``seconds`` of wall time; (calls, elapsed seconds)."""
    calls, t0 = 0, time.monotonic()
    for delay in core.play():
        calls += 1
        if time.monotonic() - t0 >= seconds:
            core.playing = False
        time.sleep(delay)
    return calls, time.monotonic() - t0


def test_the_play_loop_holds_real_time_stepping_the_frames_due_once_a_tick():
    core, shown = playing_core()
    f0 = core.frame_index
    calls, elapsed = play_for(core, 1.0)
    frames = core.frame_index - f0
    real_time = elapsed / float(core.sim.dt_frame)
    # paced: never more than real time plus the catch-up and one call's steps; holding it needs ~0.1 of a core
    assert frames <= real_time + PLAY_LAG_S / float(core.sim.dt_frame) + PLAY_TICK_S / float(core.sim.dt_frame) + 2
    assert frames >= 0.8 * real_time, (frames, real_time)
    # one call a tick (the old loop: one a frame, about 400 here), each showing its last step
    assert calls <= elapsed / PLAY_TICK_S + 2, (calls, elapsed)
    assert frames >= 3 * calls
    assert len(shown) == calls and shown[-1] == core.frame_index
    assert shown == sorted(set(shown))
    # every step recorded (the recording keeps the latest RECORD_STEPS), consecutive
    rec = [r[0] for r in core.recorded(frames)]
    assert rec == list(range(core.frame_index - min(frames, RECORD_STEPS) + 1, core.frame_index + 1))


def test_a_pause_between_two_steps_of_a_call_shows_the_last_step():
    core, shown = playing_core()
    calls = core.play()
    next(calls)  # one call; then a wait of more than a tick leaves several steps due
    time.sleep(2 * PLAY_TICK_S)
    f0 = core.frame_index
    asked = 0

    def viewers() -> bool:  # the pause lands after the call's first step was judged not its last
        nonlocal asked
        asked += 1
        if asked == 2:
            core.playing = False
        return True

    core.has_viewers = viewers
    with pytest.raises(StopIteration):
        next(calls)
    assert core.frame_index == f0 + 1  # the second step was not taken
    assert shown[-1] == core.frame_index  # and the first reached the viewers


def test_a_failing_step_shows_the_last_good_step_then_the_error():
    core, shown = playing_core()
    events: list[str] = []
    core.on_event = lambda msg: events.append(msg["type"])
    good = core.sim.advance
    taken = 0

    def advance():
        nonlocal taken
        taken += 1
        if taken == 3:
            raise RuntimeError("a non-finite state")
        return good()

    core.sim.advance = advance  # type: ignore[method-assign]
    for delay in core.play():  # the first call takes one step; the wait leaves several due for the second
        time.sleep(max(delay, 2 * PLAY_TICK_S))
    assert not core.playing and events == ["error"]
    assert shown and shown[-1] == core.frame_index  # the last good step was shown before the error
