"""The page's frame rate in headless Chromium (Debian's package, software GL:
SwiftShader behind ANGLE, as the browser test drives it): a real ``hybridmpm
serve`` and the page in its benchmark mode (``?bench=1``: it draws on every
animation frame, turning a 3D camera a little each time, so the frame rate is
the page's own, not the stream's). Per case: frames drawn per second over a
few seconds, the median and p95 CPU time of one draw (the page's
``__hmpm.drawMs``), and, in a second run with ``?sync=1`` (a one-pixel
``readPixels`` after the draw, inside its timing, waits for the GPU), the
median draw time with the GPU's work included. Because the machine is
shared, it also reports the CPU time the browser's processes (renderer, GPU process: SwiftShader draws on the
CPU) spent per frame drawn, which does not depend on what else runs, the
machine's load average and the share of its CPU time the other jobs took
during the measurement.

Cases: the 3D scenes (water3d seed 26: 4032 particles, sand3d seed 3: 4032,
the largest of their first 30 seeds; the scenes cap at 4096) in the fluid and
the particles looks, the simulation paused (rendering alone) and playing (the
server simulating on the same cores), at 3/4 of a CSS pixel, at full
resolution and (water) at half, the 2D dam break, the 3D dam break (23,520
particles; cases 10-15) and the page's default 3D scene, paddle3d (the same
water and a paddle; cases 16-19). Cases 0-19 fix a quality level by its
resolution (``?scale=``: the highest level drawn at it, every particle
splatted, ``static/quality.js``); cases 20-21 let the page choose
(``?quality=auto``: it steps down while it draws under 24 frames/s), and are
measured once no level has changed for 3 s (at most 60 s); cases 22-29 fix
each of the eight levels in turn (``?quality=N``), playing, and 30-37 paused.
With ``--advance N`` a case starts N frames in (stepped over HTTP first,
paused: the water spread over the floor, the costly case for the splats; a
playing case then plays from there). The
old target was 50 frames/s; the page keeps 24. Playing, it also reports the
simulation frames the session advanced per second while the page watched
(the session's ``frame`` from ``GET /v1/sessions/{id}`` before and after).

    python benchmarks/bench_page.py [--seconds 5] [--dpr 1] [--cases 20,21] [--advance 300] [--no-sync] [--out benchmarks/results/page]

``--pour jello`` pours a 0.12 m cube of a material (a model or a preset) behind
the paddle before each case, as the page's palette drops one (the quality the
page keeps with a jelly in: ``--pour jello --cases 20``).

``--ladder R`` measures the quality levels' costs instead (the ``cost`` of
``static/quality.js``'s levels): one paddle3d page, paused ``--advance``
frames in, the levels taken in turn R times (interleaved, so that a shared
machine's load falls on each alike), the median browser CPU per frame each.
"""

from __future__ import annotations

import argparse
import functools
import json
import os
import shutil
import subprocess
import tempfile
import time
from pathlib import Path

import httpx
import numpy as np
from playwright.sync_api import sync_playwright

from hybridmpm.bench.harness import load_average, write_results
from hybridmpm.service.testing import LiveServer

TARGET_FPS = 24.0  # static/quality.js TARGET_FPS
SETTLE_S, SETTLE_MAX_S = 3.0, 60.0  # an auto case is measured once its quality has not changed for SETTLE_S
CLK_TCK = os.sysconf("SC_CLK_TCK")


def _stat(pid: int) -> list[str] | None:
    try:
        text = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return None
    return text[text.rindex(")") + 2 :].split()  # the fields after the command name


def browser_pids() -> list[int]:
    """This process's descendants that run a Chromium binary (the browser, its renderers and GPU process)."""
    parent: dict[int, int] = {}
    for d in Path("/proc").iterdir():
        if d.name.isdigit() and (f := _stat(int(d.name))) is not None:
            parent[int(d.name)] = int(f[1])
    mine = {os.getpid()}
    changed = True
    while changed:
        changed = False
        for pid, pp in parent.items():
            if pp in mine and pid not in mine:
                mine.add(pid)
                changed = True
    out = []
    for pid in mine:
        try:
            exe = os.readlink(f"/proc/{pid}/exe")
        except OSError:
            continue
        if "chrom" in Path(exe).name:
            out.append(pid)
    return out


def cpu_seconds(pids: list[int]) -> float:
    total = 0
    for pid in pids:
        if (f := _stat(pid)) is not None:
            total += int(f[11]) + int(f[12])  # utime, stime
    return total / CLK_TCK


