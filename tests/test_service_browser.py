"""End to end in headless Chromium (Debian's package, driven by Playwright
through its executable path; never a downloaded browser; WebGL2 through its
software GL): the page loads without console errors, frames render, a drawn
rightward arrow moves the fluid right on the server, an upward stroke moves it
up (the y flip); a 3D scene renders and turns with the camera, an arrow drawn
in 3D moves the fluid's centroid along it, the sketch and the plan's centroid
path stay on the canvas through the controlled horizon; the downloads (the
session's trajectory, PLY frames, the control's trajectory, a GIF) read back;
the Canvas2D fallback draws; the page on its default scene (``?solver=default``: the
scene's fixed configuration, not the page's default real-time session, whose grid may change while it plays) shows
the 3D dam break with its paddle as a body of water, holds the frame while paused, advances exactly T frames
over a T-frame control, and a rightward arrow moves the water's pixels right; the
drag tool drags an obstacle through the water, in 2D and in 3D. With ``HYBRIDMPM_PAGE_SCREENSHOTS=DIR`` the 2D and
3D pages with a sketch applied are saved as ``DIR/page_2d.png``, ``DIR/page_3d.png``,
``DIR/page_paddle3d.png``, and the 3D drag as ``DIR/page_paddle3d_drag.png``
(the docs' pictures: ``HYBRIDMPM_PAGE_SCREENSHOTS=docs/img``)."""

from __future__ import annotations

import io
import os
import time
import zipfile
from pathlib import Path

import numpy as np
import pytest
from conftest import needs_chromium, watched_page

pytest.importorskip("fastapi")
httpx = pytest.importorskip("httpx")
pytest.importorskip("playwright.sync_api")

from hybridmpm.service.testing import LiveServer, step_binary  # noqa: E402

SCREENSHOTS = os.environ.get("HYBRIDMPM_PAGE_SCREENSHOTS")
INK = np.array([209, 36, 90])  # the page's sketch colour
PLAN = np.array([11, 122, 75])  # the plan's centroid path
# alone: frame rates and real-time drags on Chromium's CPU renderer; scripts/test.sh runs these after the parallel phase
pytestmark = [needs_chromium, pytest.mark.alone]


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    with LiveServer(max_sessions=10, log=tmp_path_factory.mktemp("browser") / "server.log") as s:
        yield s


def drag(page, a, b, steps=20):
    """Mouse drag between domain points ``a`` → ``b`` (y up) on the sketch canvas."""
    box = page.locator("#ink").bounding_box()

    def px(p):
        return box["x"] + p[0] * box["width"], box["y"] + (1 - p[1]) * box["height"]

    page.mouse.move(*px(a))
    page.mouse.down()
    page.mouse.move(*px(b), steps=steps)
    page.mouse.up()


def control_displacement(server, page, timeout=30_000):
    before = page.evaluate("window.__hmpm.controls.length")
    page.click("#apply")
    page.wait_for_function(f"window.__hmpm.controls.length > {before}", timeout=timeout)
    c = page.evaluate("window.__hmpm.controls.at(-1)")
    assert "error" not in c, c
    with httpx.Client(base_url=server.url, timeout=30) as client:
        t = client.get(c["trajectory"])
    with np.load(io.BytesIO(t.content), allow_pickle=False) as z:
        pos, types = z["positions"], z["particle_type"]
    fluid = pos[:, types != 3]
    return fluid[-1].mean(0) - fluid[0].mean(0), page.evaluate("window.__hmpm.lastSketch")


def test_page_end_to_end(server, browser, tmp_path):
    errors: list[str] = []
    page = watched_page(browser, errors, dpr=2)
    page.goto(server.url + "/?scene=dam_break2d&solver=mpm&method=constant")
    page.wait_for_function("window.__hmpm.framesRendered >= 30", timeout=20_000)
    shot = tmp_path / "page.png"
    page.locator("#sim").screenshot(path=str(shot))
    from PIL import Image

    img = np.asarray(Image.open(shot).convert("L"), np.float64)
    assert img.std() > 5, "blank canvas"
    print(f"screenshot kept at {shot}")
    hook = page.evaluate("window.__hmpm")
    # the page draws the stream as it comes: every draw is timed, and no more frames are drawn than received
    # (latest wins). How fast it draws is a wall-clock figure of a shared machine: benchmarks/bench_page.py
    # measures its frames/s on software GL (docs/page.md), the suite does not assert it.
    assert len(hook["drawMs"]) >= 30 and all(ms >= 0 for ms in hook["drawMs"])
    assert hook["framesRendered"] <= hook["framesReceived"]
    print(f"median draw {np.median(hook['drawMs']):.1f} ms over {len(hook['drawMs'])} draws")
    assert hook["session"]["scene"] == "dam_break2d"

    # pause and reset: each sketch acts on the column at rest (the free dam break would reach the far wall)
    page.click("#play")
    page.click("#reset")
    page.wait_for_function("window.__hmpm.lastFrame === 0", timeout=10_000)
    # a rightward arrow: the fluid's centroid moves right on the server
    drag(page, (0.15, 0.55), (0.45, 0.55))
    d, sketch = control_displacement(server, page)
    pts = np.array(sketch["points"])
    assert np.abs(pts[0] - [0.15, 0.55]).max() < 0.02 and np.abs(pts[-1] - [0.45, 0.55]).max() < 0.02  # coordinates round-trip
    assert d[0] >= 0.5 * 0.3 and abs(d[1]) < d[0]

    # an upward stroke: upward motion (y flipped exactly once)
    page.click("#reset")
    page.wait_for_function("window.__hmpm.lastFrame === 0", timeout=10_000)
    drag(page, (0.5, 0.3), (0.5, 0.5))
    d, sketch = control_displacement(server, page)
    assert sketch["points"][-1][1] > sketch["points"][0][1]
    assert d[1] >= 0.5 * 0.2
    page.wait_for_function("window.__hmpm.framesRendered > 0", timeout=5_000)

    # a scene without a shipped model offers its default (plain MPM) and MPM: choosing it (solver hybrid) falls back to the default and streams
    page.select_option("#solver", "hybrid")
    page.select_option("#scene", "water_columns2d")
    page.wait_for_function("window.__hmpm.session && window.__hmpm.session.scene === 'water_columns2d'", timeout=20_000)
    assert page.eval_on_selector("#solver", "s => s.value") == "default"
    assert page.eval_on_selector("#solver", "s => [...s.options].filter(o => o.disabled).map(o => o.value).sort()") == ["hybrid", "neural"]
    assert page.evaluate("window.__hmpm.session.solver") == "default"
    page.select_option("#scene", "water2d")  # a scene with a model offers every solver again
    assert page.eval_on_selector("#solver", "s => [...s.options].filter(o => o.disabled).length") == 0
    assert errors == [], errors
    page.close()


