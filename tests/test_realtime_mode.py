"""Real-time mode (hybridmpm.sim.realtime, docs/realtime.md): the ladder, the change of rung (mass, momentum,
bodies and pours carried bit for bit), bitwise checkpoints across a change, and the choice with hysteresis on a
fake clock (a test never asserts a speed: the clock is the test's)."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest

from hybridmpm.conventions import MATERIAL_WATER
from hybridmpm.errors import InvalidInputError
from hybridmpm.scenes import SceneSpec, make_scene
from hybridmpm.scenes.registry import DOMAINS
from hybridmpm.sim import MpmSimulator, make_simulator, step_realtime
from hybridmpm.sim import ladder as rl
from hybridmpm.sim import realtime as rt
from hybridmpm.sim.ladder import candidate_rungs, make_ladder, pareto
from hybridmpm.sim.pour import pour_block
from hybridmpm.sim.realtime import RealtimeSimulator


def _momentum(sim: MpmSimulator) -> tuple[float, np.ndarray]:
    m = np.asarray(sim.solver.masses, np.float64)
    v = np.asarray(sim.solver.velocities, np.float64)
    return float(m.sum()), (m[:, None] * v).sum(0)


@pytest.mark.parametrize("name", sorted(DOMAINS))
def test_every_scene_has_a_ladder_whose_steps_down_buy_time_and_the_projection_only_where_it_steps(name: str) -> None:
    scene = make_scene(name)
    ladder = make_ladder(scene)
    assert ladder, name
    ratios = [r.time_ratio for r in ladder]
    assert all(b < a for a, b in zip(ratios, ratios[1:])), (name, ratios)  # each step down is faster (chart or priors)
    errors = [r.error for r in ladder]
    if all(e is not None for e in errors):
        assert errors == sorted(errors), (name, errors)  # and the most accurate first
    water_only = bool(np.all(np.asarray(scene.material) == MATERIAL_WATER))
    free_slip_only = all(c.condition != "sticky" and c.friction == 0.0 for c in scene.params.colliders)  # bodies: coupled in its solve
    projection = any(r.integrator == "projection" for r in candidate_rungs(scene))
    assert projection == (water_only and free_slip_only), name
    assert all(r.n_grid <= scene.params.resolved_n_grid() for r in ladder)


def test_pareto_keeps_only_rungs_that_buy_time() -> None:
    R = rl.Rung
    rungs = [R(64, "explicit", 0.3, 0.5), R(128, "explicit", 0.1, 1.0), R(96, "explicit", 0.2, 1.2), R(64, "projection", 0.4, 0.2)]
    assert [r.key for r in pareto(rungs)] == ["g128-explicit", "g64-explicit", "g64-projection"]  # 96 is slower than 128


@pytest.mark.parametrize(("name", "rung"), [("dam_break2d", "g64-projection"), ("jelly_dam_break2d", "g64-explicit"), ("water3d", "g32-projection")])
def test_a_change_of_rung_keeps_the_particles_bit_for_bit_so_mass_and_momentum_are_conserved(name: str, rung: str) -> None:
    sim = make_simulator(name, "realtime")
    assert isinstance(sim, RealtimeSimulator)
    for _ in range(25):
        sim.advance()
    m0, p0 = _momentum(sim)
    x0, v0 = np.array(sim.solver.positions), np.array(sim.solver.velocities)
    sim.set_rung(rung)
    assert sim.rung == rung and sim.solver.params.resolved_n_grid() == int(rung[1:].split("-")[0])
    assert sim.solver.params.integrator == rung.split("-")[1]
    m1, p1 = _momentum(sim)
    assert m1 == m0  # the same particles: exactly
    assert np.abs(p1 - p0).max() <= 1e-6 * max(1.0, float(np.abs(p0).max()))
    assert np.array_equal(sim.solver.positions, x0) and np.array_equal(sim.solver.velocities, v0)
    fr = sim.advance()  # and it steps on
    assert np.isfinite(fr.positions).all() and fr.frame_index == 26


def test_a_checkpoint_taken_after_a_change_restores_bitwise_into_a_fresh_session() -> None:
    sim = make_simulator("dam_break2d", "realtime")
    for _ in range(10):
        sim.advance()
    sim.set_rung("g64-projection")
    for _ in range(7):  # a projection step may span frames: the state holds them
        sim.advance()
    state = sim.state()
    assert state["rung"] == "g64-projection"
    for _ in range(15):
        sim.advance()
    other = make_simulator("dam_break2d", "realtime")
    other.restore(state)
    assert other.rung == "g64-projection"
    for _ in range(15):
        other.advance()
    assert other.solver.checkpoint() == sim.solver.checkpoint()


def test_a_restore_refuses_a_foreign_rung_and_leaves_the_simulator_as_it_was() -> None:
    sim = make_simulator("water2d", "realtime")
    sim.advance()
    state = sim.state()
    before = sim.solver.checkpoint()
    with pytest.raises(InvalidInputError) as e:
        sim.restore({**state, "rung": "g7-explicit"})
    assert e.value.field == "state.rung"
    broken = {**state, "rung": "g64-explicit", "solver": b"not a checkpoint"}
    with pytest.raises(InvalidInputError, match="not a hybridmpm MpmSolver checkpoint"):
        sim.restore(broken)
    assert sim.rung == "g128-explicit" and sim.solver.checkpoint() == before


def test_bodies_and_poured_blocks_cross_a_change_of_grid() -> None:
    sim = make_simulator("crates2d", "realtime")
    assert [r.key for r in sim.ladder][:1] == ["g128-explicit"]
    for _ in range(5):
        sim.advance()
    own = sim.solver.num_particles
    n = pour_block(sim, {"material": "water", "lo": [0.6, 0.7], "hi": [0.7, 0.8]})
    assert n == sim.solver.num_particles > own and sim.pours == [n - own]
    m0, p0 = _momentum(sim)
    core0 = sim.solver._core.bodies()["state"].copy()
    sim.set_rung(min((r for r in sim.ladder if r.r_p == 1.0), key=lambda r: r.time_ratio).key)
    m1, p1 = _momentum(sim)
    assert m1 == m0 and np.abs(p1 - p0).max() <= 1e-6 * max(1.0, float(np.abs(p0).max()))
    assert np.array_equal(sim.solver._core.bodies()["state"], core0)  # the bodies' exact states
    assert sim.solver.num_particles == n and sim.pours == [n - own]
    state = sim.state()
    for _ in range(5):
        sim.advance()
    again = make_simulator("crates2d", "realtime")
    again.restore(state)
    for _ in range(5):
        again.advance()
    assert again.solver.checkpoint() == sim.solver.checkpoint()


def _totals(sim: RealtimeSimulator) -> tuple[float, np.ndarray, np.ndarray]:
    """Mass, momentum and first moment of mass of what the solver steps."""
    m = np.asarray(sim.solver.masses, np.float64)
    return (
        float(m.sum()),
        (m[:, None] * np.asarray(sim.solver.velocities, np.float64)).sum(0),
        (m[:, None] * np.asarray(sim.solver.positions, np.float64)).sum(0),
    )


def test_merged_particles_conserve_mass_momentum_and_force_and_split_back_to_the_scene_s_own() -> None:
    sim = make_simulator("dam_break2d", "realtime")
    assert isinstance(sim, RealtimeSimulator)
    scene_masses = np.array(sim.solver.masses)
    n = sim.particles.num_fluid
    for _ in range(20):
        sim.advance()
    m0, p0, c0 = _totals(sim)
    sim.set_rung("g64-explicit-rp0.25")
    m1, p1, c1 = _totals(sim)
    k = sim.solver.num_particles
    assert n / 4 <= k < n / 2  # at most 2 x 2 of the lattice a group (the scene's default is clustered already)
    assert sim.realtime_info()["particles"] == k and sim.realtime_info()["label"] == "MPM 64² explicit, r_p 0.25"
    assert m1 == m0  # each group's mass is its members' (registered scenes' masses sum exactly in float32)
    tol = 1e-6 * max(1.0, float(np.abs(p0).max()))
    assert np.abs(p1 - p0).max() <= tol and np.abs(c1 - c0).max() <= 1e-6 * float(np.abs(c0).max())
    # what it shows is still the scene's particles: the frame, the velocities and a forcing keep their count
    assert sim.frame.positions.shape[0] == sim.particles.num_total and sim.particles.num_fluid == n
    assert np.array_equal(sim.particles.masses, scene_masses)
    acc = np.random.default_rng(0).normal(size=(n, 2)).astype(np.float32)
    sim.forcing = acc
    sim.advance()
    force = (scene_masses[:, None].astype(np.float64) * acc).sum(0)
    applied = (np.asarray(sim.solver.masses, np.float64)[:, None] * sim.solver.external_acceleration).sum(0)
    assert np.abs(applied - force).max() <= 1e-5 * float(np.abs(force).max())  # the groups push as hard as their members
    sim.forcing = None
    for _ in range(10):
        sim.advance()
    m2, p2, _ = _totals(sim)
    shown = sim.velocities
    sim.set_rung("g128-explicit")  # split back: the scene's own particles, their own masses
    m3, p3, _ = _totals(sim)
    assert sim.solver.num_particles == n and np.array_equal(sim.solver.masses, scene_masses)
    assert m3 == m2 and np.abs(p3 - p2).max() <= 1e-6 * max(1.0, float(np.abs(p2).max()))
    assert np.array_equal(sim.solver.velocities, shown)  # each at its group's affine velocity, as shown before
    assert np.isfinite(sim.advance().positions).all()


def test_a_merged_state_restores_bitwise_through_a_pour_and_a_split_and_a_forged_one_is_refused() -> None:
    sim = make_simulator("crates2d", "realtime")
    for _ in range(3):
        sim.advance()
    own = sim.solver.num_particles
    poured = pour_block(sim, {"material": "water", "lo": [0.6, 0.7], "hi": [0.7, 0.8]}) - own
    block = {f: np.array(sim.solver.field(f))[own:] for f in ("positions", "velocities", "masses")}
    bodies = sim.solver._core.bodies()["state"].copy()
    merged = next(r.key for r in sim.ladder if r.r_p < 1.0 and r.integrator == "explicit")
    sim.set_rung(merged)
    k = sim.solver.num_particles - poured
    assert k < own / 2 and sim.pours == [poured] and sim.poured_particles == poured
    for f, a in block.items():  # the poured block stays whole after the groups
        assert np.array_equal(np.array(sim.solver.field(f))[k:], a), f
    assert np.array_equal(sim.solver._core.bodies()["state"], bodies)
    for _ in range(3):
        sim.advance()
    state = sim.state()
    assert state["rung"] == merged and state["merge"]["labels"].shape == (own,)
    before = sim.solver.checkpoint()
    with pytest.raises(InvalidInputError) as e:
        sim.restore({**state, "merge": {**state["merge"], "labels": state["merge"]["labels"] + 1}})  # no group 0
    assert e.value.field == "state.merge.labels" and sim.solver.checkpoint() == before and sim.rung == merged
    with pytest.raises(InvalidInputError):  # one group of all: its mass is not the checkpoint's first particle's
        sim.restore({**state, "merge": {**state["merge"], "labels": np.zeros(own, np.int32)}})
    assert sim.solver.checkpoint() == before
    with pytest.raises(InvalidInputError) as e:
        sim.restore({**state, "merge": None})
    assert e.value.field == "state.merge"
    for _ in range(3):
        sim.advance()
    sim.set_rung(sim.ladder[0].key)  # split back, then on
    sim.advance()
    again = make_simulator("crates2d", "realtime")
    again.restore(state)
    assert again.rung == merged and again.particles.num_fluid == sim.particles.num_fluid
    for _ in range(3):
        again.advance()
    again.set_rung(again.ladder[0].key)
    again.advance()
    assert again.solver.checkpoint() == sim.solver.checkpoint()


def test_realtime_takes_the_settings_default_takes_and_refuses_the_rest_naming_them() -> None:
    with pytest.raises(InvalidInputError) as e:
        make_simulator("dam_break2d", "realtime", n_grid=64)
    assert e.value.field == "n_grid"
    with pytest.raises(InvalidInputError) as e:
        make_simulator("dam_break2d", "realtime", integrator="projection")
    assert e.value.field == "integrator"
    with pytest.raises(InvalidInputError) as e:
        RealtimeSimulator("dam_break2d", rung="g100-explicit")
    assert e.value.field == "rung"


class _Machine:
    """A fake machine: ``cost[key]`` wall seconds per frame on each rung; the clock moves only by frames."""

    def __init__(self, cost: dict[str, float]) -> None:
        self.cost = cost
        self.t = 0.0

    def __call__(self) -> float:
        return self.t


@pytest.fixture
def machine(monkeypatch: pytest.MonkeyPatch) -> Any:
    def make(sim_cost: dict[str, float]) -> _Machine:
        m = _Machine(sim_cost)
        real = MpmSimulator.advance

        def timed(self: MpmSimulator) -> Any:
            if isinstance(self, RealtimeSimulator):
                m.t += m.cost[self.rung]
            return real(self)

        monkeypatch.setattr(MpmSimulator, "advance", timed)
        return m

    return make


def _run(sim: RealtimeSimulator, frames: int) -> list[str]:
    seen = []
    for _ in range(frames):
        sim.advance()
        seen.append(sim.rung)
    return seen


def test_a_slow_machine_steps_down_to_the_most_accurate_rung_that_fits_and_stays(machine: Any) -> None:
    scene = make_scene("water2d")
    ladder = make_ladder(scene)
    budget = 2.5e-3 / rt.REALTIME_MARGIN
    # the first rung takes three budgets; every rung in proportion to its chart ratio (the prediction is exact)
    cost = {r.key: 3.0 * budget * r.time_ratio / ladder[0].time_ratio for r in ladder}
    fits = [r.key for r in ladder if cost[r.key] <= budget]
    m = machine(cost)
    sim = RealtimeSimulator(scene, clock=m)
    seen = _run(sim, 1500)  # 9 s of its wall time: past the dwell
    expect = fits[0] if fits else ladder[-1].key
    assert seen[-1] == expect
    assert len(sim.changes) == 1  # straight there, and no flapping
    assert sim.realtime_info()["realtime_factor"] == pytest.approx(2.5e-3 / cost[expect], abs=1e-3)  # rounded to 3 places


def test_a_share_of_the_machine_shrinks_the_budget_so_a_session_steps_down_to_what_fits_its_share(machine: Any) -> None:
    """A server's playing real-time sessions each get a share of its cores (service/capacity.py): on a machine
    where the first rung fits a whole budget, a session given a quarter of it steps down to the most accurate
    rung that fits a quarter (its own frame times, each frame alone on its threads, would never ask for it)."""
    scene = make_scene("water2d")
    ladder = make_ladder(scene)
    budget = 2.5e-3 / rt.REALTIME_MARGIN
    cost = {r.key: 0.6 * budget * r.time_ratio / ladder[0].time_ratio for r in ladder}
    alone, shared = RealtimeSimulator(scene, clock=machine(cost)), RealtimeSimulator(scene, clock=machine(cost))
    shared.set_share(0.25)
    assert shared.budget_s() == pytest.approx(0.25 * alone.budget_s())
    assert _run(alone, 1500)[-1] == ladder[0].key  # alone it keeps the most accurate rung
    fits = [r.key for r in ladder if cost[r.key] <= 0.25 * budget]
    assert _run(shared, 1500)[-1] == (fits[0] if fits else ladder[-1].key)
    for bad in (0, -0.5, 1.5, float("nan"), True, "1"):
        with pytest.raises(InvalidInputError) as e:
            shared.set_share(bad)
        assert e.value.field == "share"


def test_a_fast_machine_climbs_to_the_most_accurate_rung_with_hysteresis_and_dwell(machine: Any, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(rt, "DWELL_S", 0.5)  # fewer frames a dwell: the rule is the same
    monkeypatch.setattr(rt, "DOWN_AFTER_S", 0.1)  # the load's slow spells (0.2 s) last long enough to step down
    scene = make_scene("water2d")
    ladder = make_ladder(scene)
    budget = 2.5e-3 / rt.REALTIME_MARGIN
    cost = {r.key: 0.5 * budget * r.time_ratio / ladder[0].time_ratio for r in ladder}
    m = machine(cost)
    sim = RealtimeSimulator(scene, clock=m, rung=ladder[-1].key)
    stamps = []
    for _ in range(20000):
        before = len(sim.changes)
        sim.advance()
        if len(sim.changes) > before:
            stamps.append(m.t)
        if sim.rung == ladder[0].key:
            break
    assert sim.rung == ladder[0].key
    assert (np.diff([0.0, *stamps]) >= rt.DWELL_S - 1e-9).all(), stamps  # one change per dwell at most
    assert len(stamps) <= len(ladder) - 1


def test_a_rung_at_the_edge_of_the_budget_does_not_flap(machine: Any) -> None:
    scene = make_scene("water2d")
    ladder = make_ladder(scene)
    assert len(ladder) >= 2
    budget = 2.5e-3 / rt.REALTIME_MARGIN
    # the first rung just over the budget, the second well inside it but not inside budget / HYSTERESIS after scaling
    cost = {r.key: budget * 1.05 * r.time_ratio / ladder[0].time_ratio for r in ladder}
    m = machine(cost)
    sim = RealtimeSimulator(scene, clock=m)
    _run(sim, 3000)
    assert len(sim.changes) == 1  # down once; the way back up asks for HYSTERESIS of headroom
    assert m.t >= 3000 * min(cost.values())


def test_changes_are_at_least_the_dwell_apart_in_wall_time(machine: Any, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(rt, "DWELL_S", 0.5)  # fewer frames a dwell: the rule is the same
    monkeypatch.setattr(rt, "DOWN_AFTER_S", 0.1)  # the load's slow spells (0.2 s) last long enough to step down
    scene = make_scene("water2d")
    ladder = make_ladder(scene)
    budget = 2.5e-3 / rt.REALTIME_MARGIN
    # a machine whose load alternates every 0.2 s of wall time between ten times slow and fast: it would flap
    base = {r.key: budget * r.time_ratio / ladder[0].time_ratio for r in ladder}
    m = machine(dict(base))
    sim = RealtimeSimulator(scene, clock=m)
    stamps = []
    for _ in range(3000):
        load = 10.0 if int(m.t / 0.2) % 2 == 0 else 0.6
        m.cost = {k: v * load for k, v in base.items()}
        before = len(sim.changes)
        sim.advance()
        if len(sim.changes) > before:
            stamps.append(m.t)
    assert len(stamps) >= 2, "the load moved ten-fold: it should have changed down and up"
    gaps = np.diff([0.0, *stamps])
    assert (gaps >= rt.DWELL_S - 1e-9).all(), gaps


def test_a_projection_rung_is_timed_by_its_steps_mean_not_by_the_frame_that_steps(monkeypatch: pytest.MonkeyPatch) -> None:
    # water at rest in a 64² tank: on the projection a step spans four frames (the most it may); the frame that
    # steps costs 3.6 budgets, the frames inside the step almost nothing, so their mean fits (0.92 budgets). Timed
    # frame by frame, the average would swing with the step, up to a third of a step's cost (1.2 budgets) just
    # after it, and read neither the mean nor a steady rung.
    monkeypatch.setattr(rt, "DWELL_S", 0.2)
    scene = SceneSpec.from_dict({"name": "tank", "dim": 2, "n_grid": 64, "blocks": [{"material": "water", "lo": [0.04, 0.04], "hi": [0.96, 0.3]}]}).build()
    key = rl.rung_key(64, "projection")
    budget = 2.5e-3 / rt.REALTIME_MARGIN
    clock = [0.0]
    real = MpmSimulator.advance
    steps = []

    def timed(self: MpmSimulator) -> Any:
        if isinstance(self, RealtimeSimulator):
            stepping = self.solver.substeps_for(self.dt_frame) > 0
            steps.append(stepping)
            clock[0] += (3.6 if stepping else 0.02) * budget
        return real(self)

    monkeypatch.setattr(MpmSimulator, "advance", timed)
    sim = RealtimeSimulator(scene, clock=lambda: clock[0], rung=key)
    for _ in range(800):
        sim.advance()
    assert sim.changes == [] and sim.rung == key
    k = len(steps) / sum(steps)  # frames a step spans, on average
    assert k >= 3.9, k
    mean = clock[0] / len(steps)
    assert sim.realtime_info()["frame_ms"] == pytest.approx(1e3 * mean, rel=0.1)


def test_step_realtime_drives_a_realtime_simulator_and_owes_nothing_a_slow_tick_dropped() -> None:
    sim = make_simulator("water2d", "realtime")
    tick = step_realtime(sim, 0.0125, budget_s=1e-9)  # five frames due, a budget that covers one
    assert tick.frames == 1 and tick.dropped_s == pytest.approx(4 * 2.5e-3) and tick.owed_s == pytest.approx(0.0, abs=1e-12)


def test_a_body_added_on_a_projection_rung_stays_on_it_and_moves_with_it_across_a_change() -> None:
    # the projection couples bodies in its pressure solve (docs/large-step.md): a body keeps the rung, and a
    # change of rung carries it bit for bit
    sim = RealtimeSimulator("water2d", rung="g64-projection")
    for _ in range(5):
        sim.advance()
    m0, _ = _momentum(sim)
    sim.add_body({"shape": "box", "center": [0.5, 0.8], "half_extents": [0.04, 0.04], "density": 500.0})
    assert sim.rung == "g64-projection" and _momentum(sim)[0] == m0
    for _ in range(5):
        fr = sim.advance()
    y = fr.body_center[0, 1]
    assert y < 0.8  # it falls
    while True:  # a change waits for a step that spans frames to end
        try:
            sim.set_rung("g128-projection")
            break
        except InvalidInputError:
            sim.advance()
    assert sim.rung == "g128-projection" and len(sim.solver.bodies) == 1
    for _ in range(5):
        fr = sim.advance()
    assert np.isfinite(fr.positions).all() and fr.body_center[0, 1] < y


def test_a_sand_block_poured_on_a_projection_rung_falls_back_to_the_explicit_step() -> None:
    sim = RealtimeSimulator("water2d", rung="g128-projection")
    sim.advance()
    pour_block(sim, {"material": "sand", "lo": [0.6, 0.6], "hi": [0.7, 0.7]})
    fr = sim.advance()
    assert sim.rung == "g128-explicit" and np.isfinite(fr.positions).all()


def test_a_lone_slow_frame_is_not_a_slow_machine(machine: Any) -> None:
    """A frame now and then takes many budgets (a garbage collection, the OS taking the core): the mode keeps
    its rung. The same slowness held for longer than DOWN_AFTER_S is the machine's pace, and it steps down."""
    scene = make_scene("water2d")
    ladder = make_ladder(scene)
    budget = 2.5e-3 / rt.REALTIME_MARGIN
    cost = {r.key: 0.3 * budget * r.time_ratio / ladder[0].time_ratio for r in ladder}
    m = machine(dict(cost))
    sim = RealtimeSimulator(scene, clock=m)
    for i in range(3000):
        m.cost = {k: v * (100.0 if i % 97 == 50 else 1.0) for k, v in cost.items()}  # one frame in 97 takes 30 budgets
        sim.advance()
    assert sim.rung == ladder[0].key and sim.changes == []
    for _ in range(1500):  # the machine slows ten-fold and stays so
        m.cost = {k: 10.0 * v for k, v in cost.items()}
        sim.advance()
    assert sim.rung != ladder[0].key


