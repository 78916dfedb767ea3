"""Sketch control: reverse-simulation identities, sketches and their
rasteriser, the baselines against kinematics, metrics."""

from __future__ import annotations

import math

import numpy as np
import pytest

from hybridmpm.control import (
    A_MAX,
    Controller,
    Sketch,
    control_episode,
    pd_targets,
    render_sketch,
    reverse_kinematic,
    reverse_tracking,
    sketch_from_trajectory,
    smooth,
)
from hybridmpm.control.metrics import arrow_adherence, oval_adherence
from hybridmpm.errors import InvalidInputError
from hybridmpm.mpm import MpmParams
from hybridmpm.scenes import Scene, lattice, make_scene
from hybridmpm.sim import MpmSimulator, rollout

G = np.array([0.0, -9.8])
DT = 2.5e-3


# ---------------------------------------------------------------- reverse simulation
def test_the_kinematic_reverse_field_replays_the_forward_run_backwards_exactly():
    rng = np.random.default_rng(0)
    forward = 0.5 + np.cumsum(rng.normal(0, 1e-3, (30, 7, 2)), axis=0)  # X_1 … X_T
    v_end = (forward[-1] - forward[-2]) / DT
    a = reverse_kinematic(forward, v_end, DT, G, a_max=None).astype(np.float64)
    assert a.shape == (29, 7, 2)
    # symplectic Euler, as MPM's g2p: v <- v + (a + g) dt, p <- p + v dt, from X_T with the velocity negated
    p, v = forward[-1].copy(), -v_end
    visited = [p.copy()]
    for k in range(len(a)):
        v = v + (a[k] + G) * DT
        p = p + v * DT
        visited.append(p.copy())
    np.testing.assert_allclose(np.array(visited), forward[::-1], atol=1e-9)  # y_k = X_{T-k}: ends on X_1


def test_a_reversed_free_fall_needs_no_control_after_its_first_frame():
    # forward: falling from rest. Reversed, the fluid rises and decelerates under gravity alone; the
    # second difference of a parabola is exact, so only the first frame (where the velocity is
    # handed over, not differenced) and float round-off need control
    t = np.arange(20)[:, None, None] * DT
    fall = np.array([[0.5, 0.8]]) + 0.5 * G * t**2
    v_end = (fall[-1] - fall[-2]) / DT
    a = reverse_kinematic(fall, v_end, DT, G, a_max=None)
    assert np.abs(a[1:]).max() < 1e-3
    assert np.abs(reverse_kinematic(fall, v_end, DT, G, a_max=1.0)).max() <= 1.0 + 1e-6


def test_smoothing_follows_the_paper_and_lambda_zero_is_the_identity():
    rng = np.random.default_rng(1)
    a = rng.normal(0, 10, (5, 4, 2)).astype(np.float32)
    assert np.array_equal(smooth(a, lam=0.0), a)
    s = smooth(a, lam=0.1, beta=2.0)
    assert np.array_equal(s[-1], a[-1])  # the last frame has no successor
    u, w = a[1].astype(np.float64), a[2].astype(np.float64)
    cos = (u * w).sum(-1) / np.linalg.norm(u, axis=-1) / np.linalg.norm(w, axis=-1)
    np.testing.assert_allclose(s[1], u - 0.1 * np.exp(-2.0 * cos)[:, None] * (u - w), rtol=1e-5)
    assert np.linalg.norm(np.diff(s, axis=0)) < np.linalg.norm(np.diff(a, axis=0))  # smoother


def _moving_state(seed: int = 3, frames: int = 30) -> tuple[MpmSimulator, np.ndarray, np.ndarray]:
    """A clustered water2d state in flow, then a forward run X_1..X_T and the velocity at X_T."""
    sim = MpmSimulator(make_scene("water2d", seed=seed), r_p=0.3, seed=seed, threads=1)
    rollout(sim, 40)
    start = sim.state()
    forward = rollout(sim, frames - 1).fluid_positions.astype(np.float64)
    v_end = sim.velocities
    sim.restore(start)
    return sim, forward, v_end


