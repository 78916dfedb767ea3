"""Grid resolution as a knob: a scene on another grid of the same domain.

Checked against physics and geometry, not against earlier output: the walls'
faces stay where they were, mass is the same on every grid, free fall follows
g·t²/2 on every grid, the dam break still matches Martin & Moyce (1952) on
the coarse grids, a state moves between grids bit for bit when the particles
are the same, and a grid too coarse for a scene is refused naming the field.
Plus the classical front of the benchmark on hand-made rows.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from hybridmpm.bench.methods import mpm_grid_methods
from hybridmpm.bench.report import front_error_at, mpm_front
from hybridmpm.cli import main
from hybridmpm.errors import CheckpointError, InvalidInputError
from hybridmpm.metrics import grid_mass_error
from hybridmpm.mpm import MpmParams, WallParams
from hybridmpm.scenes import Block, SceneSpec, make_scene, scene_spec, wall_face
from hybridmpm.scenes.resolution import full_resolution, on_grid
from hybridmpm.sim import MpmSimulator, make_simulator, reference, rollout
from hybridmpm.validation import dam_break_front_height, score_dam_break


@pytest.mark.parametrize(("scene", "n"), [("water2d", 96), ("water2d", 64), ("sand2d", 64), ("water_sand2d", 64), ("water3d", 32), ("sand3d", 48)])
def test_same_blocks_walls_and_mass_on_a_coarser_grid(scene: str, n: int):
    fine, coarse = make_scene(scene, seed=11), make_scene(scene, seed=11, n_grid=n)
    assert coarse.params.resolved_n_grid() == n and coarse.info["base_n_grid"] == fine.params.resolved_n_grid()
    # walls: the face lies at the fine grid's face, or (when face·n is not an integer) less than one cell inside it
    f0, f1 = wall_face(fine.params), wall_face(coarse.params)
    assert f0 <= f1 < f0 + 1.0 / n
    if float(f0 * n).is_integer():
        assert f1 == pytest.approx(f0, abs=1e-12)
    # the same blocks in metres: the same total mass (density × block volume), the same bounding box within a lattice spacing
    m0, m1 = fine.make_solver(num_threads=1).masses.sum(), coarse.make_solver(num_threads=1).masses.sum()
    assert m1 == pytest.approx(m0, rel=1e-5)
    for s in (fine, coarse):
        assert np.all(s.positions >= 1.0 / s.params.resolved_n_grid())
    for d in range(fine.dim):
        assert coarse.positions[:, d].min() == pytest.approx(fine.positions[:, d].min(), abs=1.0 / (2 * n))
        assert coarse.positions[:, d].max() == pytest.approx(fine.positions[:, d].max(), abs=1.0 / (2 * n))
    # 2 particles per cell per axis: 2^D fewer particles per halving of the grid (the registry's blocks are disjoint;
    # on a 3/4 grid the lattice rounds each side to whole particles)
    if fine.params.resolved_n_grid() % n == 0:
        assert coarse.num_particles == fine.num_particles * (n / fine.params.resolved_n_grid()) ** fine.dim
    # its reference is the fine scene, bit for bit
    ref = full_resolution(coarse)
    assert np.array_equal(ref.positions, fine.positions) and ref.params.resolved_n_grid() == fine.params.resolved_n_grid()


@pytest.mark.parametrize("n", [128, 96, 64])
def test_free_fall_on_every_grid(n: int):
    """A block far from every wall falls as the integrator's g·t²/2 (its centre of mass) on every grid."""
    spec = SceneSpec("drop", MpmParams(dim=2, n_grid=128), [Block("water", [0.4, 0.5], [0.6, 0.7])], frames=40).on_grid(n)
    sim = MpmSimulator(spec.build(), threads=1)
    y0 = sim.fluid_positions[:, 1].mean()
    ro = rollout(sim, 40)
    t = 40 * spec.dt_frame
    drop = y0 - ro.fluid_positions[-1][:, 1].mean()
    # symplectic Euler (v += g·Δt, then x += v·Δt) over the substeps each frame took: g·t²/2 as Δt → 0
    v = x = 0.0
    for k in ro.substeps[1:]:
        dt = spec.dt_frame / int(k)
        for _ in range(int(k)):
            v += 9.8 * dt
            x += v * dt
    assert x == pytest.approx(0.5 * 9.8 * t * t, rel=5e-3)
    assert drop == pytest.approx(x, rel=2e-4)


