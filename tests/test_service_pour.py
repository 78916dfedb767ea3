"""POST /v1/sessions/{id}/blocks: a block poured between frames (test client).
The added particles are the block's lattice in its material and parameter
set, viewers are told the new count and types, every refusal is a 422 naming
the field and leaves the session bit for bit as it was (its checkpoint bytes)."""

from __future__ import annotations

import json

import numpy as np
import pytest

pytest.importorskip("fastapi")
pytest.importorskip("httpx")

from fastapi.testclient import TestClient  # noqa: E402

from hybridmpm.conventions import GNS_ELASTIC, GNS_WATER  # noqa: E402
from hybridmpm.scenes import lattice  # noqa: E402
from hybridmpm.service import ServiceConfig, create_app, decode_frame  # noqa: E402
from hybridmpm.service.testing import get_checkpoint, new_session  # noqa: E402
from hybridmpm.sim import pour as pour_module  # noqa: E402

JELLY = {"material": "jello", "lo": [0.6, 0.6], "hi": [0.7, 0.7]}


@pytest.fixture(scope="module")
def client():
    with TestClient(create_app(ServiceConfig(max_sessions=50, max_sessions_per_client=50, idle_ttl_s=600))) as c:
        yield c


def test_a_poured_jelly_joins_the_run_and_viewers_get_its_particles(client):
    s = new_session(client)
    sid, n0 = s["id"], s["num_particles"]
    with client.websocket_connect(f"/v1/sessions/{sid}/stream") as ws:
        assert json.loads(ws.receive_text())["type"] == "meta"
        r = client.post(f"/v1/sessions/{sid}/blocks", json=JELLY)
        assert r.status_code == 201, r.text
        out = r.json()
        # the block's lattice: 0.1 m / (dx/2 = 1/256 m) = 25.6 -> 26 particles a side
        assert out["added"] == 26 * 26 and out["num_particles"] == n0 + 26 * 26
        event, header_n = None, None
        while event is None or header_n != out["num_particles"]:
            m = ws.receive()
            if m.get("text") and json.loads(m["text"]).get("type") == "particles":
                event = json.loads(m["text"])
            elif m.get("bytes"):
                header_n = decode_frame(m["bytes"])[0].n
        assert event["num_particles"] == out["num_particles"] and event["added"] == out["added"]
        assert event["particle_type"].count(GNS_ELASTIC) == out["added"] and event["particle_type"].count(GNS_WATER) == n0
    info = client.get(f"/v1/sessions/{sid}").json()
    assert info["num_particles"] == out["num_particles"] and len(info["particle_type"]) == out["num_particles"]
    # it runs: a free-falling jelly keeps its shape (extents within 2 %) and falls g t^2 / 2
    r = client.post(f"/v1/sessions/{sid}/step", json={"frames": 40})
    assert r.status_code == 200, r.text
    pos = np.asarray(r.json()["frames"][-1]["positions"])
    jelly = pos[np.array(info["particle_type"]) == GNS_ELASTIC]
    ext = jelly.max(0) - jelly.min(0)
    assert np.all(np.abs(ext / (25 / 256) - 1) < 0.02), ext
    t = 40 * 0.0025
    y0 = lattice(np.array(JELLY["lo"]), np.array(JELLY["hi"]), 1 / 256)[:, 1].mean()
    assert jelly[:, 1].mean() == pytest.approx(y0 - 9.8 * t * t / 2, abs=1e-3)
    # a reset (the stream's message) brings the scene's own particles back, and tells the viewers
    with client.websocket_connect(f"/v1/sessions/{sid}/stream") as ws:
        assert json.loads(ws.receive_text())["num_particles"] == out["num_particles"]
        ws.send_text(json.dumps({"type": "reset"}))
        seen: dict[str, dict] = {}
        while "reset" not in seen:
            m = ws.receive()
            if m.get("text"):
                msg = json.loads(m["text"])
                seen[msg["type"]] = msg
    assert seen["particles"]["num_particles"] == n0
    assert client.get(f"/v1/sessions/{sid}").json()["num_particles"] == n0


