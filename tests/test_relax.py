"""Density relaxation between network steps (``hybridmpm.graph.relax_density``,
``relax_then_graph``, ``NeuralSimulator(relax=...)``): against a brute-force
density, against the packing it must undo, against the three calls it fuses,
and on the shipped dam-break model's own rollout."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.distance import cdist

from hybridmpm.errors import InvalidInputError
from hybridmpm.graph import kernel_density, radius_graph, relax_density, relax_then_graph


def _brute_density(x: np.ndarray, radius: float) -> np.ndarray:
    q = cdist(x.astype(np.float64), x.astype(np.float64)) / radius
    return (np.clip(1 - q, 0, None) ** 2).sum(1)


def _lattice(n: int, spacing: float, dim: int = 2) -> np.ndarray:
    axes = [np.arange(n) * spacing] * dim
    return np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, dim).astype(np.float32)


@pytest.mark.parametrize("dim", [2, 3])
def test_kernel_density_matches_brute_force(dim):
    rng = np.random.default_rng(dim)
    x = rng.random((400, dim)).astype(np.float32)
    np.testing.assert_allclose(kernel_density(x, 0.15), _brute_density(x, 0.15), rtol=1e-5, atol=1e-5)


@pytest.mark.parametrize("dim", [2, 3])
def test_relaxation_undoes_compression_and_leaves_rest_alone(dim):
    """A lattice at rest (every particle at or below the rest density) does
    not move; the same lattice squeezed to 80% spacing is denser, and the
    relaxation takes most of the excess density out while the moves are
    pairwise equal and opposite (the centroid stays); obstacles stay put."""
    r = 2.0
    n = 8 if dim == 2 else 5
    rest = _lattice(n, 1.0, dim)
    rho0 = float(kernel_density(rest, r).max())
    movable = np.ones(len(rest), bool)
    same, count, worst = relax_density(rest, movable, r, rho0, iterations=5)
    np.testing.assert_array_equal(same, rest)
    assert count == 0 and worst == 0.0
    squeezed = _lattice(n, 0.8, dim)
    out, count, worst = relax_density(squeezed, movable, r, rho0, iterations=5)
    before, after = _brute_density(squeezed, r).max(), _brute_density(out, r).max()
    assert count > 0 and worst == pytest.approx(float(_brute_density(squeezed, r).max()) / rho0 - 1, rel=1e-4)
    assert after - rho0 < 0.5 * (before - rho0)
    np.testing.assert_allclose(out.mean(0), squeezed.mean(0), atol=1e-4)
    fixed = movable.copy()
    fixed[:: n - 1] = False
    out2, _, _ = relax_density(squeezed, fixed, r, rho0, iterations=2)
    np.testing.assert_array_equal(out2[~fixed], squeezed[~fixed])
    assert (np.abs(out2[fixed] - squeezed[fixed]).max(1) > 0).any()


@pytest.mark.parametrize("dim", [2, 3])
def test_wall_clipped_stacks_and_clumps_move_a_bounded_distance(dim):
    """What clipping a prediction to the walls makes (many particles stacked on
    one corner point, rows on a wall line) and a clumping network makes (a
    clump far above the rest density): every particle moves at most R/4 per
    iteration, the stack comes apart, and the peak density falls. Before the
    cap and the coincident-pair rule a sand pile clipped into a corner threw
    a particle 85 R in one step (rust/neighbors/src/relax module docs)."""
    rng = np.random.default_rng(dim)
    r = 1.0
    rest = _lattice(6 if dim == 2 else 4, 0.5, dim)
    rho0 = float(kernel_density(rest, r).max())
    corner = np.zeros((25, dim), np.float32)
    wall_row = np.zeros((15, dim), np.float32)
    wall_row[:, 1:] = rng.uniform(0, 2, (15, dim - 1))  # all at x = 0, the wall line
    clump = (1.2 + 0.01 * r * rng.standard_normal((30, dim))).astype(np.float32)
    x = np.concatenate([rest, corner, wall_row, clump]).astype(np.float32)
    movable = np.ones(len(x), bool)
    iterations = 3
    out, count, worst = relax_density(x, movable, r, rho0, iterations=iterations)
    assert np.isfinite(out).all() and count > 0 and worst > 5
    moves = np.linalg.norm(out.astype(np.float64) - x, axis=1)
    assert moves.max() <= iterations * r / 4 * (1 + 1e-5)
    stack = out[len(rest) : len(rest) + len(corner)]
    assert len(np.unique(stack, axis=0)) == len(stack)
    assert _brute_density(out, r).max() < 0.8 * _brute_density(x, r).max()


def test_relaxation_bad_input_names_the_field():
    x = _lattice(4, 0.5)
    mv = np.ones(len(x), bool)
    cases = [
        (dict(positions=x[:, :1]), "positions"),
        (dict(positions=np.where(np.arange(len(x))[:, None] == 3, np.nan, x)), "positions"),
        (dict(movable=mv[1:]), "movable"),
        (dict(movable=mv.astype(np.int8)), "movable"),
        (dict(radius=0.0), "radius"),
        (dict(radius=float("inf")), "radius"),
        (dict(rest_density=float("nan")), "rest_density"),
        (dict(rest_density=-1.0), "rest_density"),
        (dict(iterations=-1), "iterations"),
        (dict(iterations=101), "iterations"),
        (dict(iterations=True), "iterations"),
        (dict(omega=2.5), "omega"),
        (dict(omega=0.0), "omega"),
    ]
    for change, field in cases:
        args = dict(positions=x, movable=mv, radius=1.0, rest_density=2.0, iterations=3, omega=1.0) | change
        with pytest.raises(InvalidInputError) as e:
            relax_density(**args)
        assert e.value.field == field, (change, e.value)


def _in_turn(x, mv, radius, rho0, iterations, bounds, max_neighbors=None):
    """numpy.clip, relax_density, numpy.clip and radius_graph one after the other."""
    if bounds is not None:
        x = np.clip(x, bounds[0], bounds[1])
    out, compressed, worst = relax_density(x, mv, radius, rho0, iterations)
    clamped = 0
    if bounds is not None:
        clamped = int(((out < bounds[0]) | (out > bounds[1])).any(1).sum())
        out = np.clip(out, bounds[0], bounds[1])
    return out, compressed, worst, clamped, radius_graph(out, radius, max_neighbors=max_neighbors)


def _same(a, b):
    out_a, *rest_a, graph_a = a
    out_b, *rest_b, graph_b = b
    assert out_a.dtype == out_b.dtype == np.float32
    assert np.array_equal(out_a.view(np.uint32), out_b.view(np.uint32))
    assert rest_a == rest_b
    for u, v in zip(graph_a, graph_b, strict=True):
        assert u.dtype == v.dtype and np.array_equal(u, v)


@pytest.mark.parametrize("scene", ["dam_break2d", "sand3d"])
def test_relax_then_graph_is_the_three_calls_in_turn_on_network_steps(scene):
    """On the shipped model's own predictions (the simulator's inputs to the
    relaxation, early and late in a rollout) and with a compressed clump and
    particles past the walls added: the relaxed positions, the counts and the
    graph are those of numpy.clip, relax_density, numpy.clip and radius_graph in turn,
    bit for bit, whether the lists were updated or searched again."""
    from hybridmpm.sim import NeuralSimulator

    sim = NeuralSimulator(scene, detect_failures=False, mpm_threads=1)
    while sim.warming_up:
        sim.advance()
    bounds = (sim._lo, sim._hi)
    rng = np.random.default_rng(0)
    for step in range(12):
        x = sim.propose().predicted
        if step in (0, 11):
            for variant in range(3):
                y = x.copy()
                if variant == 1:  # a clump: few particles move, the lists are updated
                    y[:40] = y[40] + 0.05 * sim.model.radius * rng.standard_normal((40, y.shape[1]))
                if variant == 2:  # some past the walls
                    y[::17] += 0.5 * (sim._hi - sim._lo)
                args = (y, sim._movable, sim.model.radius, sim.rest_density, 3)
                _same(relax_then_graph(*args, bounds=bounds), _in_turn(*args, bounds))
                _same(relax_then_graph(*args), _in_turn(*args, None))
                _same(relax_then_graph(*args, bounds=bounds, max_neighbors=6), _in_turn(*args, bounds, 6))
        sim.advance()


def test_relax_then_graph_bad_input_names_the_field():
    x = _lattice(4, 0.5)
    mv = np.ones(len(x), bool)
    cases = [
        (dict(positions=x[:, :1]), "positions"),
        (dict(movable=mv[1:]), "movable"),
        (dict(radius=0.0), "radius"),
        (dict(iterations=101), "iterations"),
        (dict(bounds=(np.zeros(3), np.ones(3))), "bounds"),
        (dict(bounds=(np.ones(2), np.zeros(2))), "bounds"),
        (dict(bounds=(np.array([0.0, np.nan]), np.ones(2))), "bounds"),
        (dict(bounds="walls"), "bounds"),
        (dict(graph_radius=-1.0), "radius"),
        (dict(max_neighbors=0), "max_neighbors"),
        (dict(max_edges=-1), "max_edges"),
        (dict(max_edges=3), "radius"),
    ]
    for change, field in cases:
        args = dict(positions=x, movable=mv, radius=1.0, rest_density=2.0, iterations=3) | change
        with pytest.raises(InvalidInputError) as e:
            relax_then_graph(**args)
        assert e.value.field == field, (change, e.value)


def test_the_network_rollout_stays_packed_like_the_material():
    """The shipped dam-break network alone packs its particles step after
    step (the mean number of neighbours within R grows); with the density
    relaxation (the default) it grows far less, and the relaxation corrects
    particles in its steps; relax = 0 is the network's own output."""
    from hybridmpm.sim import NeuralSimulator

    degrees = {}
    for relax in (0, 3):
        sim = NeuralSimulator("dam_break2d", relax=relax, detect_failures=False, mpm_threads=1)
        assert sim.rest_density > 1.0
        relaxed = 0
        for _ in range(5 + 20):  # warm-up, then 20 network steps (80 frames)
            sim.advance()
            relaxed += sim.last_relaxed
        x = sim.positions
        degrees[relax] = len(radius_graph(x, sim.model.radius)[0]) / len(x)
        assert (relaxed > 0) == (relax > 0)
    d0 = NeuralSimulator("dam_break2d", relax=0, mpm_threads=1).initial_degree
    assert degrees[0] > 1.3 * d0, degrees  # the raw network packs its particles
    assert degrees[3] - d0 < 0.5 * (degrees[0] - d0), degrees


