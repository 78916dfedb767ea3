"""The ``hybridmpm`` command line: datasets: generate a GNS-layout dataset of MPM rollouts (``generate``) and check one (``inspect``)."""

from __future__ import annotations

import argparse
import json
import sys
from typing import Any

from hybridmpm.cli.common import parse_seed
from hybridmpm.errors import InvalidInputError
from hybridmpm.jsonutil import json_safe


def _generate(args: argparse.Namespace) -> int:
    # import time: loaded by this command only
    from hybridmpm.train.datasets import GenerateConfig, generate_dataset

    try:
        split = tuple(float(v) for v in args.split.split(","))
    except ValueError:
        raise InvalidInputError(f"split: three comma-separated fractions, e.g. 0.8,0.1,0.1; got {args.split!r}", "split") from None
    config = GenerateConfig(
        scene=args.scene, trajectories=args.trajectories, frames=args.frames, seed=args.seed,
        r_p=args.r_p, r_t=args.r_t, lowres=args.lowres, split=split,  # type: ignore[arg-type]
    )  # fmt: skip
    try:
        report = generate_dataset(
            config, args.out, workers=args.workers, executor=args.executor, keep_parts=args.keep_parts, compress=args.compress, progress=not args.quiet
        )
    except KeyboardInterrupt:
        print(f"hybridmpm: interrupted; finished trajectories are kept in {args.out}/parts, rerun the same command to resume", file=sys.stderr)
        return 130
    if not args.quiet:
        size = sum(report.sizes.values())
        print(
            f"{args.scene}: {args.trajectories} trajectories ({report.simulated} simulated now, {report.resumed} already done) "
            f"in {report.wall_s:.1f} s with {args.workers} worker(s) (assembly {report.assemble_s:.1f} s); {size / 1e6:.1f} MB on disk -> {args.out}/"
        )
    return 0


def _inspect(args: argparse.Namespace) -> int:
    """``hybridmpm inspect DIR``: the dataset's summary as JSON; exit status 1
    if it does not match its own metadata (:func:`hybridmpm.data.gns.check_dataset`)."""
    # import time: loaded by this command only
    from hybridmpm.data import GnsDataset
    from hybridmpm.data.gns import check_dataset

    info = check_dataset(GnsDataset(args.directory))
    print(json.dumps(json_safe(info), indent=2))
    for p in info["problems"]:
        print(f"hybridmpm: problem: {p}", file=sys.stderr)
    return 1 if info["problems"] else 0


def add_parsers(sub: Any) -> None:
    """Register this group's commands on the subparsers ``sub``."""
    from hybridmpm.scenes import DOMAINS  # import time: loaded when the parser is built

    gen = sub.add_parser("generate", help="generate a GNS-layout dataset (train/valid/test.npz, metadata.json) of MPM rollouts")
    gen.add_argument("scene", choices=sorted(DOMAINS), help="domain")
    gen.add_argument("--trajectories", type=int, required=True, help="number of trajectories M (>= 3; split 80/10/10 by default)")
    gen.add_argument("--out", required=True, help="dataset directory (resumes if it holds an unfinished generation)")
    gen.add_argument("--frames", type=int, default=None, help="frames T per trajectory (default: the paper's T for the domain)")
    gen.add_argument("--workers", type=int, default=2, help="parallel worker processes (default 2)")
    gen.add_argument("--seed", type=parse_seed, default=0, help="dataset seed (default 0)")
    gen.add_argument("--r-p", type=float, default=1.0, help="spatial downsampling r_p in (0, 1] (default 1; the paper's is 0.5714)")
    gen.add_argument("--r-t", type=int, default=1, help="temporal downsampling: store every r_t-th frame (default 1; the paper's is 2)")
    gen.add_argument(
        "--lowres", default="simulate", choices=["simulate", "centroids"], help="how r_p < 1 data is made (default: simulate the clustered initial condition)"
    )
    gen.add_argument("--split", default="0.8,0.1,0.1", help="train,valid,test fractions (default 0.8,0.1,0.1)")
    gen.add_argument("--executor", default="process", choices=["process", "ray"], help="process pool (default) or Ray (RAY_ADDRESS or a local instance)")
    gen.add_argument("--compress", action="store_true", help="deflate the split files (~13%% smaller for float32 positions, slower to write)")
    gen.add_argument("--keep-parts", action="store_true", help="keep the per-trajectory files in DIR/parts after assembling")
    gen.add_argument("--quiet", action="store_true", help="no progress bar or summary line")
    gen.set_defaults(func=_generate)

    ins = sub.add_parser("inspect", help="check a GNS-layout dataset directory and print its summary as JSON")
    ins.add_argument("directory", help="dataset directory (metadata.json + train/valid/test.npz)")
    ins.set_defaults(func=_inspect)