def machine_busy() -> tuple[float, float]:
    """(busy, all) CPU seconds of the whole machine since boot (/proc/stat), steal counted as busy."""
    v = [int(x) for x in Path("/proc/stat").read_text().split("\n", 1)[0].split()[1:]]
    idle = v[3] + v[4]
    return (sum(v) - idle) / CLK_TCK, sum(v) / CLK_TCK


#: Side of the cube ``--pour`` drops [m] (the palette test's jelly).
POUR_SIDE = 0.12

#: static/quality.js's LEVELS: how many quality levels the page has (1 the cheapest)
QUALITY_LEVELS = 8
CASES = [
    # scene, seed, look, simulation playing, resolution (backing pixels per CSS pixel; software GL's default is 0.75)
    ("water3d", 26, "fluid", False, 0.75),
    ("water3d", 26, "fluid", False, 1.0),
    ("water3d", 26, "fluid", False, 0.5),
    ("water3d", 26, "particles", False, 0.75),
    ("water3d", 26, "particles", False, 1.0),
    ("water3d", 26, "fluid", True, 0.75),
    ("sand3d", 3, "fluid", False, 0.75),
    ("sand3d", 3, "fluid", False, 1.0),
    ("sand3d", 3, "fluid", True, 0.75),
    ("dam_break2d", 0, "fluid", True, 0.75),
    # the 3D dam break: 23,520 particles
    ("dam_break3d", 0, "fluid", False, 0.75),
    ("dam_break3d", 0, "fluid", True, 0.75),
    ("dam_break3d", 0, "particles", False, 0.75),
    ("dam_break3d", 0, "particles", True, 0.75),
    ("dam_break3d", 0, "fluid", False, 1.0),
    ("dam_break3d", 0, "fluid", True, 0.5),
    # the page's default 3D scene: the 3D dam break's water and a paddle downstream
    ("paddle3d", 0, "fluid", False, 0.75),
    ("paddle3d", 0, "fluid", True, 0.75),
    ("paddle3d", 0, "particles", False, 0.75),
    ("paddle3d", 0, "particles", True, 0.75),
    # the quality the page keeps: auto, then each level fixed (static/quality.js LEVELS, 1 the cheapest)
    ("paddle3d", 0, "fluid", True, "auto"),
    ("paddle3d", 0, "fluid", False, "auto"),
    *[("paddle3d", 0, "fluid", True, str(q)) for q in range(1, QUALITY_LEVELS + 1)],
    *[("paddle3d", 0, "fluid", False, str(q)) for q in range(1, QUALITY_LEVELS + 1)],
]


def settle(page) -> float:
    """Wait until the page's quality has not changed for SETTLE_S (at most SETTLE_MAX_S); returns the seconds waited."""
    t0 = time.monotonic()
    while time.monotonic() - t0 < SETTLE_MAX_S:
        n = page.evaluate("__hmpm.quality.changes.length")
        time.sleep(SETTLE_S)
        if page.evaluate("__hmpm.quality.changes.length") == n:
            break
    return time.monotonic() - t0


def pour(url: str, page, material: str) -> None:
    """Pour a cube of ``material`` (a model or preset, :data:`POUR_SIDE` a side) into the page's 3D session, on the
    floor behind the paddle as the palette test drops its jelly, and wait until the page holds its particles."""
    session = page.evaluate("window.__hmpm.session")
    face, dim = session["wall_thickness"], session["dim"]
    centre = [0.75, face + POUR_SIDE / 2 + 0.01, 0.5][:dim]
    block = {"material": material, "lo": [c - POUR_SIDE / 2 for c in centre], "hi": [c + POUR_SIDE / 2 for c in centre]}
    r = httpx.post(f"{url}/v1/sessions/{session['id']}/blocks", json=block, timeout=60)
    r.raise_for_status()
    page.wait_for_function(f"window.__hmpm.session.num_particles === {r.json()['num_particles']}", timeout=60_000)


