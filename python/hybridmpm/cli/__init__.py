"""The ``hybridmpm`` command line.

``hybridmpm simulate [SCENE] [--solver hybrid|mpm|neural] --frames N --out DIR
[--r-c 0.8] [--reference] [--export ply|vtu|mesh|usd ...]`` runs a scene (default: the
dam break, hybrid) and writes ``trajectory.npz``, ``summary.json`` and
``render.gif`` (hybrid: also ``timeline.png``).

``hybridmpm export TRAJ.npz --mesh [--usd] --out DIR`` writes fluid surface
meshes and/or one USD file from a saved trajectory (also ``simulate --export
mesh usd``; docs/mesh.md, docs/usd.md).

``hybridmpm bench SCENE [--seeds K] [--frames T] [--out DIR]``
runs every method from the same held-out initial conditions and writes
error-against-latency charts and tables (:func:`hybridmpm.bench.bench`);
``hybridmpm tune SCENE --error-budget E`` writes the fastest configuration
within the budget, which ``simulate SCENE --solver auto`` then uses.

``hybridmpm stress SCENE`` runs neural-only, MPM-only and hybrid through the
failure cases of :mod:`hybridmpm.bench.stress` and writes a table.

``hybridmpm generate SCENE --trajectories M --out DIR`` writes a GNS-layout
dataset of MPM rollouts (:func:`hybridmpm.train.datasets.generate_dataset`);
``hybridmpm inspect DIR`` checks and summarises a GNS dataset (ours or
another tool's).

``hybridmpm evaluate PRED.npz REF.npz [--n-grid N] [--scene SCENE] [--out metrics.json]``
compares two trajectories (:func:`hybridmpm.metrics.evaluate`: grid-mass
error, position MSE, kinetic energy, and the scores of a chaotic flow:
short-horizon error, Sinkhorn divergence, kinetic energy's relative error,
the dam break's front with ``--scene``) and writes the metrics as JSON.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence

from hybridmpm.cli import bench, control, data, export, serve, simulate, train
from hybridmpm.errors import HybridMpmError

#: The command groups, each a module that owns its commands' parsers and handlers.
GROUPS = (simulate, export, control, bench, data, train, serve)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="hybridmpm", description="Real-time hybrid neural / MLS-MPM fluid simulation.")
    sub = parser.add_subparsers(dest="command", required=True)
    for group in GROUPS:
        group.add_parsers(sub)
    for p in sub.choices.values():
        p.add_argument("--debug", action="store_true", help="show the full traceback of an error")
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Run a command; every :class:`HybridMpmError` (bad input, failed
    simulation, a rollout that made fewer frames than asked: ``simulate`` and
    ``control`` write what was made first) ends as one line on stderr with exit status 2, an OS error
    (missing or unwritable file) with status 1, Ctrl-C with 130. ``--debug``
    shows the traceback instead."""
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        return int(args.func(args))
    except (HybridMpmError, OSError, KeyboardInterrupt) as e:
        if getattr(args, "debug", False):
            raise
        if isinstance(e, KeyboardInterrupt):
            print("hybridmpm: interrupted", file=sys.stderr)
            return 130
        print(f"hybridmpm: error: {e}", file=sys.stderr)
        return 2 if isinstance(e, HybridMpmError) else 1


__all__ = ["build_parser", "main"]
