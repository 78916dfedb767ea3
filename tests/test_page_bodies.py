"""Rigid bodies on the page (``static/bodies.js``, the palette's crate and
ball: docs/bodies.md "The page"), in headless Chromium (Debian's package
through Playwright's executable path, as ``tests/test_page_palette.py``
drives it). On the default 3D scene (``paddle3d`` on MPM) the server steps
400 frames (the surge has spread into a layer), then a crate armed and a
click on the water drops one centred where the pointer's ray meets the drop
height's plane, at rest; the server steps exactly 200 more frames (raw
float32, the page a viewer of them) and the crate floats: its centre where
Archimedes puts it for 500 kg/m³ against the water's level measured beside
it (within 1.5 cells + 2 % of its height), off the floor, at rest, and the
page drew it at the server's pose of that frame (the binary frame's, float32
for float32). A drag throws a ball along the drag. Capsules and convex
meshes (synthetic descriptions) and the 2D ``crates2d`` bodies are drawn
where they are, in wood brown."""

from __future__ import annotations

import json
import time
from io import BytesIO

import numpy as np
import pytest
from conftest import needs_chromium, watched_page

pytest.importorskip("fastapi")
httpx = pytest.importorskip("httpx")
pytest.importorskip("playwright.sync_api")
Image = pytest.importorskip("PIL.Image")

from hybridmpm.conventions import GNS_WATER  # noqa: E402
from hybridmpm.service.testing import LiveServer  # noqa: E402

pytestmark = [needs_chromium, pytest.mark.alone]
SIDE = 0.09  # the crate's edge [m]: 3 cells of paddle3d's 34³ grid, its draft (half of it) in the 8 cm the surge leaves
PRE = 400  # frames stepped before the drop: the surge has spread into a layer over the floor
AFTER = 200  # frames stepped after it, when the crate's pose is read
STEP_FRAMES = 20  # frames a step request asks for
RHO_CRATE, RHO_WATER = 500.0, 1000.0
WOOD = np.array([176, 122, 60])  # BODY_FILL, #b07a3c


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    with LiveServer(max_sessions=8, log=tmp_path_factory.mktemp("bodies") / "server.log") as s:
        yield s


def _open(browser, url: str, errors: list[str]):
    page = watched_page(browser, errors)
    page.goto(url)
    page.wait_for_function("window.__hmpm.framesRendered >= 1 && window.__hmpm.session", timeout=60_000)
    return page


def _step(c, sid: str, frames: int, shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray | None]:
    """Step ``frames`` frames in requests of STEP_FRAMES: the last frame's positions [N, D] and body poses [B, D + D²] (or None)."""
    poses = None
    while frames:
        k = min(STEP_FRAMES, frames)
        r = c.post(f"/v1/sessions/{sid}/step?bodies=1", json={"frames": k}, headers={"Accept": "application/octet-stream"})
        assert r.status_code == 200, r.text
        pos = np.frombuffer(r.content, "<f4", k * shape[0] * shape[1]).reshape(k, *shape)[-1].astype(np.float64)
        if "x-bodies" in r.headers:
            b = [int(x) for x in r.headers["x-bodies"].split(",")]
            poses = np.frombuffer(r.content, "<f4", offset=4 * k * shape[0] * shape[1]).reshape(b)[-1]
        frames -= k
    return pos, poses


def _level(water: np.ndarray, x: float, z: float, half: float, dx: float, inner: float, outer: float) -> float:
    """The water's level [m] beside a square footprint of half side ``half`` centred at (x, z): the median over
    the grid's columns (dx × dx in x–z) whose centre lies ``inner`` to ``outer`` cells outside it of their highest particle."""
    ring = np.maximum(np.abs(water[:, 0] - x), np.abs(water[:, 2] - z)) - half
    q = water[(ring > inner * dx) & (ring < outer * dx)]
    cols = np.floor(q[:, 0] / dx).astype(int) * 4096 + np.floor(q[:, 2] / dx).astype(int)
    tops = [q[cols == k, 1].max() for k in np.unique(cols)]
    assert len(tops) >= 20, f"only {len(tops)} columns of water beside ({x}, {z})"
    return float(np.median(tops))