def run_case(
    browser,
    url: str,
    scene: str,
    seed: int,
    look: str,
    playing: bool,
    preset: float | str,
    seconds: float,
    dpr: float,
    sync: bool,
    advance: int = 0,
    material: str | None = None,
    solver: str = "mpm",
) -> dict:
    """One case: ``preset`` a resolution (``?scale=``) or a quality (``?quality=auto|1…8``); ``material``: a block of
    it poured first (:func:`pour`); ``solver`` the session's (``realtime``: the page's default, real-time mode)."""
    page = browser.new_page(viewport={"width": 1100, "height": 800}, device_scale_factor=dpr, bypass_csp=True)
    errors: list[str] = []
    page.on("console", lambda m: errors.append(m.text) if m.type == "error" else None)
    fix = f"quality={preset}" if isinstance(preset, str) else f"scale={preset:g}"
    query = (
        f"/?scene={scene}&seed={seed}&solver={solver}&look={look}&{fix}&bench=1"
        + ("" if playing and not advance else "&autoplay=0")
        + ("&sync=1" if sync else "")
    )
    page.goto(url + query)
    page.wait_for_function("window.__hmpm.framesRendered >= 10", timeout=60_000)
    if material:
        pour(url, page, material)
    if advance:  # paused while it steps; a playing case plays from there
        sid = page.evaluate("window.__hmpm.session.id")
        for left in range(advance, 0, -100):
            httpx.post(f"{url}/v1/sessions/{sid}/step", json={"frames": min(100, left)}, timeout=300).raise_for_status()
        page.wait_for_function(f"window.__hmpm.lastFrame >= {advance}", timeout=60_000)
        if playing:
            page.click("#play")
    time.sleep(1.0)  # warm up
    settled_s = settle(page) if preset == "auto" else 0.0
    pids = browser_pids()
    sid = page.evaluate("window.__hmpm.session.id")
    frame0, t0 = httpx.get(f"{url}/v1/sessions/{sid}", timeout=30).json()["frame"], time.monotonic()
    start = page.evaluate("[window.__hmpm.framesRendered, performance.now(), window.__hmpm.view.surfacesDrawn, window.__hmpm.quality.changes.length]")
    cpu0, (busy0, all0), load0 = cpu_seconds(pids), machine_busy(), load_average()[0]
    time.sleep(seconds)
    end = page.evaluate("[window.__hmpm.framesRendered, performance.now(), window.__hmpm.view.surfacesDrawn, window.__hmpm.quality.changes.length]")
    described = httpx.get(f"{url}/v1/sessions/{sid}", timeout=30).json()
    frame1, t1 = described["frame"], time.monotonic()
    realtime = described.get("realtime") or {}
    cpu1, (busy1, all1), load1 = cpu_seconds(pids), machine_busy(), load_average()[0]
    hook = page.evaluate(
        "({drawMs: __hmpm.drawMs, look: __hmpm.look, renderer: __hmpm.renderer, n: __hmpm.session.num_particles, received: __hmpm.framesReceived,"
        " quality: __hmpm.quality, frame: __hmpm.lastFrame})"
    )
    size = page.evaluate("[document.getElementById('sim').width, document.getElementById('sim').height]")
    page.close()
    httpx.delete(f"{url}/v1/sessions/{sid}", timeout=30)
    draw = np.array(hook["drawMs"])
    drawn = max(1, end[0] - start[0])
    browser_cpu = cpu1 - cpu0
    return {
        "fps": (end[0] - start[0]) * 1000.0 / (end[1] - start[1]),
        "sim_fps": (frame1 - frame0) / (t1 - t0),
        "solver": solver,
        "rung": realtime.get("rung"),
        "session_realtime_factor": realtime.get("realtime_factor"),
        "browser_cpu_ms_per_frame": 1000.0 * browser_cpu / drawn,
        "load_average": 0.5 * (load0 + load1),
        "others_cpu_share": max(0.0, (busy1 - busy0) - browser_cpu) / max(1e-9, all1 - all0),
        "draw_ms_median": float(np.median(draw)),
        "draw_ms_p95": float(np.percentile(draw, 95)),
        "particles": hook["n"],
        "look": hook["look"],
        "renderer": hook["renderer"],
        "canvas_px": size,
        "frames_received": hook["received"],
        "frame": hook["frame"],
        "quality_level": hook["quality"]["level"] + 1,
        "quality_label": hook["quality"]["settings"]["label"],
        "quality_changes": [(c["from"] + 1, c["to"] + 1, c["why"], round(c["fps"], 1)) for c in hook["quality"]["changes"]],
        "quality_changes_measured": end[3] - start[3],
        "settle_s": settled_s,
        "surfaces_per_frame": (end[2] - start[2]) / drawn,
        "console_errors": errors,
    }