def test_the_coarsest_grid_also_merges_to_half_its_density_per_axis_and_back_conserving_mass_and_momentum() -> None:
    """The ladder's last resort: on its coarsest grid the particles merged in cubes of twice the side (r_p a
    further 2^-D). Reached from the merged rung it splits back to the scene's particles and merges anew."""
    scene = make_scene("dam_break2d")
    assert "g64-explicit-rp0.0625" in [r.key for r in candidate_rungs(scene)]
    assert not any(r.r_p < 0.25 and r.n_grid == 128 for r in candidate_rungs(scene))  # the coarsest grid only
    sim = make_simulator("dam_break2d", "realtime")
    assert isinstance(sim, RealtimeSimulator)
    scene_masses = np.array(sim.solver.masses)
    for _ in range(20):
        sim.advance()
    sim.set_rung("g64-explicit-rp0.25")
    k4 = sim.solver.num_particles
    m0, p0, _ = _totals(sim)
    sim.set_rung("g64-explicit-rp0.0625")
    m1, p1, _ = _totals(sim)
    k16 = sim.solver.num_particles
    assert k4 / 4 <= k16 < k4 / 2  # groups of at most 4 x 4 of the lattice: fewer than half the 2 x 2 groups
    assert m1 == m0 and np.abs(p1 - p0).max() <= 1e-6 * max(1.0, float(np.abs(p0).max()))
    assert sim.realtime_info()["label"] == "MPM 64² explicit, r_p 0.0625"
    for _ in range(10):
        sim.advance()
    m2, p2, _ = _totals(sim)
    sim.set_rung("g128-explicit")
    m3, p3, _ = _totals(sim)
    assert np.array_equal(sim.solver.masses, scene_masses)
    assert m3 == m2 and np.abs(p3 - p2).max() <= 1e-6 * max(1.0, float(np.abs(p2).max()))
    assert np.isfinite(sim.advance().positions).all()