def test_tracking_lands_the_replay_much_closer_to_x1_than_the_kinematic_field():
    sim, forward, v_end = _moving_state()
    scene_g = np.array([0.0, -9.8])

    def reversed_start() -> MpmSimulator:
        s = MpmSimulator(sim.scene, threads=1)
        s.solver.positions = forward[-1].astype(np.float32)
        s.solver.velocities = (-v_end).astype(np.float32)
        return s

    kin = reverse_kinematic(forward, v_end, DT, scene_g)
    replay = reversed_start()
    replay.forcing = lambda f, x, v: kin[f] if f < len(kin) else None
    end_kin = replay.particles.fluid(rollout(replay, len(kin)).positions[-1])
    tracked = reverse_tracking(reversed_start(), forward)
    replay = reversed_start()
    replay.forcing = lambda f, x, v: tracked[f] if f < len(tracked) else None
    end_trk = replay.particles.fluid(rollout(replay, len(tracked)).positions[-1])
    miss_kin = np.abs(end_kin - forward[0]).mean()
    miss_trk = np.abs(end_trk - forward[0]).mean()
    assert miss_trk < 0.2 * miss_kin, (miss_trk, miss_kin)
    assert np.linalg.norm(tracked, axis=-1).max() <= A_MAX * (1 + 1e-6)


# ----------------------------------------------------------------------- sketches
def _ink_axis(img: np.ndarray, channel: int) -> tuple[np.ndarray, float]:
    rows, cols = np.nonzero(img[:, :, channel] > 64)
    pts = np.stack([cols + 0.5, img.shape[0] - (rows + 0.5)], -1).astype(np.float64)  # back to y up
    c = pts.mean(0)
    vals, vecs = np.linalg.eigh(np.cov((pts - c).T))
    return c / img.shape[0], math.degrees(math.atan2(vecs[1, -1], vecs[0, -1]))


@pytest.mark.parametrize("angle", [0.0, 30.0, 90.0, 145.0, 260.0])
def test_a_rendered_arrow_points_where_it_was_drawn_with_y_up(angle):
    c = np.array([0.5, 0.5])
    d = 0.3 * np.array([math.cos(math.radians(angle)), math.sin(math.radians(angle))])
    img = render_sketch(Sketch.arrow(c - d, c + d), size=128)
    centre, axis = _ink_axis(img, 0)
    diff = (axis - angle) % 180.0
    assert min(diff, 180.0 - diff) < 3.0
    head, _ = _ink_axis(img, 1)  # the head sits at the tip, not the tail
    assert np.linalg.norm(head - (c + d)) < np.linalg.norm(head - (c - d))


def test_a_rendered_oval_keeps_its_centre_and_radii():
    sk = Sketch.oval([0.4, 0.6], [0.2, 0.1], angle=0.5)
    c, r, ang = sk.ellipse()
    np.testing.assert_allclose(c, [0.4, 0.6], atol=1e-3)
    np.testing.assert_allclose(r, [0.2, 0.1], rtol=0.02)
    assert abs(math.sin(ang - 0.5)) < 0.02
    img = render_sketch(sk, size=128)
    centre, axis = _ink_axis(img, 2)
    np.testing.assert_allclose(centre, [0.4, 0.6], atol=0.01)
    assert abs(math.sin(math.radians(axis) - 0.5)) < 0.05
    assert not render_sketch(None).any()  # the blank sketch
    # drawn by hand: sampled unevenly (slow on one side), wobbly, not quite closed
    rng = np.random.default_rng(3)
    th = np.sort(rng.uniform(0, 1.9 * np.pi, 80) ** 1.3 / (1.9 * np.pi) ** 0.3)
    pts = np.stack([0.4 + 0.2 * np.cos(th), 0.6 + 0.1 * np.sin(th)], -1) + rng.normal(0, 0.003, (80, 2))
    c, r, _ = Sketch("oval", pts).ellipse()
    np.testing.assert_allclose(c, [0.4, 0.6], atol=0.01)
    np.testing.assert_allclose(r, [0.2, 0.1], rtol=0.06)