def ladder(browser, url: str, scene: str, advance: int, rounds: int, seconds: float) -> list[dict]:
    """The quality levels' costs on one page, paused ``advance`` frames in, the camera turning: the levels taken in
    turn (the quality select), ``rounds`` times, so that what else runs on the machine meanwhile falls on every level
    alike; per level the median over the rounds of the browser's CPU per frame drawn and of the frames drawn per
    second, and the splats drawn (the water's particles, or its cells' splats)."""
    page = browser.new_page(viewport={"width": 1100, "height": 800}, bypass_csp=True)
    page.goto(f"{url}/?scene={scene}&solver=mpm&look=fluid&bench=1&autoplay=0&quality=1")
    page.wait_for_function("window.__hmpm.framesRendered >= 2", timeout=60_000)
    sid = page.evaluate("window.__hmpm.session.id")
    for left in range(advance, 0, -100):
        httpx.post(f"{url}/v1/sessions/{sid}/step", json={"frames": min(100, left)}, timeout=300).raise_for_status()
    page.wait_for_function(f"window.__hmpm.lastFrame >= {advance}", timeout=60_000)
    levels = page.evaluate("__hmpm.quality.levels")
    pids = browser_pids()
    got: dict[int, list[tuple[float, float, int]]] = {q: [] for q in range(1, levels + 1)}
    for _ in range(rounds):
        for q in got:
            page.select_option("#quality", str(q))
            time.sleep(0.8)
            a, c0 = page.evaluate("[__hmpm.framesRendered, performance.now()]"), cpu_seconds(pids)
            time.sleep(seconds)
            b, c1 = (
                page.evaluate("[__hmpm.framesRendered, performance.now(), __hmpm.view.lod ? __hmpm.view.splats.count : __hmpm.view.drawn]"),
                cpu_seconds(pids),
            )
            n = max(1, b[0] - a[0])
            got[q].append((1000.0 * (c1 - c0) / n, n * 1000.0 / (b[1] - a[1]), b[2]))
    page.close()
    httpx.delete(f"{url}/v1/sessions/{sid}", timeout=30)
    base = float(np.median([x[0] for x in got[1]]))
    return [
        {
            "level": q,
            "browser_cpu_ms_per_frame": float(np.median([x[0] for x in v])),
            "rounds_ms": [round(x[0], 1) for x in v],
            "relative": float(np.median([x[0] for x in v])) / base,
            "fps": float(np.median([x[1] for x in v])),
            "splats": v[-1][2],
        }
        for q, v in got.items()
    ]


def chromium_version(path: str) -> str:
    try:
        return subprocess.run([path, "--version"], capture_output=True, text=True, timeout=30).stdout.strip()
    except OSError:
        return "?"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seconds", type=float, default=5.0)
    ap.add_argument("--dpr", type=float, default=1.0, help="device pixel ratio of the page (the canvas is 640 CSS px square)")
    ap.add_argument("--cases", default=None, help="comma-separated indices into CASES (default: all)")
    ap.add_argument("--out", default=None, help="write the results here (.json and .md)")
    ap.add_argument("--advance", type=int, default=0, help="step the session this many frames first (paused; playing cases then play)")
    ap.add_argument("--no-sync", action="store_true", help="skip the second run that waits for the GPU (draw + GPU column)")
    ap.add_argument("--ladder", type=int, default=0, help="instead of the cases: the quality levels' costs on paddle3d, this many rounds")
    ap.add_argument("--solver", default="mpm", help="the sessions' solver: mpm (one fixed configuration) or realtime (the page's default)")
    ap.add_argument("--pour", default=None, help="pour a cube of this material (e.g. jello) behind the paddle before each case")
    args = ap.parse_args()
    chromium = os.environ.get("HYBRIDMPM_CHROMIUM") or shutil.which("chromium") or "/usr/bin/chromium"
    if args.ladder:
        with LiveServer(max_sessions=4, log=Path(tempfile.mkdtemp()) / "server.log") as srv, sync_playwright() as p:
            browser = p.chromium.launch(executable_path=chromium, headless=True, args=["--no-sandbox"])
            rows = ladder(browser, srv.url, "paddle3d", args.advance, args.ladder, args.seconds)
            version = browser.version
            browser.close()
        for r in rows:
            print(json.dumps(r))
        if args.out:  # the harness's header says the command, the machine and the load before and after
            lines = [
                "# The quality levels' costs: paddle3d, paused, headless Chromium, software GL",
                "",
                f"{version}: the levels in turn on one page, {args.ladder} rounds, {args.advance} frames in.",
                "",
                "| level | browser CPU / frame [ms] (median) | rounds [ms] | relative | frames/s | splats |",
                "|---:|---:|---|---:|---:|---:|",
                *[
                    f"| {r['level']} | {r['browser_cpu_ms_per_frame']:.1f} | {', '.join(map(str, r['rounds_ms']))} | {r['relative']:.2f} | {r['fps']:.1f} | {r['splats']} |"
                    for r in rows
                ],
            ]
            out = Path(args.out)
            doc = {"chromium": version, "advance": args.advance, "rounds": args.ladder, "seconds": args.seconds, "levels": rows}
            write_results(out.parent, out.stem, doc=doc, markdown="\n".join(lines))
        return
    cases = CASES if args.cases is None else [CASES[int(i)] for i in args.cases.split(",")]
    rows: list[dict] = []
    with LiveServer(max_sessions=16, log=Path(tempfile.mkdtemp()) / "server.log") as srv, sync_playwright() as p:
        browser = p.chromium.launch(executable_path=chromium, headless=True, args=["--no-sandbox"])
        for scene, seed, look, playing, preset in cases:
            # one case, drawn for `seconds` without (or with, `sync`) waiting for the GPU
            case = functools.partial(
                run_case, browser, srv.url, scene, seed, look, playing, preset, dpr=args.dpr, advance=args.advance, material=args.pour, solver=args.solver
            )
            r = case(seconds=args.seconds, sync=False)
            skip = args.no_sync or preset == "auto"  # an auto case would settle again, elsewhere
            r["draw_ms_gpu_median"] = float("nan") if skip else case(seconds=min(args.seconds, 3.0), sync=True)["draw_ms_median"]
            r.update(scene=scene, seed=seed, playing=playing, preset=preset, poured=args.pour)
            rows.append(r)
            print(json.dumps(r), flush=True)
            if args.out:  # after every case: a run cut short keeps what it measured
                write(Path(args.out), rows, args, browser.version, chromium)
        browser.close()


