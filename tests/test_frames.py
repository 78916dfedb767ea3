"""The stream's binary frame (``hybridmpm.service.frames``): a frame without
bodies is byte for byte the layout clients read before bodies existed; one
with bodies carries each body's centre and rotation after the positions and
reads back to the same float32 values; a short, forged or damaged frame is
refused with a ValueError saying what is wrong. Through the service (test
client): a session's stream frames carry its bodies' poses, equal to the
JSON step's, and ``POST .../step?bodies=1`` with ``Accept:
application/octet-stream`` appends them after the positions (``X-Bodies``),
while the answer without it stays the positions alone."""

from __future__ import annotations

import json
import struct

import numpy as np
import pytest

from hybridmpm.service.frames import FLAG_BODIES, HEADER, HEADER_SIZE, MAGIC, decode_frame, encode_frame, frame_message
from hybridmpm.sim import Frame


def _rotations(rng: np.random.Generator, b: int, dim: int) -> np.ndarray:
    q, _ = np.linalg.qr(rng.normal(size=(b, dim, dim)))
    return q.astype(np.float32)


def _example(dim: int = 3, n: int = 57, b: int = 3, seed: int = 0):
    rng = np.random.default_rng(seed)
    pos = rng.uniform(0, 1, (n, dim)).astype(np.float32)
    center = rng.uniform(0.1, 0.9, (b, dim)).astype(np.float32)
    return pos, center, _rotations(rng, b, dim)


@pytest.mark.parametrize("dim", [2, 3])
def test_a_frame_without_bodies_is_the_layout_before_bodies(dim):
    pos, _, _ = _example(dim)
    want = HEADER.pack(MAGIC, 1, dim, 2, 41, len(pos), 0.1025, 0, 1, 0, 7) + pos.astype("<f4").tobytes()
    assert encode_frame(pos, 41, 0.1025, "mpm", True, 7) == want
    empty = (np.zeros((0, dim)), np.zeros((0, dim, dim)))
    assert encode_frame(pos, 41, 0.1025, "mpm", True, 7, *empty) == want  # no bodies left: no block either
    assert frame_message(Frame(41, 41, 0.1025, pos, "mpm", controlled=True), 7) == want
    h, back = decode_frame(want)
    assert (h.dim, h.frame, h.n, h.time, h.solver, h.controlled, h.control_frame) == (dim, 41, len(pos), 0.1025, "mpm", True, 7)
    assert h.body_center is None and h.body_rotation is None and np.array_equal(back, pos)


@pytest.mark.parametrize("dim", [2, 3])
def test_bodies_follow_the_positions_and_read_back_exactly(dim):
    pos, center, rot = _example(dim)
    fr = Frame(12, 12, 0.03, pos, "neural", body_center=center.astype(np.float64), body_rotation=rot.astype(np.float64))
    data = frame_message(fr)
    b, per = len(center), dim + dim * dim
    assert len(data) == HEADER_SIZE + 4 * pos.size + 4 + 4 * b * per
    assert data[7] == FLAG_BODIES | 4 and data[: HEADER_SIZE + 4 * pos.size][8:] == encode_frame(pos, 12, 0.03, "neural")[8:]
    assert struct.unpack_from("<I", data, HEADER_SIZE + 4 * pos.size) == (b,)
    h, back = decode_frame(data)
    assert h.solver == "neural" and h.frame == 12 and np.array_equal(back, pos)
    assert h.body_center.dtype == np.float32 and np.array_equal(h.body_center, center)
    assert h.body_rotation.shape == (b, dim, dim) and np.array_equal(h.body_rotation, rot)  # row-major: R[i, j] at i·dim + j
    # float64 poses are written as float32 (what a viewer draws)
    c64 = center.astype(np.float64) + 1e-9
    h, _ = decode_frame(encode_frame(pos, 12, 0.03, "mpm", body_center=c64, body_rotation=rot))
    assert np.array_equal(h.body_center, c64.astype(np.float32))


def test_body_arrays_of_the_wrong_shape_are_refused_by_name():
    pos, center, rot = _example(3)
    with pytest.raises(ValueError, match="body_center"):
        encode_frame(pos, 0, 0.0, "mpm", body_center=center[:, :2], body_rotation=rot)
    with pytest.raises(ValueError, match="body_rotation"):
        encode_frame(pos, 0, 0.0, "mpm", body_center=center, body_rotation=rot[:2])


def _hostile() -> list[tuple[str, bytes, str]]:
    pos, center, rot = _example(3, n=5, b=2)
    plain, full = encode_frame(pos, 3, 0.0, "mpm"), encode_frame(pos, 3, 0.0, "mpm", body_center=center, body_rotation=rot)
    end = HEADER_SIZE + 4 * pos.size

    def patch(data: bytes, offset: int, fmt: str, value: int) -> bytes:
        b = bytearray(data)
        struct.pack_into(fmt, b, offset, value)
        return bytes(b)

    return [
        ("empty", b"", "shorter than its 32-byte header"),
        ("header cut", plain[:31], "shorter than its 32-byte header"),
        ("magic", b"XXXX" + plain[4:], "bad magic"),
        ("version", patch(plain, 4, "<H", 2), "bad magic or version"),
        ("dim 0", patch(plain, 6, "<B", 0), "dim 0"),
        ("dim 7", patch(plain, 6, "<B", 7), "dim 7"),
        ("unknown flag", patch(plain, 7, "<B", 0x40), "unknown flag bits"),
        ("quantised flag", patch(plain, 7, "<B", 1), "unknown flag bits"),
        ("solver code", patch(plain, 24, "<B", 9), "solver code 9"),
        ("positions cut", plain[:-4], "5 particles need 60 bytes"),
        ("n forged huge", patch(plain, 12, "<I", 0xFFFFFFFF), "particles need"),
        ("trailing bytes", plain + b"\0\0\0\0", "4 bytes after the positions"),
        ("bodies flag, no count", patch(plain, 7, "<B", FLAG_BODIES), "body count is missing"),
        ("bodies cut", full[:-1], "2 bodies need 96 bytes"),
        ("bodies count forged", patch(full, end, "<I", 0xFFFFFFFF), "bodies need"),
        ("zero bodies", patch(full, end, "<I", 0)[: end + 4], "0 bodies need"),
        ("bodies and more", full + b"\0" * 4, "2 bodies need 96 bytes"),
    ]


