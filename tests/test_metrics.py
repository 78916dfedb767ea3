"""hybridmpm.metrics, hybridmpm.trajectory and `hybridmpm evaluate`.

Checked against brute force (a NumPy quadratic B-spline splat written here),
hand computations and analytic motion (free fall), never against the code's
own earlier output.
"""

from __future__ import annotations

import itertools
import json

import numpy as np
import pytest

from hybridmpm import InvalidInputError
from hybridmpm.cli import main
from hybridmpm.conventions import GNS_KINEMATIC
from hybridmpm.metrics import align_frames, evaluate, fluid_mask, grid_mass_error, kinetic_energy, position_mse, rollout_summary
from hybridmpm.trajectory import Trajectory

DT = 2.5e-3


# ----------------------------------------------------------------- helpers
def splat(x: np.ndarray, n: int, masses: np.ndarray | None = None) -> np.ndarray:
    """Brute-force normalised grid mass: quadratic B-spline p2g onto nodes
    i/n (indices clamped to the grid), float64, sums to 1."""
    x = np.asarray(x, dtype=np.float64)
    dim = x.shape[1]
    m = np.ones(len(x)) if masses is None else np.asarray(masses, dtype=np.float64)
    xg = x * n
    base = np.floor(xg - 0.5).astype(int)
    f = xg - base
    w = [0.5 * (1.5 - f) ** 2, 0.75 - (f - 1) ** 2, 0.5 * (f - 0.5) ** 2]  # each [N, D]
    g = np.zeros((n,) * dim)
    for o in itertools.product(range(3), repeat=dim):
        idx = tuple(np.clip(base[:, d] + o[d], 0, n - 1) for d in range(dim))
        np.add.at(g, idx, m * np.prod([w[o[d]][:, d] for d in range(dim)], axis=0))
    return g / g.sum()


def brute_error(a: np.ndarray, b: np.ndarray, n: int, wa=None, wb=None) -> float:
    ga, gb = splat(a, n, wa), splat(b, n, wb)
    return float(np.linalg.norm(ga - gb) / np.linalg.norm(gb))


def block(lo: float, side: float, per_side: int, dim: int) -> np.ndarray:
    """A cube [lo, lo + side]^dim filled by a cell-centred lattice of per_side points a side."""
    ax = lo + (np.arange(per_side) + 0.5) * side / per_side
    grid = np.meshgrid(*[ax] * dim, indexing="ij")
    return np.stack([g.ravel() for g in grid], axis=1).astype(np.float32)


# ----------------------------------------------------------------- grid-mass error
def test_grid_mass_error_zero_for_identical_and_invariant_to_permutation():
    rng = np.random.default_rng(0)
    a = rng.uniform(0.2, 0.8, (3, 400, 2)).astype(np.float32)
    b = a + rng.normal(0, 0.01, a.shape).astype(np.float32)
    assert (grid_mass_error(a, a, 64) == 0).all()
    base = grid_mass_error(b, a, 64)
    assert (base > 0).all()
    perm_p, perm_r = rng.permutation(400), rng.permutation(400)
    assert np.allclose(grid_mass_error(b[:, perm_p], a, 64), base, rtol=1e-5, atol=1e-7)
    assert np.allclose(grid_mass_error(b, a[:, perm_r], 64), base, rtol=1e-5, atol=1e-7)
    # a single frame [N, D] is T = 1
    assert grid_mass_error(a[0], a[0], 64).shape == (1,)


@pytest.mark.parametrize("dim", [2, 3])
def test_grid_mass_error_matches_brute_force_for_a_known_displacement(dim):
    rng = np.random.default_rng(dim)
    n = 32
    ref = rng.uniform(0.3, 0.7, (2, 150, dim)).astype(np.float32)
    shift = np.array([0.3, -0.7, 0.5][:dim], dtype=np.float32) / n
    pred = (ref + shift)[:, :120]  # different particle counts are fine
    wp = rng.uniform(0.5, 2.0, 120).astype(np.float32)
    got = grid_mass_error(pred, ref, n)
    got_w = grid_mass_error(pred, ref, n, pred_weights=wp)
    for t in range(2):
        assert got[t] == pytest.approx(brute_error(pred[t], ref[t], n), rel=1e-4)
        assert got_w[t] == pytest.approx(brute_error(pred[t], ref[t], n, wa=wp), rel=1e-4)
    assert got.dtype == np.float64 and (got > 0.1).all()


