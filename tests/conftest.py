"""Suite-wide settings.

* Property tests: hypothesis's "ci" profile (derandomised: the same examples
  on every run, no example database) when the environment sets ``CI``; the
  "dev" profile (random examples, hypothesis's defaults) otherwise, so local
  runs keep exploring. ``HYPOTHESIS_PROFILE`` picks one explicitly.
* In CI a skipped test is a failure: the browser, service, Ray and
  schemathesis tests skip when their packages or Debian's chromium are
  missing, and CI installs them all, so a skip there means CI stopped testing
  something. A test whose skip is legitimate on some CI machines says why
  with ``@pytest.mark.may_skip_in_ci(reason)``. Skips raised while a module
  is collected (``pytest.importorskip`` at module level) cannot be turned into
  test failures; they are listed at the end and make the run fail.
* Parallel runs (pytest-xdist): ``scripts/test.sh`` runs ``-n 2 --dist
  loadfile --no-loadscope-reorder -m "not alone"``, then ``-m alone`` by itself. One worker runs all
  of a file's tests, so a module-scoped fixture is built once, as in a serial
  run. The files that take longest are handed out first (``_LONGEST_FILES``
  with ``--no-loadscope-reorder``), so that no worker ends the run alone on
  one of them. Tests marked ``alone`` assert rates on this machine's cores (the
  page's frame rates, real-time drags in the browser); they run after the
  parallel phase, with no other test beside them. The workers write the files
  that hold them to ``HYBRIDMPM_ALONE_FILES`` when it is set, so that the
  ``alone`` phase collects those files only (the whole suite takes about 20 s
  of one core to collect). Tests that share a node id
  (schemathesis's one test per API operation: its items are named
  ``test[GET /path]`` but keep the function's node id under pytest 9) are
  given their names as node ids, so that pytest-xdist tells them apart and
  runs them on a worker; any still shared are marked ``alone`` (pytest-xdist
  would run one of them). The skip rule above holds
  on the workers: a skipped test's report is failed before it leaves the
  worker, and a module skipped while collected is reported to the
  controller, which fails the run.
* The browser tests (``test_page_*.py``, ``test_service_browser.py``) drive
  Debian's chromium through Playwright's executable path (never a downloaded
  browser; ``HYBRIDMPM_CHROMIUM`` names another binary): each marks its
  module ``needs_chromium`` (a skip where the binary is missing, which CI
  fails as above) and ``alone``, takes the module-scoped ``browser`` fixture
  (one headless chromium a file: a page a test left open dies with its file,
  so it draws nothing while another file measures frame rates), and opens its
  pages with ``watched_page``, which collects their errors.
"""

from __future__ import annotations

import os
import shutil
from collections import Counter
from collections.abc import Iterator
from typing import Any

import pytest
from hypothesis import settings

settings.register_profile("ci", derandomize=True, database=None, print_blob=True)
settings.register_profile("dev")


def in_ci() -> bool:
    """Whether the environment says this is CI (``CI`` set to anything but empty, 0 or false)."""
    return os.environ.get("CI", "").strip().lower() not in ("", "0", "false", "no")


settings.load_profile(os.environ.get("HYPOTHESIS_PROFILE") or ("ci" if in_ci() else "dev"))

_COLLECTION_SKIPS: list[str] = []


def pytest_configure(config: pytest.Config) -> None:
    config.addinivalue_line("markers", "may_skip_in_ci(reason): the test may skip in CI (CI otherwise fails on a skip); the reason says when and why")
    config.addinivalue_line(
        "markers",
        "alone: scripts/test.sh runs the test after the parallel phase, by itself: it asserts rates on this machine's cores (frame rates), or shares "
        "its node id with another test (which pytest-xdist cannot tell apart)",
    )


# The files whose tests take longest on the 2-core machine (pytest --durations, summed per file, 60-100 s of a worker
# each for the first three): on the workers of a parallel run they are collected first, so each starts early.
_LONGEST_FILES = (
    "test_control_diffusion.py",
    "test_bench.py",
    "test_service_cluster.py",
    "test_service_hostile_live.py",
    "test_service_live.py",
    "test_hybrid.py",
    "test_generate.py",
    "test_probe_obstacle_moves.py",
    "test_ddp.py",
    "test_readme.py",
)


def _rename(item: pytest.Item, nodeid: str) -> None:
    """Give ``item`` the node id ``nodeid``: pytest 9 keeps it structured (``_id``), pytest 8 as a string. Private
    to pytest: where neither holds (another version), the item keeps its id and the shared ids run ``alone``."""
    if hasattr(item, "_id"):
        try:
            from _pytest.nodes import coerce_node_id
        except ImportError:
            return
        item._id = coerce_node_id(nodeid)
    elif hasattr(item, "_nodeid"):
        item._nodeid = nodeid