@pytest.mark.parametrize(("data", "message"), [h[1:] for h in _hostile()], ids=[h[0] for h in _hostile()])
def test_a_damaged_frame_is_refused_saying_why(data, message):
    with pytest.raises(ValueError, match=message):
        decode_frame(data)


def test_what_is_not_bytes_is_a_type_error():
    with pytest.raises(TypeError, match="expected bytes, got str"):
        decode_frame("HMPF")  # type: ignore[arg-type]


# ---------------------------------------------------------------- through the service
pytest.importorskip("fastapi")
pytest.importorskip("httpx")

from fastapi.testclient import TestClient  # noqa: E402

from hybridmpm.service import ServiceConfig, create_app  # noqa: E402

BOX = {"shape": "box", "center": [0.65, 0.65], "half_extents": [0.04, 0.03], "angle_deg": 20.0, "density": 500.0}
BALL = {"shape": "circle", "center": [0.4, 0.8], "radius": 0.03, "mass": 1.5}
OCTET = {"Accept": "application/octet-stream"}


@pytest.fixture(scope="module")
def client():
    with TestClient(create_app(ServiceConfig(max_sessions=10, max_sessions_per_client=10, idle_ttl_s=600))) as c:
        yield c


def _binary(ws) -> bytes:
    while True:
        m = ws.receive()
        if m.get("bytes") is not None:
            return m["bytes"]


def test_the_stream_and_the_binary_step_carry_the_bodies_poses(client):
    sid = client.post("/v1/sessions", json={"scene": "dam_break2d", "solver": "mpm", "seed": 0}).json()["id"]
    with client.websocket_connect(f"/v1/sessions/{sid}/stream") as ws:
        assert json.loads(ws.receive_text())["type"] == "meta"
        h, _ = decode_frame(_binary(ws))
        assert h.body_center is None  # no bodies: the frame as before
        for body in (BOX, BALL):
            assert client.post(f"/v1/sessions/{sid}/bodies", json=body).status_code == 201
        frames = client.post(f"/v1/sessions/{sid}/step", json={"frames": 3}).json()["frames"]
        got = [decode_frame(_binary(ws))]
        while got[-1][0].frame < frames[-1]["frame"]:  # a viewer may be handed the latest frame only
            got.append(decode_frame(_binary(ws)))
    by_frame = {f["frame"]: f for f in frames}
    for h, pos in got:
        f = by_frame[h.frame]
        assert np.array_equal(pos, np.asarray(f["positions"], np.float32))
        assert np.array_equal(h.body_center, np.asarray([b["center"] for b in f["bodies"]], np.float32))
        assert np.array_equal(h.body_rotation, np.asarray([b["rotation"] for b in f["bodies"]], np.float32))
    a = np.radians(20.0)  # the box's rotation as given: its columns its axes, row-major on the wire
    assert np.allclose(got[0][0].body_rotation[0], [[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]], atol=1e-5)
    assert np.allclose(got[0][0].body_rotation[1], np.eye(2), atol=1e-6)
    # the binary step: the positions alone by default (the layout X-Shape gives), the poses after them on request
    r = client.post(f"/v1/sessions/{sid}/step", json={"frames": 2}, headers=OCTET)
    shape = tuple(int(x) for x in r.headers["x-shape"].split(","))
    assert "x-bodies" not in r.headers and len(r.content) == 4 * int(np.prod(shape))
    r = client.post(f"/v1/sessions/{sid}/step?bodies=1", json={"frames": 2}, headers=OCTET)
    shape, bshape = (tuple(int(x) for x in r.headers[k].split(",")) for k in ("x-shape", "x-bodies"))
    assert shape[0] == 2 and bshape == (2, 2, 6) and len(r.content) == 4 * (int(np.prod(shape)) + int(np.prod(bshape)))
    pos = np.frombuffer(r.content, "<f4", int(np.prod(shape))).reshape(shape)
    poses = np.frombuffer(r.content, "<f4", offset=4 * pos.size).reshape(bshape)
    now = client.get(f"/v1/sessions/{sid}").json()
    assert np.array_equal(poses[-1, :, :2], np.asarray([b["center"] for b in now["bodies"]], np.float32))
    assert np.array_equal(poses[-1, :, 2:].reshape(2, 2, 2), np.asarray([b["rotation"] for b in now["bodies"]], np.float32))
    assert np.isfinite(pos).all() and now["frame"] == frames[-1]["frame"] + 4
    r = client.post(f"/v1/sessions/{sid}/step?bodies=maybe", json={"frames": 1}, headers=OCTET)
    assert r.status_code == 422 and r.json()["detail"][0]["loc"] == ["query", "bodies"], r.text
    # without bodies, ?bodies=1 changes nothing
    for _ in range(2):
        assert client.delete(f"/v1/sessions/{sid}/bodies/0").status_code == 200
    r = client.post(f"/v1/sessions/{sid}/step?bodies=1", json={"frames": 1}, headers=OCTET)
    assert "x-bodies" not in r.headers and len(r.content) == 4 * now["num_particles"] * 2
