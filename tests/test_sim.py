"""The simulator interface (hybridmpm.sim): the protocol, the forcing hook
against Newton's second law, the hybrid handing control to MPM while a forcing
is set, whole-state checkpoints, rollout break-offs, and the particle set."""

from __future__ import annotations

import numpy as np
import pytest

from hybridmpm.conventions import GNS_KINEMATIC, GNS_SAND, GNS_TYPE_OF_MATERIAL, GNS_WATER, MATERIAL_SAND, MATERIAL_WATER
from hybridmpm.errors import InvalidInputError
from hybridmpm.models import shipped_model
from hybridmpm.mpm import MpmParams
from hybridmpm.neural import GnsRuntime
from hybridmpm.scenes import Scene, lattice, make_scene
from hybridmpm.sim import (
    MPM,
    NEURAL,
    Frame,
    HybridSimulator,
    MpmSimulator,
    NeuralSimulator,
    Simulator,
    make_simulator,
    reference,
    rollout,
)
from hybridmpm.trajectory import all_finite


@pytest.fixture(scope="module")
def water_model() -> GnsRuntime:
    return GnsRuntime(shipped_model("water2d"))


def blob(gravity=(0.0, -9.8)) -> Scene:
    """A small water square in the middle of the tank, far from every wall."""
    p = MpmParams(dim=2, gravity=list(gravity))
    x = lattice([0.45, 0.45], [0.55, 0.55], 0.5 / 128)
    return Scene("blob", p, x, np.zeros(len(x), np.int32), np.zeros_like(x))


def com_velocity(sim: MpmSimulator) -> np.ndarray:
    m = sim.particles.masses.astype(np.float64)
    return (m[:, None] * sim.solver.velocities).sum(0) / m.sum()


# ----------------------------------------------------------------- protocol
def test_the_three_simulators_share_the_protocol(water_model):
    scene = make_scene("water2d", seed=5)
    sims = [MpmSimulator(scene, threads=1), NeuralSimulator(scene, water_model, mpm_threads=1), HybridSimulator(scene, water_model, mpm_threads=1)]
    for sim in sims:
        assert isinstance(sim, Simulator)
        assert isinstance(sim.frame, Frame) and sim.frame.step == 0 and sim.frame.solver == MPM
        assert sim.positions.shape == (sim.particles.num_total, 2) and sim.positions.dtype == np.float32
        fr = sim.advance()
        assert fr.step == 1 and fr.frame_index == sim.r_t and fr.time == pytest.approx(sim.r_t * 2.5e-3) and fr.seconds > 0
        assert sim.frame is fr


def test_make_simulator_builds_each_kind_and_names_bad_settings(water_model):
    scene = make_scene("water2d", seed=5)
    assert isinstance(make_simulator(scene, "mpm", r_p=0.5, threads=1), MpmSimulator)
    assert isinstance(make_simulator(scene, "neural", model=water_model, threads=1), NeuralSimulator)
    assert isinstance(make_simulator(scene, "hybrid", model=water_model, threads=1), HybridSimulator)
    with pytest.raises(InvalidInputError) as e:
        make_simulator(scene, "magic")
    assert e.value.field == "solver"
    with pytest.raises(InvalidInputError) as e:
        make_simulator(scene, "neural", model=water_model, r_p=0.5)
    assert e.value.field == "r_p"


# ------------------------------------------------------------------ forcing
def test_a_constant_forcing_accelerates_the_centre_of_mass_by_newtons_law():
    # away from the walls MLS-MPM conserves momentum exactly in p2g/g2p: the
    # centre of mass accelerates at gravity + the applied acceleration
    a = np.array([3.0, 12.0])
    sim = MpmSimulator(blob(), threads=1)
    sim.forcing = np.tile(a.astype(np.float32), (sim.particles.num_fluid, 1))
    ro = rollout(sim, 8)
    assert ro.controlled[1:].all() and not ro.controlled[0]
    want = (a + np.array([0.0, -9.8])) * 8 * 2.5e-3
    np.testing.assert_allclose(com_velocity(sim), want, rtol=2e-4, atol=1e-5)
    # cleared: gravity alone from then on
    sim.forcing = None
    v0 = com_velocity(sim)
    ro = rollout(sim, 4)
    assert not ro.controlled[1:].any()  # (the first entry is the last forced frame)
    np.testing.assert_allclose(com_velocity(sim) - v0, [0.0, -9.8 * 4 * 2.5e-3], rtol=2e-4, atol=1e-5)