def test_a_rung_that_keeps_failing_is_retried_ever_more_rarely(machine: Any, monkeypatch: pytest.MonkeyPatch) -> None:
    """The first rung takes 1.5 budgets, but the chart's ratios, scaled by the fast rungs' times, keep predicting
    that it fits: each time its measured time expires the mode climbs back and fails again. Each failure keeps
    the measured time twice as long (MAX_BACKOFF doublings), so over 20 times the TTL it retries a handful of
    times, not once a TTL."""
    monkeypatch.setattr(rt, "DWELL_S", 0.05)
    monkeypatch.setattr(rt, "MEASURED_TTL_S", 0.5)  # the same rule on a shorter clock
    scene = make_scene("water2d")
    ladder = make_ladder(scene)
    budget = 2.5e-3 / rt.REALTIME_MARGIN
    cost = {r.key: 0.3 * budget for r in ladder}
    cost[ladder[0].key] = 1.5 * budget
    m = machine(cost)
    sim = RealtimeSimulator(scene, clock=m)
    while m.t < 10.0:
        sim.advance()
    ups = [c for c in sim.changes if c["to"] == ladder[0].key]
    assert 2 <= len(ups) <= 6, sim.changes  # once a TTL (0.5 s) without the backoff: about 20


def test_a_scene_on_its_own_grid_only_has_a_last_resort_merged_four_times_the_lattice_spacing() -> None:
    """paddle3d's grid is its only one: its merged rung (cubes of twice the lattice spacing, r_p 2^-3) and the last
    resort (four times, r_p 4^-3) keep mass exactly and momentum, and the last resort holds at most an eighth of
    the merged rung's particles plus the cubes cut by the block's edges."""
    assert [r.key for r in candidate_rungs(make_scene("paddle3d")) if r.integrator == "explicit"] == [
        "g34-explicit",
        "g34-explicit-rp0.125",
        "g34-explicit-rp0.0156",
    ]
    sim = RealtimeSimulator("paddle3d", rung="g34-explicit-rp0.125", adaptive=False)
    for _ in range(5):
        sim.advance()
    k8 = sim.solver.num_particles
    m0, p0, _ = _totals(sim)
    sim.set_rung("g34-explicit-rp0.0156")
    m1, p1, _ = _totals(sim)
    k64 = sim.solver.num_particles
    assert k8 / 8 <= k64 < k8 / 4
    assert m1 == m0 and np.abs(p1 - p0).max() <= 1e-6 * max(1.0, float(np.abs(p0).max()))
    assert np.isfinite(sim.advance().positions).all()


