"""End to end in headless Chromium (Debian's package, driven by Playwright
through its executable path; never a downloaded browser): the page loads
without console errors, frames render, a drawn rightward arrow moves the fluid
right on the server, an upward stroke moves it up (the y flip)."""

from __future__ import annotations

import io
import os
import shutil

import numpy as np
import pytest

pytest.importorskip("fastapi")
httpx = pytest.importorskip("httpx")
sync_api = pytest.importorskip("playwright.sync_api")

from hybridmpm.service.testing import LiveServer  # noqa: E402

CHROMIUM = os.environ.get("HYBRIDMPM_CHROMIUM") or shutil.which("chromium") or "/usr/bin/chromium"
pytestmark = pytest.mark.skipif(not os.path.exists(CHROMIUM), reason=f"no chromium binary at {CHROMIUM} (apt-get install chromium; CI installs it)")


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    with LiveServer(max_sessions=10, log=tmp_path_factory.mktemp("browser") / "server.log") as s:
        yield s


@pytest.fixture(scope="module")
def browser():
    with sync_api.sync_playwright() as p:
        b = p.chromium.launch(executable_path=CHROMIUM, headless=True, args=["--no-sandbox"])
        yield b
        b.close()


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
    page = browser.new_page(
        viewport={"width": 1100, "height": 800}, device_scale_factor=2, bypass_csp=True
    )  # the page's CSP forbids eval; the test hooks need it
    errors: list[str] = []
    page.on("console", lambda m: errors.append(m.text) if m.type == "error" else None)
    page.on("pageerror", lambda e: errors.append(str(e)))
    page.goto(server.url + "/?scene=dam_break2d&solver=mpm&method=constant")
    page.wait_for_function("window.__hmpm.framesRendered >= 30", timeout=20_000)
    shot = tmp_path / "page.png"
    page.locator("#sim").screenshot(path=str(shot))
    from PIL import Image

    img = np.asarray(Image.open(shot).convert("L"), np.float64)
    assert img.std() > 5, "blank canvas"
    print(f"screenshot kept at {shot}")
    hook = page.evaluate("window.__hmpm")
    # the page draws the stream as it comes: every draw is timed, most frames received are drawn (latest
    # wins: 119 of 130 here). How fast it draws is a wall-clock figure and is measured by
    # benchmarks/bench_page.py (median 1.1 ms here against a 50 ms budget), not asserted in the suite.
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

    # a scene without a shipped model offers MPM only: choosing it (solver hybrid) falls back to mpm and streams
    page.select_option("#solver", "hybrid")
    page.select_option("#scene", "water_columns2d")
    page.wait_for_function("window.__hmpm.session && window.__hmpm.session.scene === 'water_columns2d'", timeout=20_000)
    assert page.eval_on_selector("#solver", "s => s.value") == "mpm"
    assert page.eval_on_selector("#solver", "s => [...s.options].filter(o => o.disabled).map(o => o.value).sort()") == ["hybrid", "neural"]
    assert page.evaluate("window.__hmpm.session.solver") == "mpm"
    page.select_option("#scene", "water2d")  # a scene with a model offers every solver again
    assert page.eval_on_selector("#solver", "s => [...s.options].filter(o => o.disabled).length") == 0
    assert errors == [], errors
    page.close()
