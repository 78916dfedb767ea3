"""The free-motion prior of the planned controllers (``hybridmpm.control.prior``):
the coarse rollout against free fall and the walls, the sketch correction's
geometry, the material codes."""

from __future__ import annotations

import numpy as np
import pytest

from hybridmpm.control import Sketch
from hybridmpm.control.prior import BALLISTIC_TOL, ballistic_path, free_motion, in_free_flight, material_of, prior_path
from hybridmpm.control.targets import pd_targets
from hybridmpm.conventions import DT_FRAME, GNS_SAND, GNS_WATER, MATERIAL_SAND, MATERIAL_WATER
from hybridmpm.errors import InvalidInputError
from hybridmpm.scenes import make_scene


def _cloud(n: int = 400, centre: tuple[float, float] = (0.5, 0.6), seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return (np.asarray(centre) + rng.uniform(-0.05, 0.05, size=(n, 2))).astype(np.float32)


@pytest.mark.parametrize("material", [MATERIAL_WATER, MATERIAL_SAND])
def test_a_cloud_in_free_flight_follows_the_ballistic_path(material: int) -> None:
    """Away from the walls a cloud in uniform motion has no stress, so every
    particle (simulated or carried by its nearest simulated neighbour) moves on
    ``x + v t + g t²/2``, to the first-order substep term."""
    params = make_scene("water2d", seed=0).params
    g = np.asarray(params.to_dict()["gravity"], np.float64)
    x = _cloud()
    v = np.tile(np.float32([0.4, 0.3]), (len(x), 1))
    frames = 20
    path = free_motion(x, v, np.full(len(x), material, np.int32), params, frames, dt_frame=DT_FRAME)
    assert path.shape == (frames + 1, len(x), 2) and path.dtype == np.float64
    t = np.arange(frames + 1)[:, None, None] * DT_FRAME
    ballistic = x[None].astype(np.float64) + v[None] * t + 0.5 * g * t * t
    assert np.abs(path - ballistic).max() < 2e-4  # 1.2 cm of fall in 50 ms: 1.6 % at most
    np.testing.assert_allclose(ballistic_path(x, v, g, frames, DT_FRAME), ballistic, atol=1e-12)
    assert in_free_flight(path, x, v, g, DT_FRAME)


def test_the_walls_hold_a_cloud_thrown_at_the_floor() -> None:
    params = make_scene("water2d", seed=0).params
    x = _cloud(centre=(0.5, 0.15))
    v = np.tile(np.float32([-0.5, -3.0]), (len(x), 1))
    path = free_motion(x, v, np.zeros(len(x), np.int32), params, 80, dt_frame=DT_FRAME)
    assert np.isfinite(path).all()
    from hybridmpm.mpm import MpmSolver

    lo, hi = MpmSolver(params).domain_bounds
    assert lo <= path.min() and path.max() <= hi  # every particle inside the walls at every frame
    # ballistic, the centroid would end 0.8 m below where it started (under the floor); the floor stops it
    assert path[-1, :, 1].mean() > lo and path[:, :, 1].mean(1).min() > lo
    g = np.asarray(params.to_dict()["gravity"], np.float64)
    assert not in_free_flight(path, x, v, g, DT_FRAME)  # the floor acted: no free flight
    assert in_free_flight(path[:4], x, v, g, DT_FRAME)  # (the first 7.5 ms, before it lands, are)


def test_free_flight_is_judged_by_the_largest_deviation_from_the_parabola() -> None:
    x = _cloud(seed=2).astype(np.float64)
    v = np.tile([0.2, 1.0], (len(x), 1))
    g = np.array([0.0, -9.81])
    path = ballistic_path(x, v, g, 30, DT_FRAME)
    assert in_free_flight(path, x, v, g, DT_FRAME)
    path[17, 123, 0] += 1.2 * BALLISTIC_TOL  # one particle, one frame, pushed off its parabola
    assert not in_free_flight(path, x, v, g, DT_FRAME)
    assert in_free_flight(path, x, v, g, DT_FRAME, tol=2 * BALLISTIC_TOL)
    with pytest.raises(InvalidInputError, match="free"):
        in_free_flight(path[:, :10], x, v, g, DT_FRAME)
    assert not in_free_flight(np.zeros((30, 0, 2)), x[:0], v[:0], g, DT_FRAME)  # no fluid: nothing in flight


def test_free_motion_is_deterministic_and_checks_its_input() -> None:
    params = make_scene("sand2d", seed=0).params
    x = _cloud(seed=3)
    v = np.zeros_like(x)
    m = np.ones(len(x), np.int32)
    a = free_motion(x, v, m, params, 10, dt_frame=DT_FRAME)
    assert np.array_equal(a, free_motion(x, v, m, params, 10, dt_frame=DT_FRAME))
    with pytest.raises(InvalidInputError, match="frames"):
        free_motion(x, v, m, params, 0, dt_frame=DT_FRAME)
    with pytest.raises(InvalidInputError, match="positions"):
        free_motion(x, v[:5], m, params, 10, dt_frame=DT_FRAME)


def test_prior_path_lands_on_the_sketch() -> None:
    rng = np.random.default_rng(1)
    x = _cloud(seed=1).astype(np.float64)
    free = x[None] + np.cumsum(rng.normal(0, 1e-3, size=(30, len(x), 2)), 0)
    free[0] = x
    assert np.array_equal(prior_path(free, x, None), free)  # blank: the free motion
    arrow = Sketch.arrow([0.5, 0.6], [0.3, 0.7])
    p = prior_path(free, x, arrow)
    np.testing.assert_allclose(p[0], x, atol=1e-12)
    np.testing.assert_allclose(p[-1].mean(0), x.mean(0) + arrow.vector, atol=1e-12)
    oval = Sketch.oval([0.4, 0.4], [0.12, 0.05], 0.5)
    p = prior_path(free, x, oval)
    np.testing.assert_allclose(p[-1], pd_targets(free[-1], oval), atol=1e-12)
    np.testing.assert_allclose(p[-1].mean(0), [0.4, 0.4], atol=1e-9)


def test_material_codes_round_trip() -> None:
    np.testing.assert_array_equal(material_of(np.array([GNS_WATER, GNS_SAND, GNS_WATER])), [MATERIAL_WATER, MATERIAL_SAND, MATERIAL_WATER])
    with pytest.raises(InvalidInputError, match="particle_type"):
        material_of(np.array([GNS_WATER, 3]))