def test_a_block_poured_on_a_merged_projection_rung_keeps_the_merge_on_the_explicit_step() -> None:
    """The projection steps water only: a sand block poured on ``g64-projection-rp0.25`` moves the simulator to
    the explicit rung of the same grid and the same merged particles (not back to the scene's own)."""
    sim = RealtimeSimulator("water2d", rung="g64-projection-rp0.25", adaptive=False)
    sim.advance()
    k = sim.solver.num_particles
    added = pour_block(sim, {"material": "sand", "lo": [0.6, 0.6], "hi": [0.7, 0.7]}) - k
    fr = sim.advance()
    assert sim.rung == "g64-explicit-rp0.25" and sim.solver.num_particles == k + added
    assert np.isfinite(fr.positions).all()


def test_with_another_material_poured_the_mode_steps_down_the_explicit_rungs_own_ladder(machine: Any, monkeypatch: pytest.MonkeyPatch) -> None:
    """A projection rung that is more accurate and faster than an explicit one drops it from the ladder. Once sand
    is poured into the water the projection steps nothing, and the explicit rungs are ranked among themselves:
    the mode takes the most accurate explicit rung that fits (here ``g64-explicit``, which the whole ladder
    dropped), not the next explicit rung the whole ladder kept."""
    errors = {"g128-explicit": 0.0, "g128-projection": 0.05, "g64-explicit": 0.10, "g64-projection": 0.12}
    errors |= {"g64-explicit-rp0.25": 0.2, "g64-projection-rp0.25": 0.25, "g64-explicit-rp0.0625": 0.3, "g64-projection-rp0.0625": 0.35}
    ratios = {"g128-explicit": 1.0, "g128-projection": 0.3, "g64-explicit": 0.5, "g64-projection": 0.15}
    ratios |= {"g64-explicit-rp0.25": 0.12, "g64-projection-rp0.25": 0.05, "g64-explicit-rp0.0625": 0.04, "g64-projection-rp0.0625": 0.02}
    chart = {"rungs": [{"key": k, "error": e, "time_ratio": ratios[k]} for k, e in errors.items()]}
    monkeypatch.setattr(rl, "realtime_chart", lambda scene: chart)
    scene = make_scene("water2d")
    assert "g64-explicit" not in [r.key for r in make_ladder(scene)]  # dominated by g128-projection
    assert [r.key for r in make_ladder(scene, ("explicit",))][:2] == ["g128-explicit", "g64-explicit"]
    budget = 2.5e-3 / rt.REALTIME_MARGIN
    m = machine({k: budget * (1.5 if k == "g128-explicit" else 0.75 * r / 0.5 if k == "g64-explicit" else 0.2) for k, r in ratios.items()})
    sim = RealtimeSimulator(scene, clock=m, rung="g128-projection")
    sim.advance()
    pour_block(sim, {"material": "sand", "lo": [0.6, 0.6], "hi": [0.7, 0.7]})
    seen = _run(sim, 1500)
    assert seen[0] == "g128-explicit" and seen[-1] == "g64-explicit", sim.changes