# ---------------------------------------------------------------- helpers of the WebGL tests
def new_page(browser, query, server, dpr=1):
    errors: list[str] = []
    page = watched_page(browser, errors, dpr)
    page.goto(server.url + "/" + query)
    page.wait_for_function("window.__hmpm.framesRendered >= 1", timeout=30_000)
    return page, errors


def shot(page, selector="#stage"):
    from PIL import Image

    return np.asarray(Image.open(io.BytesIO(page.locator(selector).screenshot())).convert("RGB"), np.float64)


def redrawn(page, action):
    """Run ``action`` (JavaScript) and wait until the page has drawn again."""
    n = page.evaluate("window.__hmpm.framesRendered")
    page.evaluate(action)
    page.wait_for_function(f"window.__hmpm.framesRendered > {n}", timeout=10_000)


def stepped(page, server, frames):
    """The page's session (not playing: ``autoplay=0``) stepped ``frames`` frames over HTTP; the page shows the last one.
    The steps ask for binary answers: the JSON of 100 frames of the 3D scenes is ~160 MB, and building it took 7x the
    time of the steps themselves."""
    sid = page.evaluate("window.__hmpm.session.id")
    with httpx.Client(base_url=server.url, timeout=60) as c:
        for k in range(0, frames, 100):
            step_binary(c, sid, min(100, frames - k))
    page.wait_for_function(f"window.__hmpm.lastFrame === {frames}", timeout=10_000)
    page.wait_for_timeout(300)


def near(img, pts, color, tol=70.0, radius=2):
    """Share of the CSS points ``pts`` ([x, y] in the screenshot's pixels) with a pixel within ``radius`` of the colour ``color``."""
    hits = 0
    for x, y in pts:
        xi, yi = int(round(x)), int(round(y))
        patch = img[max(0, yi - radius) : yi + radius + 1, max(0, xi - radius) : xi + radius + 1]
        hits += bool(patch.size and (np.linalg.norm(patch - color, axis=-1) < tol).any())
    return hits / max(1, len(pts))


def along(poly, count=24, skip=0.08):
    """``count`` points spaced along the polyline ``poly`` (its first and last ``skip`` of length left out: the arrow's head)."""
    p = np.asarray(poly, np.float64)
    seg = np.linalg.norm(np.diff(p, axis=0), axis=1)
    s = np.concatenate([[0], np.cumsum(seg)])
    out = []
    for t in np.linspace(skip, 1 - skip, count) * s[-1]:
        i = min(len(seg) - 1, int(np.searchsorted(s, t, side="right")) - 1)
        u = (t - s[i]) / max(seg[i], 1e-9)
        out.append(p[i] + u * (p[i + 1] - p[i]))
    return out


def draw_stroke(page, a, b, steps=16):
    """A mouse stroke from CSS point ``a`` to ``b`` of the sketch canvas."""
    box = page.locator("#ink").bounding_box()
    page.mouse.move(box["x"] + a[0], box["y"] + a[1])
    page.mouse.down()
    page.mouse.move(box["x"] + b[0], box["y"] + b[1], steps=steps)
    page.mouse.up()


def keep_screenshot(page, name):
    if SCREENSHOTS:
        Path(SCREENSHOTS).mkdir(parents=True, exist_ok=True)
        page.locator("#stage").screenshot(path=str(Path(SCREENSHOTS) / name))


def download(page, selector, tmp_path):
    with page.expect_download(timeout=60_000) as d:
        page.click(selector)
    path = tmp_path / d.value.suggested_filename
    d.value.save_as(path)
    return path


