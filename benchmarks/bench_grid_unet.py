"""Cost of the grid model's U-Net in onnxruntime, per grid size, width and depth.

Exports an untrained grid model (the U-Net's arithmetic does not depend on
its weights) for each configuration and times one call (``r_t`` frames) on 1
and 2 onnxruntime threads: the 20th percentile of ``--calls`` calls after a
warm-up, which is what the machine can do when nothing else runs. The
transfers (p2g, g2p, advection) are not included: ``--particles`` times them
once per configuration with random particles.

    python benchmarks/bench_grid_unet.py [--calls 60] [--out benchmarks/results/grid_unet.md]
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np
import onnxruntime as ort

from hybridmpm.bench.harness import write_results
from hybridmpm.conventions import GNS_WATER
from hybridmpm.neural.grid import GridRuntime
from hybridmpm.train.grid import GridConfig, GridModel, export_grid

CONFIGS = [(32, 16, 3), (32, 24, 3), (32, 32, 3), (48, 8, 3), (64, 8, 3), (64, 8, 4), (64, 16, 3), (64, 24, 3)]


def _time(fn, calls: int) -> float:
    for _ in range(max(3, calls // 6)):
        fn()
    ts = []
    for _ in range(calls):
        t = time.perf_counter()
        fn()
        ts.append(time.perf_counter() - t)
    return float(np.percentile(ts, 20)) * 1e3


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--calls", type=int, default=60)
    ap.add_argument("--particles", type=int, default=1300)
    ap.add_argument("--out", default=None, help="write a markdown table here (FILE.md)")
    args = ap.parse_args()
    rows = []
    rng = np.random.default_rng(0)
    with tempfile.TemporaryDirectory() as tmp:
        for g, w, levels in CONFIGS:
            cfg = GridConfig(dim=2, bounds=[[0.015625, 0.984375]] * 2, dt_frame=2.5e-3, gravity=[0.0, -9.8], grid=g, width=w, levels=levels, pressure=True)
            path = export_grid(GridModel(cfg), Path(tmp) / "u.onnx", {"r_p": 0.5714})
            x = rng.random((1, cfg.in_channels, g, g), dtype=np.float32)
            times = []
            for threads in (1, 2):
                opts = ort.SessionOptions()
                opts.intra_op_num_threads = threads
                opts.add_session_config_entry("session.intra_op.allow_spinning", "1" if threads > 1 else "0")
                sess = ort.InferenceSession(str(path), opts, providers=["CPUExecutionProvider"])
                times.append(_time(lambda s=sess, x=x: s.run(None, {"grid": x}), args.calls))
            rt = GridRuntime(path)
            pos = rng.uniform(0.05, 0.6, (args.particles, 2)).astype(np.float32)
            hist = np.stack([pos + 1e-3 * i for i in range(cfg.t_in)]).astype(np.float32)
            pt = np.full(args.particles, GNS_WATER)
            whole = _time(lambda rt=rt, hist=hist, pt=pt: rt.frames(hist, pt), args.calls)
            rows.append((g, w, levels, times[0], times[1], whole))
            print(f"{g}^2 width {w} levels {levels}: U-Net {times[0]:.3f} ms (1 thread) {times[1]:.3f} ms (2 threads); whole call {whole:.3f} ms", flush=True)
    if args.out:
        lines = [
            "# Grid model: U-Net cost per call (r_t = 4 frames)",
            "",
            "20th percentile of the calls, ms.",
            "",
            f"| grid | width | levels | U-Net, 1 thread | U-Net, 2 threads | whole call, {args.particles} particles, 1 thread |",
            "|---|---|---|---|---|---|",
            *[f"| {g}² | {w} | {lv} | {a:.3f} | {b:.3f} | {c:.3f} |" for g, w, lv, a, b, c in rows],
            "",
        ]
        out = Path(args.out)
        write_results(out.parent, out.stem, markdown="\n".join(lines))


if __name__ == "__main__":
    main()