@pytest.mark.parametrize("n", [96, 64])
def test_dam_break_matches_martin_moyce_on_coarse_grids(n: int):
    """The published-experiment test of the engine (tests/test_dam_break.py) on the 3/4 and half grids: the same tolerances."""
    scene = make_scene("dam_break2d", n_grid=n)
    sim = scene.make_solver()
    frames = 140
    pos = np.empty((frames + 1, scene.num_particles, 2), np.float32)
    pos[0] = sim.positions
    for f in range(frames):
        sim.step_frame(scene.dt_frame)
        pos[f + 1] = sim.positions
    info = scene.info
    assert info["spacing"] == pytest.approx(0.5 / n)
    z, h = dam_break_front_height(pos, info["a"], info["x_wall"], info["y_floor"], info["spacing"])
    score = score_dam_break(np.arange(frames + 1) * scene.dt_frame, z, h, info["a"])
    assert score.rms_front_shifted <= 0.12, score
    assert 0.90 <= score.ratio_min and score.ratio_max <= 1.32 and score.shallow_water_ok, score
    assert 0.85 <= score.height_ratio_min and score.height_ratio_max <= 1.25, score


def test_the_rough_floor_brakes_a_sliding_sand_layer_alike_on_every_grid():
    """Coulomb friction acts on the nodes of the floor's band, whose stencil reaches 1.5 cells into the sand: twice as far
    in metres on the half grid. A sand layer two cells of 64² thick sliding at 1.5 m/s must still lose its speed at the
    same rate on every grid, stopping near a rigid block's v²/(2μg) (docs/engine.md, "Coarse grids and sand")."""
    mu, speed = math.tan(math.radians(30.0)), 1.5
    params = MpmParams(dim=2, n_grid=128, walls=WallParams(friction=mu))
    face = wall_face(params)
    spec = SceneSpec("slide", params, [Block("sand", [0.1, face], [0.4, face + 2 / 64], [speed, 0.0])], frames=200)
    travel = {}
    for n in (128, 96, 64):
        sim = (spec if n == 128 else spec.on_grid(n)).build().make_solver(num_threads=1)
        x0 = float(np.mean(sim.positions[:, 0]))
        for _ in range(spec.frames):
            sim.step_frame()
        assert float(np.abs(sim.velocities).max()) < 0.02, f"{n}²: still sliding"
        travel[n] = float(np.mean(sim.positions[:, 0])) - x0
    rigid = speed**2 / (2 * mu * 9.81)
    for n, d in travel.items():
        assert 0.95 <= d / rigid <= 1.15, (n, d, rigid)
        assert d == pytest.approx(travel[128], rel=0.06), travel


def test_a_state_moves_between_grids_bit_for_bit_with_the_same_particles():
    scene = make_scene("water2d", seed=5)
    coarse = MpmSimulator(scene, n_grid=64, keep_particles=True, threads=1)
    fine = MpmSimulator(scene, threads=1)
    assert coarse.scene.num_particles == scene.num_particles
    assert np.array_equal(coarse.solver.masses, fine.solver.masses) and np.array_equal(coarse.solver.volumes, fine.solver.volumes)
    rollout(coarse, 12)
    blob = coarse.solver.checkpoint()
    fine.solver.restore_particles(blob)
    for name in ("positions", "velocities", "affine", "volume_ratio"):
        assert np.array_equal(getattr(fine.solver, name), getattr(coarse.solver, name)), name
    # and back: the fine solver's frame moves onto the coarse grid exactly
    fine.advance()
    coarse.solver.restore_particles(fine.solver.checkpoint())
    assert np.array_equal(coarse.solver.positions, fine.solver.positions)
    # other particles, or other physics, are refused
    other = MpmSimulator(make_scene("water2d", seed=6), n_grid=64, threads=1)
    with pytest.raises(CheckpointError):
        other.solver.restore_particles(blob)
    sand = MpmSimulator(make_scene("sand2d", seed=5), threads=1)
    with pytest.raises(CheckpointError):
        sand.solver.restore_particles(blob)


