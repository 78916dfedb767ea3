"""Grid mass (p2g of mass, normalised): against a brute-force NumPy splat."""

from __future__ import annotations

import itertools

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from hybridmpm import InvalidInputError
from hybridmpm.mpm import grid_mass


def brute_force(x, n, masses=None):
    x = x.astype(np.float64)
    dim = x.shape[1]
    m = np.ones(len(x)) if masses is None else masses.astype(np.float64)
    g = np.zeros((n,) * dim)
    for p, mp in zip(x, m):
        xg = p * n
        base = np.floor(xg - 0.5).astype(int)
        f = xg - base
        w = [0.5 * (1.5 - f) ** 2, 0.75 - (f - 1) ** 2, 0.5 * (f - 0.5) ** 2]
        for o in itertools.product(range(3), repeat=dim):
            idx = tuple(int(np.clip(base[d] + o[d], 0, n - 1)) for d in range(dim))
            g[idx] += mp * np.prod([w[o[d]][d] for d in range(dim)])
    return g / g.sum()


@settings(max_examples=30, deadline=None)
@given(
    dim=st.sampled_from([2, 3]),
    n=st.integers(1, 60),
    grid=st.sampled_from([8, 16, 33]),
    seed=st.integers(0, 2**31 - 1),
    weighted=st.booleans(),
)
def test_matches_brute_force(dim, n, grid, seed, weighted):
    rng = np.random.default_rng(seed)
    x = rng.uniform(0.0, 1.0, (n, dim)).astype(np.float32)
    m = rng.uniform(0.1, 2.0, n).astype(np.float32) if weighted else None
    got = grid_mass(x, grid, m)
    assert got.shape == (grid,) * dim and got.dtype == np.float32
    assert np.allclose(got, brute_force(x, grid, m), atol=1e-6)
    assert got.sum() == pytest.approx(1.0, abs=1e-5)


def test_invariant_to_particle_order_and_zero_for_identical():
    rng = np.random.default_rng(0)
    x = rng.uniform(0.2, 0.8, (500, 2)).astype(np.float32)
    a = grid_mass(x, 64)
    b = grid_mass(x[rng.permutation(500)], 64)
    assert np.allclose(a, b, atol=1e-7)


@pytest.mark.parametrize("bad, field", [(np.zeros((3, 4), np.float32), "positions"), (np.array([[np.nan, 0.5]], np.float32), "positions")])
def test_bad_input(bad, field):
    with pytest.raises(InvalidInputError) as e:
        grid_mass(bad, 16)
    assert e.value.field == field
    with pytest.raises(InvalidInputError) as e:
        grid_mass(np.full((2, 2), 0.5, np.float32), 16, np.array([1.0, -1.0], np.float32))
    assert e.value.field == "masses"