def _pixel(page, world) -> np.ndarray:
    """The stage's colour at world point ``world`` (RGB, a screenshot's pixel)."""
    css = page.evaluate(f"window.__hmpm.toCss({list(map(float, world))})")
    box = page.locator("#ink").bounding_box()
    img = Image.open(BytesIO(page.screenshot(clip={"x": box["x"] + css[0] - 1, "y": box["y"] + css[1] - 1, "width": 3, "height": 3})))
    return np.asarray(img.convert("RGB"))[1, 1].astype(int)


def test_a_crate_dropped_on_the_water_floats_and_the_page_draws_it_at_the_servers_pose(server, browser):
    errors: list[str] = []
    page = _open(browser, server.url + "/?solver=mpm&autoplay=0", errors)  # its camera still: the click lands where the test projects
    session = page.evaluate("window.__hmpm.session")
    assert session["scene"] == "paddle3d" and session["dim"] == 3 and session["bodies"] == []
    sid, n, dx = session["id"], session["num_particles"], 1.0 / session["n_grid"]
    types = np.array(session["particle_type"])
    floor = session["wall_thickness"]  # the walls' inner faces: the bodies' floor (docs/bodies.md "Where a body may be")
    with httpx.Client(base_url=server.url, timeout=120) as c:
        pos, poses = _step(c, sid, PRE, (n, 3))
        assert poses is None
        page.wait_for_function(f"window.__hmpm.lastFrame === {PRE}", timeout=60_000)
        # the drop: centred on the water's surface at (0.75, 0.5) in x–z, downstream of the paddle
        x, z = 0.75, 0.5
        level0 = _level(pos[types == GNS_WATER], x, z, SIDE / 2, dx, -10, 1)
        centre = [x, level0, z]
        page.fill("#drop-height", f"{level0:.4f}")
        page.fill("#drop-side", str(SIDE))
        page.click("#palette button[data-body=crate]")
        css = page.evaluate(f"window.__hmpm.toCss({centre})")
        box = page.locator("#ink").bounding_box()
        page.mouse.click(box["x"] + css[0], box["y"] + css[1])
        page.wait_for_function("window.__hmpm.bodyDrops.length > 0", timeout=30_000)
        drop = page.evaluate("window.__hmpm.bodyDrops.at(-1)")
        assert "error" not in drop, drop
        body = drop["body"]
        assert drop["frame"] == PRE and drop["index"] == 0 and drop["num_bodies"] == 1
        assert body["shape"] == "box" and body["density"] == RHO_CRATE and body["half_extents"] == [SIDE / 2] * 3 and body["velocity"] == [0, 0, 0]
        assert np.allclose(body["center"], centre, atol=0.005), (body["center"], centre)  # where the pointer was
        assert np.allclose(body["center"][1], float(f"{level0:.4f}"), atol=1e-9)  # on the drop height's plane
        info = c.get(f"/v1/sessions/{sid}").json()
        assert np.allclose(info["bodies"][0]["center"], body["center"], atol=1e-6)
        # drawn at once, paused (the frame shown has no bodies yet: the description's pose)
        page.wait_for_function("window.__hmpm.bodiesDrawn.length === 1", timeout=30_000)
        drawn = page.evaluate("window.__hmpm.bodiesDrawn[0]")
        assert drawn["shape"] == "box" and np.allclose(drawn["center"], body["center"], atol=1e-6)

        pos, poses = _step(c, sid, AFTER, (n, 3))
        info = c.get(f"/v1/sessions/{sid}").json()
    assert info["frame"] == PRE + AFTER and poses is not None and poses.shape == (1, 12)
    crate = info["bodies"][0]
    assert np.array_equal(np.float32(crate["center"]), poses[0, :3]) and np.array_equal(np.float32(crate["rotation"]).ravel(), poses[0, 3:])
    # it floats: Archimedes' draft (ρ_b / ρ_w of its height) below the level beside it, for the crate as it is turned (its
    # height along y: its box's extent, a tilt included)
    cx, cy, cz = crate["center"]
    height = float(np.sum(np.abs(np.asarray(crate["rotation"])[1])) * SIDE)
    level = _level(pos[types == GNS_WATER], cx, cz, height / 2, dx, 1, 4)
    want = level - RHO_CRATE / RHO_WATER * height + height / 2
    said = f"crate centre y {cy:.4f} m, level beside it {level:.4f} m, Archimedes {want:.4f} m ({(cy - want) / dx:+.2f} cells); floor {floor:.4f} m"
    print(said)
    assert abs(cy - want) <= 1.5 * dx + 0.02 * height, said
    assert cy - height / 2 > floor + 0.5 * dx, f"on the floor: {said}"
    assert np.linalg.norm(crate["velocity"]) < 0.5, f"not at rest: velocity {crate['velocity']} m/s; {said}"
    # the page drew it at the server's pose of that frame (the binary frame's float32 values)
    page.wait_for_function(
        f"window.__hmpm.lastFrame === {PRE + AFTER} && window.__hmpm.bodiesDrawn.length === 1 && window.__hmpm.bodiesDrawn[0].frame === {PRE + AFTER}",
        timeout=60_000,
    )
    drawn = page.evaluate("window.__hmpm.bodiesDrawn[0]")
    assert drawn["from"] == "frame" and np.array_equal(np.float32(drawn["center"]), poses[0, :3]), (drawn, poses)
    assert np.array_equal(np.float32(drawn["rotation"]).ravel(), poses[0, 3:])
    # seen: its top face, above the water, in the particles look (the fluid look's coarse splats may lap over a crate 4 cm proud)
    page.click("input[name=look][value=particles]")
    page.wait_for_function("window.__hmpm.look === 'particles'")
    time.sleep(0.5)  # a frame drawn in it
    colour = _pixel(page, crate["center"][:1] + [cy + height / 2 - 0.005] + crate["center"][2:])
    assert np.abs(colour - WOOD).max() < 90 and colour[0] > colour[1] > colour[2], colour
    assert page.evaluate("__hmpm.view.glError()") == 0
    assert page.evaluate("__hmpm.errors") == [] and errors == [], errors
    page.close()