def test_kept_particles_keep_their_mass_and_reference():
    scene = make_scene("sand2d", seed=3)
    kept = on_grid(scene, 64, keep_particles=True)
    assert kept.num_particles == scene.num_particles and np.array_equal(kept.positions, scene.positions)
    assert kept.params.resolved_n_grid() == 64 and kept.params.walls.cells == 2
    assert np.array_equal(full_resolution(kept).positions, scene.positions)
    with pytest.raises(InvalidInputError, match="particles_per_cell"):
        on_grid(scene, 64, 2, keep_particles=True)


def _field(fn) -> str:  # type: ignore[no-untyped-def]
    with pytest.raises(InvalidInputError) as e:
        fn()
    return str(e.value.field)


def test_a_grid_too_coarse_for_the_scene_names_the_field():
    # ramps are two cells of the 128 grid thick: no coarser grid holds them
    assert _field(lambda: make_scene("water_ramps2d", seed=1, n_grid=96)) == "obstacles[0].half_extents"
    for bad in (64.5, "64", True, 10**6, 8, -64):
        assert _field(lambda bad=bad: make_scene("water2d", seed=1, n_grid=bad)) == "n_grid"
    for bad in (0, 5, 2.0):
        assert _field(lambda bad=bad: make_scene("water2d", seed=1, n_grid=64, particles_per_cell=bad)) == "particles_per_cell"
    thin = SceneSpec("thin", MpmParams(dim=2, n_grid=128), [Block("water", [0.3, 0.3], [0.6, 0.3 + 1.5 / 128])])
    assert _field(lambda: thin.on_grid(64)) == "blocks[0]"
    thin.on_grid(96)  # 2 cells of 128 are 1.5 of 96: still a cell thick
    thick_walls = SceneSpec("walls", MpmParams(dim=2, n_grid=128, walls=WallParams(cells=20)), [Block("water", [0.3, 0.3], [0.6, 0.6])])
    assert thick_walls.on_grid(32).params.walls.cells == 6  # the face at 19/128 m: 4.75 cells of 32, the next node in
    assert _field(lambda: thick_walls.on_grid(16)) == "n_grid"
    # a grid is a knob of plain MPM; a network runs at its model's resolution
    assert _field(lambda: make_simulator("water2d", "neural", n_grid=64)) == "n_grid"
    # the bench leaves refused grids out, with the reason
    methods, refused = mpm_grid_methods("water_ramps2d", 0.5714)
    assert methods == [] and set(refused) == {96, 64} and "thinner than 2 grid cells" in refused[64]


def test_other_lattices_carry_their_own_volume():
    """3 particles per cell per axis fill the same blocks with the same mass (a lattice's volume is spacing^D, not (dx/2)^D)."""
    spec = scene_spec("water2d", seed=4)
    two, three = spec.build(), spec.on_grid(128, 3).build()
    assert three.num_particles == pytest.approx(two.num_particles * 9 / 4, rel=0.02)
    assert three.make_solver(num_threads=1).masses.sum() == pytest.approx(two.make_solver(num_threads=1).masses.sum(), rel=1e-5)


