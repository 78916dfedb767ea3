"""The Fluid ControlNet's numerics and pipeline: temporal basis
against scipy, the DDIM sampler against its closed form, the per-particle
sketch sampling against torch's grid_sample, ONNX against torch on graphs
with many edges per receiver, and a CI training smoke run through export to
a controlled rollout."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch

from hybridmpm.control import Controller, Sketch, control_episode
from hybridmpm.control.diffusion import (
    ControlModel,
    add_noise,
    bilinear_sample,
    cosine_alpha_bar,
    ddim_step,
    expand,
    path_basis,
    project,
    temporal_basis,
    trailing_timesteps,
)
from hybridmpm.control.targets import sketch_geometry
from hybridmpm.conventions import DT_FRAME
from hybridmpm.errors import InvalidInputError
from hybridmpm.scenes import make_scene


# ----------------------------------------------------------------- basis
@pytest.mark.parametrize("k", [4, 8, 13])
def test_temporal_basis_matches_scipy(k: int) -> None:
    from scipy.interpolate import BSpline

    frames = 100
    inner = np.linspace(0.0, 1.0, k - 2)
    knots = np.concatenate([[0.0] * 3, inner, [1.0] * 3])
    u = np.linspace(0.0, 1.0, frames)
    ref = BSpline.design_matrix(u, knots, 3).toarray()
    np.testing.assert_allclose(temporal_basis(frames, k), ref, atol=1e-12)


def test_path_basis_starts_at_zero_and_projection_is_exact_in_span() -> None:
    b = path_basis(100, 8)
    assert b.shape == (100, 8) and np.all(b[0] == 0)
    rng = np.random.default_rng(0)
    coef = rng.normal(size=(30, 8, 2))
    field = expand(coef, b)
    np.testing.assert_allclose(project(field, b), coef, atol=1e-4)
    # a smooth path (a parabola) is represented to < 1e-3 of its size
    t = np.linspace(0, 1, 100)[:, None, None] * np.ones((1, 5, 2))
    path = 0.3 * t + 0.2 * t**2
    fit = expand(project(path, b), b)
    assert np.abs(fit - path).max() < 1e-3 * np.abs(path).max()


def test_the_sketch_prior_is_a_smoothstep_to_each_target_held_exactly_by_the_basis() -> None:
    from hybridmpm.control.diffusion import prior_coefficients
    from hybridmpm.control.targets import smoothstep

    b = path_basis(100, 8)
    off = np.random.default_rng(5).normal(size=(20, 2)) * 0.1
    plan = expand(prior_coefficients(off, b).reshape(20, 8, 2), b)
    np.testing.assert_allclose(plan, smoothstep(100)[:, None, None] * off[None], atol=1e-9)
    np.testing.assert_allclose(plan[-1], off, atol=1e-12)


def test_basis_rejects_bad_size() -> None:
    with pytest.raises(InvalidInputError, match="k"):
        temporal_basis(10, 3)


# ----------------------------------------------------------------- schedule and DDIM
def test_cosine_schedule_matches_its_definition() -> None:
    ab = cosine_alpha_bar(100)
    f = lambda s: math.cos((s + 0.008) / 1.008 * math.pi / 2) ** 2  # noqa: E731
    # away from the capped end, ᾱ_t = f((t+1)/T) / f(0) (Nichol & Dhariwal Eq. 17)
    for t in (0, 10, 50, 90):
        assert abs(ab[t] - f((t + 1) / 100) / f(0)) < 1e-9
    assert np.all(np.diff(ab) < 0) and 0 < ab[-1] < 1e-3


def test_trailing_timesteps_start_at_pure_noise() -> None:
    assert trailing_timesteps(10, 100).tolist() == [99, 89, 79, 69, 59, 49, 39, 29, 19, 9]
    assert trailing_timesteps(1, 100).tolist() == [99]
    with pytest.raises(InvalidInputError, match="steps"):
        trailing_timesteps(0)


def test_ddim_with_a_fixed_x0_follows_the_closed_form() -> None:
    """With η = 0 and a model that always predicts the same x0, DDIM keeps the
    first ε̂ and x_t = √ᾱ_t·x0 + √(1 − ᾱ_t)·ε̂ at every visited t (Song et al. Eq. 12)."""
    rng = np.random.default_rng(1)
    x0 = rng.normal(size=(50, 16))
    ab = cosine_alpha_bar(100)
    ts = trailing_timesteps(10, 100)
    x = rng.normal(size=x0.shape)
    eps = (x - math.sqrt(ab[ts[0]]) * x0) / math.sqrt(1 - ab[ts[0]])
    for i, t in enumerate(ts):
        prev = ab[ts[i + 1]] if i + 1 < len(ts) else 1.0
        x = ddim_step(x, x0, float(ab[t]), float(prev))
        np.testing.assert_allclose(x, math.sqrt(prev) * x0 + math.sqrt(1 - prev) * eps, atol=1e-10)
    np.testing.assert_allclose(x, x0, atol=1e-12)
    # and add_noise is the forward process DDIM inverts
    xt = add_noise(x0, eps, float(ab[40]))
    np.testing.assert_allclose(ddim_step(xt, x0, float(ab[40]), 1.0), x0, atol=1e-12)


# ----------------------------------------------------------------- sketch sampling
def test_bilinear_sample_matches_torch_grid_sample() -> None:
    from hybridmpm.train.control.model import sample_local

    rng = np.random.default_rng(2)
    fmap = rng.normal(size=(8, 32, 32)).astype(np.float32)
    xy = rng.uniform(-0.05, 1.05, size=(500, 2)).astype(np.float32)  # some outside the image: zeros padding
    ref = sample_local(torch.from_numpy(fmap)[None], torch.from_numpy(xy)).numpy()
    np.testing.assert_allclose(bilinear_sample(fmap, xy), ref, atol=1e-5)


def test_sketch_geometry_blank_is_zero_and_arrow_is_the_vector() -> None:
    x = np.random.default_rng(3).uniform(0.3, 0.5, size=(40, 2))
    g, off = sketch_geometry(None, x)
    assert not g.any() and not off.any()
    g, off = sketch_geometry(Sketch.arrow([0.4, 0.4], [0.7, 0.4]), x)
    assert g[0] == 1 and g[1] == 1 and abs(g[3] - 1.0) < 1e-6 and abs(g[4]) < 1e-6
    np.testing.assert_allclose(off, np.tile([1.0, 0.0], (40, 1)), atol=1e-6)  # every particle offset by the arrow / 0.3 m


# ----------------------------------------------------------------- training smoke run, export, controlled rollout
@pytest.fixture(scope="module")
def smoke_model(tmp_path_factory: pytest.TempPathFactory) -> dict:
    from hybridmpm.train.control.cases import generate_control
    from hybridmpm.train.control.train import train_control

    root = tmp_path_factory.mktemp("ctl")
    generate_control("water2d", root / "data", 8, 100, progress=False)
    summary = train_control(
        "water2d", root / "data", root / "run", steps=200, lr=3e-3, checkpoint_every=1000, valid_fraction=0.2, progress=False,
        prior="sketch_ramp",
    )  # fmt: skip
    log = [json.loads(line) for line in (root / "run" / "log.jsonl").read_text().splitlines()]
    # the shipped kind (plans relative to the free motion), briefly: for the serving path, not for the loss
    free = train_control("water2d", root / "data", root / "free", steps=20, valid_fraction=0.2, progress=False)
    return {"root": root, "summary": summary, "log": log, "free_summary": free}


def test_smoke_training_loss_falls(smoke_model: dict) -> None:
    """A13: 200 steps of training on 8 cases (about half a minute on the 2-core
    machine: a wall-clock figure, printed, not asserted; the step count
    decides, so a slow machine trains as far) lower the loss by ≥ 30 % (to
    0.36 of its first value here; 0.26 after 400 steps). On the
    sketch-ramp target: the free-sketch target (the true path minus the coarse
    free motion bent onto the sketch) is mostly splash the state does not
    predict, and its loss falls by only about a quarter in that time
    (docs/control.md)."""
    s = smoke_model["summary"]
    print(f"{s['steps']} training steps in {s['seconds']:.1f} s")
    assert s["steps"] == 200
    # measured at fixed noise levels and draws on training pairs, so the per-step sampling noise cannot decide it
    assert s["fit_last"] <= 0.7 * s["fit_first"], s


def test_onnx_matches_torch_on_many_edges_per_receiver(smoke_model: dict) -> None:
    """The exported graphs reproduce the trained torch model (≤ 1e-4) on a
    dense cloud where each receiver has dozens of incoming edges."""
    from hybridmpm.control.sketch import render_sketch
    from hybridmpm.graph import radius_graph
    from hybridmpm.train.control.model import ControlNetConfig, FluidControlNet

    run = smoke_model["root"] / "run"
    ck = torch.load(run / "ckpt.pt", map_location="cpu", weights_only=False)
    net = FluidControlNet(ControlNetConfig.from_dict(ck["config"]))
    net.load_state_dict(ck["ema"])
    net.eval()
    cm = ControlModel(run / "model")
    rng = np.random.default_rng(4)
    x = rng.uniform(0.3, 0.36, size=(300, 2)).astype(np.float32)
    v = rng.normal(size=x.shape).astype(np.float32)
    s, r, _, _ = radius_graph(x, cm.radius)
    assert np.bincount(r).max() > 30
    pt = np.full(len(x), 5, np.int64)
    sk = Sketch.oval([0.5, 0.5], [0.1, 0.05], 0.3)
    img = render_sketch(sk).astype(np.float32).transpose(2, 0, 1)[None] / 255.0
    geo, off = sketch_geometry(sk, x)
    xt = rng.normal(size=(len(x), cm.k_basis * 2)).astype(np.float32)
    with torch.no_grad():
        h, e, local, glob = net.encode(*(torch.from_numpy(a) for a in (x, v, pt, s, r, img)))
        cond = torch.cat([glob, torch.from_numpy(geo)[None]], 1)
        ref = net.head(torch.from_numpy(xt), h, local, torch.from_numpy(off), e, torch.from_numpy(s), torch.from_numpy(r), torch.tensor([0.37]), cond).numpy()
    hs, es = cm.sessions["state_encoder"].run(None, {"positions": x, "velocities": v, "particle_type": pt, "senders": s, "receivers": r})
    gl, lm = cm.sessions["sketch_encoder"].run(None, {"image": img})
    loc = bilinear_sample(lm[0], x)
    feed = {"x_t": xt, "h": hs, "local": loc, "offset": off, "edges": es, "senders": s, "receivers": r}
    feed.update({"t": np.array([0.37], np.float32), "cond": np.concatenate([gl, geo[None]], 1)})
    out = cm.sessions["denoiser_head"].run(None, feed)[0]
    assert np.abs(ref).max() > 1e-3  # a trained, non-trivial output
    np.testing.assert_allclose(out, ref, atol=1e-4)
    # its sums are ScatterNDs, which lose updates on more than one onnxruntime thread: only 1 is accepted
    for bad in (2, 0, True):
        with pytest.raises(InvalidInputError) as err:
            ControlModel(run / "model", threads=bad)
        assert err.value.field == "threads"


def test_exported_model_controls_a_rollout_deterministically(smoke_model: dict) -> None:
    from hybridmpm.train.control.cases import make_case

    case = make_case("water2d", 5001, "oval", tracking=False)
    model = ControlModel(smoke_model["root"] / "free" / "model")  # the shipped kind: the free-motion rollout on a second thread
    assert model.needs_free
    runs = []
    for seed in (7, 7, 8):
        ep = control_episode(case.simulator(), case.sketch, Controller("diffusion", frames=40, model=model, seed=seed), target=case.target)
        fluid = ep.rollout.fluid_positions
        assert np.isfinite(fluid).all() and ep.rollout.failure is None
        runs.append((ep.plan.path, fluid))
    assert np.array_equal(runs[0][0], runs[1][0]) and np.array_equal(runs[0][1], runs[1][1])  # same seed: same bits
    assert not np.array_equal(runs[0][0], runs[2][0])  # another seed: another sample
    # classifier-free guidance (a blank pass per step) gives a finite plan that starts where the fluid is
    sim = case.simulator()
    plan = Controller("diffusion", model=model, guidance=2.0).plan(sim, case.sketch)
    assert plan.path is not None and np.isfinite(plan.path).all()
    np.testing.assert_allclose(plan.path[0], sim.particles.fluid(sim.positions), atol=1e-6)
    # no sketch: no force (the blank sketch is the sampler's unconditional branch, not a request)
    blank = Controller("diffusion", frames=40, model=model).plan(sim, None)
    assert blank.path is None and blank(0, np.zeros((1, 2)), np.zeros((1, 2))) is None


def test_the_free_motion_prior_is_required_and_may_come_from_another_thread(smoke_model: dict) -> None:
    """A free-sketch model refuses to sample without the free motion (naming
    ``free``), and a Future of it gives the same bits as the array."""
    from concurrent.futures import ThreadPoolExecutor

    from hybridmpm.control.prior import free_motion, free_motion_of, material_of
    from hybridmpm.train.control.cases import make_case

    model = ControlModel(smoke_model["root"] / "free" / "model")
    assert model.needs_free
    case = make_case("water2d", 5003, "arrow", tracking=False)
    sim = case.simulator()
    p = sim.particles
    x, v, pt = p.fluid(sim.positions), sim.velocities, p.particle_type[: p.num_fluid]
    with pytest.raises(InvalidInputError, match="free"):
        model.sample(x, v, pt, case.sketch)
    args = (x, v, material_of(pt), sim.scene.params, model.frames - 1)
    free = free_motion(*args, dt_frame=sim.dt_frame)
    assert np.array_equal(free, free_motion_of(sim, model.frames - 1))  # what the controller calls
    with pytest.raises(InvalidInputError, match="free"):
        model.sample(x, v, pt, case.sketch, free=free[:-1])
    a = model.sample(x, v, pt, case.sketch, seed=3, free=free).path
    with ThreadPoolExecutor(1) as pool:
        b = model.sample(x, v, pt, case.sketch, seed=3, free=pool.submit(free_motion, *args, dt_frame=sim.dt_frame)).path
    assert np.array_equal(a, b)
    c = model.sample(x, v, pt, case.sketch, seed=3, free=free, guidance=1.5).path  # CFG needs both branches' priors first
    assert np.isfinite(c).all() and not np.array_equal(a, c)


def test_a_free_sketch_plan_ends_on_the_sketch(smoke_model: dict) -> None:
    """The served plan (free-sketch model) keeps the sketch's end constraint
    whatever the network samples: an arrow's tip is where the centroid ends;
    an oval is the end cloud's ±2σ ellipse (centre, radii, axis), checked here
    on the end's own second moments, not through the mapping that imposes them."""
    from hybridmpm.control.prior import free_motion_of
    from hybridmpm.train.control.cases import make_case

    model = ControlModel(smoke_model["root"] / "free" / "model")
    for seed, kind in ((5004, "arrow"), (5005, "oval")):
        case = make_case("water2d", seed, kind, tracking=False)
        sim = case.simulator()
        p = sim.particles
        x = p.fluid(sim.positions).astype(np.float64)
        path = model.sample(x, sim.velocities, p.particle_type[: p.num_fluid], case.sketch, seed=1, free=free_motion_of(sim, model.frames - 1)).path
        np.testing.assert_allclose(path[0], x, atol=1e-6)
        end = path[-1, :, :2]
        if kind == "arrow":
            np.testing.assert_allclose(end.mean(0), x[:, :2].mean(0) + case.sketch.vector, atol=1e-9)
        else:
            centre, radii, angle = case.sketch.ellipse()
            vals, vecs = np.linalg.eigh(np.cov(end.T))
            np.testing.assert_allclose(end.mean(0), centre, atol=1e-9)
            np.testing.assert_allclose(2.0 * np.sqrt(vals[::-1]), radii, rtol=1e-6)
            axis = vecs[:, -1]
            assert abs(abs(axis @ [math.cos(angle), math.sin(angle)]) - 1.0) < 1e-6