def test_a_block_driven_into_the_floor_is_relaxed_until_it_is_packed_like_the_material():
    """The shipped sand2d network drives a falling block into the floor: the
    predicted positions are clipped onto the wall's line and three
    iterations cannot undo that (the mean neighbour count reached 2× the
    initial one and the step failed "compressed"). The simulator relaxes such
    a step again until it is packed below ``RELAX_AGAIN_DEGREE`` × the
    initial count; every other step takes one round. Over 400 frames of
    several seeds no step fails, and after every step the packing is within
    the bound (or the rounds ran out)."""
    from hybridmpm.sim import NeuralSimulator
    from hybridmpm.sim.neural import RELAX_AGAIN_DEGREE, RELAX_MAX_ROUNDS

    again = 0
    for seed in (0, 2):
        sim = NeuralSimulator("sand2d", seed=seed, mpm_threads=1)
        d0 = sim.initial_degree
        while sim.frame.frame_index < 400:
            sim.advance()  # raises NetworkFailure for a rejected step
            if sim.step_index < sim.t_in:
                continue
            x = sim.positions
            degree = len(radius_graph(x, sim.model.radius)[0]) / len(x)
            assert 1 <= sim.last_relax_rounds <= RELAX_MAX_ROUNDS + 1
            if sim.last_relax_rounds > 1:
                again += 1
                assert degree <= RELAX_AGAIN_DEGREE * d0 or sim.last_relax_rounds == RELAX_MAX_ROUNDS + 1, (seed, sim.frame.frame_index, degree, d0)
            assert degree <= 2 * d0
    assert again > 0  # the impact happened and was relaxed again


def test_relaxation_settings_are_checked_and_reach_the_hybrid():
    from hybridmpm.sim import HybridSimulator, NeuralSimulator

    for field, bad in (("relax", -1), ("relax", 101), ("relax", 1.5), ("rest_percentile", 0.0), ("rest_percentile", float("nan")), ("rest_percentile", 101)):
        with pytest.raises(InvalidInputError) as e:
            NeuralSimulator("dam_break2d", **{field: bad})
        assert e.value.field == field
    h = HybridSimulator("dam_break2d", relax=0, rest_percentile=50.0, mpm_threads=1)
    assert h.neural.relax == 0
    assert h.neural.rest_density < NeuralSimulator("dam_break2d", mpm_threads=1).rest_density
