"""The ``hybridmpm`` command line: measurement: error against latency for every method (``bench``), the cheapest configuration within a budget (``tune``), the failure cases (``stress``)."""

from __future__ import annotations

import argparse
import json
import sys
from typing import Any

from hybridmpm.cli.common import out_dir, out_file, parse_seed, seed_range
from hybridmpm.errors import HybridMpmError

#: Most seeds one ``bench`` or ``tune`` runs (``--seeds``): each is a whole benchmark of every method.
MAX_SEEDS = 10_000


def _bench_kwargs(args: argparse.Namespace) -> dict:
    # import time: loaded by this command only
    from hybridmpm.bench import ERROR_TOL_SWEEP, R_C_SWEEP

    def numbers(field: str, text: str) -> tuple[float, ...]:
        try:
            return tuple(float(x) for x in text.split(",") if x.strip())
        except ValueError:
            raise HybridMpmError(f"{field}: expected comma-separated numbers, got {text!r}") from None

    r_cs = R_C_SWEEP if args.r_c is None else numbers("r_c", args.r_c)
    tols = ERROR_TOL_SWEEP if args.error_tols is None else numbers("error_tols", args.error_tols)
    return {
        "frames": args.frames, "r_cs": r_cs, "error_tols": tols, "model": args.model, "variants": not args.no_variants,
        "extra_models": tuple(args.extra_model or ()), "warmup": args.warmup, "mpm_threads": args.threads, "nn_threads": args.nn_threads,
        "nn_alone_threads": args.nn_alone_threads,
    }  # fmt: skip


def _bench(args: argparse.Namespace) -> int:
    # import time: loaded by this command only
    from hybridmpm.bench import TEST_SEED0, bench

    seeds = seed_range(TEST_SEED0 if args.first_seed is None else args.first_seed, args.seeds, "--first-seed", "--seeds", MAX_SEEDS)
    out = out_dir(args.out if args.out is not None else f"runs/bench/{args.scene}")
    cmd = "hybridmpm " + " ".join(sys.argv[1:]) if sys.argv[1:2] == ["bench"] else f"hybridmpm bench {args.scene}"
    res = bench(args.scene, seeds=seeds, out=out, command=cmd, progress=not args.quiet, **_bench_kwargs(args))
    if not args.quiet:
        for r in res["rows"]:
            print(
                f"{r['label']:<48} error {r['error_mean']:.3f} (first 50 frames {r['short_error']:.3f}), Sinkhorn {r['sinkhorn']:.2e} m², "
                f"KE {r['ke_error']:.3f}  {r['ms_mean']:7.2f} ms/frame{'  (Pareto)' if r['pareto'] else ''}"
            )
        print(f"Pareto front: {'; '.join(res['pareto'])}\n-> {res['out']}/report.md")
    return 0


def _tune(args: argparse.Namespace) -> int:
    # import time: loaded by this command only
    from hybridmpm.bench import VALID_SEED0, tune
    from hybridmpm.sim.config import tuned_path

    seeds = seed_range(VALID_SEED0, args.seeds, "--first-seed", "--seeds", MAX_SEEDS)
    # before any work: --out a file it can write (an existing one given by --out is refused; the default tuned/SCENE.json is replaced), --work a folder
    out_file(tuned_path(args.scene, args.out), "out", replace=args.out is None)
    work = out_dir(args.work if args.work is not None else f"runs/tune/{args.scene}", "work")
    doc = tune(args.scene, args.error_budget, seeds=seeds, metric=args.metric, out=args.out, work=work, progress=not args.quiet, **_bench_kwargs(args))
    if not args.quiet:
        c, m = doc["config"], doc["measured"]
        print(
            f"{args.scene}: {c['label']} — {args.metric} {m[args.metric]:.4g} <= budget {args.error_budget:g} (grid-mass error "
            f"{m['error_mean']:.3f} mean / {m['error_last']:.3f} last), {m['ms_mean']:.2f} ms/frame -> {doc['path']}\n"
            f"use it: hybridmpm simulate {args.scene} --solver auto" + (f" --tuned {doc['path']}" if args.out else "")
        )
    return 0


def _stress(args: argparse.Namespace) -> int:
    # import time: loaded by this command only
    from hybridmpm.bench.stress import CASES, METHODS, markdown_table, stress

    cases = tuple(args.cases.split(",")) if args.cases else CASES
    methods = tuple(args.methods.split(",")) if args.methods else METHODS
    for c in cases:
        if c not in CASES:
            raise HybridMpmError(f"cases: unknown case {c!r} (choose from {', '.join(CASES)})")
    for m in methods:
        if m not in METHODS:
            raise HybridMpmError(f"methods: unknown method {m!r} (choose from {', '.join(METHODS)})")
    if args.frames < 1:
        raise HybridMpmError("frames: must be >= 1")
    out = out_dir(args.out)
    res = stress(args.scene, cases=cases, methods=methods, frames=args.frames, seed=args.seed, model=args.model, threads=args.threads, progress=not args.quiet)
    table = markdown_table(res)
    cmd = "hybridmpm stress " + " ".join(sys.argv[2:]) if sys.argv[1:2] == ["stress"] else f"hybridmpm stress {args.scene}"
    (out / f"stress_{args.scene}.md").write_text(f"Command: `{cmd}`\n\n" + table)
    (out / f"stress_{args.scene}.json").write_text(json.dumps([r.row() for r in res], indent=2))
    if not args.quiet:
        print(table + f"-> {out}/stress_{args.scene}.md")
    return 0


