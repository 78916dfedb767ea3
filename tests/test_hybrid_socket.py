"""The hybrid's socket for its cheap half (hybridmpm.sim.cheap): a cheap half
it has never heard of driven through it under each rule, bit for bit MPM; the
classical twin (coarse MPM) that loads no network, keeps its particles within a
cell of their groups and can carry its grid's own particles. The hybrid with
the network: tests/test_hybrid.py."""

from __future__ import annotations

import numpy as np
import pytest

from hybridmpm.errors import InvalidInputError
from hybridmpm.models import shipped_model
from hybridmpm.neural import GnsRuntime
from hybridmpm.scenes import make_scene
from hybridmpm.sim import Frame, HybridSimulator, MpmSimulator, rollout


class _MirrorHalf:
    """A cheap half the hybrid has never heard of: MPM on the scene's own grid, handed over by checkpoint.
    Whatever the rule, the hybrid of it must be MPM at r_p bit for bit, and every audit must read 0."""

    kind = name = "mirror"
    model = None

    def __init__(self, scene, r_t: int, t_in: int = 6):
        self.sim = MpmSimulator(scene, r_t=r_t, threads=1)
        self.particles, self.r_t, self.t_in = self.sim.particles, r_t, t_in
        self._before = None
        self.calls: dict[str, int] = {}

    def _count(self, what: str) -> None:
        self.calls[what] = self.calls.get(what, 0) + 1

    @property
    def velocities(self):
        return self.sim.velocities

    mean_degree = initial_degree = float("nan")

    def propose(self, checks=None):
        from hybridmpm.sim.cheap import Proposal

        self._count("propose")
        self._before = self.sim.solver.checkpoint()
        pos = self.sim.advance().positions
        return Proposal(np.zeros(0), pos, pos, None, None)

    def commit(self, proposal):
        self._count("commit")
        self._before = None
        return proposal.positions

    def take_over(self, fine, trajectory):
        self._count("take_over")
        assert trajectory.shape[0] >= self.t_in and np.array_equal(trajectory[-1], fine.positions)
        self.sim.solver.restore_particles(fine.checkpoint())
        self._before = None

    def hand_back(self, fine, trajectory):
        self._count("hand_back")
        fine.restore_particles(self._before if self._before is not None else self.sim.solver.checkpoint())

    def state(self):
        return {"mpm": self.sim.state()}

    def prepare_restore(self, state):
        return self.sim.prepare_restore(state["mpm"])


def test_the_hybrid_drives_any_cheap_half_through_the_socket():
    from hybridmpm.scenes.resolution import at_resolution
    from hybridmpm.sim import AuditRule, CheapHalf, ErrorRule, FailureChecks, PaperRule

    scene = at_resolution(make_scene("water2d", seed=1005), 0.5714, 1005)
    ref = MpmSimulator(scene, r_t=4, threads=1)
    push = np.tile(np.array([[3.0, 0.0]], np.float32), (ref.particles.num_fluid, 1))

    def run(sim, steps: int) -> list[Frame]:
        out = []
        for k in range(steps):
            sim.forcing = push if 12 <= k < 16 else None
            out.append(sim.advance())
        return out

    want = [f.positions for f in run(ref, 40)]
    for rule in (AuditRule(r_c=0.3, audit_every=1, audit_tol=1e-9), PaperRule(r_c=-1.0), ErrorRule(audit_tol=1e-9, dwell=2)):
        half = _MirrorHalf(scene, 4)
        assert isinstance(half, CheapHalf)
        sim = HybridSimulator.compose(scene, half, rule, FailureChecks(), mpm_threads=1)
        frames = run(sim, 40)
        assert np.array_equal(np.stack([f.positions for f in frames]), np.stack(want)), rule
        solvers = [f.solver for f in frames]
        assert set(solvers) == {"mpm", "mirror"} and sim.stats.steps["mirror"] == solvers.count("mirror") > 5
        assert frames[12].event == "switch:mpm" and frames[12].solver == "mpm" and frames[11].solver == "mirror"  # the push
        audits = [f.audit for f in frames if np.isfinite(f.audit)]
        assert all(a == 0.0 for a in audits) and len(audits) == sim.stats.audits and (len(audits) > 0) == (rule.name != "paper")
        assert half.calls["take_over"] == 1 + sum(f.event == "switch:neural" for f in frames)
        assert half.calls["commit"] == solvers.count("mirror") and half.calls["hand_back"] >= 1
        st = sim.state()
        a = run(sim, 6)
        sim.restore(st)
        assert [f.positions.tobytes() for f in run(sim, 6)] == [f.positions.tobytes() for f in a]
    with pytest.raises(InvalidInputError, match="cheap"):
        HybridSimulator.compose(scene, _MirrorHalf(at_resolution(make_scene("water2d", seed=1005), 0.8, 1005), 4), PaperRule())