def test_a_fluid_in_free_flight_is_planned_on_its_parabola_without_the_network(smoke_model: dict) -> None:
    """A blob thrown upward in mid-air meets no wall in the horizon: its free motion stays on the parabola, so the
    diffusion controller plans the parabola bent onto the sketch (no network), and tracking it with the arrow the
    parabola draws costs next to nothing and lands on the parabola's end; with the rule off the network plans."""
    from hybridmpm.control.prior import ballistic_path
    from hybridmpm.mpm import MpmParams
    from hybridmpm.scenes import Scene
    from hybridmpm.sim import MpmSimulator

    params = make_scene("water2d", seed=0).params
    from hybridmpm.scenes import lattice

    x = lattice([0.46, 0.31], [0.54, 0.39], 0.5 / params.resolved_n_grid())  # 2 particles per cell a side, at rest density
    v = np.tile(np.float32([0.3, 2.0]), (len(x), 1))
    d = params.to_dict()
    scene = Scene("thrown blob", MpmParams.from_dict(d), x, np.zeros(len(x), np.int32), v, dt_frame=DT_FRAME, frames=100)
    sim = MpmSimulator(scene, threads=1)
    model = ControlModel(smoke_model["root"] / "free" / "model")
    g = np.asarray(d["gravity"], np.float64)
    parabola = ballistic_path(x, v, g, model.frames - 1, DT_FRAME)
    arrow = Sketch.arrow(x.mean(0), parabola[-1].mean(0))
    plan = Controller("diffusion", model=model, frames=model.frames - 1).plan(sim, arrow)
    assert plan.network is False
    np.testing.assert_allclose(plan.path, parabola, atol=1e-5)  # the arrow is the parabola's own (float32 state): bent by nothing
    ep = control_episode(MpmSimulator(scene, threads=1), arrow, Controller("diffusion", model=model, frames=model.frames - 1))
    end = ep.rollout.fluid_positions[-1]
    assert ep.metrics["network"] is False  # (reported with the episode's metrics: CLI summary, service, benchmark)
    assert ep.metrics["effort_mean_g"] < 0.05 and ep.metrics["effort_max_g"] < 0.25  # a drawn sketch costs g's
    assert np.sqrt(((end - parabola[-1]) ** 2).sum(-1)).max() < 2e-3
    again = Controller("diffusion", model=model, frames=model.frames - 1, free_flight=False).plan(MpmSimulator(scene, threads=1), arrow)
    assert again.network is True and not np.allclose(again.path, parabola, atol=1e-4)


