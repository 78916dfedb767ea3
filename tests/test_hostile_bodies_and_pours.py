"""Bodies and pours that cannot wedge a simulation (docs/bodies.md
"Bounds", docs/materials.md, docs/limits.md): what a frame cannot simulate
is refused when it is asked, naming the user's key with the value given,
and what is accepted runs.

- A body's density (given, or implied by its mass) lies in
  [``MIN_BODY_DENSITY``, ``MAX_BODY_DENSITY``]: a body of 1e-45 kg/m³ is 0 kg
  in float32, one of 1e25 kg/m³ does not fall in rapier's float32
  integration, one of 1e-6 kg/m³ is thrown out of the water at tens of m/s.
  At the bounds a body falls at ``g·t`` (in the air) and rises at the flow's
  pace (under water).
- A body's velocity and rim speed are bounded as a block's, and by the
  substeps a frame may take.
- A tampered checkpoint's body state is refused and changes nothing.
- A number that float32 cannot hold is refused with the user's value, not
  the core's rounding; a material whose wave speed (or viscous limit) needs
  more than ``max_substeps`` substeps is refused naming its key, in-process
  and over HTTP, and the session keeps stepping.
- A CFL error names what sets the step (a body, a parameter set)."""

from __future__ import annotations

import re

import numpy as np
import pytest

from hybridmpm import _core
from hybridmpm.errors import CheckpointError, InvalidInputError, SimulationError
from hybridmpm.scenes.spec import SceneSpec
from hybridmpm.sim import MpmSimulator, rollout
from hybridmpm.sim.pour import pour_block

BOX = {"shape": "box", "center": [0.5, 0.7], "half_extents": [0.04, 0.03], "density": 500.0}


def _shows(v: float, text: str) -> bool:
    """Whether ``text`` holds the number ``v`` as Python or Rust prints it (``1e+25``, ``1e25``, ``1e-06``, ``1e-6``)."""
    g = f"{v:g}"
    return any(c in text for c in (repr(v), g, g.replace("e+0", "e").replace("e+", "e").replace("e-0", "e-")))


def tank(bodies: list[dict], dim: int = 2, **top: object) -> MpmSimulator:
    """Water 0.3 m deep on a 64² grid (3D: 0.32 m deep on 24³) with ``bodies``."""
    if dim == 2:
        block = {"material": "water", "lo": [0.05, 0.05], "hi": [0.95, 0.35]}
        d = {"name": "t", "dim": 2, "n_grid": 64, "blocks": [block], "bodies": bodies, **top}
    else:
        block = {"material": "water", "lo": [0.13, 0.13, 0.13], "hi": [0.87, 0.45, 0.87]}
        d = {"name": "t", "dim": 3, "n_grid": 24, "blocks": [block], "bodies": bodies, **top}
    return MpmSimulator(SceneSpec.from_dict(d).build(), threads=1)


@pytest.mark.parametrize(
    ("change", "field"),
    [
        ({"density": 1e-45}, "density"),  # 0 kg in float32
        ({"density": None, "mass": 1e-45}, "mass"),
        ({"density": 1e-300}, "density"),
        ({"density": 1e25}, "density"),  # does not fall in rapier's float32
        ({"density": 1e20}, "density"),
        ({"density": None, "mass": 1e30}, "mass"),
        ({"density": 1e-6}, "density"),  # thrown out of the water
        ({"density": None, "mass": 1e-4}, "mass"),  # 0.024 kg/m³ for this box
        ({"velocity": [1e6, 0.0]}, "velocity"),
        ({"velocity": [0.0, 1e39]}, "velocity"),  # infinite in float32
        ({"angular_velocity": 1e6}, "angular_velocity"),
        ({"half_extents": [1e39, 0.03]}, "half_extents"),
    ],
)
def test_a_body_a_frame_cannot_simulate_is_refused_naming_the_users_key(change, field):
    sim = tank([])
    before = sim.solver.checkpoint()
    body = {k: v for k, v in {**BOX, **change}.items() if v is not None}
    with pytest.raises(InvalidInputError) as e:
        sim.add_body(body)
    assert e.value.field == f"bodies[0].{field}", e.value
    given = change.get(field)
    if not isinstance(given, list):
        assert _shows(float(given), str(e.value)), e.value  # the value given
    assert sim.solver.checkpoint() == before  # nothing changed
    # the same through a scene file's table
    with pytest.raises(InvalidInputError) as e:
        tank([body])
    assert e.value.field == f"bodies[0].{field}", e.value