@pytest.mark.parametrize(
    ("change", "field"),
    [
        ({"material": "lava"}, "material"),
        ({"E": 0.0}, "E"),
        ({"E": -5.0}, "E"),
        ({"nu": 0.5}, "nu"),
        ({"nu": -0.1}, "nu"),
        ({"density": 0.0}, "density"),
        ({"material": "mud", "yield_stress": -1.0}, "yield_stress"),
        ({"material": "mud", "viscosity": -1.0}, "viscosity"),
        ({"material": "snow", "theta_c": 0.0}, "theta_c"),
        ({"material": "snow", "theta_s": 1.0}, "theta_s"),
        ({"material": "water", "E": 1e5}, "E"),  # not a parameter of water
        ({"E": "stiff"}, "E"),
        ({"lo": [0.0, 0.6]}, "lo"),  # inside the wall band
        ({"hi": [0.7, 1.2]}, "hi"),
        ({"hi": [0.5, 0.7]}, "hi"),  # hi below lo
        ({"lo": [0.05, 0.05], "hi": [0.15, 0.15]}, "lo"),  # in the water column
        ({"lo": [0.1, 0.3], "hi": [0.9, 0.9]}, "hi"),  # more than one pour may add
        ({"lo": [0.6, 0.6, 0.6], "hi": [0.7, 0.7, 0.7]}, "lo"),  # 3 numbers in 2D
        ({"velocity": [1e9, 0.0]}, "velocity"),
    ],
)
def test_refusals_name_the_field_and_change_nothing(client, change, field):
    sid = new_session(client)["id"]
    before = get_checkpoint(client, sid)
    assert get_checkpoint(client, sid) == before  # the bytes are the state's alone
    r = client.post(f"/v1/sessions/{sid}/blocks", json={**JELLY, **change})
    assert r.status_code == 422, r.text
    assert r.json()["detail"][0]["loc"][-1] == field, r.text
    assert get_checkpoint(client, sid) == before


def test_nan_density_and_the_budget_are_refused(client, monkeypatch):
    sid = new_session(client)["id"]
    before = get_checkpoint(client, sid)
    body = json.dumps(JELLY)[:-1] + ', "density": NaN}'
    r = client.post(f"/v1/sessions/{sid}/blocks", content=body, headers={"Content-Type": "application/json"})
    assert r.status_code == 422 and r.json()["detail"][0]["loc"][-1] == "density", r.text
    monkeypatch.setattr(pour_module, "MAX_POURED_TOTAL", 5000)  # the session holds 4608
    r = client.post(f"/v1/sessions/{sid}/blocks", json=JELLY)
    assert r.status_code == 422 and r.json()["detail"][0]["loc"][-1] == "hi" and "5000" in r.text, r.text
    assert get_checkpoint(client, sid) == before


def test_only_mpm_sessions_take_a_pour(client):
    sid = new_session(client, scene="water2d", solver="neural")["id"]
    assert client.post(f"/v1/sessions/{sid}/blocks", json={**JELLY, "material": "water"}).status_code == 409


def test_a_pour_is_charged_to_the_memory_budget_until_its_session_goes(client, monkeypatch):
    from hybridmpm.scenes.core import BYTES_PER_PARTICLE
    from hybridmpm.service.sessions import SESSION_STATE_COPIES

    base = client.get("/healthz").json()["memory_used"]
    sid = new_session(client)["id"]
    held = client.get("/healthz").json()["memory_used"]
    r = client.post(f"/v1/sessions/{sid}/blocks", json=JELLY)
    assert r.status_code == 201, r.text
    used = client.get("/healthz").json()["memory_used"]
    assert used - held >= SESSION_STATE_COPIES * BYTES_PER_PARTICLE * r.json()["added"], (base, held, used)  # and its new frames
    # a pour the budget cannot hold at its largest is refused (503, retry later) and changes nothing
    before = get_checkpoint(client, sid)
    monkeypatch.setattr(pour_module, "MAX_POUR_PARTICLES", 1 << 40)
    r = client.post(f"/v1/sessions/{sid}/blocks", json={**JELLY, "lo": [0.75, 0.6], "hi": [0.85, 0.7]})
    assert r.status_code == 503 and r.headers["retry-after"], r.text
    assert get_checkpoint(client, sid) == before and client.get("/healthz").json()["memory_used"] == used
    assert client.delete(f"/v1/sessions/{sid}").status_code == 204
    assert client.get("/healthz").json()["memory_used"] == base