def test_diffusion_needs_a_model() -> None:
    with pytest.raises(InvalidInputError, match="model"):
        Controller("diffusion")
    with pytest.raises(InvalidInputError, match="scene"):
        Controller.for_scene("no_such_scene", "diffusion")
    with pytest.raises(InvalidInputError, match="model"):
        ControlModel("/nonexistent/dir")


def test_a_model_names_its_own_step_count(tmp_path) -> None:  # type: ignore[no-untyped-def]
    """``control.json``'s ``sample_steps`` is the default a controller samples
    with (the shipped 3D models keep 4, the 2D ones use SAMPLE_STEPS); an
    explicit ``steps`` wins; a malformed value is refused naming ``model``."""
    import shutil

    from hybridmpm.control.controller import shipped_control_model
    from hybridmpm.control.diffusion import SAMPLE_STEPS

    src = shipped_control_model("water2d")
    assert Controller.for_scene("water2d", "diffusion").steps == json.loads((src / "control.json").read_text()).get("sample_steps", SAMPLE_STEPS)
    for bad, good in ((0, 7), ("4", 7)):
        dst = tmp_path / f"m{bad}"
        shutil.copytree(src, dst)
        meta = json.loads((dst / "control.json").read_text())
        (dst / "control.json").write_text(json.dumps({**meta, "sample_steps": good}))
        assert Controller("diffusion", model=dst).steps == good
        assert Controller("diffusion", model=dst, steps=2).steps == 2
        (dst / "control.json").write_text(json.dumps({**meta, "sample_steps": bad}))
        with pytest.raises(InvalidInputError, match="model"):
            ControlModel(dst)