def test_a_huge_angle_is_an_angle():
    sim = tank([])
    sim.add_body({**BOX, "angle_deg": 1e308})
    assert np.isfinite(sim.bodies.rotation).all()
    r = sim.bodies.rotation[0]
    np.testing.assert_allclose(r @ r.T, np.eye(2), atol=1e-6)


@pytest.mark.parametrize("dim", [2, 3])
def test_the_heaviest_body_falls_at_g_t(dim):
    c = [0.5, 0.7] if dim == 2 else [0.5, 0.7, 0.5]
    body = {"shape": "box", "center": c, "half_extents": [0.05] * dim, "density": float(_core.MAX_BODY_DENSITY)}
    sim = tank([body], dim)
    ro = rollout(sim, 20)
    assert ro.failure is None
    t = 20 * sim.dt_frame
    g = sim.solver.params.gravity[1]
    assert sim.bodies.velocity[0][1] == pytest.approx(g * t, rel=1e-3)  # in the air: free fall


@pytest.mark.parametrize(
    ("dim", "body"),
    [
        (2, {"shape": "circle", "center": [0.5, 0.15], "radius": 0.04}),
        (2, {"shape": "box", "center": [0.5, 0.15], "half_extents": [0.06, 0.03], "angle_deg": 20.0}),
        (2, {"shape": "capsule", "center": [0.5, 0.15], "radius": 0.03, "half_height": 0.04, "angle_deg": 60.0}),
        (3, {"shape": "sphere", "center": [0.5, 0.25, 0.5], "radius": 0.08}),
        (3, {"shape": "box", "center": [0.5, 0.25, 0.5], "half_extents": [0.1, 0.06, 0.08]}),
    ],
)
def test_the_lightest_body_rises_at_the_flows_pace(dim, body):
    """At ``MIN_BODY_DENSITY`` (about air's) a body released under water rises
    to the surface at under 1.5 m/s (a ping-pong ball rises at a few tenths of
    a m/s; the terminal speed here is of that order, the start's transient a
    little faster) and every frame runs."""
    sim = tank([{**body, "density": float(_core.MIN_BODY_DENSITY)}], dim)
    y0 = sim.bodies.center[0][1]
    fastest = 0.0
    for _ in range(20 if dim == 2 else 12):  # 0.5 s in 2D, 0.3 s in 3D
        ro = rollout(sim, 10)
        assert ro.failure is None, ro.failure_detail
        fastest = max(fastest, float(np.linalg.norm(sim.bodies.velocity[0])))
    assert fastest < 1.5
    if dim == 2:
        assert sim.bodies.center[0][1] > y0 + 0.1  # it rose to the surface (0.35 m)


@pytest.mark.parametrize(
    "row",
    [
        lambda s: s.__setitem__(slice(0, 2), [5.0, 5.0]),  # outside the domain
        lambda s: s.__setitem__(1, 0.01),  # in the floor's wall band
        lambda s: s.__setitem__(0, 1.27e30),
        lambda s: s.__setitem__(7, 2.0**100),  # speed
        lambda s: s.__setitem__(12, 2.0**100),  # angular speed
        lambda s: s.__setitem__(slice(3, 5), [3.0, 0.0]),  # not a rotation
    ],
)
def test_a_tampered_body_state_is_refused_and_changes_nothing(row):
    sim = tank([dict(BOX, center=[0.5, 0.3])])
    rollout(sim, 5)
    blob = sim.solver.checkpoint()
    from hybridmpm.mpm.solver import _body_state

    states = [list(map(float, r)) for r in _body_state(blob)]
    row(states[0])
    broken = sim.solver.with_header(blob, {"body_state": states})
    with pytest.raises(CheckpointError, match="body state"):
        sim.solver.restore(broken)
    with pytest.raises(CheckpointError, match="body state"):
        type(sim.solver).from_checkpoint(broken)
    assert sim.solver.checkpoint() == blob
    assert rollout(sim, 3).failure is None