def test_sketch_json_round_trips_and_bad_fields_are_named():
    sk = Sketch.from_json({"kind": "arrow", "points": [[0.1, 0.2], [0.5, 0.7]], "t": [0.0, 0.3], "width": [0.01, 0.02]})
    assert Sketch.from_json(sk.to_json()).to_json() == sk.to_json()
    for bad, field in [
        ({"kind": "spiral", "points": [[0, 0], [1, 1]]}, "kind"),
        ({"kind": "arrow", "points": [[0, 0]]}, "points"),
        ({"kind": "arrow", "points": [[0, 0], [float("nan"), 1]]}, "points"),
        ({"kind": "arrow", "points": [[0, 0], [9, 1]]}, "points"),
        ({"kind": "arrow", "points": [[0.5, 0.5], [0.5, 0.5]]}, "points"),
        ({"kind": "arrow", "points": [[0, 0], [1, 1]], "t": [1, 0]}, "t"),
        ({"kind": "arrow", "points": [[0, 0], [1, 1]], "width": [0.01]}, "width"),
        ({"kind": "arrow", "points": [[0, 0], [1, 1]], "colour": "red"}, "colour"),
        ({"points": [[0, 0], [1, 1]]}, "kind"),
        ("{nope", "sketch"),
    ]:
        with pytest.raises(InvalidInputError) as e:
            Sketch.from_json(bad)
        assert e.value.field == field, bad


def test_training_sketches_follow_the_centroids_and_principal_axes():
    rng = np.random.default_rng(2)
    start = rng.normal([0.3, 0.3], 0.02, (4000, 2))
    end = rng.normal([0.6, 0.5], [0.08, 0.02], (4000, 2))
    arrow = sketch_from_trajectory(start, end, "arrow")
    np.testing.assert_allclose(arrow.start, start.mean(0))
    np.testing.assert_allclose(arrow.end, end.mean(0))
    oval = sketch_from_trajectory(start, end, "oval")
    c, r, ang = oval.ellipse()
    np.testing.assert_allclose(c, [0.6, 0.5], atol=5e-3)
    np.testing.assert_allclose(r, [0.16, 0.04], rtol=0.05)  # ±2σ
    assert abs(math.sin(ang)) < 0.05
    # 3D: depth drawn as width, nearer (larger z) wider; constant when z does not change
    s3 = np.c_[start, np.full(len(start), 0.5)]
    e3 = np.c_[end, np.full(len(end), 0.7)]
    w = sketch_from_trajectory(s3, e3, "arrow").width
    assert w is not None and w[1] > w[0]
    w = sketch_from_trajectory(s3, np.c_[end, np.full(len(end), 0.5)], "arrow").width
    assert w is not None and w[0] == w[1]


# ---------------------------------------------------------------------- baselines
def _blob() -> Scene:
    p = MpmParams(dim=2)
    x = lattice([0.4, 0.5], [0.5, 0.6], 0.5 / 128)
    return Scene("blob", p, x, np.zeros(len(x), np.int32), np.zeros_like(x))


def test_the_constant_force_lands_a_free_clouds_centroid_on_the_arrow_tip():
    sim = MpmSimulator(_blob(), threads=1)
    c0 = sim.particles.fluid(sim.positions).mean(0)
    sk = Sketch.arrow(c0, c0 + np.array([0.15, 0.1]))
    ep = control_episode(sim, sk, Controller("constant", frames=60))
    end = sim.particles.fluid(sim.positions).mean(0)
    np.testing.assert_allclose(end, sk.end, atol=2e-3)  # free cloud, no wall touched: kinematics
    assert ep.metrics["cosine"] > 0.999 and abs(ep.metrics["length_ratio"] - 1) < 0.02
    assert ep.metrics["smoothness"] == pytest.approx(1.0)


@pytest.mark.parametrize("method", ["constant", "pd"])
def test_a_flipped_arrow_flips_the_motion_and_no_sketch_no_effort(method):
    def run(vec):  # type: ignore[no-untyped-def]
        sim = MpmSimulator(_blob(), threads=1)
        c = sim.particles.fluid(sim.positions).mean(0)
        return control_episode(sim, Sketch.arrow(c, c + vec), Controller(method, frames=40))

    a = run(np.array([0.1, 0.05]))
    b = run(np.array([-0.1, -0.05]))
    assert a.metrics["cosine"] > 0.9 and b.metrics["cosine"] > 0.9
    sim = MpmSimulator(_blob(), threads=1)
    none = control_episode(sim, None, Controller("none", frames=40))
    assert none.metrics["effort_mean_g"] == 0.0
    with pytest.raises(InvalidInputError) as e:
        Controller(method).plan(sim, None)
    assert e.value.field == "sketch"