def test_a_forcing_callable_is_asked_for_every_frame_by_its_index():
    asked: list[int] = []
    sim = MpmSimulator(blob(gravity=(0.0, 0.0)), r_t=2, threads=1)
    push = np.tile(np.array([[5.0, 0.0]], np.float32), (sim.particles.num_fluid, 1))

    def forcing(frame: int, positions: np.ndarray, velocities: np.ndarray):
        assert positions.shape == velocities.shape == (sim.particles.num_fluid, 2)
        asked.append(frame)
        return push if frame < 3 else None

    sim.forcing = forcing
    ro = rollout(sim, 6)
    assert asked == [0, 1, 2, 3, 4, 5]
    assert list(ro.controlled) == [False, True, True, False]
    np.testing.assert_allclose(com_velocity(sim), [5.0 * 3 * 2.5e-3, 0.0], rtol=2e-4, atol=1e-6)


def test_bad_forcings_name_the_field(water_model):
    sim = MpmSimulator(blob(), threads=1)
    n = sim.particles.num_fluid
    for bad in (np.zeros((n + 1, 2)), np.zeros((n, 3)), np.full((n, 2), np.nan), np.array(["a"] * n)):
        with pytest.raises(InvalidInputError) as e:
            sim.forcing = bad
        assert e.value.field == "forcing"
    sim.forcing = lambda f, x, v: np.zeros((3, 2))  # wrong shape, found when used
    with pytest.raises(InvalidInputError, match="forcing"):
        sim.advance()
    neural = NeuralSimulator(make_scene("water2d", seed=5), water_model, mpm_threads=1)
    with pytest.raises(InvalidInputError, match="MPM") as e:
        neural.forcing = np.zeros((neural.particles.num_fluid, 2))
    assert e.value.field == "forcing"
    neural.forcing = None  # allowed: nothing to apply


def test_the_hybrid_runs_mpm_while_a_forcing_is_set(water_model):
    sim = HybridSimulator(make_scene("water2d", seed=1000), water_model, r_c=0.0, dwell=3, mpm_threads=1)
    ro = rollout(sim, 40)  # warm-up on MPM, then the network (no complexity trigger)
    assert ro.solver[-1] == NEURAL
    n = sim.particles.num_fluid
    sim.forcing = np.tile(np.array([[0.0, 9.8]], np.float32), (n, 1))  # cancel gravity
    forced = [sim.advance() for _ in range(4)]
    assert [f.solver for f in forced] == [MPM] * 4 and all(f.controlled for f in forced)
    assert forced[0].event == "switch:mpm"
    sim.forcing = None
    after = rollout(sim, 40)
    tags = list(after.solver[1:])
    assert not after.controlled[1:].any()
    assert tags[:2] == [MPM, MPM] and NEURAL in tags  # dwell calm steps on MPM, then the network again
    assert tags.index(NEURAL) == 3  # dwell = 3 steps of s >= r_c, then the hand-over


# ---------------------------------------------------------------- checkpoint
@pytest.mark.parametrize("kind", ["mpm", "neural_warmup", "neural", "hybrid"])
def test_state_restore_continues_bit_for_bit(kind, water_model):
    scene = make_scene("water2d", seed=1001)
    sim: Simulator
    if kind == "mpm":
        sim = MpmSimulator(scene, r_t=2, threads=1)
    elif kind.startswith("neural"):
        sim = NeuralSimulator(scene, water_model, mpm_threads=1)
    else:
        sim = HybridSimulator(scene, water_model, mpm_threads=1)
    rollout(sim, 8 if kind == "neural_warmup" else 60)
    if kind == "neural_warmup":
        assert sim.warming_up  # type: ignore[attr-defined]
    st = sim.state()
    a = rollout(sim, 60)
    sim.restore(st)
    assert sim.frame.frame_index == a.frame_index[0]
    b = rollout(sim, 60)
    assert np.array_equal(a.positions, b.positions) and np.array_equal(a.solver, b.solver)
    with pytest.raises(InvalidInputError) as e:
        sim.restore({**st, "version": 99})
    assert e.value.field == "state"
    c = rollout(sim, 4)  # a refused state changes nothing
    assert c.frame_index[0] == b.frame_index[-1]


