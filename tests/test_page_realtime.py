"""The page's real-time readout, in headless Chromium (Debian's package through
Playwright's executable path, as ``tests/test_service_browser.py`` drives it).

* The page opened bare: the 3D default scene (``paddle3d``) in a real-time
  session (the page's default solver where the scene offers ``realtime``),
  playing. Within a bounded time the latest frame's header carries a measured
  real-time factor (``__hmpm.realtimeFactor``: finite, > 0; flag bit4 and the
  u16 at byte 26, ``static/frames.js``) and the readout beside the frames/s
  shows it with the configuration in use (``__hmpm.realtimeLabel``: the
  session description's ``realtime.label``, then the stream's ``realtime``
  events'). What
  the factor is depends on this machine: no speed is asserted.
* ``?solver=default`` gives the session the page made before real-time mode:
  not real-time, its frames without the factor, the readout hidden.
"""

from __future__ import annotations

import math

import pytest
from conftest import needs_chromium, watched_page

pytest.importorskip("fastapi")
pytest.importorskip("playwright.sync_api")

from hybridmpm.service.testing import LiveServer  # noqa: E402

# alone: a page playing the 3D scene in real time, on Chromium's CPU renderer, beside the server it measures itself on
pytestmark = [needs_chromium, pytest.mark.alone]

READOUT = "[...document.querySelectorAll('.only-rt')].map((el) => [el.hidden, el.textContent])"


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    with LiveServer(max_sessions=4, log=tmp_path_factory.mktemp("realtime") / "server.log") as s:
        yield s


def open_page(browser, url, errors):
    page = watched_page(browser, errors)
    page.goto(url)
    page.wait_for_function("window.__hmpm.framesRendered >= 1 && window.__hmpm.session", timeout=60_000)
    return page


def test_the_default_page_plays_in_real_time_and_shows_its_factor_and_configuration(server, browser):
    errors: list[str] = []
    page = open_page(browser, server.url + "/", errors)
    session = page.evaluate("window.__hmpm.session")
    assert session["scene"] == "paddle3d" and session["dim"] == 3 and session["solver"] == "realtime", session["solver"]
    assert page.eval_on_selector("#solver", "s => s.value") == "realtime"
    rt = session["realtime"]
    assert isinstance(rt, dict) and rt["rung"] in rt["ladder"] and rt["label"], rt
    assert page.locator("#play").text_content() == "pause"  # it plays by default

    # the factor is measured on the server and sent in the frames' header: bounded in time, whatever its value
    page.wait_for_function("Number.isFinite(window.__hmpm.realtimeFactor) && window.__hmpm.realtimeFactor > 0", timeout=120_000)
    factor, label = page.evaluate("[__hmpm.realtimeFactor, __hmpm.realtimeLabel]")
    assert math.isfinite(factor) and factor > 0, factor
    assert isinstance(label, str) and label.strip(), label

    # the readout beside the frames/s: both shown, the factor as "sim N× real time", the configuration's label
    page.wait_for_function("document.getElementById('r-rtf').textContent.includes('real time')", timeout=10_000)
    shown = page.evaluate(READOUT)
    assert shown and not any(hidden for hidden, _ in shown), shown
    assert page.locator("#r-rtf").text_content().startswith("sim ")
    assert page.locator("#r-rung").text_content() == page.evaluate("__hmpm.realtimeLabel")
    assert page.evaluate("__hmpm.errors") == [] and errors == [], errors
    page.close()


def test_solver_default_asks_for_the_old_session_without_the_readout(server, browser):
    errors: list[str] = []
    page = open_page(browser, server.url + "/?solver=default", errors)
    session = page.evaluate("window.__hmpm.session")
    assert session["scene"] == "paddle3d" and session["solver"] == "default" and session.get("realtime") is None, session["solver"]
    page.wait_for_function("window.__hmpm.framesReceived >= 3", timeout=60_000)
    assert page.evaluate("[__hmpm.realtimeFactor, __hmpm.realtimeLabel]") == [None, None]
    shown = page.evaluate(READOUT)
    assert shown and all(hidden for hidden, _ in shown), shown
    assert page.evaluate("__hmpm.errors") == [] and errors == [], errors
    page.close()
