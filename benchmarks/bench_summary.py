"""One table over every scene benchmarked by ``hybridmpm bench`` (docs/benchmarks.md).

    python benchmarks/bench_summary.py benchmarks/results/bench --out benchmarks/results/bench/summary.md

Reads ``DIR/*/results.csv``; per scene and method the means over seeds; the
Pareto front recomputed from them (:func:`hybridmpm.bench.pareto_front`).
Prints the tables; ``--out FILE.md`` also writes them there, under the
harness's header (the command, the machine).
"""

from __future__ import annotations

import argparse
import csv
import sys
from collections import defaultdict
from pathlib import Path

import numpy as np

from hybridmpm.bench import pareto_front
from hybridmpm.bench.harness import script_argv, write_results
from hybridmpm.bench.report import CHART_METRICS, front_error_at, mpm_front
from hybridmpm.models import shipped_default


def scene_rows(path: Path) -> list[dict]:
    with open(path) as f:
        cells = list(csv.DictReader(f))
    by: dict[str, list[dict]] = defaultdict(list)
    for c in cells:
        by[c["method"]].append(c)
    rows = []
    for key, cs in by.items():
        r = {"key": key, "label": cs[0]["label"], "kind": cs[0]["kind"], "role": cs[0]["role"], "seeds": len(cs), "frames": cs[0]["frames"]}
        for k in ("error_mean", "error_last", "ms_mean", "particles", "mpm_share", "substeps_per_frame", "mflop_per_frame", *CHART_METRICS):
            r[k] = float(np.mean([float(c[k]) if c.get(k) not in (None, "") else float("nan") for c in cs]))
        r["failures"] = sum(1 for c in cs if c.get("failure"))
        rows.append(r)
    for i in pareto_front([(r["ms_mean"], r["error_mean"]) for r in rows]):
        rows[i]["pareto"] = True
    return rows


def rule_of(row: dict) -> str:
    """The switching rule of the GNS hybrid's row, from its label "hybrid, GNS with its shipped rule (RULE)"."""
    return str(row["label"]).split("(", 1)[-1].rstrip(")")


