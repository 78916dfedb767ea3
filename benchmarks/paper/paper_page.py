"""docs/paper.md's generated tables and docs/img/paper_*.png, from the results document of
benchmarks/paper/reproduce.py alone (``OUT/results.json``; ``tests/test_paper_page.py`` checks the page against it).

Each generated block of the page stands between ``<!-- paper:begin NAME -->`` and ``<!-- paper:end NAME -->``:
:func:`render_blocks` makes them, :func:`page_blocks` reads them back, :func:`write_page` fills the page and draws the
figures. No experiment runs here."""

from __future__ import annotations

import math
import re
from pathlib import Path
from typing import Any

from paper_numbers import CONTROL_METHODS, PAPER, PAPER_RC

from hybridmpm.bench.harness import save_figure, table, write_file

#: Numbers outside the generated blocks of the page that are not results (the paper's arXiv id).
NOT_RESULTS = ("2505.18926",)


def _f(x: float, nd: int = 3) -> str:
    if x is None or not math.isfinite(x):
        return "–"
    return f"{x:.{nd}g}" if abs(x) < 1e-2 else f"{x:.{nd}f}"


def _ms(x: float) -> str:
    return "–" if not math.isfinite(x) else f"{x:.3f}" if x < 10 else f"{x:.0f}"


def _x(x: float) -> str:
    return "–" if x is None or not math.isfinite(x) else f"{x:.2f}×"


def _pct(x: float, nd: int = 0) -> str:
    return "–" if not math.isfinite(x) else f"{100 * x:+.{nd}f} %"


def _front_words(v: dict[str, Any]) -> str:
    if math.isnan(v["ratio"]):
        return "faster than every plain MPM"
    if math.isinf(v["ratio"]):
        return "slower than full-resolution MPM"
    return f"{_x(v['ratio'])} the front's error at its time"


def _front(v: dict[str, Any]) -> str:
    if math.isnan(v["ratio"]):
        return "faster than every plain MPM"
    if math.isinf(v["ratio"]):
        return "above (full-resolution MPM is as fast)"
    return f"{_x(v['ratio'])} ({'below' if v['below'] else 'above'})"


def _verdict_line(v: str) -> str:
    return f"**Verdict: {v}.**"


