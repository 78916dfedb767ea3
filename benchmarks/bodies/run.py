"""Rigid bodies' long checks and cost (docs/bodies.md "Stability" and "Checks").

Three parts, each selectable by name (default: all):

* ``archimedes``: the full-length floating checks of ``rust/mpm/tests/engine/bodies.rs``
  (its ``#[ignore]``d tests, in the ``checks`` profile): boxes of 250 / 500 /
  750 kg/m³ on 128², the last 400 of 1,200 frames, as placed and in held-out
  variations (shifted by a few cells, tilted by 10°); the 500 kg/m³ cube on 32³.
  Per box: the mean share of its area below the level beside it, the worst
  error against ρ_b / ρ_w, the tolerance (one cell + 2 % of its height) / height.
* ``stability``: ``rust/mpm/tests/engine/body_stability.rs`` run for 2,000 frames (a light
  body in a dam break, 20 bodies piled in a 3D tank): the mechanical energy's
  largest rise over its start and its end, as shares of the start.
* ``cost``: ``dam_break3d`` (as the Python scene builds it) with 8 bodies in the
  surge's path against the same scene without them, the two interleaved and
  paired, fresh solvers each repeat: ms per frame and per substep, the ratio of
  the medians and the spread of the paired ratios. A timing: run it on a quiet
  machine.

``python benchmarks/bodies/run.py [archimedes] [stability] [cost] --out benchmarks/results/bodies``
writes ``NAME.json`` and ``NAME.md`` per part there.
"""

from __future__ import annotations

import argparse
import os
import re
import statistics
import subprocess
import time
from pathlib import Path
from typing import Any

from hybridmpm.bench import harness

ROOT = Path(__file__).resolve().parents[2]

#: The floating checks: (name, test, environment).
ARCHIMEDES_CASES = [
    ("boxes 2D as placed", "boxes_float_at_their_archimedes_depth_2d", {}),
    ("boxes 2D shifted 3 cells, tilted 10°", "boxes_float_at_their_archimedes_depth_2d", {"BODIES_SHIFT": "3", "BODIES_TILT": "10"}),
    ("boxes 2D shifted -4 cells", "boxes_float_at_their_archimedes_depth_2d", {"BODIES_SHIFT": "-4"}),
    ("cube 3D as placed", "cube_floats_at_its_archimedes_depth_3d", {}),
    ("cube 3D tilted 10°", "cube_floats_at_its_archimedes_depth_3d", {"BODIES_TILT": "10"}),
]

_SHARE = re.compile(
    r"density (?P<rho>[\d.]+): mean share (?P<mean>[\d.]+) \(expected (?P<exp>[\d.]+)\), worst error (?P<worst>[\d.]+) \(tolerance (?P<tol>[\d.]+)\)"
)
_ENERGY = re.compile(
    r"(?P<name>[^:\n]+): (?P<frames>\d+) frames, energy at start (?P<e0>[\d.]+) J, largest rise (?P<rise>-?[\d.]+) %, at the end (?P<end>[\d.]+) % of the start, most retries in a frame (?P<retries>\d+)"
)


def cargo_test(module: str, name: str | None, env: dict[str, str], ignored: bool) -> tuple[str, bool, float]:
    """Runs one test (or a module's tests) of the engine's test binary in the checks profile; (output, passed, seconds)."""
    cmd = ["cargo", "test", "-q", "-p", "hybridmpm-mpm", "--profile", "checks", "--test", "engine", "--"]
    cmd += ["--nocapture", "--test-threads", "1"] + (["--ignored"] if ignored else []) + (["--exact", f"{module}::{name}"] if name else [f"{module}::"])
    t0 = time.perf_counter()
    proc = subprocess.run(cmd, cwd=ROOT, env={**os.environ, **env}, capture_output=True, text=True, check=False)
    return proc.stdout + proc.stderr, proc.returncode == 0, time.perf_counter() - t0


def archimedes() -> tuple[dict[str, Any], list[str]]:
    rows, lines = [], ["# Bodies: floating at their Archimedes depth (full length)", ""]
    table = []
    for label, test, env in ARCHIMEDES_CASES:
        out, ok, secs = cargo_test("bodies", test, env, ignored=True)
        boxes = [{k: float(v) for k, v in m.groupdict().items()} for m in _SHARE.finditer(out)]
        rows.append({"case": label, "test": test, "env": env, "passed": ok, "seconds": round(secs, 1), "boxes": boxes})
        for b in boxes:
            table.append(
                [
                    label,
                    f"{b['rho']:g}",
                    f"{b['mean']:.4f}",
                    f"{b['exp']:.3f}",
                    f"{b['worst']:.4f}",
                    f"{b['tol']:.4f}",
                    "yes" if b["worst"] <= b["tol"] else "**no**",
                ]
            )
    lines += harness.table(["case", "ρ_b", "mean share", "ρ_b/ρ_w", "worst error", "tolerance", "within"], table)
    return {"cases": rows}, lines


