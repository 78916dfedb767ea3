"""``step_realtime(sim, wall_dt, owed_s=...)``, the host loop's tick (hybridmpm.sim.rollout): it advances the
frames the wall time covers, carries the remainder under a step, drops what its budget cannot cover instead of
owing it (no catch-up spiral), runs the same frames as a rollout, and refuses bad input naming the field."""

from __future__ import annotations

import math

import numpy as np
import pytest

from hybridmpm.errors import InvalidInputError
from hybridmpm.sim import MpmSimulator, rollout, step_realtime
from hybridmpm.sim.rollout import MAX_WALL_DT


@pytest.fixture
def sim() -> MpmSimulator:
    return MpmSimulator("water2d", threads=1)


def test_frames_follow_the_wall_time_with_the_remainder_carried(sim):
    rng = np.random.default_rng(0)
    ticks = rng.uniform(0.0, 0.012, size=40)  # a host loop at an uneven 80-1000 Hz
    frames, owed = 0, 0.0
    for dt in ticks:
        t = step_realtime(sim, float(dt), owed_s=owed, budget_s=60.0)
        owed = t.owed_s
        assert t.dropped_s == 0.0 and 0.0 <= t.owed_s < sim.dt_frame
        assert t.rollout.failure is None
        frames += t.frames
    assert frames == math.floor(ticks.sum() / sim.dt_frame + 1e-9)  # every due frame, none twice
    assert sim.frame.frame_index == frames


def test_the_ticks_run_the_rollouts_frames(sim):
    owed = 0.0
    for _ in range(6):
        owed = step_realtime(sim, 0.0075, owed_s=owed, budget_s=60.0).owed_s  # 3 frames each
    other = MpmSimulator("water2d", threads=1)
    rollout(other, 18)
    assert np.array_equal(sim.fluid_positions, other.fluid_positions)


def test_time_the_budget_cannot_cover_is_dropped_not_owed(sim):
    t = step_realtime(sim, 0.1, budget_s=1e-9)  # a budget of nothing: one step, the rest dropped
    assert t.frames == 1 and t.rollout.failure == "budget"
    assert t.dropped_s == pytest.approx(0.1 - sim.dt_frame, abs=1e-12)
    assert t.owed_s < sim.dt_frame
    nxt = step_realtime(sim, 0.005, owed_s=t.owed_s, budget_s=60.0)  # the next tick is owed its own time only
    assert nxt.frames == math.floor((0.005 + t.owed_s) / sim.dt_frame + 1e-9) <= 3
    assert nxt.realtime_factor == pytest.approx(nxt.simulated_s / 0.005)


def test_coarse_steps_are_whole():
    sim = MpmSimulator("water2d", threads=1, r_t=2)
    t = step_realtime(sim, 0.0125, budget_s=60.0)  # 5 frames of wall time: 2 steps of 2 frames, 1 frame owed
    assert t.frames == 4 and t.owed_s == pytest.approx(sim.dt_frame)


def test_a_longer_pause_is_one_tick(sim):
    t = step_realtime(sim, 3600.0, budget_s=60.0)
    assert t.frames == math.floor(MAX_WALL_DT / sim.dt_frame + 1e-9)


@pytest.mark.parametrize(
    ("kw", "field"),
    [
        ({"wall_dt": float("nan")}, "wall_dt"),
        ({"wall_dt": -0.01}, "wall_dt"),
        ({"wall_dt": "0.01"}, "wall_dt"),
        ({"wall_dt": True}, "wall_dt"),
        ({"wall_dt": 0.01, "budget_s": 0.0}, "budget_s"),
        ({"wall_dt": 0.01, "budget_s": float("inf")}, "budget_s"),
    ],
)
def test_bad_input_is_refused_naming_the_field(sim, kw, field):
    with pytest.raises(InvalidInputError) as e:
        step_realtime(sim, **kw)
    assert e.value.field == field
    assert sim.frame.frame_index == 0