def test_a_drag_throws_a_ball_along_the_drag(server, browser):
    errors: list[str] = []
    page = _open(browser, server.url + "/?solver=mpm&autoplay=0", errors)
    sid = page.evaluate("window.__hmpm.session.id")
    h = 0.6
    page.fill("#drop-height", str(h))
    page.fill("#drop-side", "0.1")
    page.click("#palette button[data-body=ball]")
    a, b = [0.55, h, 0.45], [0.8, h, 0.6]
    box = page.locator("#ink").bounding_box()
    pa, pb = (page.evaluate(f"window.__hmpm.toCss({p})") for p in (a, b))
    page.mouse.move(box["x"] + pa[0], box["y"] + pa[1])
    page.mouse.down()
    page.mouse.move(box["x"] + pb[0], box["y"] + pb[1], steps=12)
    page.mouse.up()
    page.wait_for_function("window.__hmpm.bodyDrops.length > 0", timeout=30_000)
    drop = page.evaluate("window.__hmpm.bodyDrops.at(-1)")
    assert "error" not in drop, drop
    body, d = drop["body"], np.subtract(b, a)
    v = np.asarray(body["velocity"])
    assert body["shape"] == "sphere" and body["radius"] == 0.05 and body["density"] == 700.0
    assert np.allclose(body["center"], a, atol=0.005), body  # thrown from where the press was
    assert v[1] == 0 and 0 < np.linalg.norm(v) <= 4.0 + 1e-9, v  # on the drop plane, at most THROW_MAX
    assert v @ d / (np.linalg.norm(v) * np.linalg.norm(d)) > 0.995, (v, d)  # along the drag
    with httpx.Client(base_url=server.url, timeout=60) as c:
        info = c.get(f"/v1/sessions/{sid}").json()
    assert np.allclose(info["bodies"][0]["velocity"], v, atol=1e-5)
    assert page.evaluate("__hmpm.errors") == [] and errors == [], errors
    # a refused one (too small for the grid: a radius under 1 cell) says why in the status line; the page goes on
    page.fill("#drop-side", "0.02")
    page.mouse.click(box["x"] + pa[0], box["y"] + pa[1])
    page.wait_for_function("window.__hmpm.bodyDrops.length > 1", timeout=30_000)
    refused = page.evaluate("window.__hmpm.bodyDrops.at(-1)")
    assert refused["error"].startswith("422") and "radius" in refused["error"], refused
    assert "the ball was refused: 422" in page.evaluate("__hmpm.status")
    assert page.evaluate("__hmpm.errors") == [] and [e for e in errors if "status of 422" not in e] == [], errors  # the browser logs the 422 itself
    page.close()


