"""The coarse-grid ladder's experiments (docs/correction.md), out of the
package in ``benchmarks/``: the learned correction of coarse MPM
(``benchmarks/experiments/learned_correction``: its teacher, the split of a
coarse state onto the scene's grid, its features, its runtime and its
training loop) and rung 2's projection of full resolution onto the coarse
particles (``benchmarks/coarse_ladder_rung2.py``), checked against exact
facts (the full-resolution lattice, conservation, free fall, translation
invariance, brute-force sums) rather than "it ran"."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

from hybridmpm.errors import InvalidInputError
from hybridmpm.mpm import MpmParams, MpmSolver
from hybridmpm.scenes import make_scene
from hybridmpm.scenes.resolution import on_grid
from hybridmpm.sim import rollout

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))  # the experiments are scripts' modules, not the package's
from coarse_ladder_rung2 import Projection  # noqa: E402
from experiments.learned_correction.features import num_features, particle_features  # noqa: E402
from experiments.learned_correction.forcing import CorrectionForcing, LabelledForcing, OracleForcing, cell_average, coarse_simulator  # noqa: E402
from experiments.learned_correction.model import Correction  # noqa: E402
from experiments.learned_correction.teacher import split_state, teacher_frame  # noqa: E402

DT = 2.5e-3


@pytest.mark.parametrize("scene", ["water2d", "sand2d", "water3d"])
def test_the_split_of_the_coarse_lattice_is_the_full_resolution_lattice(scene: str):
    """Children of the coarse scene's particles on the scene's grid sit exactly on the full-resolution lattice,
    carry its mass, and a moving state keeps mass, momentum and each parent's centre."""
    base = make_scene(scene, seed=4)
    coarse = on_grid(base, base.params.resolved_n_grid() // 2, 2).make_solver(num_threads=1)
    fine = split_state(coarse, base.params)
    full = base.make_solver(num_threads=1)
    key = lambda p: np.lexsort(p.T[::-1])  # noqa: E731
    a, b = np.asarray(fine.positions), np.asarray(full.positions)
    assert a.shape == b.shape and np.allclose(a[key(a)], b[key(b)], atol=1e-6)
    assert np.isclose(fine.masses.sum(), full.masses.sum(), rtol=1e-5)
    rng = np.random.default_rng(0)
    n, d = coarse.positions.shape
    coarse.velocities = rng.normal(0, 0.3, (n, d)).astype(np.float32)
    coarse.affine = rng.normal(0, 5.0, (n, d, d)).astype(np.float32)
    fine = split_state(coarse, base.params)
    k = 2**d
    mom_c = (coarse.masses[:, None] * coarse.velocities).sum(0)
    mom_f = (fine.masses[:, None] * fine.velocities).sum(0)
    assert np.allclose(mom_f, mom_c, rtol=1e-4, atol=1e-4)
    assert np.allclose(np.asarray(fine.positions).reshape(n, k, d).mean(1), coarse.positions, atol=1e-6)
    # the children's velocities are the parent's APIC field at their offsets: v + C (x_child - x_parent)
    off = np.asarray(fine.positions).reshape(n, k, d) - np.asarray(coarse.positions)[:, None]
    want = coarse.velocities[:, None] + np.einsum("nij,nkj->nki", coarse.affine, off)
    assert np.allclose(np.asarray(fine.velocities).reshape(n, k, d), want, atol=1e-4)


def test_the_teacher_of_a_free_falling_block_is_gravity():
    """A stress-free block away from every wall: one fine frame gives every particle g·Δt (APIC moves a uniform
    velocity field exactly), so the teacher's mean velocity is g·Δt."""
    coarse_p = MpmParams(n_grid=32)
    coarse = MpmSolver(coarse_p)
    g = np.arange(0.4, 0.6, 0.5 / 32, dtype=np.float32)
    pos = np.stack(np.meshgrid(g, g, indexing="ij"), -1).reshape(-1, 2)
    coarse.add_particles(pos, 0)
    x, v = teacher_frame(coarse, MpmParams(n_grid=64), DT)
    gy = coarse_p.resolved_gravity()[1]
    assert np.allclose(v, [0.0, gy * DT], atol=1e-5)
    dy = x[:, 1] - pos[:, 1]
    assert np.allclose(x[:, 0], pos[:, 0], atol=1e-6) and np.ptp(dy) < 1e-6  # a rigid drop
    # symplectic Euler over n >= 2 equal substeps: Δy = g·Δt²·(n + 1)/(2n), between g·Δt²/2 and 3/4 of g·Δt²
    r = dy.mean() / (gy * DT * DT)
    assert 0.5 < r <= 0.75 + 1e-3
    assert np.array_equal(coarse.positions, pos)  # the coarse state is untouched


def test_features_are_local_and_translation_invariant():
    """Width as documented; a block far from the walls moved by whole coarse cells has the same features."""
    for dim in (2, 3):
        s = make_scene("water2d" if dim == 2 else "water3d", seed=1)
        sim = coarse_simulator(s, s.params.resolved_n_grid() // 2)
        assert particle_features(sim.solver, DT).shape == (s.num_particles // 2**dim, num_features(dim))
    n = 32
    dx = 1.0 / n
    g = np.arange(0.3 + dx / 4, 0.45, dx / 2, dtype=np.float32)
    pos = np.stack(np.meshgrid(g, g, indexing="ij"), -1).reshape(-1, 2)
    rng = np.random.default_rng(3)
    vel = rng.normal(0, 0.2, pos.shape).astype(np.float32)
    feats = []
    for shift in (0, 3):
        s = MpmSolver(MpmParams(n_grid=n))
        s.add_particles(pos + np.float32(shift * dx), 0, velocities=vel)
        f = particle_features(s, DT)
        assert np.isfinite(f).all()
        feats.append(f)
    assert np.allclose(feats[0], feats[1], atol=1e-5)


def test_the_model_round_trips_and_its_acceleration_has_the_documented_units(tmp_path: Path):
    f = num_features(2)
    m = Correction(
        [np.zeros((f, 2), np.float32)],
        [np.array([1.0, -2.0], np.float32)],
        np.zeros(f, np.float32),
        np.ones(f, np.float32),
        np.array([0.5, 0.5], np.float32),
        {"scene": "x"},
    )
    x = np.random.default_rng(0).normal(size=(7, f)).astype(np.float32)
    assert np.allclose(m.velocity_change(x), [[0.5, -1.0]] * 7)
    assert np.allclose(m.acceleration(x, 64, DT), np.array([[0.5, -1.0]] * 7) / 64 / DT / DT, rtol=1e-5)
    m.save(tmp_path / "m.npz")
    back = Correction.load(tmp_path / "m.npz")
    assert np.array_equal(back.velocity_change(x), m.velocity_change(x)) and back.meta == {"scene": "x"}
    (tmp_path / "bad.npz").write_bytes(b"not a model")
    with pytest.raises(InvalidInputError) as e:
        Correction.load(tmp_path / "bad.npz")
    assert e.value.field == "model"


def test_labels_oracle_and_a_zero_correction():
    """No model is plain coarse MPM bit for bit; the labels are the teacher's velocity minus a plain frame's; the
    oracle, which applies them, brings the coarse frame's velocities closer to the teacher's than a plain frame."""
    base = make_scene("water2d", seed=2)
    plain = coarse_simulator(base, 64)
    zero = coarse_simulator(base, 64)
    zero.forcing = CorrectionForcing(zero, None)
    assert np.array_equal(rollout(plain, 30).fluid_positions, rollout(zero, 30).fluid_positions)
    lab = LabelledForcing(zero, None, base.params, every=1, smooth=False)
    zero.forcing = lab
    _, vt = teacher_frame(zero.solver, base.params, DT)
    before = zero.solver.checkpoint()
    zero.advance()
    assert len(lab.ys) == 1
    v_plain = zero.velocities.astype(np.float64)
    assert np.allclose(lab.ys[0], (vt - v_plain) * DT * 64, atol=1e-4)  # cells per frame
    zero.solver.restore(before)
    oracle = OracleForcing(zero, base.params)
    zero.forcing = oracle
    zero.advance()
    gap_o = np.linalg.norm(zero.velocities - vt)
    gap_p = np.linalg.norm(v_plain - vt)
    assert gap_o < 0.5 * gap_p
    # cell_average: a brute-force mean per cell
    p = np.random.default_rng(1).uniform(0.1, 0.9, (50, 2))
    m = np.random.default_rng(2).uniform(1, 2, 50)
    v = np.random.default_rng(3).normal(size=(50, 1))
    got = cell_average(p, m, v, 4)
    for i in range(50):
        same = np.all(np.floor(p * 4) == np.floor(p[i] * 4), axis=1)
        assert np.isclose(got[i, 0], (m[same] * v[same, 0]).sum() / m[same].sum())


def test_dagger_fits_below_no_correction(tmp_path: Path):
    """One round on two short trajectories: the held-out one-step loss is below the loss of no correction."""
    pytest.importorskip("torch", reason="training needs the train extra (torch)")
    from experiments.learned_correction.train import CorrectionTrainConfig, train_correction

    cfg = CorrectionTrainConfig(scene="sand2d", train_seeds=2, val_seeds=1, frames=40, every=2, rounds=1, steps=300, workers=1, scales=(1.0,))
    res = train_correction(cfg, tmp_path)
    one = res["log"][0]
    assert one["one_step_val"] < 0.8 * one["no_correction"]
    assert (tmp_path / "model.npz").exists() and Correction.load(tmp_path / "model.npz").meta["n_grid"] == 64


def test_collider_features_are_the_scenes_signed_distance_and_its_normal():
    """The collider columns use the scene's own signed distance; the normal is unit and points outwards (a point
    moved along it gets farther from the obstacle)."""
    from experiments.learned_correction.features import _collider_sdf

    from hybridmpm.mpm import Box, Sphere
    from hybridmpm.scenes.spec import collider_sdf

    obstacles = [Box([0.5, 0.4], [0.1, 0.04], angle_deg=25.0), Sphere([0.5, 0.75], 0.06)]
    p = np.random.default_rng(4).uniform(0.1, 0.9, (200, 2))
    sdf, normal = _collider_sdf(p, obstacles)
    want = np.min([collider_sdf(c, p) for c in obstacles], axis=0)
    assert np.allclose(sdf, want)
    assert np.allclose(np.linalg.norm(normal, axis=1), 1.0, atol=1e-6)
    farther = np.min([collider_sdf(c, p + 1e-3 * normal) for c in obstacles], axis=0)
    assert np.all(farther > sdf)


# ------------------------------------------------------------------ rung 2: full resolution seen through the coarse particles


def _sand_pair(seed: int = 4) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """sand2d's full-resolution particles (positions, masses) and its half grid's positions."""
    base = make_scene("sand2d", seed=seed)
    fine = base.make_solver(num_threads=1)
    coarse = on_grid(base, base.params.resolved_n_grid() // 2, 2).make_solver(num_threads=1)
    return np.asarray(fine.positions, np.float64), np.asarray(fine.masses, np.float64), np.asarray(coarse.positions, np.float64)


def test_the_projection_keeps_mass_and_momentum_and_groups_the_lattice_in_fours():
    """Brute force: every coarse particle of the half grid has the 4 fine particles of the lattice around it as
    children; the groups' masses add up to the fine set's, and mass times the projected velocity (and position)
    summed over the coarse particles is the fine set's momentum (and first moment), for any velocity field and
    unequal masses."""
    xf, mf, xc = _sand_pair()
    mf = mf * np.random.default_rng(5).uniform(0.5, 2.0, len(mf))  # the lattice's masses are equal: a plain mean would pass
    proj = Projection(xf, mf, xc, spacing=0.5 / 64, vunit=1.0)
    assert np.all(np.bincount(proj.parent, minlength=len(xc)) == 4)
    assert np.all(np.abs(xf - xc[proj.parent]).max(axis=1) < 0.5 / 64 * 0.5)  # each child within half a coarse spacing of its parent
    assert np.isclose(proj.group_mass.sum(), mf.sum(), rtol=1e-12)
    v = np.random.default_rng(0).normal(0.0, 1.0, xf.shape)
    for field in (v, xf):
        got = (proj.group_mass[:, None] * proj.mean(field)).sum(axis=0)
        want = np.array([sum(mf[i] * field[i, k] for i in range(len(mf))) for k in range(2)])  # the brute-force sum
        assert np.allclose(got, want, rtol=1e-10, atol=1e-12)
    # each coarse particle's projection is its own children's mass-weighted mean, summed one by one
    for j in np.random.default_rng(1).choice(len(xc), 5, replace=False):
        kids = np.flatnonzero(proj.parent == j)
        assert np.allclose(proj.mean(v)[j], (mf[kids, None] * v[kids]).sum(axis=0) / mf[kids].sum())


def test_the_privileged_features_are_the_childrens_covariance():
    """A fine set that is exactly the coarse set (each coarse particle its own only child) has no sub-cell state:
    zero spread; the lattice's children at rest have the lattice's own covariance (children at ±s/4 per axis:
    (s/4)² = 1/16 spacings² on the diagonal, 0 off it) and no velocity spread; and any state's features are the
    weighted covariances computed with numpy, group by group."""
    xf, mf, xc = _sand_pair()
    mc = np.full(len(xc), 4 * mf[0])
    same = Projection(xc, mc, xc, spacing=0.5 / 64, vunit=1.0)
    vc = np.random.default_rng(2).normal(0.0, 1.0, xc.shape)
    assert np.all(same.privileged(xc, vc) == 0.0)
    proj = Projection(xf, mf, xc, spacing=0.5 / 64, vunit=0.4)
    rest = proj.privileged(xf, np.zeros_like(xf))
    assert np.allclose(rest[:, :3], [1 / 16, 0.0, 1 / 16], atol=1e-6) and np.all(np.abs(rest[:, 3:]) < 1e-12)
    rng = np.random.default_rng(3)
    x, v = xf + rng.normal(0.0, 1e-3, xf.shape), rng.normal(0.0, 1.0, xf.shape)
    got = proj.privileged(x, v)
    for j in rng.choice(len(xc), 5, replace=False):
        kids = np.flatnonzero(proj.parent == j)
        cx = np.cov(x[kids].T / proj.spacing, aweights=mf[kids], bias=True)
        cv = np.cov(v[kids].T * proj.vunit, aweights=mf[kids], bias=True)
        assert np.allclose(got[j], [cx[0, 0], cx[0, 1], cx[1, 1], cv[0, 0], cv[0, 1], cv[1, 1]], rtol=1e-8, atol=1e-12)