def render_blocks(res: dict[str, Any]) -> dict[str, str]:
    """The generated parts of docs/paper.md, by marker name, from ``results.json``'s document alone."""
    c, p, st = res["claims"], res["paper"], res["settings"]
    prov = res["provenance"]
    out: dict[str, str] = {}
    load = prov.get("load_before", [float("nan")])[0], prov.get("load_after", [float("nan")])[0]
    horizon = "the paper's T" if st["scene_frames"] is None else f"at most {st['scene_frames']} frames"
    out["run"] = "\n".join([
        f"Mode: **{res['mode']}** (`{prov['command']}`); held-out seeds {res['seeds']['simulation'][0]}–{res['seeds']['simulation'][-1]} "
        f"(simulations) and {res['seeds']['control'][0]}–{res['seeds']['control'][-1]} (control cases).  ",
        f"Settings: water2d {st['water_seeds']} seed(s) × {st['water_frames']} frames; the other scenes {st['scene_seeds']} seed(s) × "
        f"{horizon}; {st['control_cases']} control cases per scene; "
        f"r_c {', '.join(f'{r:.1f}' for r in st['r_cs'])}.  ",
        f"Machine: {prov['machine']}, {prov['cores']} cores, shared; load average {load[0]:.1f} before, {load[1]:.1f} after; "
        f"hybridmpm {prov['hybridmpm']} (commit {prov['commit']}), onnxruntime {prov['onnxruntime']}.  ",
        f"Run: {prov['started']} to {prov['date']}; this invocation {res['wall_seconds'] / 60:.1f} min, "
        f"the cells' own compute {res['cells_seconds'] / 60:.1f} min (cached cells are reused).",
    ])  # fmt: skip

    out["summary"] = "\n".join(summary_table(res))

    a = c["latency"]
    rows = a["rows"]
    tab = table(
        ["configuration", "r_p", "r_t", "ms / frame", "× network r_p = r_t = 1", "× MPM full", "grid-mass error (mean)", "vs the plain-MPM front"],
        [
            [_label(k, rows, a), f"{rows[k]['r_p']:.3g}", str(rows[k]["r_t"]), _ms(rows[k]["ms_mean"]), _x(rows[k]["ms_mean"] / rows[a["full"]]["ms_mean"]),
             _x(rows[k]["ms_mean"] / rows["mpm_full"]["ms_mean"]), _f(rows[k]["error_mean"]), _front(_vs(c, k)) if rows[k]["kind"] != "mpm" else "–"]
            for k in rows
        ],
        "lccrrrrl",
    )  # fmt: skip
    out["latency"] = "\n".join([
        f"| | paper, {p['latency']['source']} | this machine |", "|---|---:|---:|",
        f"| network r_p = r_t = 1, ms / frame | {p['latency']['full_ms']} | {_ms(rows[a['full']]['ms_mean'])} |",
        f"| network at r_p = 1/1.75, r_t = 2, ms / frame | {p['latency']['paper_ms']} | {_ms(rows[a['paper']]['ms_mean'])} |",
        f"| change | {_pct(-p['latency']['reduction'], 1)} | {_pct(-a['reduction'], 1)} |",
        "", *tab, "", _verdict_line(a["verdict"]),
    ])  # fmt: skip

    b = c["hybrid"]
    h, n = b["hybrid"], b["network"]
    out["hybrid"] = "\n".join([
        f"| over T frames (paper T = {p['hybrid']['T']}; here T = {b['T']}) | paper: hybrid | paper: network r_p = r_t = 1 | hybrid, r_c = {PAPER_RC} | network r_p = r_t = 1 | MPM at r_p |",
        "|---|---:|---:|---:|---:|---:|",
        f"| time for T frames, ms | {p['hybrid']['hybrid_ms']} | {p['hybrid']['network_ms']} | {_ms(h['total_ms'])} | {_ms(n['total_ms'])} | {_ms(b['mpm_rp']['total_ms'])} |",
        f"| grid-mass error at the last frame | {p['hybrid']['hybrid_error']} | {p['hybrid']['network_error']} | {_f(h['error_last'])} | {_f(n['error_last'])} | {_f(b['mpm_rp']['error_last'])} |",
        f"| grid-mass error, mean over the frames | – | – | {_f(h['error_mean'])} | {_f(n['error_mean'])} | {_f(b['mpm_rp']['error_mean'])} |",
        f"| network's share of steps | – | – | {100 * h['neural_share']:.0f} % | {100 * n['neural_share']:.0f} % | 0 % |",
        "",
        f"Hybrid ÷ network: time {_x(b['time_ratio'])} (paper {_x(p['hybrid']['hybrid_ms'] / p['hybrid']['network_ms'])}), error at the last frame "
        f"{_x(b['error_last_ratio'])} (paper {_x(p['hybrid']['hybrid_error'] / p['hybrid']['network_error'])}), mean error {_x(b['error_mean_ratio'])}. "
        f"Hybrid ÷ MPM at r_p: time per frame {_x(b['vs_mpm_rp']['time'])}, mean error {_x(b['vs_mpm_rp']['error'])}. "
        f"Hybrid against the plain-MPM front at its time: {_front(b['vs_front'])}."
        + ("" if not n["failures"] else f" The network alone broke off ({', '.join(n['failures'])}) after {n['frames_done']:.0f} frames on average; its figures are over the frames it made."),
        "", _verdict_line(b["verdict"]),
    ])  # fmt: skip

    sw = c["rc_sweep"]
    pr = p["rc_sweep"]
    paper_at = dict(zip(pr["r_c"], zip(pr["error"], pr["ms"], strict=True), strict=True))
    tab = table(
        ["r_c", "paper: error", "paper: ms / step", "ms / frame", "× MPM at r_p", "grid-mass error (mean)", "× MPM at r_p", "network's share", "vs the plain-MPM front"],
        [
            [f"{r['r_c']:.1f}", paper_at[r["r_c"]][0], paper_at[r["r_c"]][1], _ms(r["ms_mean"]), _x(r["time_vs_mpm_rp"]), _f(r["error_mean"]),
             _x(r["error_vs_mpm_rp"]), f"{100 * r['neural_share']:.0f} %", _front(r["vs_front"])]
            for r in sw["rows"]
        ],
        "crrrrrrrl",
    )  # fmt: skip
    out["rc_sweep"] = "\n".join([
        *tab, "",
        f"MPM at r_p: {_ms(sw['mpm_rp']['ms_mean'])} ms / frame, error {_f(sw['mpm_rp']['error_mean'])}. "
        f"Higher r_c {'lowers the error and raises the time, as in the paper' if sw['trend'] else 'does not both lower the error and raise the time here'}.",
        "", _verdict_line(sw["verdict"]),
    ])  # fmt: skip

    d = c["scenes"]
    tab = table(
        ["scene", "seeds × frames", "MPM full ms / frame", "hybrid ms / frame", "latency change", "× MPM at r_p (time)", "× MPM at r_p (error)", "network's share", "vs the plain-MPM front"],
        [
            [r["scene"], f"{r['seeds']} × {r['frames']}", _ms(r["mpm_full_ms"]), _ms(r["hybrid_ms"]), _pct(r["change"]), _x(r["time_vs_mpm_rp"]),
             _x(r["error_vs_mpm_rp"]), f"{100 * r['neural_share']:.0f} %", _front(r["vs_front"])]
            for r in d["rows"]
        ],
        "lcrrrrrrl",
    )  # fmt: skip
    out["scenes"] = "\n".join([
        *tab, "",
        f"Paper: {_pct(p['scenes']['range'][0])} to {_pct(p['scenes']['range'][1])} latency against MPM (Water-Sand 2D {_paper_example(p, 'water_sand2d')}, "
        f"Sand 3D {_paper_example(p, 'sand3d')}). "
        f"Here: {_pct(d['change_min'])} to {_pct(d['change_max'])}; the hybrid is faster than full-resolution MPM on {d['holds']} of {len(d['rows'])} scenes "
        f"and below the plain-MPM front on {d['below']} of {len(d['rows'])}.",
        "", _verdict_line(d["verdict"]),
    ])  # fmt: skip

    e = c["control"]
    tab = table(
        ["scene", "cases", "paper: constant", "paper: diffusion", "paper: ratio", "none", "constant", "PD", "diffusion", "diffusion ÷ constant", "diffusion ÷ PD", "diffusion better than constant"],
        [
            [r["scene"], r["cases"], PAPER["control"]["constant"][r["scene"]], PAPER["control"]["diffusion"][r["scene"]], _x(r["paper_ratio"]),
             *[_f(r["methods"][m]["rmse_m"]) for m in CONTROL_METHODS], _x(r["diffusion_vs_constant"]), _x(r["diffusion_vs_pd"]), f"{100 * r['better_than_constant']:.0f} %"]
            for r in e["rows"]
        ],
        "lrrrrrrrrrrr",
    )  # fmt: skip
    tab2 = table(
        ["scene", "none", "constant", "PD", "diffusion", "effort g: constant / PD / diffusion"],
        [
            [r["scene"], *[_f(r["methods"][m]["grid_mass_error"]) for m in CONTROL_METHODS],
             " / ".join(f"{r['methods'][m]['effort_mean_g']:.1f}" for m in ("constant", "pd", "diffusion"))]
            for r in e["rows"]
        ],
        "lrrrrr",
    )  # fmt: skip
    out["control"] = "\n".join([
        "Grid RMSE_m̃ at the last step (root mean square over the grid's nodes of the normalised mass difference, `rmse_m`), mean over the cases:", "",
        *tab, "", "The same cases by the relative grid-mass error at the last step (docs/design.md), with the mean effort:", "", *tab2, "",
        _verdict_line(e["verdict"]),
    ])  # fmt: skip
    return out