def test_pd_fills_a_drawn_oval():
    sim = MpmSimulator(_blob(), threads=1)
    sk = Sketch.oval([0.6, 0.4], [0.12, 0.05], angle=0.3)
    ep = control_episode(sim, sk, Controller("pd"))
    assert ep.metrics["inside"] > 0.8
    end = sim.particles.fluid(sim.positions)
    assert oval_adherence(end, sk)["inside"] == ep.metrics["inside"]
    assert np.isfinite(end).all()


@pytest.mark.parametrize("seed", range(8))
def test_an_oval_target_turns_the_cloud_and_never_mirrors_it(seed):
    """pd_targets on an asymmetric cloud (an L of two bars, long axis at a random angle): its own ±2σ oval
    (sketch_from_trajectory) leaves every particle where it is, and the same oval turned by θ (|θ| < 90°)
    turns the cloud rigidly by θ about its centroid — a rotation with det +1, not a reflection."""
    rng = np.random.default_rng(seed)
    bar = np.stack(np.meshgrid(np.linspace(0, 0.2, 21), np.linspace(0, 0.03, 4), indexing="ij"), -1).reshape(-1, 2)
    leg = np.stack(np.meshgrid(np.linspace(0, 0.03, 4), np.linspace(0.03, 0.08, 6), indexing="ij"), -1).reshape(-1, 2)
    phi = rng.uniform(-math.pi, math.pi)
    rot = lambda a: np.array([[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]])  # noqa: E731
    x = np.concatenate([bar, leg]) @ rot(phi).T + rng.uniform(0.35, 0.65, 2)
    own = sketch_from_trajectory(x, x, "oval")
    np.testing.assert_allclose(pd_targets(x, own), x, atol=1e-9)
    theta = rng.uniform(-1.4, 1.4)
    c, radii, angle = own.ellipse()
    y = pd_targets(x, Sketch.oval(c, radii, angle + theta))
    np.testing.assert_allclose(y - c, (x - c) @ rot(theta).T, atol=1e-9)


def test_the_same_state_and_sketch_give_a_bitwise_equal_episode():
    runs = []
    for _ in range(2):
        sim = MpmSimulator(make_scene("water2d", seed=7), threads=1)
        rollout(sim, 20)
        runs.append(control_episode(sim, Sketch.oval([0.5, 0.3], [0.1, 0.1]), Controller("pd", frames=30)).rollout.positions)
    assert np.array_equal(runs[0], runs[1])


def test_controllers_refuse_bad_settings():
    for kw, field in [
        ({"method": "magic"}, "method"),
        ({"method": "diffusion"}, "model"),
        ({"frames": 0}, "frames"),
        ({"method": "oracle"}, "oracle"),
        ({"steps": 0}, "steps"),
        ({"guidance": -1}, "guidance"),
        ({"seed": -1}, "seed"),
    ]:
        with pytest.raises(InvalidInputError) as e:
            Controller(**kw)
        assert e.value.field == field


def test_arrow_adherence_by_hand():
    start = np.zeros((3, 2))
    end = start + np.array([0.0, 0.2])
    m = arrow_adherence(start, end, Sketch.arrow([0.1, 0.1], [0.1, 0.5]))
    assert m["cosine"] == pytest.approx(1.0) and m["length_ratio"] == pytest.approx(0.5)


# ------------------------------------------------------------------ PNG sketches
def _png(img: np.ndarray) -> bytes:
    import io

    from PIL import Image

    buf = io.BytesIO()
    Image.fromarray(img).save(buf, format="PNG")
    return buf.getvalue()