def test_capsules_meshes_and_2d_bodies_are_drawn_where_they_are(server, browser):
    errors: list[str] = []
    page = _open(browser, server.url + "/?solver=mpm&autoplay=0", errors)
    tetra = {
        "shape": "mesh",
        "vertices": [[0.08, -0.05, 0.0], [-0.08, -0.05, 0.06], [-0.08, -0.05, -0.06], [0.0, 0.08, 0.0]],
        "faces": [[0, 1, 2], [0, 1, 3], [1, 2, 3], [2, 0, 3]],
    }
    c, s = np.cos(0.5), np.sin(0.5)
    synthetic = [
        {"shape": "capsule", "radius": 0.04, "half_height": 0.06, "center": [0.3, 0.7, 0.5], "rotation": [[c, -s, 0], [s, c, 0], [0, 0, 1]]},
        {**tetra, "center": [0.7, 0.7, 0.5], "rotation": [[1, 0, 0], [0, 1, 0], [0, 0, 1]]},
        {"shape": "sphere", "radius": 0.05, "center": [0.5, 0.85, 0.5]},
        {"shape": "mesh", "vertices": [[0, 0, 0]], "faces": [[0, 1, 7]], "center": [0.5, 0.6, 0.5]},  # broken: nothing drawn, no error
    ]
    page.evaluate(f"window.__hmpm.showBodies({json.dumps(synthetic)})")
    page.wait_for_function("window.__hmpm.bodiesDrawn.length === 4", timeout=30_000)
    drawn = page.evaluate("window.__hmpm.bodiesDrawn")
    assert [d["shape"] for d in drawn] == ["capsule", "mesh", "sphere", "mesh"] and all(d["from"] == "description" for d in drawn)
    assert np.allclose(drawn[0]["rotation"], synthetic[0]["rotation"], atol=1e-12)
    for b in synthetic[:3]:
        colour = _pixel(page, b["center"])
        assert np.abs(colour - WOOD).max() < 90 and colour[0] > colour[1] > colour[2], (b["shape"], colour)
    # the capsule's end along its local y axis (turned 0.5 rad about z) is brown, the point as far off it along x is not
    tip = np.add(synthetic[0]["center"], 0.09 * np.array([-s, c, 0]))
    assert _pixel(page, tip)[0] > _pixel(page, tip)[2] and np.abs(_pixel(page, np.add(synthetic[0]["center"], [0.09 * c, 0.09 * s, 0])) - WOOD).max() > 60
    assert page.evaluate("__hmpm.view.glError()") == 0 and page.evaluate("__hmpm.errors") == [] and errors == [], errors
    page.close()
    # 2D: crates2d's four boxes, drawn at the description's pose before a frame carries them, then at the frames'
    page = _open(browser, server.url + "/?scene=crates2d&solver=mpm&autoplay=0", errors)
    page.wait_for_function("window.__hmpm.bodiesDrawn.length === 4", timeout=30_000)
    bodies = page.evaluate("window.__hmpm.session.bodies")
    for b in bodies:
        colour = _pixel(page, b["center"])
        assert np.abs(colour - WOOD).max() < 60, (b, colour)
    assert [d["from"] for d in page.evaluate("window.__hmpm.bodiesDrawn")] == ["frame"] * 4  # the stream's first frame carries them
    # a 2D capsule (a stadium), turned 30° by its angle as given: brown along its local y axis, not across it
    page.evaluate("window.__hmpm.showBodies([{shape: 'capsule', radius: 0.03, half_height: 0.05, center: [0.3, 0.8], angle_deg: 30}])")
    page.wait_for_function("window.__hmpm.bodiesDrawn.length === 1 && window.__hmpm.bodiesDrawn[0].shape === 'capsule'", timeout=30_000)
    a = np.radians(30.0)
    along, across = np.array([-np.sin(a), np.cos(a)]), np.array([np.cos(a), np.sin(a)])
    for p, brown in ((np.array([0.3, 0.8]), True), (np.array([0.3, 0.8]) + 0.07 * along, True), (np.array([0.3, 0.8]) + 0.07 * across, False)):
        colour = _pixel(page, p)
        assert (np.abs(colour - WOOD).max() < 30) == brown, (p, colour)
    assert page.evaluate("__hmpm.view.glError()") == 0 and page.evaluate("__hmpm.errors") == [] and errors == [], errors
    page.close()