@pytest.hookimpl(tryfirst=True)  # before -m deselects: the marks added here count
def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    """Tests that share a node id (schemathesis's one test per API operation) get their names as node ids
    (pytest-xdist hands out tests by node id: all but one of a shared id would never run on a worker); any whose id
    is still shared is marked ``alone``. On a pytest-xdist worker, the files holding ``alone`` tests are written to
    ``HYBRIDMPM_ALONE_FILES`` (when set), and the longest files come first (a stable sort, so each file keeps its
    tests' order)."""
    counts = Counter(item.nodeid for item in items)
    for item in items:
        if counts[item.nodeid] > 1 and "::" in item.nodeid:
            _rename(item, f"{item.nodeid.rsplit('::', 1)[0]}::{item.name}")  # what pytest names any other item
    counts = Counter(item.nodeid for item in items)
    for item in items:
        if counts[item.nodeid] > 1:
            item.add_marker(pytest.mark.alone)
    if not hasattr(config, "workerinput"):
        return
    listing = os.environ.get("HYBRIDMPM_ALONE_FILES")
    if listing:
        files = sorted({str(item.path) for item in items if item.get_closest_marker("alone") is not None})
        part = f"{listing}.{os.getpid()}"  # both workers write the same list: each whole, then renamed over it
        with open(part, "w") as fh:
            fh.write("".join(f"{f}\n" for f in files))
        os.replace(part, listing)
    rank = {name: i for i, name in enumerate(_LONGEST_FILES)}
    items.sort(key=lambda item: rank.get(item.path.name, len(rank)))


def _skip_reason(longrepr: object) -> str:
    if isinstance(longrepr, tuple) and len(longrepr) == 3:
        return str(longrepr[2])
    return str(longrepr)


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_makereport(item: pytest.Item, call: pytest.CallInfo) -> object:
    outcome = yield
    rep = outcome.get_result()
    if in_ci() and rep.skipped and not hasattr(rep, "wasxfail") and item.get_closest_marker("may_skip_in_ci") is None:
        rep.outcome = "failed"
        rep.longrepr = f"skipped in CI, which fails the run (CI installs every test dependency): {_skip_reason(rep.longrepr)}"


def pytest_collectreport(report: pytest.CollectReport) -> None:
    if in_ci() and report.skipped:
        _COLLECTION_SKIPS.append(f"{report.nodeid}: {_skip_reason(report.longrepr)}")


def pytest_terminal_summary(terminalreporter, exitstatus: int, config: pytest.Config) -> None:  # type: ignore[no-untyped-def]
    if _COLLECTION_SKIPS:
        terminalreporter.section("modules skipped in CI (a failure)", red=True)
        for line in _COLLECTION_SKIPS:
            terminalreporter.line(line)


def pytest_sessionfinish(session: pytest.Session, exitstatus: int) -> None:
    if _COLLECTION_SKIPS and session.exitstatus == 0:
        session.exitstatus = pytest.ExitCode.TESTS_FAILED


CHROMIUM = os.environ.get("HYBRIDMPM_CHROMIUM") or shutil.which("chromium") or "/usr/bin/chromium"
needs_chromium = pytest.mark.skipif(not os.path.exists(CHROMIUM), reason=f"no chromium binary at {CHROMIUM} (apt-get install chromium; CI installs it)")


@pytest.fixture(scope="module")
def browser() -> Iterator[Any]:
    """Headless chromium (``CHROMIUM``) through Playwright, one a test module."""
    from playwright.sync_api import sync_playwright  # the browser tests' modules importorskip it while collected

    with sync_playwright() as p:
        b = p.chromium.launch(executable_path=CHROMIUM, headless=True, args=["--no-sandbox"])
        yield b
        b.close()


def watched_page(browser: Any, errors: list[str], dpr: float = 1, console: bool = True) -> Any:
    """A new 1100 × 800 page of ``browser`` (``dpr`` device pixels a CSS pixel) whose uncaught exceptions, and its
    console's errors unless ``console`` is false, are appended to ``errors``. The page's CSP forbids eval; the tests'
    hooks need it (``bypass_csp``)."""
    page = browser.new_page(viewport={"width": 1100, "height": 800}, device_scale_factor=dpr, bypass_csp=True)
    if console:
        page.on("console", lambda m: errors.append(m.text) if m.type == "error" else None)
    page.on("pageerror", lambda e: errors.append(str(e)))
    return page
