"""How much the neural → MPM conversion alone changes MPM's next step.

The hybrid's MPM audit compares a network step with MPM's step from the same
*converted* state (:func:`hybridmpm.sim.convert.neural_to_mpm`: positions,
velocities from the position history, fitted APIC ``C``, ``J``). Even a
perfect network would differ from that reference by what the conversion
loses. This script measures that floor on MPM's own trajectories, where the
truth is known: MPM at the model's ``r_p`` and ``r_t`` runs a scene; every
``--every`` steps (after the warm-up) one step is taken twice from the same
moment, once by the solver as it is and once after overwriting its state
with the conversion of its last positions; the RMS over fluid particles of
the position difference divided by ``dt_step²``, in g, is reported — the
audit's unit (:class:`hybridmpm.sim.HybridSimulator`).

    python benchmarks/conversion_floor.py --scenes water2d dam_break2d sand2d water_sand2d --seeds 2000 2001 \
        --out benchmarks/results/conversion_floor

Variants: the velocity estimate (``second``: second-order backward
difference, the velocity at the last position; ``last``: the last finite
difference) and water's ``J`` (``density`` or ``one``).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from hybridmpm.bench.harness import script_argv, write_results
from hybridmpm.conventions import G
from hybridmpm.models import shipped_model
from hybridmpm.neural import GnsRuntime
from hybridmpm.scenes import make_scene
from hybridmpm.sim import MpmSimulator

#: (label, conversion keyword arguments)
VARIANTS = [
    ("velocity last, J density (default)", {"velocity": "last", "volume_ratio": "density"}),
    ("velocity second, J density", {"velocity": "second", "volume_ratio": "density"}),
    ("velocity second, J = 1", {"velocity": "second", "volume_ratio": "one"}),
    ("velocity last, J = 1", {"velocity": "last", "volume_ratio": "one"}),
]


def floor_samples(scene_name: str, seed: int, steps: int, every: int) -> dict[str, list[float]]:
    """The floor [g] of every variant at steps ``every, 2·every, …`` (≥ 6) of one rollout."""
    model = GnsRuntime(shipped_model(scene_name))
    sim = MpmSimulator(make_scene(scene_name, seed=seed), r_p=model.r_p, r_t=model.r_t, seed=seed, threads=1)
    dt_step = sim.dt_frame * sim.r_t
    n = sim.particles.num_fluid
    hist = [sim.particles.fluid(sim.frame.positions).copy()]
    out: dict[str, list[float]] = {label: [] for label, _ in VARIANTS}
    for step in range(1, steps + 1):
        if step >= 6 and step % every == 0:
            before = sim.state()
            truth = sim.particles.fluid(sim.advance().positions).astype(np.float64)
            for label, conv in VARIANTS:
                sim.restore(before)
                sim.load_history(np.stack(hist[-3:]), dt_step, affine="fit", affine_radius=model.radius, **conv)
                got = sim.particles.fluid(sim.advance().positions).astype(np.float64)
                d = (truth - got)[:n]
                out[label].append(float(np.sqrt(np.mean(np.sum(d * d, axis=1)))) / dt_step**2 / G)
            sim.restore(before)
        hist.append(sim.particles.fluid(sim.advance().positions).copy())
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scenes", nargs="+", default=["water2d", "dam_break2d", "sand2d", "water_sand2d"])
    ap.add_argument("--seeds", nargs="+", type=int, default=[2000, 2001])
    ap.add_argument("--steps", type=int, default=80, help="coarse steps per rollout")
    ap.add_argument("--every", type=int, default=5, help="steps between samples")
    ap.add_argument("--out", required=True)
    args = ap.parse_args(argv)
    rows = []
    for scene in args.scenes:
        pooled: dict[str, list[float]] = {label: [] for label, _ in VARIANTS}
        for seed in args.seeds:
            for label, vals in floor_samples(scene, seed, args.steps, args.every).items():
                pooled[label].extend(vals)
        for label, vals in pooled.items():
            v = np.asarray(vals)
            rows.append({"scene": scene, "variant": label, "samples": len(v), "median_g": float(np.median(v)), "p90_g": float(np.percentile(v, 90))})
            print(f"{scene:14s} {label:38s} median {np.median(v):.2f} g, p90 {np.percentile(v, 90):.2f} g ({len(v)} samples)", file=sys.stderr)
    lines = [
        f"One-step difference [g] between MPM continuing and MPM restarted from the converted state; seeds {args.seeds}, "
        f"{args.steps} steps, a sample every {args.every} steps from step 6 on; median and 90th percentile over samples.",
        "",
        "| scene | conversion | median [g] | p90 [g] | samples |",
        "|---|---|---|---|---|",
    ]
    lines += [f"| {r['scene']} | {r['variant']} | {r['median_g']:.2f} | {r['p90_g']:.2f} | {r['samples']} |" for r in rows]
    out = Path(args.out)
    write_results(out.parent, out.name, doc={"rows": rows}, markdown="\n".join(lines), argv=script_argv(__file__, argv))
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    sys.exit(main())
