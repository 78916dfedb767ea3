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
server simulating on the same cores), at the resolution software GL starts
with (3/4 of a CSS pixel), at full resolution and (water) at half, the 2D
dam break, the 3D dam break (23,520 particles; cases 10-15) and the page's
default 3D scene, paddle3d (the same water and a paddle; cases 16-19). The
page's target is 50 frames/s. Playing, it also reports the simulation frames
the session advanced per second while the page watched (the session's
``frame`` from ``GET /v1/sessions/{id}`` before and after).

    python benchmarks/bench_page.py [--seconds 5] [--dpr 1] [--out benchmarks/results/page]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import shutil
import subprocess
import tempfile
import time
from pathlib import Path

import httpx
import numpy as np
from playwright.sync_api import sync_playwright

from hybridmpm.service.testing import LiveServer

TARGET_FPS = 50.0
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
]


def run_case(browser, url: str, scene: str, seed: int, look: str, playing: bool, scale: float, seconds: float, dpr: float, sync: bool) -> dict:
    page = browser.new_page(viewport={"width": 1100, "height": 800}, device_scale_factor=dpr, bypass_csp=True)
    errors: list[str] = []
    page.on("console", lambda m: errors.append(m.text) if m.type == "error" else None)
    query = f"/?scene={scene}&seed={seed}&solver=mpm&look={look}&scale={scale:g}&bench=1" + ("" if playing else "&autoplay=0") + ("&sync=1" if sync else "")
    page.goto(url + query)
    page.wait_for_function("window.__hmpm.framesRendered >= 10", timeout=60_000)
    time.sleep(1.0)  # warm up
    pids = browser_pids()
    sid = page.evaluate("window.__hmpm.session.id")
    frame0, t0 = httpx.get(f"{url}/v1/sessions/{sid}", timeout=30).json()["frame"], time.monotonic()
    start = page.evaluate("[window.__hmpm.framesRendered, performance.now()]")
    cpu0, (busy0, all0), load0 = cpu_seconds(pids), machine_busy(), os.getloadavg()[0]
    time.sleep(seconds)
    end = page.evaluate("[window.__hmpm.framesRendered, performance.now()]")
    frame1, t1 = httpx.get(f"{url}/v1/sessions/{sid}", timeout=30).json()["frame"], time.monotonic()
    cpu1, (busy1, all1), load1 = cpu_seconds(pids), machine_busy(), os.getloadavg()[0]
    hook = page.evaluate(
        "({drawMs: __hmpm.drawMs, look: __hmpm.look, renderer: __hmpm.renderer, n: __hmpm.session.num_particles, received: __hmpm.framesReceived})"
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
        "console_errors": errors,
    }


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
    args = ap.parse_args()
    chromium = os.environ.get("HYBRIDMPM_CHROMIUM") or shutil.which("chromium") or "/usr/bin/chromium"
    cases = CASES if args.cases is None else [CASES[int(i)] for i in args.cases.split(",")]
    rows = []
    with LiveServer(max_sessions=16, log=Path(tempfile.mkdtemp()) / "server.log") as srv, sync_playwright() as p:
        browser = p.chromium.launch(executable_path=chromium, headless=True, args=["--no-sandbox"])
        for scene, seed, look, playing, scale in cases:
            r = run_case(browser, srv.url, scene, seed, look, playing, scale, args.seconds, args.dpr, sync=False)
            r["draw_ms_gpu_median"] = run_case(browser, srv.url, scene, seed, look, playing, scale, min(args.seconds, 3.0), args.dpr, sync=True)[
                "draw_ms_median"
            ]
            r.update(scene=scene, seed=seed, playing=playing, scale=scale)
            rows.append(r)
            print(json.dumps(r))
        version = browser.version
        browser.close()
    res = {
        "chromium": version,
        "chromium_binary": chromium_version(chromium),
        "gl": "SwiftShader (ANGLE, Vulkan), software",
        "dpr": args.dpr,
        "seconds": args.seconds,
        "target_fps": TARGET_FPS,
        "machine": platform.machine(),
        "cpus": os.cpu_count(),
        "cases": rows,
    }
    if args.out:
        out = Path(args.out)
        out.with_suffix(".json").write_text(json.dumps(res, indent=1) + "\n")
        lines = [
            "# The page's frame rate in headless Chromium, software GL",
            "",
            f"`python benchmarks/bench_page.py --seconds {args.seconds:g} --dpr {args.dpr:g}{f' --cases {args.cases}' if args.cases else ''}` — {version}, "
            "SwiftShader (software GL),",
            f"{os.cpu_count()} cores shared by the server, the browser and its GPU process; canvas 640 CSS px × dpr {args.dpr:g}.",
            "frames/s: frames the page drew per second drawing on every animation frame (`?bench=1`);",
            "draw: CPU time of one draw call sequence; draw + GPU: the same waiting for the GPU (`?sync=1`: a 1-pixel `readPixels`);",
            "browser CPU / frame: CPU time of all the browser's processes (SwiftShader draws in the GPU process) per frame drawn;",
            "load: the machine's 1-minute load average; others: the share of the machine's CPU time taken by processes other than",
            "the browser meanwhile (the server included).",
            "",
            "| scene | particles | look | simulation | resolution | canvas [px] | frames/s | draw median [ms] | draw p95 [ms] | draw + GPU median [ms] "
            "| browser CPU / frame [ms] | load | others | simulation frames/s |",
            "|---|---:|---|---|---:|---|---:|---:|---:|---:|---:|---:|---:|---:|",
        ]
        for r in rows:
            lines.append(
                f"| {r['scene']} (seed {r['seed']}) | {r['particles']} | {r['look']} | {'playing' if r['playing'] else 'paused'} | {r['scale']:g} | "
                f"{r['canvas_px'][0]}×{r['canvas_px'][1]} | {r['fps']:.1f} | {r['draw_ms_median']:.1f} | {r['draw_ms_p95']:.1f} | {r['draw_ms_gpu_median']:.1f} "
                f"| {r['browser_cpu_ms_per_frame']:.1f} | {r['load_average']:.1f} | {100 * r['others_cpu_share']:.0f} % | {r['sim_fps']:.0f} |"
            )
        out.with_suffix(".md").write_text("\n".join(lines) + "\n")


if __name__ == "__main__":
    main()