def add_parsers(sub: Any) -> None:
    """Register this group's commands on the subparsers ``sub``."""
    from hybridmpm.metrics import ROLLOUT_METRICS  # import time: loaded when the parser is built
    from hybridmpm.scenes import DOMAINS

    st = sub.add_parser("stress", help="neural-only, MPM-only and hybrid through failure cases over long rollouts; writes a table")
    st.add_argument("scene", help="registered scene (its shipped model is used unless --model)")
    st.add_argument("--frames", type=int, default=1000, help="frames per rollout (default 1000)")
    st.add_argument("--cases", default=None, help="comma-separated subset of baseline,fast,obstacle,dense (default all)")
    st.add_argument("--methods", default=None, help="comma-separated subset of neural,mpm,hybrid (default all)")
    st.add_argument("--model", default=None, help="ONNX model (default: the shipped model for the scene)")
    st.add_argument("--seed", type=parse_seed, default=0, help="seed of the scene's initial condition and clustering")
    st.add_argument("--threads", type=int, default=1, help="MPM threads (default 1)")
    st.add_argument("--out", default="runs/stress", help="directory of stress_SCENE.md / .json (default runs/stress)")
    st.add_argument("--quiet", action="store_true")
    st.set_defaults(func=_stress)

    def bench_args(p: argparse.ArgumentParser) -> None:
        p.add_argument("scene", choices=sorted(DOMAINS), help="registered scene")
        p.add_argument("--frames", type=int, default=None, help="frames per rollout (default: the paper's T of the scene)")
        p.add_argument("--r-c", default=None, help="comma-separated hybrid thresholds (default 0,0.1,...,0.9)")
        p.add_argument("--error-tols", default=None, help="comma-separated audit tolerances [g] of the hybrid's error rule (default 0.5,1,2,3,5; '' = none)")
        p.add_argument("--model", default=None, help="the hybrid's ONNX model (default: the shipped model of the scene)")
        p.add_argument("--extra-model", action="append", help="another ONNX model to run alone (repeatable)")
        p.add_argument("--no-variants", action="store_true", help="skip the shipped variant networks (full-resolution, spatial-/temporal-only)")
        p.add_argument("--warmup", type=int, default=24, help="frames at the start not timed (default 24)")
        p.add_argument("--threads", type=int, default=0, help="MPM threads (0 = all cores)")
        p.add_argument("--nn-threads", type=int, default=1, help="onnxruntime threads of the hybrid (default 1)")
        p.add_argument(
            "--nn-alone-threads", type=int, default=0, help="onnxruntime threads of the networks run alone (0 = all cores, the default: MPM is idle then)"
        )
        p.add_argument("--quiet", action="store_true", help="no progress bar or summary")

    be = sub.add_parser("bench", help="error against latency for every method from the same held-out initial conditions; charts and report")
    bench_args(be)
    be.add_argument("--seeds", type=int, default=3, help=f"number of held-out seeds, at most {MAX_SEEDS} (default 3: 1000, 1001, 1002)")
    be.add_argument(
        "--first-seed", type=parse_seed, default=None, help="first seed (default 1000, the held-out test seeds); the last, first + seeds - 1, below 2^63"
    )
    be.add_argument("--out", default=None, help="output directory (default runs/bench/SCENE; resumes finished cells)")
    be.set_defaults(func=_bench)

    tu = sub.add_parser("tune", help="the fastest configuration (r_p, r_t, r_c, model) within an error budget, for --solver auto")
    bench_args(tu)
    tu.add_argument("--error-budget", type=float, required=True, help="largest allowed value of --metric (default: the grid-mass error over the rollout)")
    tu.add_argument(
        "--metric", default="error_mean", choices=list(ROLLOUT_METRICS),
        help="the score to hold within the budget: " + "; ".join(f"{k}: {v}" for k, v in ROLLOUT_METRICS.items()) + " (docs/benchmarks.md)",
    )  # fmt: skip
    tu.add_argument("--seeds", type=int, default=2, help=f"number of validation seeds, at most {MAX_SEEDS} (default 2: 2000, 2001)")
    tu.add_argument("--out", default=None, help="config file to write, not an existing one (default tuned/SCENE.json, replaced)")
    tu.add_argument("--work", default=None, help="benchmark directory (default runs/tune/SCENE; resumes finished cells)")
    tu.set_defaults(func=_tune)