def test_a_foreign_state_is_refused(water_model):
    mpm = MpmSimulator(make_scene("water2d", seed=1), threads=1)
    other = MpmSimulator(make_scene("sand2d", seed=1), threads=1)
    with pytest.raises(InvalidInputError):
        mpm.restore(HybridSimulator(make_scene("water2d", seed=1), water_model, mpm_threads=1).state())
    with pytest.raises(Exception, match="parameters|particle"):
        mpm.restore(other.state())


# -------------------------------------------------------------------- rollout
def test_rollout_breaks_off_and_keeps_what_came_before(water_model):
    sim = NeuralSimulator(make_scene("water2d", seed=1000), water_model, mpm_threads=1)
    ro = rollout(sim, 200, stop=lambda fr, s: "enough" if fr.frame_index >= 40 else None)
    assert ro.failure == "enough" and ro.frame_index[-1] == 40 and ro.frames_done == 40
    with pytest.raises(InvalidInputError) as e:
        rollout(sim, -1)
    assert e.value.field == "frames"


def test_a_rollout_keeps_each_frame_as_the_simulator_made_it():
    sim = MpmSimulator(blob(), threads=1)
    seen = [sim.positions.copy()]
    ro = rollout(sim, 6, on_frame=lambda fr: seen.append(sim.positions.copy()))
    assert ro.positions.shape == (7, *seen[0].shape) and ro.positions.dtype == np.float32
    assert all(np.array_equal(ro.positions[k], seen[k]) for k in range(7))
    assert not np.array_equal(ro.positions[1], ro.positions[6])  # each frame its own row, the water falling
    short = rollout(sim, 50, stop=lambda fr, s: "enough" if fr.frame_index >= 8 else None)
    assert short.positions.shape[0] == len(short.frame_index) == 3


class _Shrinking(MpmSimulator):
    """Returns a frame with a particle fewer from the second step: a rollout keeps one particle count."""

    def advance(self) -> Frame:
        fr = super().advance()
        return Frame(fr.step, fr.frame_index, fr.time, fr.positions[:-1], fr.solver) if fr.step >= 2 else fr


def test_a_frame_with_another_particle_count_is_refused_naming_positions():
    sim = _Shrinking(blob(), threads=1)
    n = sim.particles.num_total
    with pytest.raises(InvalidInputError, match=rf"got \[{n - 1}, 2\]") as e:
        rollout(sim, 5)
    assert e.value.field == "positions"


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_all_finite_agrees_with_isfinite_everywhere(dtype):
    rng = np.random.default_rng(5)
    assert all_finite(np.zeros((0, 3), dtype))
    for bad in (np.nan, np.inf, -np.inf, None):
        for _ in range(20):
            x = rng.normal(size=(int(rng.integers(1, 50)), 3)).astype(dtype) * 1e30
            if bad is not None:
                x.flat[int(rng.integers(x.size))] = bad
            assert all_finite(x) == bool(np.isfinite(x).all())


class _Exploding(GnsRuntime):
    def predict(self, history, particle_type, max_neighbors=None, graph=None):
        acc, nxt, g = super().predict(history, particle_type, max_neighbors, graph)
        return acc, nxt + 1.0, g  # 1 m in one step: escapes the domain