def test_grid_mass_error_grows_with_a_shift():
    n = 128
    a = block(0.3, 0.25, 64, 2)
    shifts = [0.25, 0.5, 1.0, 2.0, 4.0]
    errs = [grid_mass_error(a + np.float32(s / n), a, n)[0] for s in shifts]
    assert errs[0] > 0.01 and all(e1 < e2 for e1, e2 in zip(errs, errs[1:])), errs


def test_two_resolutions_of_a_uniform_block_2d():
    """A 2D block of 32×32 cells (dx = 1/128) filled at spacing dx/2 (64² =
    4096 particles, the reference) against the same block at the paper's
    spatial reduction r_p ≈ 1/1.75 (48² = 2304 particles, spacing 2dx/3)
    and at the inverse (85² = 7225 particles, spacing ≈ dx/(2·√1.75)).

    Measured: 0.0223 (coarse) and 0.00335 (dense); bounds 0.035 and 0.006.
    The residual is the quadratic B-spline's aliasing of the lattice (ripple
    ~ sinc³(dx/h), ≈1% at h = 2dx/3) plus the block's edges; for scale, the
    same block shifted by a quarter cell gives 0.063.
    """
    n = 128
    ref = block(0.3, 0.25, 64, 2)
    coarse = grid_mass_error(block(0.3, 0.25, 48, 2), ref, n)[0]
    dense = grid_mass_error(block(0.3, 0.25, 85, 2), ref, n)[0]
    assert 0 < coarse < 0.035
    assert 0 < dense < 0.006


def test_two_resolutions_of_a_uniform_block_3d():
    """3D block of 16³ cells (dx = 1/64) at spacing dx/2 (32³ = 32768
    particles) against 26³ = 17576 particles (r_p ≈ 1/1.86).

    Measured 0.0149; bound 0.025.
    """
    ref = block(0.3, 0.25, 32, 3)
    err = grid_mass_error(block(0.3, 0.25, 26, 3), ref, 64)[0]
    assert 0 < err < 0.025


def test_grid_mass_error_bad_input_names_the_field():
    a = np.full((2, 5, 2), 0.5, np.float32)
    cases = [
        (lambda: grid_mass_error(a, a[:1], 16), "ref"),  # different T
        (lambda: grid_mass_error(a, np.full((2, 5, 3), 0.5, np.float32), 16), "ref"),  # different D
        (lambda: grid_mass_error(np.where(a > 0, np.nan, a), a, 16), "pred"),
        (lambda: grid_mass_error(a, a, 2), "n_grid"),
        (lambda: grid_mass_error(a, a, 16, ref_weights=np.ones(4)), "ref_weights"),
        (lambda: grid_mass_error(a, a, 16, pred_weights=-np.ones(5)), "pred_weights"),
    ]
    for call, field in cases:
        with pytest.raises(InvalidInputError) as e:
            call()
        assert e.value.field == field


def test_fluid_mask_drops_only_kinematic_particles():
    assert fluid_mask(np.array([5, 3, 6, 3])).tolist() == [True, False, True, False]
    assert GNS_KINEMATIC == 3


# ----------------------------------------------------------------- position MSE
def test_position_mse_by_hand_and_rollout_summary():
    ref = np.zeros((2, 2, 2))
    pred = ref.copy()
    pred[0, 1] = [3.0, 4.0]  # squared error 25 over 2 particles × 2 dims
    pred[1, :, 0] = 1.0  # squared error 1 + 1
    mse = position_mse(pred, ref)
    assert mse.tolist() == [6.25, 0.5]
    s = rollout_summary(mse)
    assert s == {"mean": 3.375, "last": 0.5, "per_frame": [6.25, 0.5]}
    with pytest.raises(InvalidInputError) as e:
        position_mse(pred[:, :1], ref)
    assert e.value.field == "ref"
    with pytest.raises(InvalidInputError):
        rollout_summary([])