def test_the_classical_twin_loads_no_network(monkeypatch):
    """The twin reads the network's r_p, r_t and T_in from the model file's metadata (the same as
    onnxruntime reads there) and never opens an onnxruntime session."""
    import json

    import onnxruntime as ort

    from hybridmpm.models import shipped_models
    from hybridmpm.neural.base import Runtime, file_metadata, read_header
    from hybridmpm.neural.constants import METADATA_KEY

    for scene in sorted(shipped_models()):
        path = shipped_model(scene)
        session = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
        assert file_metadata(path) == json.loads(session.get_modelmeta().custom_metadata_map[METADATA_KEY])
        runtime = GnsRuntime(path)
        assert isinstance(runtime, Runtime)
        h = read_header(path)
        assert (h.r_p, h.r_t, h.t_in, h.kind) == (runtime.r_p, runtime.r_t, runtime.t_in, "gns")

    def refuse(*a, **k):
        raise AssertionError("an onnxruntime session was opened")

    monkeypatch.setattr(ort, "InferenceSession", refuse)
    twin = HybridSimulator("water2d", seed=1005, cheap="mpm-coarse", mpm_threads=1)
    assert twin.model.r_p == 0.5714 and twin.t_in == 6 and twin.r_t == 4
    assert rollout(twin, 40).stats["steps"]["coarse"] > 0
    with pytest.raises(InvalidInputError, match="relax"):
        HybridSimulator("water2d", seed=1005, cheap="mpm-coarse", relax=0)


def test_the_hybrid_names_no_cheap_half_kind():
    """sim/hybrid.py branches on no kind of cheap half: no isinstance of it (nor of a model), and the
    halves' classes appear only in the table of builders, outside the class."""
    import ast

    import hybridmpm.sim.hybrid as module

    tree = ast.parse(open(module.__file__).read())
    checked = [ast.unparse(n.args[0]) for n in ast.walk(tree) if isinstance(n, ast.Call) and isinstance(n.func, ast.Name) and n.func.id == "isinstance"]
    assert not [c for c in checked if any(w in c for w in ("half", "cheap", "neural", "model"))], checked
    cls = next(n for n in tree.body if isinstance(n, ast.ClassDef) and n.name == "HybridSimulator")
    names = {n.id for n in ast.walk(cls) if isinstance(n, ast.Name)}
    assert not names & {"NeuralSimulator", "CoarseMpmHalf", "GnsRuntime", "GridRuntime"}


def test_the_own_particle_twin_holds_its_particles_within_a_cell_of_their_group():
    """A long spell on the coarse grid under a stretching flow grew the offsets that place each particle in its
    group without bound; a particle split far out of its group's kernel took the group's affine velocity there
    (water_sand2d seed 1001: 1,948 m/s at a hand-back, MPM refused the frame). Each proposal now holds every
    offset within one coarse cell, and the run that broke off finishes."""
    twin = HybridSimulator("water_sand2d", seed=1001, cheap="mpm-coarse", cheap_particles="grid", safeguard="error", audit_tol=2.0, mpm_threads=1)
    half = twin.half
    ro = rollout(twin, 400)
    assert ro.failure is None, ro.failure_detail
    assert ro.stats["steps"]["coarse"] > 0.5 * sum(ro.stats["steps"].values())  # a long spell on the coarse grid
    assert np.linalg.norm(half.offsets, axis=1).max() <= half.max_offset * (1 + 1e-9)
    assert half.max_offset == pytest.approx(1 / 64)