def write(out: Path, rows: list[dict], args: argparse.Namespace, version: str, chromium: str) -> None:
    """The results so far as ``out``.json and ``out``.md (:func:`hybridmpm.bench.harness.write_results`)."""
    res = {
        "chromium": version,
        "chromium_binary": chromium_version(chromium),
        "gl": "SwiftShader (ANGLE, Vulkan), software",
        "dpr": args.dpr,
        "seconds": args.seconds,
        "target_fps": TARGET_FPS,
        "cases": rows,
    }
    lines = [
        "# The page's frame rate in headless Chromium, software GL",
        "",
        f"{version}, SwiftShader (software GL),",
        f"{os.cpu_count()} cores shared by the server, the browser and its GPU process; canvas 640 CSS px × dpr {args.dpr:g}.",
        "frames/s: frames the page drew per second drawing on every animation frame (`?bench=1`);",
        "draw: CPU time of one draw call sequence; draw + GPU: the same waiting for the GPU (`?sync=1`: a 1-pixel `readPixels`);",
        "browser CPU / frame: CPU time of all the browser's processes (SwiftShader draws in the GPU process) per frame drawn;",
        "load: the machine's 1-minute load average; others: the share of the machine's CPU time taken by processes other than",
        "the browser meanwhile (the server included). quality: the level drawn (static/quality.js; `auto`: the level the page",
        "settled on); surfaces: the share of the frames drawn whose water went through the fluid passes; simulation frames/s:",
        "the frames the session advanced while the page watched (400 a second is real time); rung: a real-time session's",
        "configuration at the end (`--solver realtime`), and the real-time factor the session measured of its own frames.",
        "",
        "| scene | particles | look | simulation | preset | quality | canvas [px] | frames/s | draw median [ms] | draw p95 [ms] | draw + GPU median [ms] "
        "| browser CPU / frame [ms] | load | others | simulation frames/s | frame | surfaces | rung | session RTF |",
        "|---|---:|---|---|---|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---|---:|",
    ]
    for r in rows:
        preset = f"quality={r['preset']}" if isinstance(r["preset"], str) else f"scale={r['preset']:g}"
        lines.append(
            f"| {r['scene']} (seed {r['seed']}) | {r['particles']} | {r['look']} | {'playing' if r['playing'] else 'paused'} | {preset} | "
            f"{r['quality_level']}/{QUALITY_LEVELS} | {r['canvas_px'][0]}×{r['canvas_px'][1]} | {r['fps']:.1f} | {r['draw_ms_median']:.1f} | {r['draw_ms_p95']:.1f} "
            f"| {r['draw_ms_gpu_median']:.1f} | {r['browser_cpu_ms_per_frame']:.1f} | {r['load_average']:.1f} | {100 * r['others_cpu_share']:.0f} % "
            f"| {r['sim_fps']:.0f} | {r['frame']} | {100 * r['surfaces_per_frame']:.0f} % | {r.get('rung') or ''} | {r.get('session_realtime_factor') or ''} |"
        )
    write_results(out.parent, out.stem, doc=res, markdown="\n".join(lines))  # the harness's header: the command, the machine, the load


if __name__ == "__main__":
    main()