# ----------------------------------------------------------------- kinetic energy
def test_kinetic_energy_of_free_fall_is_exact_at_midpoints():
    rng = np.random.default_rng(1)
    n, steps = 50, 20
    p0 = rng.uniform(0.3, 0.7, (n, 2))
    v0 = rng.normal(0, 1.0, (n, 2))
    g = np.array([0.0, -9.8])
    t = np.arange(steps)[:, None, None] * DT
    pos = p0 + v0 * t + 0.5 * g * t**2  # float64, p = p0 + v0 t − ½ |g| t² ŷ
    t_mid = (np.arange(steps - 1) + 0.5)[:, None, None] * DT
    v_mid = v0 + g * t_mid
    expected = 0.5 * np.sum(v_mid**2, axis=2)  # [T-1, N]
    ke = kinetic_energy(pos, DT)
    assert ke.shape == (steps - 1,)
    assert np.allclose(ke, expected.mean(axis=1), rtol=1e-9, atol=0)
    m = rng.uniform(0.1, 1.0, n)
    assert np.allclose(kinetic_energy(pos, DT, m), expected @ m, rtol=1e-9, atol=0)
    # float32 positions (what trajectories store): finite differences lose ~1e-5 m/s
    assert np.allclose(kinetic_energy(pos.astype(np.float32), DT), expected.mean(axis=1), rtol=1e-3)
    for bad, field in [
        (lambda: kinetic_energy(pos[:1], DT), "positions"),
        (lambda: kinetic_energy(pos, 0.0), "dt"),
        (lambda: kinetic_energy(pos, DT, m[:3]), "masses"),
    ]:
        with pytest.raises(InvalidInputError) as e:
            bad()
        assert e.value.field == field


# ----------------------------------------------------------------- frame alignment
def test_align_frames():
    p, r, t = align_frames(DT, 5, DT, 4)  # ratio 1, ref shorter
    assert p.tolist() == [0, 1, 2, 3] and r.tolist() == [0, 1, 2, 3]
    p, r, t = align_frames(2 * DT, 10, DT, 5)  # pred every 2 frames, longer than ref
    assert p.tolist() == [0, 1, 2] and r.tolist() == [0, 2, 4]
    assert np.allclose(t, [0.0, 2 * DT, 4 * DT])
    p, r, t = align_frames(2 * DT, 2, DT, 9)  # pred shorter
    assert p.tolist() == [0, 1] and r.tolist() == [0, 2]
    p, r, t = align_frames(DT, 7, 2 * DT, 10)  # ratio 1/2
    assert p.tolist() == [0, 2, 4, 6] and r.tolist() == [0, 1, 2, 3]
    assert np.allclose(t, [0, 2 * DT, 4 * DT, 6 * DT])
    p, r, _ = align_frames(3 * 0.1, 3, 0.1, 9)  # 0.30000000000000004 / 0.1
    assert r.tolist() == [0, 3, 6]
    for args in [(1.75 * DT, 5, DT, 5), (DT, 5, 1.5 * DT, 5)]:
        with pytest.raises(InvalidInputError) as e:
            align_frames(*args)
        assert e.value.field == "pred_dt"
    with pytest.raises(InvalidInputError) as e:
        align_frames(DT, 5, -DT, 5)
    assert e.value.field == "ref_dt"


# ----------------------------------------------------------------- Trajectory file
def _traj(rng, t=4, n=30, dim=2, **kw) -> Trajectory:
    return Trajectory(
        positions=rng.uniform(0.2, 0.8, (t, n, dim)).astype(np.float32),
        particle_type=np.full(n, 5, np.int64),
        dt_frame=DT,
        **kw,
    )


def test_trajectory_round_trip(tmp_path):
    rng = np.random.default_rng(2)
    extra = rng.normal(size=(4, 30, 2)).astype(np.float32)
    tr = _traj(rng, n_grid=64, masses=rng.uniform(0.1, 1, 30), material=np.zeros(30, np.int32), extras={"one_step_positions": extra})
    path = tr.save(tmp_path / "t.npz")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["t.npz"]  # no temporary left behind
    back = Trajectory.load(path)
    assert np.array_equal(back.positions, tr.positions) and back.positions.dtype == np.float32
    assert np.array_equal(back.particle_type, tr.particle_type) and back.particle_type.dtype == np.int64
    assert back.dt_frame == DT and back.n_grid == 64
    assert back.masses is not None and tr.masses is not None and np.array_equal(back.masses, tr.masses) and back.masses.dtype == np.float32
    assert back.material is not None and back.material.dtype == np.int32
    assert list(back.extras) == ["one_step_positions"] and np.array_equal(back.extras["one_step_positions"], extra)
    # the layout `hybridmpm simulate` wrote before this module existed
    old = tmp_path / "old.npz"
    np.savez_compressed(old, positions=tr.positions, particle_type=tr.particle_type, material=np.zeros(30, np.int32), dt_frame=np.float64(DT))
    back = Trajectory.load(old)
    assert back.n_grid is None and back.masses is None and back.extras == {} and back.num_frames == 4 and back.dim == 2