def test_the_escape_check_is_per_axis_and_per_side(water_model):
    """The failure check's "escaped" verdict (a fluid particle more than
    ``escape_cells`` cells outside the model's bounds, on either side of any
    axis) against the [N, D] comparison written out, with bounds that differ
    per axis and side, each particle pushed just inside and just outside."""
    sim = NeuralSimulator(make_scene("water2d", seed=1000), water_model, mpm_threads=1)
    sim._lo, sim._hi = np.array([0.05, 0.2], np.float32), np.array([0.9, 0.7], np.float32)
    sim._escape_key = None  # the bounds changed under the cache
    n = sim.particles.num_fluid
    margin = np.float32(sim.escape_cells * sim._dx)
    rng = np.random.default_rng(0)
    base = (sim._lo + (sim._hi - sim._lo) * rng.random((n, 2))).astype(np.float32)
    sim._history = np.stack([base] * sim.t_in)  # no motion: no kinetic energy
    assert sim.failure_of(base) is None
    for axis in (0, 1):
        for side, edge in ((-1, sim._lo - margin), (1, sim._hi + margin)):
            for eps, verdict in ((-1e-3, None), (1e-3, "escaped")):
                x = base.copy()
                x[rng.integers(n), axis] = edge[axis] + side * eps
                want = "escaped" if ((x < sim._lo - margin).any() or (x > sim._hi + margin).any()) else None
                assert want == verdict
                # only the position check can fire: undo the step's kinetic energy
                sim._history = np.stack([x] * sim.t_in)
                assert sim.failure_of(x) == verdict, (axis, side, eps)


def test_a_particle_carried_through_a_wall_by_its_own_speed_has_not_escaped(water_model):
    """A particle on the wall whose last step was L cells lands up to
    L + escape_cells cells beyond it by inertia (the wall clips it next): not
    "escaped"; one cell farther than that, or the same landing from rest, is."""
    sim = NeuralSimulator(make_scene("water2d", seed=1000), water_model, mpm_threads=1)
    n = sim.particles.num_fluid
    base = ((sim._lo + sim._hi) / 2 + np.zeros((n, 2))).astype(np.float32)
    base += np.random.default_rng(0).normal(0, 1e-3, base.shape).astype(np.float32)
    dx, margin = np.float32(sim._dx), sim.escape_cells
    for step_cells in (0.0, 6.0):
        hist = np.stack([base] * sim.t_in)
        hist[-1, 0, 0] = sim._lo[0]  # on the left wall
        hist[-2, 0, 0] = sim._lo[0] + step_cells * dx  # coming from the right at step_cells per step
        for beyond, verdict in ((step_cells + margin - 0.1, None), (step_cells + margin + 1.0, "escaped")):
            sim._history = hist
            x = hist[-1].copy()
            x[0, 0] = sim._lo[0] - beyond * dx
            # the energy check alone would not fire: a single particle's kinetic energy
            assert sim.failure_of(x) == verdict, (step_cells, beyond)


def test_a_rejected_network_step_ends_the_network_alone_unchanged():
    sim = NeuralSimulator(make_scene("water2d", seed=3), _Exploding(shipped_model("water2d")), mpm_threads=1)
    ro = rollout(sim, 100)
    assert ro.failure == "escaped" and set(ro.solver) == {MPM}  # the warm-up survives
    assert len(ro.positions) == sim.t_in and np.array_equal(sim.positions, ro.positions[-1])
    assert sim.stats.fallbacks == {"escaped": 1}


def test_reference_rebuilds_a_clustered_scene_at_full_resolution(water_model):
    full = make_scene("water2d", seed=6)
    low = MpmSimulator(full, r_p=0.5, seed=6).scene
    assert low.num_particles < full.num_particles
    a = reference(full, 12, stride=4, threads=1)
    b = reference(low, 12, stride=4, threads=1)
    assert np.array_equal(a.positions, b.positions) and a.frame_index.tolist() == [0, 4, 8, 12]