@pytest.mark.parametrize("angle", [0.0, 40.0, 100.0, 200.0, 300.0])
def test_an_arrow_drawn_in_a_png_reads_back(angle):
    from hybridmpm.control import sketch_from_png

    c = np.array([0.5, 0.5])
    d = 0.25 * np.array([math.cos(math.radians(angle)), math.sin(math.radians(angle))])
    img = 255 - render_sketch(Sketch.arrow(c - d, c + d), size=256).max(-1)  # dark ink on white, as a canvas export
    sk = sketch_from_png(_png(img))
    assert sk.kind == "arrow"
    got = math.degrees(math.atan2(sk.vector[1], sk.vector[0]))
    assert abs((got - angle + 180) % 360 - 180) < 3.0  # the direction, not just the axis: y up kept
    np.testing.assert_allclose(sk.end, c + d, atol=0.03)


def test_an_oval_drawn_in_a_png_reads_back_and_bad_pngs_are_refused():
    from hybridmpm.control import sketch_from_png

    sk = sketch_from_png(_png(render_sketch(Sketch.oval([0.4, 0.6], [0.2, 0.1], 0.5), size=256)))
    c, r, ang = sk.ellipse()
    assert sk.kind == "oval" and abs(math.sin(ang - 0.5)) < 0.05
    np.testing.assert_allclose(c, [0.4, 0.6], atol=0.01)
    np.testing.assert_allclose(r, [0.2, 0.1], rtol=0.05)
    for bad in (b"GIF89a...", _png(np.zeros((64, 64), np.uint8)), _png(np.zeros((4096, 4096), np.uint8))):
        with pytest.raises(InvalidInputError) as e:
            sketch_from_png(bad)
        assert e.value.field == "sketch"


def test_tracking_the_uncontrolled_motion_costs_no_effort():
    """The tracking law has no gravity feed-forward: a plan that is the fluid's
    own free motion (a falling blob, no wall touched) needs ~0 acceleration,
    and the tracked run reproduces it."""
    sim = MpmSimulator(_blob(), threads=1)
    start = sim.state()
    free = rollout(sim, 40).fluid_positions
    sim.restore(start)
    ep = control_episode(sim, None, Controller("oracle", frames=40, oracle_path=free))
    assert ep.metrics["effort_mean_g"] < 0.05  # what remains: a frame's mean velocity against the velocity at its start under gravity
    np.testing.assert_allclose(ep.rollout.fluid_positions[-1], free[-1], atol=1e-4)


def test_tracking_a_displaced_path_moves_the_fluid_onto_it():
    """A plan that is the free motion shifted by a growing offset: the tracked
    fluid ends near the shifted end (critically damped, settling within the horizon)."""
    sim = MpmSimulator(_blob(), threads=1)
    start = sim.state()
    free = rollout(sim, 60).fluid_positions.astype(np.float64)
    ramp = np.linspace(0.0, 1.0, len(free))[:, None, None] * np.array([0.08, 0.04])
    sim.restore(start)
    control_episode(sim, None, Controller("oracle", frames=60, oracle_path=free + ramp))
    end = sim.particles.fluid(sim.positions).mean(0)
    target = (free[-1] + ramp[-1]).mean(0)
    assert np.linalg.norm(end - target) < 0.05 * np.linalg.norm(ramp[-1])  # within 5 % of the 9 cm shift


def test_a_plan_runs_blas_on_one_thread_and_restores_it_after():
    """While a diffusion plan runs, OpenBLAS's workers must not compete with the
    two threads the plan already uses; the process's setting comes back after,
    also when the plan raises (threadpoolctl's own report, not ours)."""
    from threadpoolctl import threadpool_info

    from hybridmpm.control.controller import single_thread_blas

    def blas_threads() -> list[int]:
        return [int(i["num_threads"]) for i in threadpool_info() if i["user_api"] == "blas"]

    before = blas_threads()
    assert before, "numpy is linked against a BLAS threadpoolctl can see"
    with pytest.raises(RuntimeError):
        with single_thread_blas():
            assert blas_threads() == [1] * len(before)
            raise RuntimeError("a failing plan")
    assert blas_threads() == before


