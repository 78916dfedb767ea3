"""Durable sessions: the cost of one save and one restore of a session's
checkpoint in a store (``hybridmpm serve --store``), in this process, with the
code the server runs.

A save is what the server does per session: take the simulator's state
(with its downsampled scene's clusters), encode it (npz + JSON), write it
atomically (temporary file, flush to disk, rename). A restore is what a
restarted server or actor does per session: read and check the record,
build the simulator from its scene, seed, solver and clusters, and restore
the state into it (``hybridmpm.service.store.rebuild``).

    python benchmarks/bench_store.py [--repeats 20] [--store DIR_OR_URL] [--out benchmarks/results/service.md]
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np

from hybridmpm.bench.harness import write_results
from hybridmpm.service import checkpoint as ckpt
from hybridmpm.service.store import SessionStore, rebuild, record_state, session_key
from hybridmpm.sim import make_simulator, rollout

CASES = [("water2d", "mpm", 40), ("dam_break2d", "hybrid", 40)]
MAX_BYTES = 1 << 30


def measure(store: SessionStore, scene: str, solver: str, frames: int, repeats: int) -> dict[str, float]:
    sim = make_simulator(scene, solver, seed=0, threads=1, nn_threads=1)
    rollout(sim, frames)
    meta = {"scene": scene, "seed": 0, "solver": solver, "r_c": 0.0}  # r_c: the solver default (not read back here)
    meta.update({"last_used_at": time.time(), "client": "127.0.0.1"})
    key = session_key(f"bench-{scene}-{solver}")
    save, read, build = [], [], []
    nbytes = 0
    for _ in range(repeats):
        t0 = time.perf_counter()
        data = ckpt.dumps(record_state(sim), meta)
        store.write(key, data)
        save.append(time.perf_counter() - t0)
        nbytes = len(data)
        t0 = time.perf_counter()
        rec = store.load(key, MAX_BYTES)
        t1 = time.perf_counter()
        fresh, _ = rebuild(rec)
        t2 = time.perf_counter()
        read.append(t1 - t0)
        build.append(t2 - t1)
        assert int(fresh.frame.frame_index) == int(sim.frame.frame_index)
    store.delete(key)

    def ms(xs: list[float]) -> float:
        return float(np.median(xs)) * 1e3

    return {
        "save_ms": ms(save),
        "bytes": nbytes,
        "read_ms": ms(read),
        "build_ms": ms(build),
        "total_ms": ms([a + b for a, b in zip(read, build)]),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--repeats", type=int, default=20)
    ap.add_argument("--store", default=None, help="directory or fsspec URL (default: a temporary directory)")
    ap.add_argument("--out", default=None, help="append a Markdown report here (FILE.md)")
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        store = SessionStore(args.store or tmp).open()
        rows = [(scene, solver, frames, measure(store, scene, solver, frames, args.repeats)) for scene, solver, frames in CASES]
    lines = [
        "\n## Durable sessions: save and restore\n",
        f"Store: {'a local directory' if args.store is None else args.store}; medians of {args.repeats}.\n",
        "A save: state + npz encoding + atomic write (temporary file, fsync, rename). A restore: read and check the record,",
        "build the simulator from its scene/seed/solver and the record's clusters (no k-means; the hybrid loads its ONNX model), restore the state.\n",
        "| scene | solver | at frame | save [ms] | checkpoint [bytes] | read + check [ms] | build + restore [ms] | restore in all [ms] |",
        "|---|---|---:|---:|---:|---:|---:|---:|",
    ]
    for scene, solver, frames, r in rows:
        lines.append(
            f"| {scene} | {solver} | {frames} | {r['save_ms']:.1f} | {r['bytes']:,} | {r['read_ms']:.1f} | {r['build_ms']:.1f} | {r['total_ms']:.1f} |"
        )
    text = "\n".join(lines) + "\n"
    print(text)
    if args.out:
        out = Path(args.out)
        write_results(out.parent, out.stem, markdown=text, append=True)


if __name__ == "__main__":
    main()