def test_a_resting_bodys_checkpoint_restores():
    """A body on the floor sinks a hair into rapier's wall: its checkpoint still restores (a cell of slack)."""
    sim = tank([dict(BOX, center=[0.5, 0.2], density=3000.0)])
    rollout(sim, 200)
    blob = sim.solver.checkpoint()
    type(sim.solver).from_checkpoint(blob)
    sim.solver.restore(blob)


@pytest.mark.parametrize(
    ("block", "field"),
    [
        ({"material": "rubber", "E": 1e12}, "E"),
        ({"material": "jello", "nu": 0.4999999}, "nu"),  # near-incompressible: thousands of substeps
        ({"material": "jello", "nu": 0.49999999}, "nu"),  # 0.5 in float32
        ({"material": "honey", "viscosity": 1e30}, "viscosity"),  # the explicit viscous limit
        ({"material": "jello", "density": 1e-30}, "density"),
        ({"material": "jello", "E": 1e39}, "E"),  # infinite in float32
        ({"material": "jello", "density": 1e-300}, "density"),  # 0 in float32
    ],
)
def test_a_pour_a_frame_cannot_simulate_is_refused_naming_its_key(block, field):
    sim = MpmSimulator("water2d", threads=1)
    before = sim.solver.checkpoint()
    with pytest.raises(InvalidInputError) as e:
        pour_block(sim, {**block, "lo": [0.4, 0.7], "hi": [0.5, 0.8]})
    assert e.value.field == field, e.value
    assert repr(block[field]) in str(e.value), e.value  # the user's value, not float32's
    assert sim.solver.checkpoint() == before
    assert rollout(sim, 2).failure is None
    # the same parameters in a scene file's block: refused naming the block's key, or (a wave speed too fast for
    # the frame) a step that names the parameter set that sets it
    d = {"name": "s", "dim": 2, "n_grid": 64, "blocks": [{**block, "lo": [0.4, 0.1], "hi": [0.5, 0.2]}]}
    with pytest.raises((InvalidInputError, SimulationError)) as e:
        _run_scene(d)
    if isinstance(e.value, InvalidInputError):
        assert e.value.field == f"blocks[0].{field}", e.value
    else:
        assert re.search(r"parameter set \d+ \((elastic|water)\)", str(e.value)) and "more than max_substeps" in str(e.value), e.value


def _run_scene(d: dict) -> None:
    """Build a scene dict and ask for its first frame's substeps."""
    sim = MpmSimulator(SceneSpec.from_dict(d).build(), threads=1)
    sim.solver.substeps_for(sim.dt_frame)


def test_honey_steps_within_its_viscous_limit():
    """Viscous water is stepped within the explicit viscous limit: a block of honey 200 times as viscous as the
    preset lands on the water and runs, where the sound speed's 17 substeps went non-finite."""
    sim = MpmSimulator("water2d", threads=2)
    pour_block(sim, {"material": "honey", "viscosity": 2e3, "lo": [0.4, 0.6], "hi": [0.5, 0.7]})
    assert sim.solver.substeps_for(sim.dt_frame) > 150  # the viscous limit sets the step
    ro = rollout(sim, 100)  # it lands (about 0.2 s)
    assert ro.failure is None, ro.failure_detail


def test_the_cfl_error_names_the_body_that_sets_it():
    sim = tank([dict(BOX, velocity=[900.0, 0.0])], max_substeps=20)
    with pytest.raises(SimulationError, match=r"body 0's fastest point \(\|v\| \+ \|ω\|·R\) moving at up to 900 m/s"):
        sim.solver.substeps_for(sim.dt_frame)
    with pytest.raises(InvalidInputError) as e:  # added between frames: refused
        tank([], max_substeps=20).add_body(dict(BOX, velocity=[900.0, 0.0]))
    assert e.value.field == "bodies[0].velocity" and "body 0's fastest point" in str(e.value)
    with pytest.raises(InvalidInputError) as e:
        tank([], max_substeps=20).add_body(dict(BOX, angular_velocity=9000.0))
    assert e.value.field == "bodies[0].angular_velocity"


