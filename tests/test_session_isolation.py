"""Sessions of the same scene and seed are independent: three of them, stepped
through the HTTP service in interleaved requests of different lengths, each
match the same scene and seed run alone through :mod:`hybridmpm.sim`, bit for
bit (the hybrid's network steps included). Sessions that shared a simulator,
its network state or a position buffer would each see the others' steps."""

from __future__ import annotations

import numpy as np
import pytest

# the service is in the test extras; in CI a skip here is a failure (conftest.py)
pytest.importorskip("fastapi", reason="the service extra (fastapi) is not installed")
pytest.importorskip("httpx", reason="the service extra (httpx) is not installed")

from fastapi.testclient import TestClient  # noqa: E402

from hybridmpm.service import ServiceConfig, create_app  # noqa: E402
from hybridmpm.sim import make_simulator, rollout  # noqa: E402

OCTET = {"Accept": "application/octet-stream"}
SCENE, SEED = "dam_break2d", 7
# (session, frames) in the order the requests are made: every session ends at 48 frames
# (12 hybrid steps of r_t = 4: the 5-step MPM warm-up, then network steps), each by its own chunking
SCHEDULE = [(0, 4), (1, 24), (2, 12), (0, 8), (2, 12), (1, 4), (0, 12), (2, 12), (1, 20), (0, 24), (2, 12)]


@pytest.mark.parametrize("solver", ["mpm", "hybrid"])
def test_sessions_of_one_scene_and_seed_stepped_in_different_orders_match_a_lone_run(solver):
    frames_total = 48
    assert all(sum(f for s, f in SCHEDULE if s == k) == frames_total for k in range(3))
    with TestClient(create_app(ServiceConfig(max_sessions=8))) as client:
        ids = []
        for _ in range(3):
            r = client.post("/v1/sessions", json={"scene": SCENE, "seed": SEED, "solver": solver, "r_c": 0.8})
            assert r.status_code == 201, r.text
            ids.append(r.json()["id"])
        got: list[list[np.ndarray]] = [[], [], []]
        solvers: list[list[str]] = [[], [], []]
        for k, frames in SCHEDULE:
            r = client.post(f"/v1/sessions/{ids[k]}/step", json={"frames": frames}, headers=OCTET)
            assert r.status_code == 200, r.text
            shape = tuple(int(x) for x in r.headers["x-shape"].split(","))
            got[k].append(np.frombuffer(r.content, "<f4").reshape(shape))
            solvers[k] += r.headers["x-solvers"].split(",")
    lone = make_simulator(SCENE, solver, r_c=0.8, seed=SEED, threads=1, nn_threads=1)
    ref = rollout(lone, frames_total)
    if solver == "hybrid":  # the comparison covers network steps, not only the warm-up
        assert "neural" in set(ref.solver[1:])
    for k in range(3):
        pos = np.concatenate(got[k])
        assert pos.shape == ref.positions[1:].shape, (k, pos.shape)
        assert np.array_equal(pos, ref.positions[1:]), f"session {k} differs from the lone run"
        assert solvers[k] == [str(s) for s in ref.solver[1:]]
