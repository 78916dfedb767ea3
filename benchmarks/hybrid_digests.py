"""Digests of hybrid rollouts, to show that a refactor of the hybrid moves no float.

For each scene with a shipped model, each cheap half (the network, and the
classical twin: MPM on half the grid with the same particles, where the scene
accepts that grid), each switching rule (the one shipped with the scene's
model, ``audit``, ``audit`` at 0.5 g, ``audit`` at every network step,
``paper``, ``error``, ``error`` at 5 g, and the limits
``r_c = 0``, the cheap half alone, and ``r_c = 1.01``, MPM alone) and with and
without a forcing (a sideways push of 4 m/s² from step :data:`PUSH` [0] to
:data:`PUSH` [1]), one hybrid is stepped :data:`STEPS` [0] coarse steps, its
state is taken, it is stepped :data:`STEPS` [1] more, put back to that state
and stepped the same :data:`STEPS` [1] again. The digest of each part is the
SHA-256 of every frame's positions, the hybrid's velocities after it, the
frame's solver, event, score and audit, and the stats at its end (less the
wall-clock seconds).

Run it at two commits and compare the ``runs`` (``--compare``; the
``provenance`` differs from run to run): equal digests mean the same floats.

    python benchmarks/hybrid_digests.py --out benchmarks/results/hybrid_digests.json
    python benchmarks/hybrid_digests.py --out /tmp/after.json --compare benchmarks/results/hybrid_digests.json

Only public construction paths (``HybridSimulator(scene, cheap=..., safeguard=...)``)
are used, so the script runs unchanged on both sides of a refactor.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

import hybridmpm
from hybridmpm.bench.harness import read_results, script_argv, write_results
from hybridmpm.errors import InvalidInputError
from hybridmpm.models import shipped_models
from hybridmpm.scenes import make_scene
from hybridmpm.sim import HybridSimulator

SEED = 3
#: Coarse steps before the state is taken, and after it (run twice: on, and again after the restore).
STEPS = (14, 12)
#: The forcing is set at the first step and cleared at the second (coarse steps).
PUSH = (9, 17)
CHEAP = ("neural", "mpm-coarse")
#: Rule label -> HybridSimulator keyword arguments.
RULES: dict[str, dict[str, Any]] = {
    "shipped": {},
    "audit": {"safeguard": "audit"},
    "audit_tight": {"safeguard": "audit", "audit_tol": 0.5},
    "audit_each": {"safeguard": "audit", "audit_every": 1, "audit_tol": 3.0},
    "paper": {"safeguard": "paper"},
    "error": {"safeguard": "error"},
    "error_loose": {"safeguard": "error", "audit_tol": 5.0},
    "cheap_only": {"safeguard": "audit", "r_c": 0.0},
    "mpm_only": {"safeguard": "audit", "r_c": 1.01},
}


def _frame_record(sim: Any, fr: Any) -> tuple[bytes, bytes, list[Any]]:
    return (
        np.ascontiguousarray(fr.positions, np.float32).tobytes(),
        np.ascontiguousarray(sim.velocities, np.float32).tobytes(),
        [fr.step, fr.solver, fr.event, repr(float(fr.score)), repr(float(fr.audit))],
    )


def _stats(sim: Any) -> dict[str, Any]:
    s = sim.stats.to_dict()
    return {k: v for k, v in s.items() if "seconds" not in k}


def _steps(sim: Any, first: int, count: int, push: np.ndarray | None) -> dict[str, Any]:
    """Step ``count`` coarse steps from step ``first`` (the forcing set and cleared on :data:`PUSH`); the part's digest."""
    h = hashlib.sha256()
    solvers: list[str] = []
    events: list[list[Any]] = []
    for k in range(first, first + count):
        if push is not None and k == PUSH[0]:
            sim.forcing = push
        if push is not None and k == PUSH[1]:
            sim.forcing = None
        fr = sim.advance()
        pos, vel, rec = _frame_record(sim, fr)
        h.update(pos)
        h.update(vel)
        h.update(json.dumps(rec).encode())
        solvers.append(fr.solver)
        if fr.event:
            events.append([fr.step, fr.event])
    st = _stats(sim)
    h.update(json.dumps(st, sort_keys=True).encode())
    return {"sha256": h.hexdigest(), "solvers": "".join(s[0] for s in solvers), "events": events, "stats": st}


def run_one(scene_name: str, cheap: str, rule: dict[str, Any], forced: bool) -> dict[str, Any]:
    scene = make_scene(scene_name, seed=SEED)
    try:
        sim = HybridSimulator(scene, seed=SEED, cheap=cheap, mpm_threads=1, **rule)
    except InvalidInputError as e:
        return {"refused": e.field}
    push = None
    if forced:
        push = np.zeros((sim.n_fluid, scene.dim), np.float32)
        push[:, 0] = 4.0
    out = {"before": _steps(sim, 0, STEPS[0], push)}
    state = sim.state()
    out["after"] = _steps(sim, STEPS[0], STEPS[1], push)
    sim.restore(state)
    out["restored"] = _steps(sim, STEPS[0], STEPS[1], push)
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--scenes", nargs="*", default=None, help="default: every scene with a shipped model")
    ap.add_argument("--compare", type=Path, default=None, help="an earlier output: exit 1 where a digest differs")
    args = ap.parse_args(argv)
    scenes = args.scenes or sorted(shipped_models())
    doc: dict[str, Any] = {
        "package": str(Path(hybridmpm.__file__).resolve()),
        "seed": SEED,
        "steps": list(STEPS),
        "push": list(PUSH),
        "runs": {},
    }
    t0 = time.perf_counter()
    for name in scenes:
        for cheap in CHEAP:
            for label, rule in RULES.items():
                for forced in (False, True):
                    key = f"{name}/{cheap}/{label}/{'forced' if forced else 'free'}"
                    doc["runs"][key] = run_one(name, cheap, rule, forced)
                    r = doc["runs"][key]
                    print(key, r.get("refused") or r["before"]["solvers"] + "|" + r["after"]["solvers"], flush=True)
    doc["seconds"] = time.perf_counter() - t0
    write_results(args.out.parent, args.out.stem, doc=doc, sort_keys=True, argv=script_argv(__file__, argv))
    if args.compare is None:
        return 0
    old = read_results(args.compare)["runs"]
    bad = [k for k in doc["runs"] if k in old and doc["runs"][k] != old[k]]
    missing = sorted(set(old) ^ set(doc["runs"]))
    for k in bad:
        print("DIFFERS", k, file=sys.stderr)
    for k in missing:
        print("ONLY ON ONE SIDE", k, file=sys.stderr)
    print(f"{len(doc['runs']) - len(bad)} of {len(doc['runs'])} runs equal" + (f", {len(missing)} on one side only" if missing else ""))
    return 1 if bad or missing else 0


if __name__ == "__main__":
    raise SystemExit(main())
