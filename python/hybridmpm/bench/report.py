"""Tables, charts and the report of a benchmark run (paper Fig. 5, Fig. 7,
Table 2): ``results.csv``, ``threshold_sweep.csv``, ``error_sweep.csv``, ``pareto.png|svg``
(and ``pareto_METRIC.png|svg`` for every other score of
:data:`~hybridmpm.metrics.ROLLOUT_METRICS`), ``error_trajectory.png`` and ``report.md``."""

from __future__ import annotations

import csv
import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from hybridmpm.bench.methods import Method
from hybridmpm.conventions import DT_FRAME
from hybridmpm.metrics import ROLLOUT_METRICS, short_horizon_error
from hybridmpm.render.timeline import mpm_spans

#: Columns of ``results.csv`` (one row per method × seed).
RESULT_COLUMNS = (
    "scene", "method", "label", "kind", "role", "seed", "r_p", "r_t", "r_c", "safeguard", "audit_tol", "params", "model", "particles", "frames",
    "frames_done", "failure", "error_mean", "error_last", "short_error", "sinkhorn", "ke_error", "front_rms", "metric_cost", "ms_median", "ms_p95", "ms_mean", "mpm_share", "switches",
    "substeps_per_frame", "mflop_per_frame", "warmup_frames", "mpm_threads", "nn_threads", "machine", "cores", "hybridmpm", "numpy", "onnxruntime", "python", "commit",
)  # fmt: skip
#: Columns of ``threshold_sweep.csv`` (one row per hybrid threshold, means over seeds).
SWEEP_COLUMNS = ("r_c", "error_mean", "error_last", "ms_mean", "ms_median", "ms_p95", "mpm_share", "switches", "seeds")
#: Columns of ``error_sweep.csv`` (one row per audit tolerance of the "error" rule, means over seeds).
ERROR_SWEEP_COLUMNS = ("audit_tol",) + SWEEP_COLUMNS[1:]
#: The scores drawn beside the long-horizon error, one chart each (``pareto_METRIC.png``) and one column of the report's
#: table of them (``error_last`` is the long-horizon error's last frame: in the main table).
CHART_METRICS = tuple(k for k in ROLLOUT_METRICS if k not in ("error_mean", "error_last"))


def pareto_front(points: Sequence[tuple[float, float]]) -> list[int]:
    """Indices of the Pareto-optimal points when both coordinates are to be
    minimised (latency, error): a point is on the front if no other point is
    at least as good in both and strictly better in one. Points with a
    non-finite coordinate are never on it. Returned in order of latency."""
    pts = [(float(x), float(y)) for x, y in points]
    front = []
    for i, (x, y) in enumerate(pts):
        if not (math.isfinite(x) and math.isfinite(y)):
            continue
        dominated = any((x2 <= x and y2 <= y and (x2 < x or y2 < y)) for j, (x2, y2) in enumerate(pts) if j != i and math.isfinite(x2) and math.isfinite(y2))
        if not dominated:
            front.append(i)
    return sorted(front, key=lambda i: (pts[i][0], pts[i][1]))


def mpm_front(rows: Sequence[dict[str, Any]], metric: str = "error_mean") -> list[dict[str, Any]]:
    """The classical front on ``metric`` (a score of :data:`~hybridmpm.metrics.ROLLOUT_METRICS`):
    the Pareto-optimal plain-MPM rows (every grid and ``r_p`` benchmarked, the
    full-resolution reference included, none that broke off), fastest first."""
    mpm = [r for r in rows if r["kind"] == "mpm" and not r.get("failures")]
    return [mpm[i] for i in pareto_front([(r["ms_mean"], r.get(metric, math.nan)) for r in mpm])]


def front_error_at(front: Sequence[dict[str, Any]], ms: float, metric: str = "error_mean") -> float:
    """The classical front's ``metric`` at a mean latency of ``ms`` per frame:
    linear in log(latency) between the two front points around it (a grid
    between two benchmarked ones), the slowest point's value beyond it, and
    NaN below the fastest (no plain MPM that fast was measured)."""
    pts = [(math.log(r["ms_mean"]), r[metric]) for r in front if r["ms_mean"] > 0 and math.isfinite(r["ms_mean"])]
    if not pts or not (math.isfinite(ms) and ms > 0):
        return float("nan")
    x = math.log(ms)
    if x < pts[0][0]:
        return float("nan")
    for (x0, e0), (x1, e1) in zip(pts, pts[1:]):
        if x0 <= x <= x1:
            return e0 + (e1 - e0) * (x - x0) / (x1 - x0) if x1 > x0 else min(e0, e1)
    return pts[-1][1]