def test_3d_page_renders_turns_follows_an_arrow_and_hands_out_its_trajectory(server, browser, tmp_path):
    from PIL import Image

    from hybridmpm.metrics import evaluate
    from hybridmpm.trajectory import Trajectory

    frames = 200
    page, errors = new_page(browser, f"?scene=water3d&seed=26&solver=mpm&method=pd&frames={frames}&autoplay=0&scale=1", server)
    assert page.evaluate("[window.__hmpm.renderer, window.__hmpm.look]") == ["webgl2", "fluid"]
    stepped(page, server, 40)

    # the scene renders: the particles change the picture (against the same view drawn without them)
    redrawn(page, "window.__hmpm.showParticles(false)")
    empty = shot(page, "#sim")
    redrawn(page, "window.__hmpm.showParticles(true)")
    full = shot(page, "#sim")
    assert (np.abs(full - empty).max(-1) > 30).mean() > 0.01, "the fluid is not drawn"
    again = shot(page, "#sim")
    # a camera drag (right button) turns the view: the picture changes, far beyond redrawing the same view
    yaw = page.evaluate("window.__hmpm.camera.yaw")
    box = page.locator("#ink").bounding_box()
    page.mouse.move(box["x"] + 300, box["y"] + 300)
    n = page.evaluate("window.__hmpm.framesRendered")
    page.mouse.down(button="right")
    page.mouse.move(box["x"] + 420, box["y"] + 330, steps=8)
    page.mouse.up(button="right")
    page.wait_for_function(f"window.__hmpm.framesRendered > {n}", timeout=10_000)  # drawn since the camera turned
    turned = shot(page, "#sim")
    assert page.evaluate("window.__hmpm.camera.yaw") != yaw
    assert np.abs(turned - full).mean() > 5 * np.abs(again - full).mean() + 1.0
    n = page.evaluate("window.__hmpm.framesRendered")
    page.click("#view-reset")
    page.wait_for_function(f"window.__hmpm.framesRendered > {n}", timeout=10_000)
    # obstacles are drawn as solids (the 3D scenes have none: two are handed to the view, a sphere and a turned box)
    obstacles = [
        {"shape": "sphere", "center": [0.5, 0.25, 0.5], "radius": 0.08},
        {"shape": "box", "center": [0.25, 0.2, 0.75], "half_extents": [0.1, 0.03, 0.08], "rotation": [[0.94, -0.34, 0], [0.34, 0.94, 0], [0, 0, 1]]},
    ]
    bare = shot(page, "#sim")
    redrawn(page, f"window.__hmpm.view.session.obstacles = {obstacles!r}; window.__hmpm.showParticles(true)")
    solid = shot(page, "#sim")
    for ob in obstacles:
        x, y, _ = page.evaluate(f"window.__hmpm.toCss({ob['center']!r})")
        px = solid[int(y), int(x)]
        assert np.abs(px - bare[int(y), int(x)]).max() > 20 and np.ptp(px) < 40 and px.mean() < 135, (ob["shape"], px)
    redrawn(page, "window.__hmpm.view.session.obstacles = []; window.__hmpm.showParticles(true)")

    # an arrow drawn on the plane facing the camera through the fluid's centroid, then applied (PD)
    c = page.evaluate("window.__hmpm.centroidCss()")
    draw_stroke(page, (c[0], c[1]), (c[0] + 150, c[1] - 60))
    before = page.evaluate("window.__hmpm.controls.length")
    page.click("#apply")
    # halfway through the controlled horizon the stroke and the plan's centroid path are on the canvas, over the fluid
    page.wait_for_function(f"window.__hmpm.lastControlFrame >= {frames // 2}", timeout=60_000)
    img = shot(page)
    stroke_css, plan_css = page.evaluate("[window.__hmpm.strokeCss, window.__hmpm.planCss]")
    assert near(img, along(stroke_css), INK) >= 0.9, "the sketch is not on the canvas halfway through the horizon"
    assert len(plan_css) > 10 and near(img, along(plan_css, skip=0.15), PLAN, radius=4) >= 0.5, "the plan's path is not drawn"
    keep_screenshot(page, "page_3d.png")
    page.wait_for_function(f"window.__hmpm.controls.length > {before}", timeout=60_000)
    ctl = page.evaluate("window.__hmpm.controls.at(-1)")
    assert "error" not in ctl, ctl
    sketch = page.evaluate("window.__hmpm.lastSketch")
    w = np.array(sketch["width"])
    assert len(w) == len(sketch["points"]) and w.min() >= 0.006 - 1e-9 and w.max() <= 0.024 + 1e-9  # depth as width

    # the fluid's centroid moves along the 3D arrow (the server's trajectory, the control's download)
    path = download(page, "#dl-control", tmp_path)
    traj = Trajectory.load(path)
    fluid = traj.positions[:, traj.fluid_mask()]
    moved = fluid[-1].mean(0) - fluid[0].mean(0)
    stroke = np.array(page.evaluate("window.__hmpm.applied.stroke"))
    arrow = stroke[-1] - stroke[0]
    cos = float(moved @ arrow / (np.linalg.norm(moved) * np.linalg.norm(arrow)))
    assert cos >= 0.7, (cos, moved, arrow)
    assert np.linalg.norm(moved) >= 0.3 * np.linalg.norm(arrow[:2])

    # take-away: the session's recent trajectory (hybridmpm evaluate reads it), its PLY frames, a GIF
    session_traj = Trajectory.load(download(page, "#dl-npz", tmp_path))
    assert session_traj.dim == 3 and session_traj.num_frames == frames + 41  # frame 0, 40 stepped, the control's
    assert np.array_equal(session_traj.positions[-1], traj.positions[-1])
    assert np.diff(session_traj.extras["frame_index"]).tolist() == [1] * (frames + 40)
    last = Trajectory(session_traj.positions[-5:], session_traj.particle_type, session_traj.dt_frame, session_traj.n_grid)
    result = evaluate(last, Trajectory(traj.positions[-5:], traj.particle_type, traj.dt_frame, traj.n_grid))  # the same frames
    assert result["frames_compared"] == 5 and result["grid_mass_error"]["mean"] == 0.0
    with zipfile.ZipFile(download(page, "#dl-ply", tmp_path)) as z:
        assert len(z.namelist()) == frames + 41 and z.namelist()[0].endswith(".ply")
    page.fill("#gif-n", "12")
    gif = download(page, "#gif", tmp_path)
    with Image.open(gif) as im:
        assert im.format == "GIF" and im.n_frames == 12 and im.size == (320, 320)
    assert page.evaluate("window.__hmpm.errors") == [] and errors == [], errors
    page.close()