def summary_table(res: dict[str, Any]) -> list[str]:
    """One line per claim: the paper's figure, this run's, against the strongest plain baseline, the verdict."""
    c, p = res["claims"], res["paper"]
    a, b, sw, d, e = c["latency"], c["hybrid"], c["rc_sweep"], c["scenes"], c["control"]
    ra, lo, hi = a["rows"], sw["rows"][0], sw["rows"][-1]
    pr = p["rc_sweep"]
    below = sum(r["vs_front"]["below"] for r in sw["rows"])
    ctl = e["rows"]
    dc = [r["diffusion_vs_constant"] for r in ctl]
    dp = [r["diffusion_vs_pd"] for r in ctl]
    pc = [r["paper_ratio"] for r in ctl]
    rows = [
        ["r_p, r_t cut the network's latency (water2d)",
         f"{p['latency']['full_ms']} → {p['latency']['paper_ms']} ms ({_pct(-p['latency']['reduction'], 1)})",
         f"{_ms(ra[a['full']]['ms_mean'])} → {_ms(ra[a['paper']]['ms_mean'])} ms ({_pct(-a['reduction'], 1)})",
         f"network at r_p, r_t: {_front_words(a['networks_vs_front'][a['paper']])}", a["verdict"]],
        [f"the hybrid against the network over T frames (here T = {b['T']})",
         f"{p['hybrid']['hybrid_ms']} vs {p['hybrid']['network_ms']} ms; {p['hybrid']['hybrid_error']} vs {p['hybrid']['network_error']}",
         f"{_ms(b['hybrid']['total_ms'])} vs {_ms(b['network']['total_ms'])} ms; {_f(b['hybrid']['error_last'])} vs {_f(b['network']['error_last'])}",
         f"hybrid: {_front_words(b['vs_front'])}; {_x(b['vs_mpm_rp']['time'])} MPM at r_p's time", b["verdict"]],
        [f"higher r_c: lower error, more time (r_c {lo['r_c']:.1f} → {hi['r_c']:.1f})",
         f"{pr['error'][pr['r_c'].index(lo['r_c'])]} → {pr['error'][pr['r_c'].index(hi['r_c'])]}; "
         f"{pr['ms'][pr['r_c'].index(lo['r_c'])]} → {pr['ms'][pr['r_c'].index(hi['r_c'])]} ms",
         f"{_f(lo['error_mean'])} → {_f(hi['error_mean'])}; {_ms(lo['ms_mean'])} → {_ms(hi['ms_mean'])} ms",
         f"below the front at {below} of {len(sw['rows'])} r_c", sw["verdict"]],
        [f"the hybrid's latency against MPM, {len(d['rows'])} scenes", f"{_pct(p['scenes']['range'][0])} to {_pct(p['scenes']['range'][1])}",
         f"{_pct(d['change_min'])} to {_pct(d['change_max'])}", f"below the front on {d['below']} of {len(d['rows'])} scenes", d["verdict"]],
        ["diffusion control against the constant force, grid RMSE at the last step", f"{_x(min(pc))} to {_x(max(pc))}",
         f"{_x(min(dc))} to {_x(max(dc))}; lower on {sum(r['holds'] for r in ctl)} of {len(ctl)} scenes",
         f"against PD {_x(min(dp))} to {_x(max(dp))}; lower on {sum(r['beats_pd'] for r in ctl)} of {len(ctl)}", e["verdict"]],
    ]  # fmt: skip
    return table(["claim", "paper", "this run", "against the strongest plain baseline", "verdict"], rows)