def test_simulate_on_a_coarse_grid_reports_error_against_the_fine_reference(tmp_path: Path):
    out = tmp_path / "c"
    assert (
        main(
            [
                "simulate",
                "water2d",
                "--solver",
                "mpm",
                "--n-grid",
                "64",
                "--seed",
                "3",
                "--frames",
                "20",
                "--reference",
                "--out",
                str(out),
                "--no-render",
                "--quiet",
            ]
        )
        == 0
    )
    summary = json.loads((out / "summary.json").read_text())
    coarse = make_scene("water2d", seed=3, n_grid=64)
    fine = make_scene("water2d", seed=3)
    assert summary["n_grid"] == 64 and summary["particles"] == coarse.num_particles
    assert summary["reference"]["particles"] == fine.num_particles
    # the error is measured on the reference's grid, against an independent fine rollout
    ro = rollout(MpmSimulator(coarse, threads=1), 20)
    err = grid_mass_error(ro.fluid_positions, reference(fine, 20).fluid_positions, 128)
    assert summary["reference"]["grid_mass_error"]["mean"] == pytest.approx(float(err.mean()), rel=1e-6)
    assert 0.0 < err.mean() < 0.5


def _row(key: str, kind: str, ms: float, err: float) -> dict:
    return {"key": key, "kind": kind, "ms_mean": ms, "error_mean": err, "failures": 0}


def test_classical_front_and_its_error_at_equal_time():
    rows = [
        _row("mpm_full", "mpm", 8.0, 0.0),
        _row("mpm_rp", "mpm", 5.0, 0.2),  # dominated by mpm_g96 (faster, more accurate)
        _row("mpm_g96", "mpm", 4.0, 0.15),
        _row("mpm_g64", "mpm", 1.0, 0.3),
        _row("neural", "neural", 2.0, 0.5),
    ]
    front = mpm_front(rows)
    assert [r["key"] for r in front] == ["mpm_g64", "mpm_g96", "mpm_full"]
    # at 2 ms: halfway in log time between 1 ms (0.3) and 4 ms (0.15)
    assert front_error_at(front, 2.0) == pytest.approx(0.225)
    assert front_error_at(front, 4.0) == pytest.approx(0.15)
    assert front_error_at(front, 16.0) == 0.0
    assert math.isnan(front_error_at(front, 0.5))  # faster than any plain MPM measured
    # brute force: the interpolation is monotone between the front points
    xs = np.geomspace(1.0, 8.0, 50)
    ys = [front_error_at(front, float(x)) for x in xs]
    assert all(a >= b - 1e-12 for a, b in zip(ys, ys[1:]))


def test_the_classical_twin_hands_over_without_moving_a_particle():
    """The hybrid with MPM on half the grid as its cheap half: its MPM steps are bit for bit those of MPM at r_p on
    the scene's grid from the state the coarse grid handed over, and a rule that never leaves the coarse grid is
    bit for bit MPM on that grid with the same particles."""
    from hybridmpm.sim import HybridSimulator
    from hybridmpm.sim.coarse import COARSE

    twin = HybridSimulator("water2d", seed=12, cheap="mpm-coarse", safeguard="paper", r_c=-1.0, mpm_threads=1)  # r_c <= 0: the cheap half only
    assert twin.cheap_kind == COARSE and twin.neural.n_grid == 64
    ro = rollout(twin, 60)
    assert ro.stats["steps"][COARSE] > 0 and set(ro.solver[1:].tolist()) <= {COARSE, "mpm"}
    # the same particles on the coarse grid alone: the warm-up on the fine grid, then the coarse grid from its state
    warm = int(np.sum(ro.solver[1:] == "mpm"))
    fine = MpmSimulator(twin.scene, r_t=twin.r_t, threads=1)
    rollout(fine, warm * twin.r_t)
    coarse = MpmSimulator(on_grid(twin.scene, 64, keep_particles=True), r_t=twin.r_t, threads=1)
    coarse.solver.restore_particles(fine.solver.checkpoint())
    alone = rollout(coarse, (len(ro.solver) - 1 - warm) * twin.r_t)
    assert np.array_equal(alone.fluid_positions[-1], ro.fluid_positions[-1])
    # its state round-trips, and a twin's state is refused by the GNS hybrid
    st = twin.state()
    a = rollout(twin, 8).positions
    twin.restore(st)
    assert np.array_equal(rollout(twin, 8).positions, a)
    with pytest.raises(InvalidInputError):
        HybridSimulator("water2d", seed=12, mpm_threads=1).restore(st)
    assert _field(lambda: HybridSimulator("water2d", seed=12, cheap="mpm-coarse", cheap_grid=8)) == "n_grid"
    assert _field(lambda: HybridSimulator("water2d", seed=12, cheap="tensor")) == "cheap"