def test_2d_page_draws_obstacles_and_keeps_the_sketch_through_the_horizon(server, browser):
    frames = 200
    page, errors = new_page(browser, f"?scene=water_ramps2d&seed=6&solver=mpm&method=pd&frames={frames}&autoplay=0&scale=1", server)
    stepped(page, server, 150)
    session = page.evaluate("window.__hmpm.session")
    assert session["obstacles"] and session["obstacles"][0]["shape"] == "box"
    # the ramp is drawn as a solid at its place (the domain's x–y fills the canvas, y up)
    box = page.locator("#sim").bounding_box()
    img = shot(page, "#sim")
    ramp = session["obstacles"][0]["center"]
    x, y = ramp[0] * box["width"], (1 - ramp[1]) * box["height"]
    assert np.linalg.norm(img[int(y), int(x)] - [107, 114, 128]) < 30, img[int(y), int(x)]  # the legend's obstacle grey
    c = page.evaluate("window.__hmpm.centroidCss()")
    draw_stroke(page, (c[0], c[1]), (c[0] + 120, c[1] - 40))
    before = page.evaluate("window.__hmpm.controls.length")
    page.click("#apply")
    page.wait_for_function(f"window.__hmpm.lastControlFrame >= {frames // 2}", timeout=60_000)
    img = shot(page)
    assert near(img, along(page.evaluate("window.__hmpm.strokeCss")), INK) >= 0.9
    assert len(page.evaluate("window.__hmpm.planCss")) > 10
    keep_screenshot(page, "page_2d.png")
    page.wait_for_function(f"window.__hmpm.controls.length > {before}", timeout=60_000)
    assert "error" not in page.evaluate("window.__hmpm.controls.at(-1)")
    # the stroke stays after the horizon, until cleared
    page.wait_for_timeout(300)
    assert near(shot(page), along(page.evaluate("window.__hmpm.strokeCss")), INK) >= 0.9
    page.click("#clear")
    assert page.evaluate("window.__hmpm.strokeCss") == []
    assert page.evaluate("window.__hmpm.errors") == [] and errors == [], errors
    page.close()


def test_a_page_that_joins_mid_control_shows_its_sketch_and_plan(server, browser):
    """A page opened on a session (``?session=ID``: a second viewer, a reload) while a control runs there, started
    by another client, learns it from its stream's opening message: it draws that control's sketch and plan as
    the page that applied it does, says it runs, and sees it end. Leaving the page does not delete the session."""
    import concurrent.futures

    sketch = {"kind": "arrow", "points": [[0.25, 0.3], [0.45, 0.32], [0.65, 0.4]]}
    frames = 1000
    with httpx.Client(base_url=server.url, timeout=120) as c, concurrent.futures.ThreadPoolExecutor(1) as pool:
        info = c.post("/v1/sessions", json={"scene": "water3d", "seed": 2, "solver": "mpm"}).json()
        sid, start = info["id"], info["frame"]
        long = pool.submit(c.post, f"/v1/sessions/{sid}/controls", json={"sketch": sketch, "method": "constant", "frames": frames})
        deadline = time.monotonic() + 60
        while (c.get(f"/v1/sessions/{sid}").json().get("control") is None) and not long.done() and time.monotonic() < deadline:
            time.sleep(0.02)
        page, errors = new_page(browser, f"?session={sid}&gl=0&autoplay=0", server)
        page.wait_for_function("window.__hmpm.streamFrame !== undefined", timeout=30_000)
        mid = page.evaluate("window.__hmpm.streamFrame") < start + frames  # joined mid-control (8 s of MPM here: always, unless stalled)
        if mid:
            page.wait_for_function("window.__hmpm.applied && window.__hmpm.applied.plan && window.__hmpm.planCss.length > 1", timeout=30_000)
            shown = page.evaluate("window.__hmpm.applied")
            assert shown["kind"] == "arrow" and np.allclose(np.asarray(shown["stroke"])[:, :2], sketch["points"]), shown
            assert shown["plan"]["frames"] == frames and "running" in page.evaluate("window.__hmpm.status")
            page.wait_for_function("window.__hmpm.framesRendered >= 2", timeout=10_000)
            assert near(shot(page), along(page.evaluate("window.__hmpm.strokeCss")), INK) >= 0.9
        assert long.result().status_code == 200
        if mid:  # it sees the control end, and keeps its sketch until cleared (as the page that applied it does)
            page.wait_for_function("window.__hmpm.controlRunning === false && /done/.test(window.__hmpm.status)", timeout=30_000)
            assert page.evaluate("window.__hmpm.applied.stroke.length") == len(sketch["points"])
        assert page.evaluate("window.__hmpm.session.id") == sid
        assert page.evaluate("window.__hmpm.errors") == [] and errors == [], errors
        page.close()
        assert c.get(f"/v1/sessions/{sid}").status_code == 200  # a joined session is another client's: still there
        assert c.delete(f"/v1/sessions/{sid}").status_code == 204