def default_table(scenes: dict[Path, list[dict]]) -> list[str]:
    """Per scene, the shipped default (what `hybridmpm simulate SCENE` runs, ``models/defaults.json``)
    against MPM at r_p and against each score's plain-MPM front at its time ("on it", or its value ÷ the front's)."""
    out = [
        "",
        "The shipped defaults (`hybridmpm simulate SCENE`, `models/defaults.json`) on these held-out seeds: time and long-horizon "
        'error against MPM at r_p, and each score against its own plain-MPM front at the default\'s time ("on it": the default is '
        "a point of that front; otherwise its value ÷ the front's).",
        "",
        "| scene | shipped default | time × MPM r_p | error × MPM r_p | " + " | ".join(f"`{m}` vs its front" for m in ("error_mean", *CHART_METRICS)) + " |",
        "|---|---|---|---|" + "---|" * (1 + len(CHART_METRICS)),
    ]
    for d, rows in scenes.items():
        key = (shipped_default(d.name).get("config") or {}).get("key")
        k = {r["key"]: r for r in rows}
        if key not in k or "mpm_rp" not in k:
            out.append(f"| {d.name} | {key or 'none shipped'} (not in this run) |" + " – |" * (3 + len(CHART_METRICS)))
            continue
        r, lo = k[key], k["mpm_rp"]
        cells = []
        for m in ("error_mean", *CHART_METRICS):
            front = mpm_front(rows, m)
            if not np.isfinite(r.get(m, float("nan"))) or not front:
                cells.append("–")
            elif key in {q["key"] for q in front}:
                cells.append("on it")
            else:
                f = front_error_at(front, r["ms_mean"], m)
                cells.append("faster than every plain MPM" if not np.isfinite(f) else (f"{r[m] / f:.2f}×" if f > 0 else "front 0"))
        out.append(f"| {d.name} | {r['label']} | {r['ms_mean'] / lo['ms_mean']:.2f} | {r['error_mean'] / lo['error_mean']:.2f} | " + " | ".join(cells) + " |")
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("root", nargs="?", default="benchmarks/results/bench", help="the folder of hybridmpm bench's SCENE/results.csv")
    ap.add_argument("--out", default=None, help="also write the tables here (FILE.md)")
    args = ap.parse_args(argv)
    root = Path(args.root)
    dirs = sorted(d for d in root.iterdir() if (d / "results.csv").is_file())
    scenes = {d: scene_rows(d / "results.csv") for d in dirs}  # each results.csv read once
    out = [
        "| scene | seeds × frames | MPM full ms/frame | MPM r_p error / ms | neural (shipped) error / ms | neural r_p = r_t = 1 error / ms | hybrid r_c = 0.8 error / ms (MPM share) | GNS hybrid, shipped rule: rule, error / ms (MPM share), vs MPM r_p | Pareto front (fastest first) |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for d in dirs:
        rows = scenes[d]
        k = {r["key"]: r for r in rows}

        def cell(key: str, k: dict = k) -> str:
            r = k.get(key)
            return "–" if r is None else f"{r['error_mean']:.3f} / {r['ms_mean']:.2f}"

        full = next((r for r in rows if r["role"] == "full"), None)
        hyb = k.get("hybrid_rc0.8")
        hyb_cell = "–" if hyb is None else f"{cell('hybrid_rc0.8')} ({100 * hyb['mpm_share']:.0f}%)"
        dflt, lo = k.get("hybrid_default"), k["mpm_rp"]
        dflt_cell = (
            "–" if dflt is None else
            f"{rule_of(dflt)}: {cell('hybrid_default')} ({100 * dflt['mpm_share']:.0f}%), "
            f"{dflt['error_mean'] / lo['error_mean']:.2f}× / {dflt['ms_mean'] / lo['ms_mean']:.2f}×"
        )  # fmt: skip
        front = sorted((r for r in rows if r.get("pareto")), key=lambda r: r["ms_mean"])
        out.append(
            f"| {d.name} | {k['mpm_full']['seeds']} × {k['mpm_full']['frames']} | {k['mpm_full']['ms_mean']:.2f} | {cell('mpm_rp')} | {cell('neural')} | "
            f"{'–' if full is None else cell(full['key'])} | "
            f"{hyb_cell} | {dflt_cell} | {'; '.join(r['label'] for r in front)} |"
        )
    out += [
        "",
        "Cost per frame: MPM's measured work (particles × substeps) against the network's arithmetic (dense-layer FLOPs "
        "of one step on the initial graph / r_t, `hybridmpm.bench.cost.gnn_flops`), each with its measured time.",
        "",
        "| scene | MPM full: particles × substeps/frame | ms/frame | ns per particle-substep | MPM r_p: ms/frame | network (shipped): particles, MFLOP/frame | ms/frame | GFLOP/s achieved | network time / MPM full time |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for d in dirs:
        k = {r["key"]: r for r in scenes[d]}
        f, lo, nn = k["mpm_full"], k["mpm_rp"], k["neural"]
        ns = f["ms_mean"] * 1e6 / (f["particles"] * f["substeps_per_frame"])
        out.append(
            f"| {d.name} | {f['particles']:.0f} × {f['substeps_per_frame']:.1f} | {f['ms_mean']:.2f} | {ns:.0f} | {lo['ms_mean']:.2f} | "
            f"{nn['particles']:.0f}, {nn['mflop_per_frame']:.1f} | {nn['ms_mean']:.2f} | {nn['mflop_per_frame'] / nn['ms_mean']:.1f} | "
            f"{nn['ms_mean'] / f['ms_mean']:.2f} |"
        )
    out += [
        "",
        "Against MPM at r_p from the same starts (ratios of the means over seeds): the network alone (and any extra model), "
        "and the GNS hybrid under the rule shipped with its network (`hybrid_default`), with the network's share of its frames.",
        "",
        "| scene | seeds | MPM r_p error | network alone: error × | time × | GNS hybrid, shipped rule (rule) | error × | time × | network's share |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for d in dirs:
        k = {r["key"]: r for r in scenes[d]}
        lo, nn, dflt = k["mpm_rp"], k["neural"], k.get("hybrid_default")
        extra = "".join(
            f" ({key[len('neural_') :]}: {r['error_mean'] / lo['error_mean']:.2f}, time {r['ms_mean'] / lo['ms_mean']:.2f})"
            for key, r in k.items()
            if key.startswith("neural_") and r["role"] not in ("full", "spatial", "temporal", "size")
        )
        hyb = (
            "– | – | – | –" if dflt is None else
            f"{rule_of(dflt)} | {dflt['error_mean'] / lo['error_mean']:.2f} | {dflt['ms_mean'] / lo['ms_mean']:.2f} | "
            f"{100 * (1 - dflt['mpm_share']):.0f}%"
        )  # fmt: skip
        out.append(
            f"| {d.name} | {lo['seeds']} | {lo['error_mean']:.3f} | {nn['error_mean'] / lo['error_mean']:.2f}{extra} | {nn['ms_mean'] / lo['ms_mean']:.2f} | {hyb} |"
        )
    out += [
        "",
        "Against the plain-MPM front (MPM over grids and r_p, the fastest configurations for their error; "
        "`hybridmpm.bench.report.mpm_front`): each method's error ÷ the front's at its time (interpolated in log time; "
        "below 1: more accurate than any plain MPM as fast), and the methods below the front.",
        "",
        "| scene | plain-MPM front (fastest first: ms, error) | neural (shipped) | hybrid r_c = 0.8 | GNS hybrid, shipped rule | classical twin (hybrid, MPM on half the grid) | twin, its own particles | below the front |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for d in dirs:
        rows = scenes[d]
        k = {r["key"]: r for r in rows}
        front = mpm_front(rows)

        def vs(key: str, k: dict = k, front: list = front) -> str:
            r = k.get(key)
            if r is None:
                return "–"
            f = front_error_at(front, r["ms_mean"])
            if not np.isfinite(f):
                return "faster than every plain MPM"
            return "0 (slower than the reference)" if f <= 0 else f"{r['error_mean'] / f:.2f}×"

        below = [
            r["label"] for r in rows
            if r["kind"] != "mpm" and not r["failures"] and np.isfinite(front_error_at(front, r["ms_mean"])) and r["error_mean"] < front_error_at(front, r["ms_mean"])
        ]  # fmt: skip
        members = "; ".join(f"{r['label']} ({r['ms_mean']:.2f}, {r['error_mean']:.3f})" for r in front)
        out.append(
            f"| {d.name} | {members} | {vs('neural')} | {vs('hybrid_rc0.8')} | {vs('hybrid_default')} | {vs('hybrid_coarse')} | {vs('hybrid_coarse_own')} | {'; '.join(below) or 'none'} |"
        )
    out += default_table(scenes)
    print("\n".join(out))
    if args.out:
        path = Path(args.out)
        write_results(path.parent, path.stem, markdown="\n".join(out), argv=script_argv(__file__, argv))
    return 0


if __name__ == "__main__":
    sys.exit(main())