# ------------------------------------------------------------------ over HTTP
@pytest.fixture(scope="module")
def client():
    pytest.importorskip("fastapi")
    from fastapi.testclient import TestClient

    from hybridmpm.service import ServiceConfig, create_app

    with TestClient(create_app(ServiceConfig(max_sessions=20, max_sessions_per_client=20, idle_ttl_s=600))) as c:
        yield c


def _session(client) -> str:
    r = client.post("/v1/sessions", json={"scene": "dam_break2d", "solver": "mpm", "seed": 0})
    assert r.status_code == 201, r.text
    return r.json()["id"]


def _frame_after_step(client, sid) -> int:
    r = client.post(f"/v1/sessions/{sid}/step", json={"frames": 2})
    assert r.status_code == 200, r.text
    assert r.json().get("failure") is None, r.text
    return client.get(f"/v1/sessions/{sid}").json()["frame"]


@pytest.mark.parametrize(
    ("route", "body", "field"),
    [
        ("bodies", {**BOX, "density": 1e-45}, "density"),
        ("bodies", {**BOX, "density": 1e25}, "density"),
        ("bodies", {**BOX, "velocity": [1e6, 0.0]}, "velocity"),
        ("bodies", {**BOX, "angular_velocity": 1e6}, "angular_velocity"),
        ("blocks", {"material": "jello", "nu": 0.49999999, "lo": [0.6, 0.6], "hi": [0.7, 0.7]}, "nu"),
        ("blocks", {"material": "rubber", "E": 1e12, "lo": [0.6, 0.6], "hi": [0.7, 0.7]}, "E"),
        ("blocks", {"material": "honey", "viscosity": 1e30, "lo": [0.6, 0.6], "hi": [0.7, 0.7]}, "viscosity"),
        ("blocks", {"material": "jello", "density": 1e-30, "lo": [0.6, 0.6], "hi": [0.7, 0.7]}, "density"),
    ],
)
def test_over_http_a_request_a_frame_cannot_simulate_is_a_422_naming_its_key_and_the_session_steps_on(client, route, body, field):
    sid = _session(client)
    before = client.get(f"/v1/sessions/{sid}/checkpoint").content
    r = client.post(f"/v1/sessions/{sid}/{route}", json=body)
    assert r.status_code == 422, r.text
    assert r.json()["detail"][0]["loc"] == ["body", field], r.text
    assert client.get(f"/v1/sessions/{sid}/checkpoint").content == before
    assert _frame_after_step(client, sid) == 2  # frames advance


def test_over_http_a_tampered_body_state_is_refused(client):
    from hybridmpm.service import checkpoint as ckpt
    from hybridmpm.service.config import ServiceConfig

    sid = _session(client)
    assert client.post(f"/v1/sessions/{sid}/bodies", json={**BOX, "center": [0.65, 0.65]}).status_code == 201
    _frame_after_step(client, sid)
    blob = client.get(f"/v1/sessions/{sid}/checkpoint").content
    state, meta = ckpt.loads(blob, ServiceConfig().max_checkpoint_bytes)
    from hybridmpm.mpm.solver import MpmSolver, _body_state

    rows = [list(map(float, r)) for r in _body_state(state["solver"])]
    rows[0][7] = 2.0**100  # a speed no frame can simulate
    state["solver"] = MpmSolver.with_header(state["solver"], {"body_state": rows})
    r = client.put(f"/v1/sessions/{sid}/checkpoint", content=ckpt.dumps(state, meta))
    assert 400 <= r.status_code < 500 and "body state" in r.text, r.text
    assert client.get(f"/v1/sessions/{sid}/checkpoint").content == blob
    _frame_after_step(client, sid)