def test_canvas2d_fallback_draws_without_webgl(server, browser):
    page, errors = new_page(browser, "?scene=water3d&seed=1&solver=mpm&gl=0", server)
    page.wait_for_function("window.__hmpm.framesRendered >= 5", timeout=20_000)
    assert page.evaluate("[window.__hmpm.renderer, window.__hmpm.look]") == ["canvas2d", "particles"]
    assert shot(page, "#sim").std() > 5
    assert page.evaluate("window.__hmpm.errors") == [] and errors == [], errors
    page.close()


def test_the_api_behind_the_page(server, tmp_path):
    """What the page reads besides frames: the scene's walls and obstacles, the plan's centroid path (in the
    control's answer and as a stream event), the session's recent trajectory and its refusals naming the field."""
    from hybridmpm.trajectory import Trajectory

    with httpx.Client(base_url=server.url, timeout=60) as c:
        s = c.post("/v1/sessions", json={"scene": "water_ramps2d", "seed": 1, "solver": "mpm"}).json()
        assert s["n_grid"] == 128 and 0 < s["wall_thickness"] < 0.1 and s["recorded_frames"] == 1
        assert s["obstacles"] and {"shape", "center", "half_extents", "angle_deg"} <= set(s["obstacles"][0])
        c.post(f"/v1/sessions/{s['id']}/step", json={"frames": 10})
        arrow = {"kind": "arrow", "points": [[0.3, 0.6], [0.5, 0.6]]}
        for method in ("constant", "pd"):
            r = c.post(f"/v1/sessions/{s['id']}/controls", json={"sketch": arrow, "method": method, "frames": 40}).json()
            plan = r["plan"]
            assert plan["method"] == method and plan["frames"] == 40 and plan["stride"] == 1 and len(plan["centroid_path"]) == 41
            start = np.array(r["metrics"]["centroid_start"])
            assert np.allclose(plan["centroid_path"][0], start, atol=1e-4)
            assert np.allclose(plan["target"], start + [0.2, 0.0], atol=1e-4)
            if method == "constant":  # the constant force lands a free cloud's centroid on the target
                assert np.allclose(plan["centroid_path"][-1], plan["target"], atol=1e-3)
        r = c.post(f"/v1/sessions/{s['id']}/controls", json={"method": "none", "frames": 5}).json()
        assert r["plan"] is None
        t = c.get(f"/v1/sessions/{s['id']}/trajectory?frames=50")
        assert t.status_code == 200 and "attachment" in t.headers["content-disposition"]
        (tmp_path / "recent.npz").write_bytes(t.content)
        traj = Trajectory.load(tmp_path / "recent.npz")
        assert traj.num_frames == 50 and traj.dt_frame == 0.0025 and traj.n_grid == 128
        ctl = traj.extras["controlled"]  # the PD control's 40 frames, then the 5 of method none
        assert np.diff(traj.extras["frame_index"]).tolist() == [1] * 49 and ctl[-45:-5].all() and not ctl[-5:].any()
        for query, field in (("frames=0", "frames"), ("frames=301", "frames"), ("frames=x", "frames"), ("format=gif", "format")):
            r = c.get(f"/v1/sessions/{s['id']}/trajectory?{query}")
            assert r.status_code == 422 and r.json()["detail"][0]["loc"] == ["query", field], r.text
        assert c.get("/v1/sessions/nope/trajectory").status_code == 404


# ---------------------------------------------------------------- the default 3D scene
def water_pixels(img):
    """Mask of the water's pixels in a screenshot (RGB float, the page's light 3D view): blue well above red and
    green. The room's walls and floor (greys), the background, the sketch (red) and the plan's path (green) are not."""
    r, g, b = img[..., 0], img[..., 1], img[..., 2]
    return (b - r > 50) & (b - g > 20)


def session_frame(server, sid):
    with httpx.Client(base_url=server.url, timeout=60) as c:
        return c.get(f"/v1/sessions/{sid}").json()["frame"]