def stability(frames: int) -> tuple[dict[str, Any], list[str]]:
    out, ok, secs = cargo_test("body_stability", None, {"BODY_STABILITY_FRAMES": str(frames)}, ignored=False)
    runs = [
        {
            "case": m["name"].split("... ")[-1].strip(),
            "frames": int(m["frames"]),
            "energy_start_J": float(m["e0"]),
            "largest_rise_percent": float(m["rise"]),
            "end_percent": float(m["end"]),
            "most_retries": int(m["retries"]),
        }
        for m in _ENERGY.finditer(out)
    ]
    lines = ["# Bodies: stability over long runs", ""]
    lines += harness.table(
        ["case", "frames", "energy at start [J]", "largest rise over the start", "at the end", "most retries in a frame"],
        [
            [r["case"], r["frames"], f"{r['energy_start_J']:.3f}", f"{r['largest_rise_percent']:.4f} %", f"{r['end_percent']:.2f} %", r["most_retries"]]
            for r in runs
        ],
    )
    lines += ["", f"All passed (no solver error, energy within 1 % of its start): {'yes' if ok else '**no**'} ({secs:.0f} s)."]
    return {"passed": ok, "seconds": round(secs, 1), "runs": runs}, lines


_COST = re.compile(
    r"cost repeat (?P<rep>\d+) (?P<name>with|without) bodies: (?P<frames>\d+) frames, (?P<substeps>\d+) substeps, (?P<ms_frame>[\d.]+) ms per frame, (?P<ms_sub>[\d.]+) ms per substep"
)


def cost(repeats: int, frames: int) -> tuple[dict[str, Any], list[str]]:
    """``cost_of_eight_bodies_in_dam_break3d`` (rust/mpm/tests/engine/body_stability.rs): the scene
    without and with its 8 bodies, interleaved, paired, fresh solvers each repeat."""
    load_before = harness.load_average()
    env = {"BODY_COST_REPEATS": str(repeats), "BODY_COST_FRAMES": str(frames)}
    out, ok, secs = cargo_test("body_stability", "cost_of_eight_bodies_in_dam_break3d", env, ignored=True)
    load_after = harness.load_average()
    per: dict[str, list[dict[str, float]]] = {"without": [], "with": []}
    for m in _COST.finditer(out):
        per[m["name"]].append({"ms_per_frame": float(m["ms_frame"]), "ms_per_substep": float(m["ms_sub"]), "substeps": int(m["substeps"])})
    if not (ok and per["with"] and len(per["with"]) == len(per["without"])):
        raise SystemExit(f"the cost run failed:\n{out}")
    med = {name: {k: statistics.median(r[k] for r in rs) for k in ("ms_per_frame", "ms_per_substep", "substeps")} for name, rs in per.items()}
    pairs = [b["ms_per_frame"] / a["ms_per_frame"] for a, b in zip(per["without"], per["with"])]
    pairs_sub = [b["ms_per_substep"] / a["ms_per_substep"] for a, b in zip(per["without"], per["with"])]
    ratio = med["with"]["ms_per_frame"] / med["without"]["ms_per_frame"]
    ratio_sub = med["with"]["ms_per_substep"] / med["without"]["ms_per_substep"]
    doc = {
        "frames": frames,
        "repeats": repeats,
        "runs": per,
        "median": med,
        "ratio_of_medians_per_frame": ratio,
        "ratio_of_medians_per_substep": ratio_sub,
        "paired_ratios_per_frame": pairs,
        "paired_ratios_per_substep": pairs_sub,
        "load_before": load_before,
        "load_after": load_after,
        "seconds": round(secs, 1),
    }
    lines = [
        "# Bodies: the cost of 8 bodies in dam_break3d",
        "",
        f"{frames} frames from the release, {repeats} pairs interleaved (fresh solvers, the solver's default threads), load average {load_before[0]:.2f} before and {load_after[0]:.2f} after.",
        "",
    ]
    lines += harness.table(
        ["scene", "ms per frame (median)", "substeps (median)", "ms per substep (median)"],
        [[f"{n} bodies", f"{m['ms_per_frame']:.2f}", f"{m['substeps']:.0f}", f"{m['ms_per_substep']:.3f}"] for n, m in med.items()],
    )
    lines += [
        "",
        f"Ratio of the medians: {ratio:.3f} per frame, {ratio_sub:.3f} per substep; paired ratios per frame {min(pairs):.3f}–{max(pairs):.3f}, per substep {min(pairs_sub):.3f}–{max(pairs_sub):.3f} (target: ≤ 1.2 per frame).",
    ]
    return doc, lines


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("parts", nargs="*", help="archimedes, stability, cost (default: all)")
    ap.add_argument("--out", default=str(ROOT / "benchmarks" / "results" / "bodies"))
    ap.add_argument("--stability-frames", type=int, default=2000)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--cost-frames", type=int, default=200)
    args = ap.parse_args(argv)
    parts = args.parts or ["archimedes", "stability", "cost"]
    unknown = sorted(set(parts) - {"archimedes", "stability", "cost"})
    if unknown:
        ap.error(f"unknown parts {unknown}: choose from archimedes, stability, cost")
    for part in parts:
        if part == "archimedes":
            doc, lines = archimedes()
        elif part == "stability":
            doc, lines = stability(args.stability_frames)
        else:
            doc, lines = cost(args.repeats, args.cost_frames)
        paths = harness.write_results(args.out, part, doc=doc, markdown="\n".join(lines), argv=argv)
        print("\n".join(lines))
        print(f"wrote {paths['json']}")


if __name__ == "__main__":
    main()
