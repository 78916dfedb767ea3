#!/usr/bin/env python3
"""Compare the errors of a fresh ``hybridmpm bench`` run with recorded ones.

    hybridmpm bench water2d --seeds 1 --out /tmp/bench_w2d --quiet
    python benchmarks/compare_errors.py benchmarks/results/bench/water2d/results.csv /tmp/bench_w2d/results.csv

Per method on the seeds both files hold: recorded and new ``error_mean`` /
``error_last``, break-off and MPM share, and the largest difference. Errors do
not depend on the machine's load (latencies do, and are not compared): a
refactoring that changes no trajectory reproduces them to float64 round-off.
Exit status 1 if any error differs by more than ``--tol``.
"""

from __future__ import annotations

import argparse
import csv
import sys


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("recorded")
    ap.add_argument("new")
    ap.add_argument("--tol", type=float, default=1e-12)
    args = ap.parse_args(argv)
    new = {(r["method"], r["seed"]): r for r in csv.DictReader(open(args.new))}
    rec = {(r["method"], r["seed"]): r for r in csv.DictReader(open(args.recorded)) if (r["method"], r["seed"]) in new}
    if not rec:
        print("no method × seed in common", file=sys.stderr)
        return 1
    print("| method | seed | recorded error mean / last | new | break-off | MPM share | largest difference |")
    print("|---|---|---|---|---|---|---|")
    worst = 0.0
    for key in sorted(rec):
        a, b = rec[key], new[key]
        d = max(abs(float(a[k]) - float(b[k])) for k in ("error_mean", "error_last"))
        worst = max(worst, d)
        print(
            f"| {key[0]} | {key[1]} | {float(a['error_mean']):.6f} / {float(a['error_last']):.6f} | {float(b['error_mean']):.6f} / {float(b['error_last']):.6f} "
            f"| {a['failure'] or '–'} / {b['failure'] or '–'} | {float(a['mpm_share']):.3f} / {float(b['mpm_share']):.3f} | {d:.1e} |"
        )
    print(f"\nlargest difference {worst:.1e} over {len(rec)} method × seed cells")
    return 0 if worst <= args.tol else 1


if __name__ == "__main__":
    sys.exit(main())