def test_default_3d_scene_is_a_body_of_water_that_pauses_and_follows_a_rightward_arrow(server, browser):
    """The page on its default scene (WebGL2): the 3D dam break with its paddle, tens of thousands of particles drawn
    as one body of water. ``?solver=default``: the scene's fixed configuration (the page's default real-time session may
    change its grid while it plays, and the frame reached with the control is compared with the same frame replayed
    without it).
    Paused, the frame holds; a 100-frame control advances exactly 100 frames and the page stays paused after it.
    A rightward arrow (from frame 80) moves the water's pixels right on the screen (fixed camera): against the same
    frame reached without the control (reset, then stepped over HTTP), since the dam break flows right by itself."""
    page, errors = new_page(browser, "?solver=default&scale=1", server)
    session = page.evaluate("window.__hmpm.session")
    assert session["scene"] == "paddle3d" and session["dim"] == 3 and session["solver"] == "default"  # the scene's default: plain MPM
    assert [ob["shape"] for ob in session["obstacles"]] == ["box"]  # the paddle
    assert 20_000 <= session["num_fluid"] <= 60_000
    assert page.evaluate("[window.__hmpm.renderer, window.__hmpm.look]") == ["webgl2", "fluid"]
    page.evaluate("document.getElementById('badge').hidden = true")  # the badge is water-blue
    sid = session["id"]

    # it plays by default; paused, the frame holds (on the server and on the page)
    page.wait_for_function("window.__hmpm.lastFrame >= 10", timeout=30_000)
    page.click("#play")
    assert page.locator("#play").text_content() == "play"
    page.wait_for_timeout(500)
    f0 = session_frame(server, sid)
    page.wait_for_function(f"window.__hmpm.lastFrame === {f0}", timeout=10_000)
    page.wait_for_timeout(1500)
    assert session_frame(server, sid) == f0 and page.evaluate("window.__hmpm.lastFrame") == f0
    # the arrow acts from a fixed frame, 0.2 s in (the surge has just hit the paddle): where the pause fell depends on
    # the machine's speed, and from about 0.4 s on the free flow's splash up the far wall moves the water's pixels
    # right by itself nearly as far as the arrow does (12-18 px, under the 19 asked, from frames 158 and 175)
    page.click("#reset")
    page.wait_for_function("window.__hmpm.lastFrame === 0", timeout=10_000)
    f0 = 80
    stepped(page, server, f0)
    before = shot(page, "#sim")
    water0 = water_pixels(before)
    assert water0.mean() > 0.05, "the water is not drawn as a body"  # the column covers well over 5 % of the canvas

    # a rightward arrow from the water's centroid, applied with the scene's default method as the scene list gives it
    # (no learned controller ships for the dam break: PD), with no console error
    c = page.evaluate("window.__hmpm.centroidCss()")
    draw_stroke(page, (c[0], c[1]), (c[0] + 220, c[1]))
    assert page.eval_on_selector("#method", "s => s.value") == "pd"
    assert page.eval_on_selector("#method", "s => [...s.options].filter(o => o.disabled).map(o => o.value)") == ["diffusion"]
    page.click("#apply")
    page.wait_for_function("window.__hmpm.lastControlFrame >= 50", timeout=120_000)
    keep_screenshot(page, "page_paddle3d.png")
    page.wait_for_function("window.__hmpm.controls.length > 0", timeout=120_000)
    ctl = page.evaluate("window.__hmpm.controls.at(-1)")
    assert "error" not in ctl, ctl
    assert ctl["method"] == "pd" and page.eval_on_selector("#method", "s => s.value") == "pd"
    assert (ctl["start_frame"], ctl["end_frame"]) == (f0, f0 + 100)  # a control of T frames advances T frames
    page.wait_for_function(f"window.__hmpm.lastFrame === {f0 + 100}", timeout=10_000)
    page.wait_for_timeout(1500)  # still paused after the control
    assert session_frame(server, sid) == f0 + 100 and page.evaluate("window.__hmpm.lastFrame") == f0 + 100
    assert "paused" in page.evaluate("window.__hmpm.status")
    n = page.evaluate("window.__hmpm.framesRendered")
    page.click("#clear")
    page.wait_for_function(f"window.__hmpm.framesRendered > {n}", timeout=10_000)
    controlled = shot(page, "#sim")

    # the same frame without the control
    page.click("#reset")
    page.wait_for_function("window.__hmpm.lastFrame === 0", timeout=10_000)
    stepped(page, server, f0 + 100)
    free = shot(page, "#sim")

    w = before.shape[1]
    xs = np.arange(w)[None, :]

    def cx(img):
        m = water_pixels(img)
        return float((m * xs).sum() / m.sum()), float(m[:, w // 2 :].sum() / m.sum())

    (x0, right0), (xc, right_c), (xf, right_f) = cx(before), cx(controlled), cx(free)
    print(f"water centroid x [px]: before {x0:.0f}, controlled {xc:.0f}, free {xf:.0f}; right half: {right0:.2f} {right_c:.2f} {right_f:.2f}")
    assert xc - xf >= 0.03 * w and right_c > right_f + 0.03, "the arrow does not move the water right on the screen"
    assert xc > x0
    assert ctl["metrics"]["centroid_displacement"][0] > 0  # the server agrees: the fluid's centroid moved +x
    # the page knew the scene's methods from the scene list: no request refused, no console error
    assert page.evaluate("window.__hmpm.errors") == [] and errors == [], errors
    page.close()


# ---------------------------------------------------------------- the drag tool
def fluid_positions(server, sid):
    """The fluid's positions [N, D] in the session's last recorded frame (its recent trajectory, one frame)."""
    with httpx.Client(base_url=server.url, timeout=60) as c:
        t = c.get(f"/v1/sessions/{sid}/trajectory?frames=1")
    assert t.status_code == 200, t.text
    with np.load(io.BytesIO(t.content), allow_pickle=False) as z:
        pos, types = z["positions"], z["particle_type"]
    return pos[-1][types != 3]


def fluid_centroid(server, sid):
    """The fluid's centroid in the session's last recorded frame."""
    return fluid_positions(server, sid).mean(0)


def settled_frame(server, sid):
    """The session's frame once it has stopped advancing (the page pauses it again after a drag)."""
    last = -1
    for _ in range(40):
        f = session_frame(server, sid)
        if f == last:
            return f
        last = f
        time.sleep(0.4)
    raise AssertionError("the session keeps playing after the drag")


def replay_without_drag(page, server, sid, want, c0, read):
    """After a drag dropped obstacle 0 of session ``sid`` at ``want``: waits for the last ``obstacle`` event to
    report it there and for the page to pause again (it was paused before the drag), checks the server's obstacle
    lies within 0.01 m of ``want`` and the page draws it there, and reads the water (``read(server, sid)``); then resets the session (which puts
    the obstacle back at ``c0``, checked), steps it as many frames over HTTP and reads the water again. Returns
    (frames, the server's obstacle centre after the drag, water after the drag, water without it)."""
    page.wait_for_function(
        f"window.__hmpm.obstacleEvents.length && Math.hypot(...window.__hmpm.obstacleEvents.at(-1).center.map((x, d) => x - {[float(v) for v in want]}[d])) < 0.01",
        timeout=10_000,
    )
    frames = settled_frame(server, sid)
    assert page.locator("#play").text_content() == "play"
    with httpx.Client(base_url=server.url, timeout=60) as c:
        center = np.array(c.get(f"/v1/sessions/{sid}").json()["obstacle_centers"][0])
    assert np.abs(center - want).max() < 0.01, center
    assert np.abs(np.array(page.evaluate("window.__hmpm.session.obstacles[0].center")) - center).max() < 0.01  # drawn there
    dragged = read(server, sid)
    page.click("#reset")
    page.wait_for_function("window.__hmpm.lastFrame === 0", timeout=10_000)
    with httpx.Client(base_url=server.url, timeout=60) as c:
        back = c.get(f"/v1/sessions/{sid}").json()["obstacle_centers"][0]
    assert np.abs(np.array(back) - c0).max() < 1e-4, back
    stepped(page, server, frames)
    return frames, center, dragged, read(server, sid)


def test_dragging_an_obstacle_through_the_water_pushes_it(server, browser):
    """The drag tool: the ramp of water_ramps2d (seed 0, at the right) grabbed with the mouse, pulled down to the
    floor and dragged left through the water that has pooled there, slowly (one pointer move per ~60 ms: the page
    sends at most one move per coarse step, under the solver's speed limit). The page, paused, plays while dragging
    and pauses again after the last move; the server's obstacle ends at the drop point and every viewer got the
    ``obstacle`` events; the water's particles end elsewhere than the same session puts them in as many frames without
    the drag (reset, which puts the ramp back, then stepped over HTTP)."""
    page, errors = new_page(browser, "?scene=water_ramps2d&seed=0&solver=mpm&autoplay=0&scale=1", server)
    stepped(page, server, 300)  # the water falls and pools on the floor, left of the ramp
    session = page.evaluate("window.__hmpm.session")
    sid, ob = session["id"], session["obstacles"][0]
    assert ob["shape"] == "box"
    c0 = np.array(ob["center"], np.float64)
    water0 = fluid_centroid(server, sid)
    assert water0[0] < c0[0] - 0.2 and water0[1] < 0.35, water0  # low (pooling), left of the ramp
    page.check("input[name=tool][value=drag]")
    box = page.locator("#ink").bounding_box()

    def px(p):
        return box["x"] + p[0] * box["width"], box["y"] + (1 - p[1]) * box["height"]

    low, drop = np.array([c0[0], 0.14]), np.array([0.2, 0.14])
    page.mouse.move(*px(c0))
    page.mouse.down()
    assert page.evaluate("window.__hmpm.grabbed") == 0
    for a, b, n in ((c0, low, 10), (low, drop, 45)):
        for t in np.linspace(0, 1, n + 1)[1:]:
            page.mouse.move(*px(a + t * (b - a)))
            page.wait_for_timeout(60)
    page.mouse.up()
    page.wait_for_function("window.__hmpm.grabbed === null", timeout=20_000)
    moves = page.evaluate("window.__hmpm.obstacleMoves")
    assert len(moves) >= 10 and not [m for m in moves if "error" in m], moves
    # the server's ramp ends where it was dropped (the pointer's offset is 0); then the same number of frames without
    # the drag: reset (the ramp goes back), then stepped over HTTP
    frames, _, dragged, free = replay_without_drag(page, server, sid, drop, c0, fluid_positions)
    moved = float(np.linalg.norm(free - dragged, axis=1).mean())
    print(
        f"after {frames} frames: water centroid dragged {dragged.mean(0).round(4)}, free {free.mean(0).round(4)}, at the grab "
        f"{water0.round(4)}; particles moved {moved:.4f} m apart on average"
    )
    # the drag changed the flow: the same deterministic MPM without it puts the particles elsewhere. The centroids tell
    # the flows apart only while the water still sloshes: the real-time drag takes as many frames as the machine plays
    # in a few seconds (~500 here, ~4,500 on a faster one), after which both pools are near rest and their centroids can
    # lie within a cell of each other. The particles themselves end 0.12-0.28 m (16-36 cells) apart on average, over
    # drags of 3 to 77 frames a move (an HTTP replay of this drag), so 2 cells are asserted; that a moving obstacle
    # pushes the water ahead of it is asserted in tests/test_moving_obstacles.py.
    assert moved >= 2.0 / session["n_grid"], moved
    assert page.evaluate("window.__hmpm.errors") == [] and errors == [], errors
    page.close()


def test_dragging_the_paddle_through_the_water_in_3d(server, browser):
    """The drag tool in 3D, on the page's default scene (paddle3d): once the surge has hit the paddle and flowed round
    it, the right mouse button still turns the view and grabs nothing; the left button grabs the paddle where the
    pointer's ray meets its top face, and the pointer drags it along the horizontal plane through that point (its y
    stays), slowly, upstream and across z through the water. As in 2D: the page, paused, plays while dragging and
    pauses again after the last move; the server's paddle ends where it was dropped and the page draws it there; the
    ``obstacle`` events arrived; against the same session stepped as many frames without the drag (reset, which puts
    the paddle back, then stepped over HTTP), the water ends elsewhere and out of the place the paddle was dropped
    in, which it fills without the drag. ``?solver=default``: the scene's fixed configuration (the replay must run the
    drag's grid; the page's default real-time session may change its grid while it plays)."""
    page, errors = new_page(browser, "?solver=default&autoplay=0&scale=1", server)
    session = page.evaluate("window.__hmpm.session")
    assert session["scene"] == "paddle3d" and session["dim"] == 3 and page.evaluate("window.__hmpm.renderer") == "webgl2"
    sid, ob = session["id"], session["obstacles"][0]
    assert ob["shape"] == "box"
    c0 = np.array(ob["center"], np.float64)
    top = c0[1] + ob["half_extents"][1]
    stepped(page, server, 120)  # 0.3 s: the surge has hit the paddle and flows round both sides
    water0 = fluid_centroid(server, sid)
    assert water0[0] < c0[0], water0  # most of the water still upstream
    page.check("input[name=tool][value=drag]")
    box = page.locator("#ink").bounding_box()

    def px(points):  # world points -> page pixels, under the camera of the last draw (one call: the page draws slowly)
        css = page.evaluate(f"{[[float(v) for v in p] for p in points]}.map((p) => window.__hmpm.toCss(p))")
        return [(box["x"] + q[0], box["y"] + q[1]) for q in css]

    # the camera's own drag: the right button turns the view, over the paddle too, with the drag tool chosen
    yaw = page.evaluate("window.__hmpm.camera.yaw")
    page.mouse.move(*px([[c0[0], top, c0[2]]])[0])
    page.mouse.down(button="right")
    page.mouse.move(box["x"] + 0.8 * box["width"], box["y"] + 0.5 * box["height"], steps=8)
    page.mouse.up(button="right")
    assert page.evaluate("window.__hmpm.camera.yaw") != yaw and page.evaluate("window.__hmpm.grabbed") is None
    redrawn(page, "document.getElementById('view-reset').click()")  # the drag below is laid out in the default view

    # grab the middle of its top face and drag it upstream and across z, one pointer move per ~60 ms
    grip, drop = np.array([c0[0], top, c0[2]]), np.array([0.3, top, 0.35])
    path = px([grip + t * (drop - grip) for t in np.linspace(0, 1, 31)])
    page.mouse.move(*path[0])
    page.mouse.down()
    assert page.evaluate("window.__hmpm.grabbed") == 0
    for k, p in enumerate(path[1:], 1):
        page.mouse.move(*p)
        page.wait_for_timeout(60)
        if k == 20:
            keep_screenshot(page, "page_paddle3d_drag.png")  # the docs' picture: the paddle on its way, the water in its wake
    page.mouse.up()
    page.wait_for_function("window.__hmpm.grabbed === null", timeout=20_000)
    moves = page.evaluate("window.__hmpm.obstacleMoves")
    assert len(moves) >= 10 and not [m for m in moves if "error" in m], moves
    want = np.array([drop[0], c0[1], drop[2]])  # the grip is the middle of the top face: the centre lies below it
    # the server's paddle ends where it was dropped; then the same number of frames without the drag: reset (the
    # paddle goes back), then stepped over HTTP
    frames, center, dragged, free = replay_without_drag(page, server, sid, want, c0, fluid_positions)
    assert abs(center[1] - c0[1]) < 1e-6, center  # y kept

    def inside(pos):  # water particles deeper than half a cell inside the paddle where it was dropped
        return int(np.all(np.abs(pos - want) < np.array(ob["half_extents"]) - 0.5 / session["n_grid"], axis=1).sum())

    moved = float(np.linalg.norm(free - dragged, axis=1).mean())
    print(
        f"after {frames} frames: water centroid dragged {dragged.mean(0).round(4)}, free {free.mean(0).round(4)}, at the grab "
        f"{water0.round(4)}; particles moved {moved:.4f} m apart on average; in the dropped paddle's place: {inside(dragged)} dragged, {inside(free)} free"
    )
    # the paddle pushed the water out of where it was dropped, which the water fills without the drag (after a few
    # seconds of real-time dragging the water is near rest, and the centroids lie within a cell of each other: the
    # particles, not the centroid, tell the flows apart); and the flow differs (at least 0.6 cells of the 34³ grid's)
    assert inside(dragged) == 0 and inside(free) >= 20, (inside(dragged), inside(free))
    assert moved >= 0.6 / session["n_grid"], moved
    assert page.evaluate("window.__hmpm.errors") == [] and errors == [], errors
    page.close()
