"""The safeguard's switch itself: a scripted network that is right (it returns
MPM's own next state) and then goes wrong at a known step (random per-particle
kicks). The hybrid must hand over to MPM within the score's window and then
track MPM again, where the same network left in charge drifts away.

The scene is a water block in free fall (no wall touched within the
horizon): MPM's accelerations are all ``g``, so the score of the right
network's trajectory is 1 and nothing but the fault can trigger the switch."""

from __future__ import annotations

import numpy as np
import pytest

from hybridmpm.conventions import DELTA, R_C
from hybridmpm.metrics import grid_mass_error
from hybridmpm.models import shipped_model
from hybridmpm.neural import GnsRuntime
from hybridmpm.scenes import SceneSpec
from hybridmpm.sim import Frame, HybridSimulator, MpmSimulator, rollout

FRAMES = 88  # 22 steps of r_t = 4: the block is still in the air (it reaches the floor after ~25)
FAULT_AT = 6  # the scripted network's first wrong call (1-based)
KICK = 3e-3  # [m] standard deviation of the fault's per-particle kicks: 0.4 MPM cells, ~50 m/s² of noise in the accelerations
ERROR_GRID = 32  # cells of the grid-mass error: where the water is at the scale of 4 MPM cells, not the sub-cell noise itself


class Scripted(GnsRuntime):
    """The water2d model's metadata (r_p, r_t, T_in, radius) with a scripted
    prediction: until call ``at`` the next state of ``truth`` (MPM at r_p,
    looked up by the current positions), from then on a free-fall step with
    random kicks of ``kick`` metres (seeded)."""

    def __init__(self, truth: np.ndarray, at: int, kick: float = KICK):
        super().__init__(shipped_model("water2d"))
        self.next_of = {np.ascontiguousarray(a).tobytes(): b for a, b in zip(truth[:-1], truth[1:])}
        self.at, self.kick, self.calls = at, kick, 0
        self.rng = np.random.default_rng(0)

    def predict(self, history, particle_type, max_neighbors=None, graph=None):
        acc, nxt, used = super().predict(history, particle_type, max_neighbors, graph)  # for the graph the simulator reuses
        self.calls += 1
        if self.calls < self.at:
            return acc, self.next_of[np.ascontiguousarray(history[-1]).tobytes()].copy(), used
        h = history.astype(np.float64)
        dt = 0.01  # water2d's step: r_t = 4 frames of 2.5 ms
        free = 2 * h[-1] - h[-2] + np.array([0.0, -9.8 * dt * dt])
        return acc, (free + self.rng.normal(0.0, self.kick, free.shape)).astype(np.float32), used


def _scene():
    spec = {"name": "water2d", "dim": 2, "blocks": [{"lo": [0.4, 0.6], "hi": [0.6, 0.8], "material": "water"}]}
    return SceneSpec.from_dict(spec).build()


def _run(scene, model, r_c: float) -> tuple[list[Frame], np.ndarray]:
    # no audit (it would catch the fault too) and no density relaxation (it would alter the scripted output)
    sim = HybridSimulator(scene, model, r_c=r_c, audit_every=0, relax=0, mpm_threads=1)
    frames: list[Frame] = []
    ro = rollout(sim, FRAMES, on_frame=frames.append)
    assert sim.delta == DELTA and sim.r_c == r_c
    return frames, ro.positions


@pytest.fixture(scope="module")
def truth() -> np.ndarray:
    return rollout(MpmSimulator(_scene(), r_p=GnsRuntime(shipped_model("water2d")).r_p, r_t=4, threads=1), FRAMES).positions


def test_a_right_network_keeps_the_flow(truth):
    frames, pos = _run(_scene(), Scripted(truth, at=10**9), R_C)
    t_in = GnsRuntime(shipped_model("water2d")).t_in
    assert [f.solver for f in frames] == ["mpm"] * (t_in - 1) + ["neural"] * (len(frames) - t_in + 1)
    assert not any(f.event for f in frames)
    assert all(f.score >= R_C for f in frames[t_in - 1 :])
    assert np.array_equal(pos, truth)  # the stand-in is MPM itself: what follows measures the switch, not the model


def test_a_network_gone_wrong_is_handed_over_within_the_window_and_the_hybrid_recovers(truth):
    right, _ = _run(_scene(), Scripted(truth, at=10**9), R_C)
    frames, pos = _run(_scene(), Scripted(truth, at=FAULT_AT), R_C)
    t_in = GnsRuntime(shipped_model("water2d")).t_in
    k0 = t_in - 1 + FAULT_AT - 1  # index in `frames` of the first wrong network step
    for a, b in zip(frames[:k0], right[:k0]):  # right until then
        assert np.array_equal(a.positions, b.positions) and a.solver == b.solver
    assert frames[k0].solver == "neural"
    # the rule: the first step whose score falls below r_c is the network's last; MPM takes the next
    k1 = next(i for i, f in enumerate(frames) if f.solver == "neural" and not f.score >= R_C)
    assert k0 <= k1 < k0 + DELTA, (k0, k1)
    assert all(f.solver == "neural" and not f.event for f in frames[t_in - 1 : k1])
    assert frames[k1].event == "switch:mpm" and frames[k1].solver == "neural"
    # the damaged history keeps the score low for the rest of the horizon: MPM throughout
    assert [f.solver for f in frames[k1 + 1 :]] == ["mpm"] * (len(frames) - k1 - 1)

    # the same network left in charge (r_c = 0; its failure checks stay on and see nothing) drifts away from MPM
    alone, pos_alone = _run(_scene(), Scripted(truth, at=FAULT_AT), 0.0)
    assert not any(f.event for f in alone) and alone[-1].solver == "neural"
    err = grid_mass_error(pos, truth, ERROR_GRID)
    err_alone = grid_mass_error(pos_alone, truth, ERROR_GRID)
    s1 = k1 + 1  # rows of `pos` are the initial state then frames: row s1 is frames[k1]
    assert err[:s1].max() < err[s1] == err_alone[s1]  # the damage done before the switch, the same in both
    # recovery: after the handover the hybrid's distance from MPM at r_p grows at the pace of the
    # conversion (velocity from the last difference lags by g·dt/2), measured 0.005-0.009 per step;
    # the wrong network's grows 0.04-0.07 per step
    steps = len(err) - 1 - s1
    assert err[-1] - err[s1] <= 0.012 * steps, err
    assert err_alone[-1] - err_alone[s1] >= 0.03 * steps, err_alone
    assert err[-1] < err_alone[-1] / 3, (err[-1], err_alone[-1])