def test_trajectory_load_errors_name_the_field(tmp_path):
    rng = np.random.default_rng(3)
    pos = rng.uniform(0.2, 0.8, (3, 10, 2)).astype(np.float32)
    good = {"positions": pos, "particle_type": np.full(10, 5), "dt_frame": np.float64(DT)}

    def write(name, **arrays):
        path = tmp_path / name
        np.savez(path, **arrays)
        return path

    nan_pos = pos.copy()
    nan_pos[1, 4, 0] = np.nan
    cases = {
        "dt_frame": write("missing.npz", positions=pos, particle_type=good["particle_type"]),
        "positions": write("nan.npz", **{**good, "positions": nan_pos}),
        "particle_type": write("len.npz", **{**good, "particle_type": np.full(9, 5)}),
    }
    for field, path in cases.items():
        with pytest.raises(InvalidInputError) as e:
            Trajectory.load(path)
        assert e.value.field == field, (field, str(e.value))
        assert field in str(e.value)
    for dt in (0.0, -DT, np.nan):
        with pytest.raises(InvalidInputError) as e:
            Trajectory.load(write("dt.npz", **{**good, "dt_frame": np.float64(dt)}))
        assert e.value.field == "dt_frame"
    text = tmp_path / "not.npz"
    text.write_text("positions,particle_type\n")
    npy = tmp_path / "single.npy"
    np.save(npy, pos)
    truncated = tmp_path / "truncated.npz"
    truncated.write_bytes(write("full.npz", **good).read_bytes()[:200])
    for path in (text, npy, truncated, tmp_path / "absent.npz"):
        with pytest.raises(InvalidInputError) as e:
            Trajectory.load(path)
        assert e.value.field == "path" and str(path) in str(e.value)
    with pytest.raises(InvalidInputError) as e:
        Trajectory(pos[0], good["particle_type"], DT)  # [N, D]: no time axis
    assert e.value.field == "positions"


# ----------------------------------------------------------------- evaluate()
def test_evaluate_ignores_kinematic_particles_and_reports_one_step_mse():
    rng = np.random.default_rng(4)
    ref = _traj(rng, t=5, n=40)
    walls = rng.uniform(0.0, 1.0, (5, 25, 2)).astype(np.float32)
    s = 0.01
    one_step = ref.positions + np.array([s, 0], np.float32)
    one_step[0] = np.nan  # a history frame with no prediction
    pred = Trajectory(
        positions=np.concatenate([walls, ref.positions], axis=1),
        particle_type=np.r_[np.full(25, GNS_KINEMATIC), ref.particle_type],
        dt_frame=DT,
        extras={"one_step_positions": np.concatenate([walls, one_step], axis=1)},
    )
    res = evaluate(pred, ref)
    assert res["grid_mass_error"]["per_frame"] == [0.0] * 5
    assert res["position_mse_rollout"]["mean"] == 0.0
    assert res["pred"]["particles"] == 40 and res["pred"]["kinematic_particles"] == 25
    assert res["n_grid"] == 128  # 2D default
    one = res["position_mse_one_step"]
    assert one["times"] == pytest.approx([DT, 2 * DT, 3 * DT, 4 * DT])
    assert one["mean"] == pytest.approx(s * s / 2, rel=1e-4)  # shift s in x only: (s² + 0) / 2
    assert res["kinetic_energy"]["pred"] == res["kinetic_energy"]["ref"]
    json.dumps(res, allow_nan=False)
    # different resolutions: no particle correspondence
    coarse = Trajectory(ref.positions[:, ::2], ref.particle_type[::2], DT)
    res = evaluate(coarse, ref, n_grid=32)
    assert res["n_grid"] == 32 and res["position_mse_rollout"] is None and "differ" in res["position_mse_rollout_reason"]
    # 3D default grid, and dimension mismatch
    r3 = _traj(rng, t=2, n=20, dim=3)
    assert evaluate(r3, r3)["n_grid"] == 64
    with pytest.raises(InvalidInputError) as e:
        evaluate(r3, ref)
    assert e.value.field == "ref"


# ----------------------------------------------------------------- CLI
@pytest.fixture(scope="module")
def two_runs(tmp_path_factory):
    root = tmp_path_factory.mktemp("eval")
    for name in ("a", "b"):
        assert main(["simulate", "dam_break2d", "--solver", "mpm", "--frames", "4", "--out", str(root / name), "--quiet", "--no-render"]) == 0
    return root


