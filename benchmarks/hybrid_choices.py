"""Measurements behind the hybrid simulator's defaults: the dwell,
the APIC ``C`` after neural → MPM (fitted or zero), water's ``J`` (from density
or 1), the acceleration floor of the safeguard, ``r_c`` itself, and the MPM
audit's period and tolerance.

    python benchmarks/hybrid_choices.py --scene water2d --seeds 2000 2001 2002 --frames 600 \
        --out benchmarks/results/hybrid_choices_water2d

Each variant changes one setting from the defaults; rollouts from the same
initial conditions; grid-mass error against full-resolution MPM (mean over
frames and seeds, and the last frame), wall ms per frame, share of frames on
MPM and switches. Seeds other than the dataset's (which used 0…M−1).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

from hybridmpm.bench.harness import script_argv, write_results
from hybridmpm.conventions import AUDIT_EVERY, AUDIT_TOL
from hybridmpm.metrics import grid_mass_error
from hybridmpm.models import shipped_model
from hybridmpm.neural import GnsRuntime
from hybridmpm.scenes import make_scene
from hybridmpm.sim import HybridSimulator, MpmSimulator, reference, rollout

#: (label, hybrid keyword arguments); None: MPM alone at the model's r_p and r_t.
VARIANTS: list[tuple[str, dict | None]] = [
    ("defaults", {}),
    ("dwell 1", {"dwell": 1}),
    ("dwell 10", {"dwell": 10}),
    ("dwell 20", {"dwell": 20}),
    ("affine zero", {"affine": "zero"}),
    ("J = 1", {"volume_ratio": "one"}),
    ("velocity second", {"velocity": "second"}),
    ("J = 1, velocity second", {"volume_ratio": "one", "velocity": "second"}),
    ("J = 1, no audit", {"volume_ratio": "one", "audit_every": 0}),
    ("accel_floor 0", {"accel_floor": 0.0}),
    ("accel_floor 3", {"accel_floor": 3.0}),
    ("r_c 0 (no complexity trigger)", {"r_c": 0.0}),
    ("r_c 0.5", {"r_c": 0.5}),
    ("r_c 0.9", {"r_c": 0.9}),
    ("no audit", {"audit_every": 0}),
    ("audit every 1", {"audit_every": 1}),
    ("audit every 8", {"audit_every": 8}),
    ("audit tol 0.5 g", {"audit_tol": 0.5}),
    ("audit tol 1 g", {"audit_tol": 1.0}),
    ("audit tol 2 g", {"audit_tol": 2.0}),
    ("audit tol 3 g", {"audit_tol": 3.0}),
    ("rule paper", {"safeguard": "paper"}),
    ("rule error", {"safeguard": "error"}),
    ("rule error, tol 0.5 g", {"safeguard": "error", "audit_tol": 0.5}),
    ("rule error, tol 2 g", {"safeguard": "error", "audit_tol": 2.0}),
    ("rule error, tol 3 g", {"safeguard": "error", "audit_tol": 3.0}),
    ("rule error, tol 5 g", {"safeguard": "error", "audit_tol": 5.0}),
    ("rule error, residual 0.25 g", {"safeguard": "error", "residual_tol": 0.25}),
    ("rule error, residual 1 g", {"safeguard": "error", "residual_tol": 1.0}),
    ("rule error, interval 4", {"safeguard": "error", "audit_max": 4}),
    ("MPM at r_p", None),
]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scene", default="water2d")
    ap.add_argument("--seeds", nargs="+", type=int, default=[2000, 2001, 2002])
    ap.add_argument("--frames", type=int, default=600)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--variants", nargs="+", help="only these variants (labels as in the table)")
    ap.add_argument("--model", type=Path, help="a GNS .onnx file other than the scene's shipped model (e.g. a training snapshot)")
    ap.add_argument("--out", required=True)
    args = ap.parse_args(argv)
    variants = [v for v in VARIANTS if not args.variants or v[0] in args.variants]
    if args.variants and len(variants) != len(args.variants):
        ap.error(f"--variants: unknown label among {args.variants}; known: {[v[0] for v in VARIANTS]}")
    if args.model is not None and not args.model.is_file():
        ap.error(f"--model: no such file: {args.model}")
    model = GnsRuntime(args.model if args.model is not None else shipped_model(args.scene))
    refs = {}
    for seed in args.seeds:
        refs[seed] = reference(make_scene(args.scene, seed=seed), args.frames, stride=model.r_t, threads=args.threads).fluid_positions
    rows = []
    for name, kw in variants:
        errs, lasts, ms, share, sw, aud = [], [], [], [], [], []
        for seed in args.seeds:
            scene = make_scene(args.scene, seed=seed)
            if kw is None:
                sim = MpmSimulator(scene, r_p=model.r_p, r_t=model.r_t, seed=seed, threads=args.threads)
            else:
                sim = HybridSimulator(scene, model, seed=seed, mpm_threads=args.threads, **kw)
            t0 = time.perf_counter()
            ro = rollout(sim, args.frames)
            ms.append((time.perf_counter() - t0) / args.frames * 1e3)
            e = grid_mass_error(ro.fluid_positions, refs[seed], scene.params.resolved_n_grid())
            errs.append(e.mean())
            lasts.append(e[-1])
            st = ro.stats["steps"]
            share.append(st["mpm"] / (st["mpm"] + st["neural"]))
            sw.append(ro.stats["switches"])
            aud.append(ro.stats.get("fallbacks", {}).get("audit", 0))
        row = {"variant": name, "error_mean": float(np.mean(errs)), "error_last": float(np.mean(lasts)), "ms_per_frame": float(np.median(ms)),
               "mpm_share": float(np.mean(share)), "switches": float(np.mean(sw)), "audit_fallbacks": float(np.mean(aud)), "per_seed_error": [float(x) for x in errs]}  # fmt: skip
        rows.append(row)
        print(
            f"{name}: {row['error_mean']:.3f} / {row['error_last']:.3f}, {row['ms_per_frame']:.2f} ms/frame, MPM {100 * row['mpm_share']:.0f}%, {row['switches']:.1f} switches, {row['audit_fallbacks']:.1f} audit fallbacks",
            file=sys.stderr,
        )
    lines = [
        f"{args.scene}, seeds {args.seeds}, {args.frames} frames, {'model ' + str(args.model) if args.model else 'shipped model'}; one setting changed per row from the defaults "
        f"(r_c 0.8, δ 10, dwell 5, affine fit, J from density, velocity the last difference, accel_floor 1 m/s², an MPM audit every {AUDIT_EVERY} network steps with tolerance "
        f"{AUDIT_TOL:g} g).",
        "",
        "| variant | grid-mass error mean | last | ms/frame | share of frames on MPM | switches | audit fallbacks | per-seed mean error |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        lines.append(
            f"| {r['variant']} | {r['error_mean']:.3f} | {r['error_last']:.3f} | {r['ms_per_frame']:.2f} | {100 * r['mpm_share']:.0f}% | {r['switches']:.1f} | {r['audit_fallbacks']:.1f} "
            f"| {', '.join(f'{x:.3f}' for x in r['per_seed_error'])} |"
        )
    out = Path(args.out)
    write_results(out.parent, out.name, doc={"rows": rows}, markdown="\n".join(lines), argv=script_argv(__file__, argv))
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    sys.exit(main())