def test_the_coarse_half_takes_over_a_particle_in_the_fine_grids_outer_strip():
    """The fine grid's domain reaches a fine cell further out than the coarse one's: a particle the fine grid left
    there (inside the wall band) is moved onto the coarse domain's edge, every other particle moves bit for bit,
    and the fine solver is left as it was (found by the bench: water2d seed 1001 stopped on it)."""
    from hybridmpm.sim.coarse import CoarseMpmHalf

    scene = make_scene("water2d", seed=3)
    half = CoarseMpmHalf(scene, r_t=1, threads=1)
    fine = scene.make_solver(num_threads=1)
    lo_f, hi_f = fine.domain_bounds
    lo_c, hi_c = half.sim.solver.domain_bounds
    assert lo_f < lo_c and hi_c < hi_f
    pos = fine.positions
    pos[0] = [hi_f - 1e-4, lo_f + 1e-4]  # in the strip at two sides
    fine.positions = pos
    before = fine.checkpoint()
    half.take_over(fine)
    got = half.sim.solver.positions
    assert fine.checkpoint() == before
    assert np.array_equal(got[1:], pos[1:]) and np.array_equal(half.sim.solver.velocities, fine.velocities)
    assert np.allclose(got[0], [hi_c, lo_c]) and np.all(np.abs(got[0] - pos[0]) < 1.0 / 128)
    half.sim.advance()  # and the coarse grid steps on


def test_tune_can_choose_a_coarse_grid_and_simulate_auto_runs_it(tmp_path: Path):
    """tune's choice is the cheapest row within the budget; a coarse grid that is cheapest is chosen, written with its
    grid, and `simulate --solver auto` runs MPM on that grid."""
    from hybridmpm.bench import choose
    from hybridmpm.bench.methods import Method
    from hybridmpm.bench.tune import write_tuned

    def row(m: Method, err: float, ms: float) -> dict:
        return {**m.config(), "error_mean": err, "error_last": err, "ms_mean": ms, "ms_median": ms, "ms_p95": ms, "mpm_share": 1.0, "failures": 0}

    rows = [
        row(Method("mpm_full", "mpm", "MPM full resolution"), 0.0, 4.0),
        row(Method("mpm_rp", "mpm", "MPM r_p", 0.5714, role="mpm_rp"), 0.30, 2.5),
        row(Method("mpm_g64", "mpm", "MPM 64^2", role="mpm_grid", n_grid=64), 0.35, 0.6),
        row(Method("neural", "neural", "neural", 0.5714, 4, role="lowres"), 0.55, 1.4),
    ]
    chosen = choose(rows, 0.4)
    assert chosen["key"] == "mpm_g64"
    path = tmp_path / "tuned.json"
    write_tuned(path, "water2d", 0.4, "error_mean", chosen, rows, [2000], {"frames": 8})
    out = tmp_path / "auto"
    assert (
        main(["simulate", "water2d", "--solver", "auto", "--tuned", str(path), "--seed", "3", "--frames", "4", "--out", str(out), "--no-render", "--quiet"])
        == 0
    )
    summary = json.loads((out / "summary.json").read_text())
    assert summary["solver"] == "mpm" and summary["n_grid"] == 64 and summary["particles"] == make_scene("water2d", seed=3, n_grid=64).num_particles
