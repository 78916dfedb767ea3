"""A mesh body's inline ``vertices`` over HTTP and the JSON body cap agree: the most points
``BodyAdd`` takes (:data:`~hybridmpm.service.schemas.MAX_BODY_VERTICES`) fit in the default
``max_json_bytes`` at full float64 precision, so one point too many is a 422 naming
``vertices`` (not a 413), and only a body over the byte cap is a 413."""

from __future__ import annotations

import json

import numpy as np
import pytest

pytest.importorskip("fastapi")
pytest.importorskip("httpx")

from fastapi.testclient import TestClient  # noqa: E402

from hybridmpm.service import ServiceConfig, create_app  # noqa: E402
from hybridmpm.service.schemas import MAX_BODY_VERTICES, MAX_NUMBER_CHARS, VERTEX_JSON_BYTES  # noqa: E402

#: Where the hull goes in dam_break3d: in the air above and beside the water column (its grid 64³).
CENTER = [0.7, 0.7, 0.5]
#: The sphere its points lie on [m]: ~6 cells across, well over the 2 cells a hull must be thick.
RADIUS = 0.05


def _sphere(n: int, seed: int = 0) -> list[list[float]]:
    """``n`` random points on the sphere of :data:`RADIUS` about the origin (the body's frame)."""
    p = np.random.default_rng(seed).normal(size=(n, 3))
    return (RADIUS * p / np.linalg.norm(p, axis=1, keepdims=True)).tolist()


def _number(x: float) -> str:
    """``x`` at full precision, written as long as a float64's JSON can be (:data:`MAX_NUMBER_CHARS`):
    its shortest round-trip form with zeros after the last digit (the same number)."""
    s = repr(x)
    mantissa, e, exponent = s.partition("e")  # below 1e-4: 1.2345678901234567e-05
    mantissa += "" if "." in mantissa else "."
    assert len(mantissa + e + exponent) <= MAX_NUMBER_CHARS
    return mantissa + "0" * (MAX_NUMBER_CHARS - len(mantissa + e + exponent)) + e + exponent


def _mesh_body(n: int, indent: int | None = None) -> bytes:
    """The JSON text of a mesh body of ``n`` points, every coordinate :data:`MAX_NUMBER_CHARS` long:
    ``json.dumps``' separators (``indent`` None) or pretty-printed."""
    points = _sphere(n)
    marker = "@V@"
    text = json.dumps({"shape": "mesh", "center": CENTER, "vertices": marker, "density": 500.0}, indent=indent)
    if indent is None:
        vertices = "[" + ", ".join("[" + ", ".join(_number(c) for c in v) + "]" for v in points) + "]"
    else:
        pad = " " * indent
        rows = [f"{pad * 2}[\n" + ",\n".join(pad * 3 + _number(c) for c in v) + f"\n{pad * 2}]" for v in points]
        vertices = "[\n" + ",\n".join(rows) + f"\n{pad}]"
    body = text.replace(json.dumps(marker), vertices).encode()
    assert json.loads(body)["vertices"] == points  # the same numbers, all their digits
    return body


@pytest.fixture(scope="module")
def client():
    with TestClient(create_app(ServiceConfig(max_sessions=4, max_sessions_per_client=4, idle_ttl_s=600))) as c:
        yield c


def _post(client, sid: str, body: bytes):
    return client.post(f"/v1/sessions/{sid}/bodies", content=body, headers={"Content-Type": "application/json"})


def test_the_documented_vertex_cap_fits_the_json_cap_at_full_precision():
    assert MAX_BODY_VERTICES == 512  # the figure docs/bodies.md and docs/service.md state
    assert VERTEX_JSON_BYTES == 80 and len(repr(-2.2250738585072014e-308)) == MAX_NUMBER_CHARS
    assert MAX_BODY_VERTICES * VERTEX_JSON_BYTES <= ServiceConfig().max_json_bytes - 16 * 1024  # a margin for the other fields


def test_a_mesh_body_of_the_most_vertices_at_full_precision_is_taken_and_one_more_is_a_422(client):
    r = client.post("/v1/sessions", json={"scene": "dam_break3d", "solver": "mpm", "seed": 0})
    assert r.status_code == 201, r.text
    sid = r.json()["id"]
    cap = ServiceConfig().max_json_bytes
    for indent in (None, 2):  # json.dumps' separators, and pretty-printed
        body = _mesh_body(MAX_BODY_VERTICES, indent)
        assert len(body) <= cap
        r = _post(client, sid, body)
        assert r.status_code == 201, r.text
        assert r.json()["num_bodies"] == 1
        hull = client.get(f"/v1/sessions/{sid}").json()["bodies"][0]
        assert hull["shape"] == "mesh" and len(hull["vertices"]) > 100  # the hull of the points (most lie on it)
        assert client.delete(f"/v1/sessions/{sid}/bodies/0").status_code == 200
    # one point too many: refused by its count, naming the field, not by its size; the session unchanged
    body = _mesh_body(MAX_BODY_VERTICES + 1)
    assert len(body) <= cap
    r = _post(client, sid, body)
    assert r.status_code == 422, r.text
    assert r.json()["detail"][0]["loc"][:2] == ["body", "vertices"]
    assert client.get(f"/v1/sessions/{sid}").json()["bodies"] == []


def test_a_mesh_body_over_the_json_cap_is_a_413(client):
    r = client.post("/v1/sessions", json={"scene": "dam_break3d", "solver": "mpm", "seed": 0})
    sid = r.json()["id"]
    body = _mesh_body(4096)  # the old cap's worth: ~320 kB
    assert len(body) > ServiceConfig().max_json_bytes
    r = _post(client, sid, body)
    assert r.status_code == 413
    assert client.get(f"/v1/sessions/{sid}").json()["bodies"] == []