def _paper_example(p: dict[str, Any], scene: str) -> str:
    """One of the paper's examples of claim 4, in its own units (seconds per frame or ms)."""
    ex = p["scenes"]["examples"][scene]
    if ex["mpm_ms"] >= 10:
        times = f"{ex['mpm_ms'] / 1e3:g} s → {ex['hybrid_ms'] / 1e3:g} s per frame"
    else:
        times = f"{ex['mpm_ms']:.2f} ms → {ex['hybrid_ms']:.2f} ms"
    return f"{times}, {_pct(-ex['reduction'], 1)}"


def _label(k: str, rows: dict[str, Any], a: dict[str, Any]) -> str:
    """The latency table's and the chart's name of a water2d configuration."""
    if k == a["full"]:
        return "network r_p = r_t = 1 (16 × 2 variant)"
    if k == a["paper"]:
        return "network r_p = 1/1.75, r_t = 2 (the paper's; 16 × 2 variant)"
    if k == "neural":
        return "network r_p = 1/1.75, r_t = 4 (shipped)"
    return rows[k]["label"]


def _vs(c: dict[str, Any], k: str) -> dict[str, Any]:
    return c["latency"]["networks_vs_front"][k]


BLOCK = re.compile(r"<!-- paper:begin (?P<name>[a-z_]+) -->\n(?P<body>.*?)<!-- paper:end (?P=name) -->", re.S)