def test_a_rollout_saves_as_a_trajectory(tmp_path, water_model):
    from hybridmpm.trajectory import Trajectory

    ro = rollout(HybridSimulator(make_scene("water_ramps2d", seed=2), mpm_threads=1), 40)
    path = ro.save(tmp_path / "t.npz")
    tr = Trajectory.load(path)
    assert np.array_equal(tr.positions, ro.positions) and tr.dt_frame == pytest.approx(ro.r_t * 2.5e-3)
    assert np.array_equal(tr.extras["solver"], (ro.solver == NEURAL).astype(np.int8))
    n = ro.num_fluid
    assert (tr.particle_type[n:] == GNS_KINEMATIC).all() and (tr.masses[n:] == 0).all() and (tr.material[n:] == -1).all()


# ---------------------------------------------------------- particles, codes
def test_particle_set_pads_and_slices_in_one_place():
    scene = make_scene("water_ramps2d", seed=2)
    p = MpmSimulator(scene, threads=1).particles
    assert p.num_boundary == scene.num_boundary > 0 and p.num_total == scene.num_particles + scene.num_boundary
    x = np.random.default_rng(0).random((3, p.num_fluid, 2)).astype(np.float32)
    full = p.pad(x)
    assert full.shape == (3, p.num_total, 2) and np.array_equal(p.fluid(full), x)
    assert np.array_equal(full[1, p.num_fluid :], scene.boundary_positions)
    assert p.fluid_mask.sum() == p.num_fluid
    with pytest.raises(InvalidInputError) as e:
        p.pad(x[:, :-1])
    assert e.value.field == "positions"


def test_material_codes_and_gns_types_are_distinct_tables():
    assert (MATERIAL_WATER, MATERIAL_SAND) == (0, 1)
    assert (GNS_KINEMATIC, GNS_WATER, GNS_SAND) == (3, 5, 6)  # DeepMind learning_to_simulate
    scene = make_scene("water_sand2d", seed=1)
    pt = scene.particle_type()
    for mat, gns in GNS_TYPE_OF_MATERIAL.items():
        assert (pt[: scene.num_particles][scene.material == mat] == gns).all()


def test_neural_history_errors_name_the_field(water_model):
    sim = NeuralSimulator(make_scene("water2d", seed=5), water_model, warmup=False, mpm_threads=1)
    n = sim.particles.num_fluid
    with pytest.raises(InvalidInputError) as e:
        sim.advance()
    assert e.value.field == "history"
    with pytest.raises(InvalidInputError) as e:
        sim.set_history(np.zeros((sim.t_in - 1, n, 2), np.float32))
    assert e.value.field == "history"
    bad = np.full((sim.t_in, n, 2), 0.5, np.float32)
    bad[0, 0, 0] = np.nan
    with pytest.raises(InvalidInputError) as e:
        sim.set_history(bad)
    assert e.value.field == "history"


# ------------------------------------------------------------------ threads
def test_a_simulator_shared_by_two_threads_steps_and_reads_consistently(water_model):
    import threading
    import time

    scene = make_scene("water2d", seed=1002)
    want = rollout(HybridSimulator(scene, water_model, mpm_threads=1), 120).positions  # the same run, alone
    sim = HybridSimulator(scene, water_model, mpm_threads=1)
    errors: list[BaseException] = []
    seen: list[Frame] = []
    done = threading.Event()

    def stepper() -> None:
        try:
            for _ in range(30):
                sim.advance()
                time.sleep(0.002)  # a paced loop (a real-time session): the lock is not fair, a tight loop would starve the reader
        except BaseException as e:  # noqa: BLE001 - reported below
            errors.append(e)
        finally:
            done.set()

    def reader() -> None:
        try:
            k = 0
            while not done.is_set():
                seen.append(sim.frame)  # never waits
                if k % 5 == 0:
                    sim.state()  # waits for the step in progress, then a whole-state snapshot
                k += 1
                time.sleep(0.0005)
        except BaseException as e:  # noqa: BLE001
            errors.append(e)

    threads = [threading.Thread(target=stepper), threading.Thread(target=reader)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(timeout=300)
    assert not errors, errors
    assert len({fr.step for fr in seen}) > 5
    for fr in seen:  # every frame read is one the run alone produced at that step
        assert np.array_equal(fr.positions, want[fr.step])
    assert np.array_equal(sim.positions, want[-1])