def test_parameters_in_params_pour_as_the_flat_keys_do_and_a_key_the_model_lacks_is_named(client):
    """``params`` (the schema's keys of the chosen model) and the flat keys pour the same block; a key the
    model lacks, one given both ways, or a place key in ``params`` is a 422 naming it under ``params``."""
    flat, nested = new_session(client)["id"], new_session(client)["id"]
    r1 = client.post(f"/v1/sessions/{flat}/blocks", json={**JELLY, "E": 5e4, "nu": 0.4})
    r2 = client.post(f"/v1/sessions/{nested}/blocks", json={**JELLY, "params": {"E": 5e4, "nu": 0.4}})
    assert r1.status_code == r2.status_code == 201, (r1.text, r2.text)
    assert r1.json() == r2.json()
    assert get_checkpoint(client, flat) == get_checkpoint(client, nested)
    sid = new_session(client)["id"]
    before = get_checkpoint(client, sid)
    for params, extra, key, says in [
        ({"theta_c": 0.1}, {}, "theta_c", "not a parameter of elastic"),  # snow's, not jello's (elastic)
        ({"nu": 0.49999999}, {}, "nu", "got 0.49999999"),  # 0.5 in float32
        ({"E": -1.0}, {}, "E", "got -1.0"),
        ({"model": "stiff"}, {}, "model", "'stiff'"),
        ({"E": 5e4}, {"E": 6e4}, "E", "given twice"),
        ({"velocity": 1.0}, {}, "velocity", "not a material parameter"),
    ]:
        r = client.post(f"/v1/sessions/{sid}/blocks", json={**JELLY, **extra, "params": params})
        assert r.status_code == 422, r.text
        assert r.json()["detail"][0]["loc"] == ["body", "params", key], r.text
        assert says in r.json()["detail"][0]["msg"], r.text
    assert get_checkpoint(client, sid) == before


def test_the_pour_bodys_flat_keys_are_the_schemas():
    from hybridmpm.mpm.schema import SCHEMA
    from hybridmpm.service.schemas import BlockPour

    keys = {p.key for params in SCHEMA.values() for p in params}
    assert set(BlockPour.model_fields) == keys | {"material", "lo", "hi", "velocity", "params"}
    nu = BlockPour.model_fields["nu"].description
    assert "in (-1, 0.5)" in nu and "in [0, 0.5)" in nu, nu  # sand's range and the solids'


def test_get_materials_gives_the_one_schema_and_the_presets_a_pour_takes(client):
    """``GET /v1/materials``: each model's rows are :data:`~hybridmpm.mpm.schema.SCHEMA`'s, the presets
    :data:`~hybridmpm.materials.PRESETS`; a pour of each model's defaults as reported is accepted, and a
    pour at a bound the report calls exclusive (``nu`` = 0.5) is refused naming the key and the range."""
    from dataclasses import asdict

    from hybridmpm.materials import PRESET_SOURCES, PRESETS
    from hybridmpm.mpm.schema import SCHEMA

    r = client.get("/v1/materials")
    assert r.status_code == 200, r.text
    models, presets = r.json()["models"], r.json()["presets"]
    assert models == {m: [{**asdict(p), "choices": list(p.choices)} for p in params] for m, params in SCHEMA.items()}
    assert presets == {name: {"model": m.name, "params": asdict(m), "source": PRESET_SOURCES[name]} for name, m in PRESETS.items()}
    sid = new_session(client)["id"]
    for i, (model, rows) in enumerate(models.items()):
        block = {"material": model, "lo": [0.30 + 0.12 * i, 0.7], "hi": [0.36 + 0.12 * i, 0.76]}
        r = client.post(f"/v1/sessions/{sid}/blocks", json={**block, "params": {p["key"]: p["default"] for p in rows}})
        assert r.status_code == 201, (model, r.text)
    before, refused = get_checkpoint(client, sid), []
    for model, rows in models.items():
        for p in rows:
            for bound in ("lower", "upper"):
                if p[bound] is not None and p[f"{bound}_inclusive"] is False:
                    r = client.post(f"/v1/sessions/{sid}/blocks", json={**JELLY, "material": model, "params": {p["key"]: p[bound]}})
                    assert r.status_code == 422, r.text
                    assert r.json()["detail"][0]["loc"] == ["body", "params", p["key"]], r.text
                    assert p["range"] in r.json()["detail"][0]["msg"], r.text
                    refused.append((model, p["key"], p[bound]))
    assert {(m, 0.5) for m in models if m != "water"} <= {(m, x) for m, k, x in refused if k == "nu"}, refused
    assert get_checkpoint(client, sid) == before