def test_a_burst_of_slow_frames_shorter_than_down_after_s_keeps_the_rung_a_lasting_one_steps_down(machine: Any) -> None:
    """Beside a page that draws, the frames slow down for a fraction of a second at a time. A rung whose frames
    fit the budget on average is kept through such bursts (0.4 s of three budgets a frame every 1.5 s, each shorter
    than DOWN_AFTER_S); a slowdown that lasts steps down."""
    assert rt.DOWN_AFTER_S > 0.4
    scene = make_scene("water2d")
    ladder = make_ladder(scene)
    budget = 2.5e-3 / rt.REALTIME_MARGIN
    base = {r.key: 0.6 * budget * r.time_ratio / ladder[0].time_ratio for r in ladder}
    m = machine(dict(base))
    sim = RealtimeSimulator(scene, clock=m)
    while m.t < 20.0:
        load = 5.0 if (m.t % 1.5) < 0.4 else 1.0
        m.cost = {k: v * load for k, v in base.items()}
        sim.advance()
    assert sim.rung == ladder[0].key and sim.changes == [], sim.changes
    m.cost = {k: 5.0 * v for k, v in base.items()}  # the machine slows and stays slow
    while m.t < 30.0:
        sim.advance()
    assert sim.rung != ladder[0].key and len(sim.changes) >= 1


def test_a_rung_slower_than_real_time_on_average_is_left_though_its_average_dips_under_the_budget(machine: Any) -> None:
    """Frames that alternate, 0.1 s fast (half a budget each) and 0.3 s slow (3.5 budgets), dip under the budget
    every 0.4 s, so the average is never over it for DOWN_AFTER_S at a stretch; but over any second they take
    longer than real time (2.8 ms a 2.5 ms frame): the mode steps down."""
    scene = make_scene("water2d")
    ladder = make_ladder(scene)
    budget = 2.5e-3 / rt.REALTIME_MARGIN
    base = {r.key: budget * r.time_ratio / ladder[0].time_ratio for r in ladder}
    m = machine(dict(base))
    sim = RealtimeSimulator(scene, clock=m)
    while m.t < 10.0 and not sim.changes:
        load = 0.5 if (m.t % 0.4) < 0.1 else 3.5
        m.cost = {k: v * load for k, v in base.items()}
        sim.advance()
    assert sim.changes and sim.changes[0]["from"] == ladder[0].key, sim.changes