def test_the_twin_can_carry_its_grids_own_particles_merged_and_split_at_each_handover():
    """cheap_particles="grid": the coarse grid carries as many particles as plain MPM puts on it, each a
    group of the hybrid's. A merge conserves mass, centre of mass and momentum (as the r_p clustering
    does); a split right after it puts every particle back where it was (but for a group centred in the
    strip the coarse domain leaves out: less than a cell), with the group's affine
    velocity, and the merge's reported error is exactly the velocity that field does not carry."""
    from hybridmpm.scenes.resolution import on_grid
    from hybridmpm.sim.convert import merge_state, split_state

    twin = HybridSimulator("water2d", seed=1006, cheap="mpm-coarse", cheap_particles="grid", mpm_threads=1)
    half = twin.half
    assert half.sim.particles.num_fluid == on_grid(twin.scene_full, 64).num_particles < twin.n_fluid
    ro = rollout(twin, 80)
    assert ro.stats["steps"]["coarse"] > 0 and half.conversions >= 1 and ro.positions.shape[1] == twin.particles.num_total
    # a merge of MPM's own state, by hand against the sums
    fine = twin.mpm.solver
    coarse = half.sim.solver
    m, v, x = (np.asarray(a, np.float64) for a in (fine.masses, fine.velocities, fine.positions))
    offsets, residual = merge_state(fine, coarse, half.labels)
    mc = np.asarray(coarse.masses, np.float64)
    np.testing.assert_allclose(mc.sum(), m.sum(), rtol=1e-6)
    np.testing.assert_allclose((mc[:, None] * np.asarray(coarse.velocities, np.float64)).sum(0), (m[:, None] * v).sum(0), rtol=1e-5, atol=1e-9)
    np.testing.assert_allclose((mc[:, None] * np.asarray(coarse.positions, np.float64)).sum(0), (m[:, None] * x).sum(0), rtol=1e-5)
    before = fine.checkpoint()
    split_state(coarse, fine, half.labels, offsets)
    moved = np.abs(np.asarray(fine.positions, np.float64) - x).max(axis=1)
    assert moved.max() < 1 / 128 and np.mean(moved < 1e-6) > 0.95  # only a group whose centre was in the fine grid's outer strip moves (clipped)
    carried = np.asarray(fine.velocities, np.float64)
    assert residual == pytest.approx(float(np.sqrt((m * ((v - carried) ** 2).sum(1)).sum() / m.sum())), rel=1e-3, abs=1e-9)
    fine.restore(before)
    # a checkpoint round trip, and the default twin (the network's particles) untouched
    st = twin.state()
    a = rollout(twin, 12).positions
    twin.restore(st)
    assert np.array_equal(rollout(twin, 12).positions, a)
    with pytest.raises(InvalidInputError, match="cheap_particles"):
        HybridSimulator("water2d", seed=1006, cheap="mpm-coarse", cheap_particles="some")


def test_the_command_line_picks_the_twins_particles(tmp_path):
    """``simulate --cheap mpm-coarse --cheap-particles grid`` runs the twin on its grid's own particles (its
    summary says so, and the run differs from the twin on the network's particles from the same start);
    ``--cheap-particles`` without the twin is refused in one line naming it."""
    import json

    from hybridmpm.cli import main

    outs = {}
    for particles in ("network", "grid"):
        out = tmp_path / particles
        args = ["simulate", "water2d", "--solver", "hybrid", "--seed", "1006", "--frames", "24", "--cheap", "mpm-coarse", "--cheap-particles", particles]
        assert main([*args, "--out", str(out), "--quiet", "--no-render", "--threads", "1"]) == 0
        summary = json.loads((out / "summary.json").read_text())
        assert summary["cheap_particles"] == particles and summary["cheap_kind"] == "coarse"
        outs[particles] = np.load(out / "trajectory.npz")["positions"]
    assert outs["grid"].shape == outs["network"].shape and not np.array_equal(outs["grid"], outs["network"])
    with pytest.raises(InvalidInputError, match="cheap_particles"):
        from hybridmpm.sim import make_simulator

        make_simulator("water2d", "hybrid", cheap_particles="grid")
    assert main(["simulate", "water2d", "--solver", "hybrid", "--frames", "4", "--cheap-particles", "grid", "--out", str(tmp_path / "bad"), "--quiet"]) == 2