KEYS = {
    "n_grid",
    "dim",
    "frames_compared",
    "times",
    "pred",
    "ref",
    "grid_mass_error",
    "grid_mass_error_mass_weighted",
    "position_mse_rollout",
    "position_mse_rollout_reason",
    "position_mse_one_step",
    "position_mse_one_step_reason",
    "kinetic_energy",
    "short_horizon_error",
    "sinkhorn_divergence",
    "kinetic_energy_error",
    "dam_break_front",
    "metrics",
    "metric_seconds",
}


def test_cli_evaluate_identical_shifted_and_strided(two_runs, capsys):
    a, b = two_runs / "a" / "trajectory.npz", two_runs / "b" / "trajectory.npz"
    ref = Trajectory.load(b)
    assert ref.n_grid == 128 and ref.masses is not None and ref.masses.shape == (ref.num_particles,) and (ref.masses > 0).all()

    assert main(["evaluate", str(a), str(b)]) == 0
    assert "grid-mass error" in capsys.readouterr().out
    res = json.loads((two_runs / "a" / "metrics.json").read_text())  # default: next to PRED
    assert set(res) == KEYS
    assert res["frames_compared"] == 5 and res["n_grid"] == 128
    assert res["grid_mass_error"]["mean"] == 0.0 and res["grid_mass_error"]["last"] == 0.0
    assert res["position_mse_rollout"]["last"] == 0.0
    assert len(res["kinetic_energy"]["ref"]) == 4 and res["kinetic_energy"]["units"] == "J/kg"

    s = 0.5 / 128
    shifted = Trajectory(ref.positions + np.array([s, 0], np.float32), ref.particle_type, ref.dt_frame, n_grid=ref.n_grid)
    shifted.save(two_runs / "shifted.npz")
    out = two_runs / "shifted.json"
    assert main(["evaluate", str(two_runs / "shifted.npz"), str(b), "--out", str(out), "--n-grid", "64"]) == 0
    res = json.loads(out.read_text())
    assert res["n_grid"] == 64
    assert min(res["grid_mass_error"]["per_frame"]) > 0.01
    assert res["position_mse_rollout"]["mean"] == pytest.approx(s * s / 2, rel=1e-3)

    strided = Trajectory(ref.positions[::2], ref.particle_type, 2 * DT)
    strided.save(two_runs / "strided.npz")
    assert main(["evaluate", str(two_runs / "strided.npz"), str(b), "--out", str(out), "--quiet"]) == 0
    res = json.loads(out.read_text())
    assert res["frames_compared"] == 3 and res["times"] == pytest.approx([0.0, 2 * DT, 4 * DT])
    assert res["pred"]["dt_frame"] == 2 * DT and res["ref"]["dt_frame"] == DT
    assert res["grid_mass_error"]["per_frame"] == [0.0] * 3


def test_cli_evaluate_bad_file_is_exit_2(two_runs, capsys):
    bad = two_runs / "a" / "summary.json"
    assert main(["evaluate", str(bad), str(two_runs / "b" / "trajectory.npz")]) == 2
    err = capsys.readouterr().err
    assert err.startswith("hybridmpm: error: ") and str(bad) in err


def test_mass_weighted_variant_sees_merged_particles_as_the_same_mass():
    """Merging two coincident particles into one of twice the mass leaves the
    mass distribution unchanged: the mass-weighted error is 0 while the 1/N
    definition (docs/design.md) sees one particle's worth of mass missing."""
    rng = np.random.default_rng(3)
    x = rng.uniform(0.3, 0.7, (3, 50, 2)).astype(np.float32)
    x[:, 1] = x[:, 0]  # particles 0 and 1 coincide
    ref = Trajectory(positions=x, particle_type=np.full(50, 5), dt_frame=2.5e-3, masses=np.ones(50, np.float32))
    merged_m = np.ones(49, np.float32)
    merged_m[0] = 2.0
    pred = Trajectory(positions=x[:, 1:], particle_type=np.full(49, 5), dt_frame=2.5e-3, masses=merged_m)
    res = evaluate(pred, ref)
    assert res["grid_mass_error_mass_weighted"]["mean"] < 1e-6
    assert res["grid_mass_error"]["mean"] > 1e-3
    no_mass = Trajectory(positions=x[:, 1:], particle_type=np.full(49, 5), dt_frame=2.5e-3)
    assert evaluate(no_mass, ref)["grid_mass_error_mass_weighted"] is None