def page_blocks(text: str) -> dict[str, str]:
    """The generated blocks of a page, by name (each without its last newline)."""
    return {m["name"]: m["body"].removesuffix("\n") for m in BLOCK.finditer(text)}


def fill_page(text: str, blocks: dict[str, str]) -> str:
    missing = set(blocks) - set(page_blocks(text))
    if missing:
        raise SystemExit(f"docs/paper.md has no markers for {sorted(missing)}")
    return BLOCK.sub(
        lambda m: f"<!-- paper:begin {m['name']} -->\n{blocks.get(m['name'], m['body'].removesuffix(chr(10)))}\n<!-- paper:end {m['name']} -->", text
    )


def draw_figures(res: dict[str, Any], img: Path) -> dict[str, Path]:
    """docs/img/paper_*.png from the results document alone."""
    import matplotlib
    import matplotlib.ticker

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    c = res["claims"]
    written = {}
    # (b) error over time: the hybrid, the network at r_p = r_t = 1, MPM at r_p, first seed
    b = c["hybrid"]
    fig, ax = plt.subplots(figsize=(7, 3.4))
    names = {b["network"]["key"]: "network r_p = r_t = 1", f"hybrid_paper_rc{PAPER_RC:.1f}": f"hybrid, r_c = {PAPER_RC}", "mpm_rp": "MPM at r_p"}
    for k, s in b["series"].items():
        t = [f * 2.5e-3 for f in s["frame"]]
        ax.plot(t, s["error"], label=names.get(k, k), lw=1.3)
        if k.startswith("hybrid"):
            for i in range(1, len(t)):
                if not s["neural"][i]:
                    ax.axvspan(t[i - 1], t[i], color="gold", alpha=0.25, lw=0)
    ax.set_xlabel("simulated time [s]")
    ax.set_ylabel("grid-mass error")
    ax.set_title(f"water2d, seed {b['series_seed']}: error over time (shaded: the hybrid on MPM)")
    ax.legend(fontsize=8)
    written["paper_hybrid_error.png"] = save_figure(fig, img / "paper_hybrid_error.png", dpi=110, bbox_inches="tight")

    # (a, c) error against time per frame on water2d: the front, the networks, the r_c sweep
    a, sw = c["latency"], c["rc_sweep"]
    fig, ax = plt.subplots(figsize=(7, 4))
    fr = a["front"]
    ax.plot([r["ms_mean"] for r in fr], [r["error_mean"] for r in fr], "k--o", ms=4, label="plain-MPM front")
    for r in fr:
        ax.annotate(r["label"].replace("MPM ", ""), (r["ms_mean"], r["error_mean"]), fontsize=6, xytext=(3, 3), textcoords="offset points")
    for k, m in ((a["full"], "s"), (a["paper"], "D"), ("neural", "^")):
        r = a["rows"][k]
        ax.plot(r["ms_mean"], r["error_mean"], m, label=_label(k, a["rows"], a))
    ax.plot([r["ms_mean"] for r in sw["rows"]], [r["error_mean"] for r in sw["rows"]], "-o", color="tab:red", ms=4, label="hybrid, paper's rule, r_c sweep")
    ends = {sw["rows"][0]["r_c"], PAPER_RC, sw["rows"][-1]["r_c"]}
    for r in sw["rows"]:
        if r["r_c"] in ends:
            up = r["r_c"] == PAPER_RC
            ax.annotate(
                f"r_c = {r['r_c']:.1f}", (r["ms_mean"], r["error_mean"]), fontsize=7, color="tab:red", xytext=(4, 5 if up else -11), textcoords="offset points"
            )
    ax.set_xscale("log")
    ax.xaxis.set_major_formatter(matplotlib.ticker.FormatStrFormatter("%g"))
    ax.xaxis.set_minor_formatter(matplotlib.ticker.NullFormatter())
    ax.set_xticks([t for t in (0.1, 0.2, 0.5, 1, 2, 5, 10) if ax.get_xlim()[0] <= t <= ax.get_xlim()[1]])
    ax.set_xlabel("ms per frame (log)")
    ax.set_ylabel("grid-mass error, mean over the rollout")
    ax.set_title("water2d: error against latency, one run")
    ax.legend(fontsize=7)
    written["paper_water2d_front.png"] = save_figure(fig, img / "paper_water2d_front.png", dpi=110, bbox_inches="tight")

    # (d) latency change per scene
    d = c["scenes"]["rows"]
    fig, ax = plt.subplots(figsize=(7, 3.2))
    xs = range(len(d))
    ax.bar([x - 0.2 for x in xs], [100 * r["change"] for r in d], 0.4, label="hybrid vs MPM full")
    ax.bar([x + 0.2 for x in xs], [100 * (r["time_vs_mpm_rp"] - 1) for r in d], 0.4, label="hybrid vs MPM at r_p")
    lo, hi = res["paper"]["scenes"]["range"]
    ax.axhspan(100 * hi, 100 * lo, color="tab:green", alpha=0.15, label=f"paper: {100 * lo:.0f} to {100 * hi:.0f} %")
    ax.axhline(0, color="k", lw=0.8)
    ax.set_xticks(list(xs), [r["scene"] for r in d], fontsize=8, rotation=20)
    ax.set_ylabel("latency change [%]")
    ax.legend(fontsize=7)
    written["paper_scenes_latency.png"] = save_figure(fig, img / "paper_scenes_latency.png", dpi=110, bbox_inches="tight")

    # (e) control: diffusion ÷ constant and ÷ PD against the paper's ratio
    e = c["control"]["rows"]
    fig, ax = plt.subplots(figsize=(7, 3.2))
    xs = range(len(e))
    ax.bar([x - 0.27 for x in xs], [r["paper_ratio"] for r in e], 0.27, label="paper: diffusion ÷ constant")
    ax.bar(list(xs), [r["diffusion_vs_constant"] for r in e], 0.27, label="here: diffusion ÷ constant")
    ax.bar([x + 0.27 for x in xs], [r["diffusion_vs_pd"] for r in e], 0.27, label="here: diffusion ÷ PD")
    ax.axhline(1, color="k", lw=0.8)
    ax.set_xticks(list(xs), [r["scene"] for r in e])
    ax.set_ylabel("ratio of grid RMSE at the last step")
    ax.legend(fontsize=7)
    written["paper_control.png"] = save_figure(fig, img / "paper_control.png", dpi=110, bbox_inches="tight")
    return written


def write_page(res: dict[str, Any], page: Path, img: Path) -> None:
    write_file(page, fill_page(page.read_text(), render_blocks(res)))
    draw_figures(res, img)