def test_effort_and_smoothness_taken_one_field_at_a_time_equal_the_stacked_formulas():
    """AppliedStats keeps one field: its effort and smoothness equal the brute-force formulas over every field
    stacked (zero fields and particles with no force included), and a control's peak memory no longer grows
    with the fields it applied (it kept and stacked them all in float64)."""
    import tracemalloc

    from hybridmpm.control.metrics import AppliedStats
    from hybridmpm.conventions import G

    rng = np.random.default_rng(7)
    fields = [rng.normal(0, 3, (50, 2)) for _ in range(12)]
    fields[3][:10] = 0.0
    fields[5] = np.zeros((50, 2))
    st = AppliedStats()
    for a in fields:
        st.add(a.astype(np.float32))
    a = np.stack(fields).astype(np.float32).astype(np.float64)
    n = np.linalg.norm(a, axis=-1)
    assert st.effort()["effort_mean_g"] == pytest.approx(n.mean() / G, rel=1e-12)
    assert st.effort()["effort_max_g"] == pytest.approx(n.max() / G, rel=1e-12)
    u, w = a[:-1], a[1:]
    nu, nw = np.linalg.norm(u, axis=-1), np.linalg.norm(w, axis=-1)
    ok = (nu > 0) & (nw > 0)
    assert st.smoothness() == pytest.approx(((u * w).sum(-1)[ok] / (nu * nw)[ok]).mean(), rel=1e-12)
    one = AppliedStats()
    one.add(fields[0])
    assert math.isnan(one.smoothness()) and AppliedStats().effort()["effort_mean_g"] == 0.0
    # memory: a 600-frame constant control on water2d peaks at a few trajectories, not tens
    sim = MpmSimulator("water2d", seed=1, threads=1)
    traj = (600 + 1) * sim.particles.num_total * 2 * 4
    tracemalloc.start()
    try:
        control_episode(sim, Sketch("arrow", [[0.2, 0.3], [0.5, 0.3]]), Controller("constant", frames=600))
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < 5 * traj, (peak, traj)


def test_a_plan_knows_its_centroid_path_and_the_sketch_fits_its_oval_once(monkeypatch):
    """The plan carries its own geometry: the constant force's centroid path starts at the fluid's
    mass-weighted centroid and ends on the sketch's target (the arrow's tip from the start centroid), and the
    episode's centroid follows it; PD's path approaches its targets' centroid (critically damped: within 2% of
    the start error at the end). An oval's ellipse is fitted once per sketch, however many parts ask for it."""
    from hybridmpm.control import control_episode
    from hybridmpm.control.sketch import Sketch as SketchClass

    sim = MpmSimulator(make_scene("water2d", seed=3))
    rollout(sim, 5)
    arrow = Sketch.arrow([0.3, 0.3], [0.55, 0.4])
    seen = []
    ep = control_episode(sim, arrow, Controller("constant", frames=40), on_plan=seen.append)
    plan = seen[0]
    stride, path = plan.centroid_path()
    assert stride == 1 and path.shape == (41, 2)
    c0 = plan.origin.centroid
    w = plan.origin.weights
    fluid = ep.rollout.fluid_positions
    assert np.allclose(path[0], w @ fluid[0], atol=1e-6)
    assert np.allclose(path[-1], c0 + arrow.vector, atol=1e-9)
    assert np.allclose(plan.summary()["target"], np.round(c0 + arrow.vector, 5))
    assert np.linalg.norm(w @ fluid[-1] - path[-1]) < 0.25 * np.linalg.norm(arrow.vector)  # the fluid went where the plan said

    oval = Sketch.oval([0.5, 0.3], [0.12, 0.06], 0.3)
    calls = []
    fit = SketchClass._fit
    monkeypatch.setattr(SketchClass, "_fit", lambda self: calls.append(1) or fit(self))
    pd = Controller("pd", frames=40).plan(sim, oval)
    _, pd_path = pd.centroid_path()
    e0 = np.linalg.norm(pd_path[0] - pd.pd_centroid)
    assert np.linalg.norm(pd_path[-1] - pd.pd_centroid) < 0.02 * e0
    control_episode(sim, oval, Controller("pd", frames=10))
    assert oval.target(c0).tolist() == oval.ellipse()[0].tolist() and len(calls) == 1