def on_common_frames(cell: dict[str, Any], stride: int) -> dict[str, Any]:
    """``cell`` with ``error_mean`` and ``short_error`` recomputed over the
    frames that are multiples of ``stride`` (the largest ``r_t`` among the
    methods compared): every method is averaged over the same instants,
    whatever its own stride (a per-frame MPM mean and a every-4th-frame
    network mean would otherwise differ by sampling alone). ``error_last`` is
    unchanged; the other scores were computed on those frames
    (:func:`~hybridmpm.bench.run.run_cell`)."""
    f = np.asarray(cell["series"]["frame"])
    e = np.asarray(cell["series"]["error"], np.float64)
    keep = f % int(stride) == 0
    out = dict(cell)
    out["error_mean"] = float(e[keep].mean()) if keep.any() else float(e.mean())
    if keep.any():
        out["short_error"] = short_horizon_error(e[keep], f[keep] * DT_FRAME)
    return out


def aggregate(methods: list[Method], cells: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """One row per method: the method's configuration and the means over its
    seeds of errors, latencies, MPM share and switches, plus ``failures``
    (seeds whose rollout broke off; their errors are over the frames done),
    ``frames_done`` (mean) and ``pareto`` (on the front or not; never for a
    method with a broken-off rollout)."""
    rows = []
    for m in methods:
        cs = [c for c in cells if c["method"] == m.key]
        if not cs:
            continue
        row: dict[str, Any] = {**m.config(), "seeds": len(cs), "particles": float(np.mean([c["particles"] for c in cs]))}
        for k in ("ms_mean", "ms_median", "ms_p95", "mpm_share", "switches", "substeps_per_frame", "mflop_per_frame", "metric_cost", *ROLLOUT_METRICS):
            row[k] = float(np.mean([c.get(k, float("nan")) for c in cs]))
        row["failures"] = sum(1 for c in cs if c["failure"])
        row["frames_done"] = float(np.mean([c["frames_done"] for c in cs]))
        rows.append(row)
    # a rollout that broke off has no error over the whole rollout: it cannot be on the front
    front = set(pareto_front([(r["ms_mean"], r["error_mean"] if not r["failures"] else math.inf) for r in rows]))
    classical = mpm_front(rows)
    on_classical = {r["key"] for r in classical}
    for i, r in enumerate(rows):
        r["pareto"] = i in front
        # the plain-MPM front's error at this method's time (NaN: faster than every plain MPM measured)
        r["front_error"] = front_error_at(classical, r["ms_mean"])
        r["mpm_front"] = r["key"] in on_classical
    # the same on every other score: ``at_front[metric]`` its plain-MPM front's value at the method's time,
    # ``on_front[metric]`` whether the method is on that front
    for r in rows:
        r["at_front"], r["on_front"] = {}, {}
    for metric in CHART_METRICS:
        fr = mpm_front(rows, metric)
        keys = {q["key"] for q in fr}
        for r in rows:
            r["at_front"][metric] = front_error_at(fr, r["ms_mean"], metric) if fr else math.nan
            r["on_front"][metric] = r["key"] in keys
    return rows


def write_results_csv(
    path: Path, scene: str, frames: int, settings: dict[str, Any], env: dict[str, Any], methods: list[Method], cells: list[dict[str, Any]]
) -> None:
    by_key = {m.key: m for m in methods}
    with open(path, "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=RESULT_COLUMNS)
        w.writeheader()
        for c in cells:
            m = by_key[c["method"]]
            row = {**m.config(), **{k: v for k, v in c.items() if k != "series"}, **{k: v for k, v in env.items() if k in RESULT_COLUMNS}}
            row.update(
                scene=scene,
                method=m.key,
                frames=frames,
                warmup_frames=settings["warmup"],
                mpm_threads=settings["mpm_threads"],
                # the networks alone run on their own setting (absent from runs before it: the hybrid's)
                nn_threads=settings.get("nn_alone_threads", settings["nn_threads"]) if m.kind == "neural" else settings["nn_threads"],
            )
            row["failure"] = c["failure"] or ""
            row["r_c"] = "" if m.r_c is None else m.r_c
            row["safeguard"] = m.safeguard or ""
            row["audit_tol"] = "" if m.audit_tol is None else m.audit_tol
            row["model"] = Path(m.model).name if m.model else ""
            w.writerow({k: row.get(k, "") for k in RESULT_COLUMNS})


def _rc_sweep(rows: list[dict[str, Any]]) -> list[dict[str, Any]]:
    return sorted((r for r in rows if r["kind"] == "hybrid" and str(r["key"]).startswith("hybrid_rc")), key=lambda r: r["r_c"])


def _error_sweep(rows: list[dict[str, Any]]) -> list[dict[str, Any]]:
    return sorted((r for r in rows if r["kind"] == "hybrid" and str(r["key"]).startswith("hybrid_err")), key=lambda r: r["audit_tol"])


def sweep_rows(rows: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """The hybrid rows of :func:`aggregate` at each threshold ``r_c`` (the
    "audit" rule) as ``threshold_sweep.csv`` rows, by r_c."""
    return [{k: r[k] for k in SWEEP_COLUMNS} for r in _rc_sweep(rows)]


def error_sweep_rows(rows: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """The "error" rule's rows of :func:`aggregate` as ``error_sweep.csv`` rows, by audit tolerance."""
    return [{k: r[k] for k in ERROR_SWEEP_COLUMNS} for r in _error_sweep(rows)]


def write_sweep_csv(path: Path, rows: list[dict[str, Any]]) -> None:
    """``threshold_sweep.csv`` at ``path`` and ``error_sweep.csv`` beside it."""
    for p, cols, sweep in ((path, SWEEP_COLUMNS, sweep_rows(rows)), (path.with_name("error_sweep.csv"), ERROR_SWEEP_COLUMNS, error_sweep_rows(rows))):
        with open(p, "w", newline="") as f:
            w = csv.DictWriter(f, fieldnames=cols)
            w.writeheader()
            for r in sweep:
                w.writerow(r)


_STYLE = {
    "reference": ("*", "black"),
    "mpm_rp": ("s", "tab:gray"),
    "mpm_grid": ("h", "dimgray"),
    "large_step": ("P", "tab:cyan"),
    "lowres": ("^", "tab:red"),
    "full": ("v", "tab:purple"),
    "spatial": ("<", "tab:brown"),
    "temporal": (">", "tab:pink"),
    "size": ("D", "tab:olive"),
}


def plot_pareto(path_png: Path, rows: list[dict[str, Any]], title: str, metric: str = "error_mean") -> None:
    """``metric`` (y; a score of :data:`~hybridmpm.metrics.ROLLOUT_METRICS`,
    default the long-horizon grid-mass error) against mean latency per frame
    (x, log): one marker per method, the hybrid thresholds joined as a curve,
    the plain-MPM front dashed, the Pareto front on that metric highlighted
    (methods whose rollouts broke off are never on it)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(11.0, 5.0), dpi=110)

    def y(r: dict[str, Any]) -> float:
        return float(r.get(metric, math.nan))

    on = set(pareto_front([(r["ms_mean"], y(r) if not r["failures"] else math.inf) for r in rows]))
    front = sorted((r for i, r in enumerate(rows) if i in on), key=lambda r: r["ms_mean"])
    if front:
        ax.plot(
            [r["ms_mean"] for r in front],
            [y(r) for r in front],
            "-",
            color="gold",
            lw=7,
            alpha=0.45,
            zorder=1,
            label="Pareto front",
            drawstyle="steps-post",
        )
    classical = mpm_front(rows, metric)
    if classical:
        ax.plot(
            [r["ms_mean"] for r in classical],
            [y(r) for r in classical],
            "--",
            color="black",
            lw=1.2,
            zorder=2,
            label="plain-MPM front (grids × r_p)",
        )
    hyb = _rc_sweep(rows)
    if hyb:
        ax.plot([r["ms_mean"] for r in hyb], [y(r) for r in hyb], "o-", color="tab:blue", ms=5, zorder=3, label="hybrid, r_c = 0 … 0.9 (s(t) + audit)")
        for r in hyb:
            ax.annotate(f"{r['r_c']:.1f}", (r["ms_mean"], y(r)), textcoords="offset points", xytext=(4, 3), fontsize=7, color="tab:blue")
    err = _error_sweep(rows)
    if err:
        ax.plot([r["ms_mean"] for r in err], [y(r) for r in err], "s--", color="tab:cyan", ms=5, zorder=3, label="hybrid, error rule, audit tol [g]")
        for r in err:
            ax.annotate(f"{r['audit_tol']:g} g", (r["ms_mean"], y(r)), textcoords="offset points", xytext=(4, -9), fontsize=7, color="teal")
    for r in rows:
        if str(r["key"]).startswith(("hybrid_rc", "hybrid_err")):
            continue
        if r.get("cheap", "neural") != "neural":
            marker, color = "X", "dimgray"  # the classical twin
        elif r["kind"] == "hybrid":
            marker, color = ("P" if r["key"] == "hybrid_paper" else "X", "tab:blue")
        else:
            marker, color = _STYLE.get(r["role"], ("o", "tab:green"))
        broke = r["failures"] > 0
        label = r["label"] + (f" — broke off ({r['failures']}/{r['seeds']} seeds, ~{r['frames_done']:.0f} frames)" if broke else "")
        ax.plot(
            r["ms_mean"], y(r), marker, color=color, mfc="none" if broke else color, mew=1.5,
            ms=10 if marker == "*" else 8, zorder=4, label=label, ls="none",
        )  # fmt: skip
    for r in front:
        ax.plot(r["ms_mean"], y(r), "o", mfc="none", mec="darkorange", ms=14, mew=1.5, zorder=5)
    for r in rows:
        if r.get("shipped_default"):
            ax.plot(r["ms_mean"], y(r), "*", mfc="none", mec="red", ms=22, mew=1.8, zorder=6, ls="none", label=f"shipped default: {r['label']}")
    ax.set_xscale("log")
    from matplotlib.ticker import FormatStrFormatter

    ax.xaxis.set_major_formatter(FormatStrFormatter("%g"))
    ax.xaxis.set_minor_formatter(FormatStrFormatter("%g"))
    ax.tick_params(axis="x", which="minor", labelsize=7)
    ax.set_xlabel("latency per frame [ms] (mean over frames after warm-up, mean over seeds)")
    ax.set_ylabel(ROLLOUT_METRICS[metric])
    ax.set_title(title, fontsize=10)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.01, 1.0), borderaxespad=0.0)
    fig.tight_layout()
    fig.savefig(path_png)
    fig.savefig(path_png.with_suffix(".svg"))
    plt.close(fig)


def plot_metric_charts(out: Path, rows: list[dict[str, Any]], title: str) -> dict[str, str]:
    """``pareto_METRIC.png|svg`` in ``out`` for every score of
    :data:`CHART_METRICS` some method measured (``front_rms`` on the dam
    break only), drawn as ``pareto.png`` is; returns ``{file: caption}``."""
    files = {}
    for metric in CHART_METRICS:
        if not any(math.isfinite(r.get(metric, math.nan)) for r in rows):
            continue
        plot_pareto(out / f"pareto_{metric}.png", rows, title, metric)
        files[f"pareto_{metric}.png"] = f"{ROLLOUT_METRICS[metric]} against latency, every method, with the plain-MPM front on it"
    return files


def plot_error_trajectory(path: Path, cells: dict[str, dict[str, Any]], labels: dict[str, str], dt_frame: float, title: str) -> None:
    """Error over time for the given cells (one seed): neural, MPM at r_p and
    hybrid; the frames the hybrid ran on MPM shaded (paper Fig. 7)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7.5, 3.8), dpi=110)
    colors = {"neural": "tab:red", "mpm_rp": "tab:gray"}
    for key, c in cells.items():
        t = np.asarray(c["series"]["frame"]) * dt_frame
        e = np.asarray(c["series"]["error"])
        color = colors.get(key, "tab:blue")
        ax.plot(t, e, "-", color=color, lw=1.4, label=f"{labels[key]}: mean {np.mean(e):.3f}, {c['ms_mean']:.2f} ms/frame")
        if key.startswith("hybrid"):
            tags = np.where(np.asarray(c["series"]["neural"], bool), "neural", "mpm")
            step = (t[1] - t[0]) if len(t) > 1 else dt_frame
            for i, (a, b) in enumerate(mpm_spans(tags)):  # a step's positions cover the step before them
                ax.axvspan(t[a] - step, t[b - 1], color="gold", alpha=0.25, lw=0, label="hybrid on MPM" if i == 0 else None)
    ax.set_xlabel("simulated time [s]")
    ax.set_ylabel("grid-mass error")
    ax.set_title(title, fontsize=10)
    ax.grid(True, alpha=0.3)
    ax.legend(fontsize=7, loc="upper left")
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def _fmt(x: float, nd: int = 3) -> str:
    return "–" if x is None or not math.isfinite(x) else f"{x:.{nd}f}"


def report_markdown(
    scene: str,
    settings: dict[str, Any],
    env: dict[str, Any],
    seeds: Sequence[int],
    rows: list[dict[str, Any]],
    command: str,
    files: dict[str, str],
    *,
    n_grid: int | None = None,
    refused: dict[int, str] | None = None,
) -> str:
    """``report.md``: settings, machine, the method table, the Table-2-like
    threshold sweep, the charts, the methods on the Pareto front and every
    method against the plain-MPM front (``n_grid`` the scene's grid,
    ``refused`` the coarser grids the scene refused and why)."""
    front = [r["label"] for r in sorted((r for r in rows if r["pareto"]), key=lambda r: r["ms_mean"])]
    lines = [
        f"# Benchmark: {scene}",
        "",
        f"Command: `{command}`  ",
        f"Seeds (held-out initial conditions): {', '.join(map(str, seeds))}; {settings['frames']} frames per rollout; "
        f"latency excludes the first {settings['warmup']} frames and start-up.  ",
        f"Machine: {env['machine']}, {env['cores']} cores; MPM threads {settings['mpm_threads'] or 'all'}, onnxruntime threads "
        f"{settings['nn_threads'] or 'all'} in the hybrid, {settings.get('nn_alone_threads', settings['nn_threads']) or 'all'} for the networks alone.  ",
        f"Versions: hybridmpm {env['hybridmpm']} (commit {env['commit']}), numpy {env['numpy']}, onnxruntime {env['onnxruntime']}, Python {env['python']}.",
        "",
        "Error: grid-mass error against full-resolution MPM from the same initial condition (docs/design.md), mean over the "
        "rollout (at the frames every method produces: multiples of the largest r_t) and at the last frame, mean over seeds. Latency: wall time per frame [ms]; the chart plots the mean. "
        "A network run alone breaks off when its graph collapses (more than 8× the initial neighbours per particle): "
        "such a method is drawn hollow and is not eligible for the Pareto front. Network MFLOP/frame: dense layers on "
        "the initial graph / r_t (a collapsing graph costs more).",
        "",
        "| method | grid | r_p | r_t | r_c | particles | error mean | error last | ms/frame mean | median | p95 | MPM share | MPM substeps/frame | network MFLOP/frame | "
        "plain-MPM front's error at its time | Pareto |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        err = "reference" if r["role"] == "reference" else _fmt(r["error_mean"])
        fail = f" (broke off in {r['failures']}/{r['seeds']} seeds: error over ~{r['frames_done']:.0f} frames)" if r["failures"] else ""
        lines.append(
            f"| {r['label']}{fail} | {r.get('n_grid') or n_grid} | {r['r_p']:.3g} | {r['r_t']} | {'' if r['r_c'] is None else format(r['r_c'], '.1f')} | {r['particles']:.0f} | {err} | "
            f"{'–' if r['role'] == 'reference' else _fmt(r['error_last'])} | {_fmt(r['ms_mean'], 2)} | {_fmt(r['ms_median'], 2)} | "
            f"{_fmt(r['ms_p95'], 2)} | {100 * r['mpm_share']:.0f}% | {_fmt(r['substeps_per_frame'], 1) if r['kind'] == 'mpm' else ''} | "
            f"{_fmt(r['mflop_per_frame'], 1) if r['kind'] != 'mpm' else ''} | {_vs_front(r)} | {'**yes**' if r['pareto'] else ''} |"
        )
    sw = sweep_rows(rows)
    lines += _sweep_table("Hybrid threshold sweep (paper Table 2)", "threshold r_c", [f"{r['r_c']:.1f}" for r in sw], sw)
    es = error_sweep_rows(rows)
    lines += _sweep_table(
        'The error rule\'s tolerance sweep (docs/hybrid.md "Switching rules")', "audit tolerance [g]", [f"{r['audit_tol']:g}" for r in es], es
    )
    lines += ["", "## Charts", ""]
    for name, cap in files.items():
        lines.append(f"![{cap}]({name})")
        lines.append("")
    lines += ["## Pareto front", "", "On the front (fastest first): " + "; ".join(front) + ".", ""]
    lines += _classical_section(rows, refused or {})
    lines += _metrics_section(rows)
    return "\n".join(lines)


def _vs_front(r: dict[str, Any]) -> str:
    """A row's cell "front error (its error ÷ it)": the plain-MPM front at the row's time."""
    if r.get("mpm_front"):
        return "on it"
    f = r.get("front_error", float("nan"))
    if not math.isfinite(f):
        return "faster than every plain MPM"
    if f <= 0:
        return "0 (slower than the full-resolution reference)"
    return f"{f:.3f} ({r['error_mean'] / f:.2f}×)"


def _classical_section(rows: list[dict[str, Any]], refused: dict[int, str]) -> list[str]:
    """The report's comparison with the classical front: which plain-MPM
    configurations make it, and every other method's error against it at
    equal time (interpolated in log time between front points)."""
    classical = sorted((r for r in rows if r.get("mpm_front")), key=lambda r: r["ms_mean"])
    if not classical:
        return []
    lines = [
        "## Against the plain-MPM front",
        "",
        "The classical front: plain MPM over grids and r_p (the fastest configurations for their error): "
        + "; ".join(f"{r['label']} ({r['ms_mean']:.2f} ms, error {r['error_mean']:.3f})" for r in classical)
        + ". A method earns its place only below it: its error at its time against the front's, interpolated in log time between two "
        "front points (the front's slowest point beyond it).",
        "",
    ]
    below = [r for r in rows if r["kind"] != "mpm" and not r["failures"] and math.isfinite(r["front_error"]) and r["error_mean"] < r["front_error"]]
    faster = [r for r in rows if r["kind"] != "mpm" and not r["failures"] and not math.isfinite(r["front_error"])]
    lines.append(
        "Below the front (more accurate than plain MPM at equal time): " + ("; ".join(f"{r['label']} ({_vs_front(r)})" for r in below) or "none") + "."
    )
    if faster:
        lines.append("")
        lines.append("Faster than every plain MPM measured (no front to compare with): " + "; ".join(r["label"] for r in faster) + ".")
    for n, why in sorted(refused.items()):
        lines += ["", f"Not run on a {n} grid: {why}"]
    lines.append("")
    return lines


def _g(x: float) -> str:
    return "–" if x is None or not math.isfinite(x) else f"{x:.3g}"


def _vs_metric_front(r: dict[str, Any], metric: str) -> str:
    """A row's cell "value (÷ the plain-MPM front's at its time)" on ``metric``."""
    v = r.get(metric, math.nan)
    if not math.isfinite(v):
        return "–"
    if r.get("on_front", {}).get(metric):
        return f"{_g(v)} (on it)"
    f = r.get("at_front", {}).get(metric, math.nan)
    if not math.isfinite(f):
        return f"{_g(v)} (faster than every plain MPM)"
    return f"{_g(v)} ({v / f:.2f}×)" if f > 0 else f"{_g(v)} (front 0)"


def _metrics_section(rows: list[dict[str, Any]]) -> list[str]:
    """The report's table of the scores of a chaotic flow (docs/benchmarks.md
    "Metrics for a chaotic flow"): each method's value and its ratio to the
    plain-MPM front's at its time, the methods below each front, and what the
    metrics cost per rollout."""
    metrics = [m for m in CHART_METRICS if any(math.isfinite(r.get(m, math.nan)) for r in rows)]
    if not metrics:
        return []
    lines = [
        "## Metrics for a chaotic flow",
        "",
        "Beside the long-horizon grid-mass error: " + "; ".join(f"`{m}`: {ROLLOUT_METRICS[m]}" for m in metrics) + ". Each value with its "
        "ratio to the plain-MPM front's on the same metric at the method's time (`pareto_METRIC.png`); the metrics' cost is their wall time "
        'over a rollout ÷ the rollout\'s own (docs/benchmarks.md "Metrics for a chaotic flow").',
        "",
        "| method | ms/frame | " + " | ".join(metrics) + " | metrics' cost ÷ rollout |",
        "|---|---|" + "---|" * len(metrics) + "---|",
    ]
    for r in rows:
        cells = ["reference" if r["role"] == "reference" and m != "front_rms" else _vs_metric_front(r, m) for m in metrics]
        lines.append(f"| {r['label']} | {_fmt(r['ms_mean'], 2)} | " + " | ".join(cells) + f" | {_fmt(r.get('metric_cost', math.nan), 2)} |")
    lines.append("")
    for m in metrics:
        below = [
            r["label"] for r in rows
            if r["kind"] != "mpm" and not r["failures"] and math.isfinite(r.get("at_front", {}).get(m, math.nan)) and r[m] < r["at_front"][m]
        ]  # fmt: skip
        lines.append(f"Below the plain-MPM front on `{m}`: " + ("; ".join(below) or "none") + ".  ")
    lines.append("")
    return lines


def default_section(scene: str, rows: list[dict[str, Any]]) -> list[str]:
    """The report's section on the scene's shipped default (the row flagged
    ``shipped_default``: what ``hybridmpm simulate SCENE`` runs): its time and
    every score against MPM at ``r_p`` and against each score's plain-MPM
    front at its time. Empty where no row is flagged."""
    d = next((r for r in rows if r.get("shipped_default")), None)
    lo = next((r for r in rows if r["key"] == "mpm_rp"), None)
    if d is None or lo is None:
        return []
    metrics = ["error_mean", *(m for m in CHART_METRICS if math.isfinite(d.get(m, math.nan)))]

    def front_cell(m: str) -> str:
        on = d.get("mpm_front") if m == "error_mean" else d.get("on_front", {}).get(m)
        if on:
            return "on it"
        f = d.get("front_error", math.nan) if m == "error_mean" else d.get("at_front", {}).get(m, math.nan)
        if not math.isfinite(f):
            return "faster than every plain MPM"
        return f"{_g(f)} ({d[m] / f:.2f}×)" if f > 0 else f"{_g(f)}"

    lines = [
        "## The shipped default",
        "",
        f"`hybridmpm simulate {scene}` runs **{d['label']}** (`models/defaults.json`, chosen on validation seeds by "
        "`benchmarks/release/ship_defaults.py`; the red star on every chart). On these seeds it takes "
        f"{d['ms_mean']:.2f} ms per frame, {d['ms_mean'] / lo['ms_mean']:.2f}× MPM at r_p's time.",
        "",
        "| score | shipped default | MPM at r_p | default ÷ MPM at r_p | the score's plain-MPM front at the default's time (default ÷ it) |",
        "|---|---|---|---|---|",
    ]
    for m in metrics:
        v, ref = d.get(m, math.nan), lo.get(m, math.nan)
        ratio = f"{v / ref:.2f}" if math.isfinite(v) and math.isfinite(ref) and ref > 0 else "–"
        lines.append(f"| `{m}` | {_g(v)} | {_g(ref)} | {ratio} | {front_cell(m)} |")
    lines.append("")
    return lines


def _sweep_table(title: str, head: str, thresholds: list[str], sweep: list[dict[str, Any]]) -> list[str]:
    """A report section: one column per threshold of a hybrid sweep (error, time, MPM share); none for an empty sweep."""
    if not sweep:
        return []
    return [
        "",
        f"## {title}",
        "",
        f"| {head} | " + " | ".join(thresholds) + " |",
        "|---|" + "---|" * len(sweep),
        "| grid-mass error | " + " | ".join(_fmt(r["error_mean"], 4) for r in sweep) + " |",
        "| time per frame (ms) | " + " | ".join(_fmt(r["ms_mean"], 3) for r in sweep) + " |",
        "| share of frames on MPM | " + " | ".join(f"{100 * r['mpm_share']:.0f}%" for r in sweep) + " |",
    ]


def peer_markdown(res: dict[str, Any]) -> str:
    """The report's section on the Taichi peer (``peer_taichi.json``, ``benchmarks/taichi_peer.py --bench-scene``)."""
    return (
        "\n## Peer: Taichi CPU MLS-MPM (same scene, seed and run)\n\n"
        f"Taichi {res['taichi']} ({res['arch']}, {res['threads']} threads): {res['particles']} particles, "
        f"mean {res['ms_mean']:.2f} ms/frame (median {res['ms_median']:.2f}, p95 {res['ms_p95']:.2f}) against our MPM at full "
        f"resolution {res['ours_ms_mean']:.2f} ms/frame in the same run: ratio {res['ms_mean'] / res['ours_ms_mean']:.2f}. "
        "Taichi's MPM here is the textbook MLS-MPM (same grid, substeps, materials approximated: see benchmarks/taichi_peer.py).\n"
    )
