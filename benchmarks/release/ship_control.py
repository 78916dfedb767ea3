#!/usr/bin/env python3
"""Ship a trained diffusion controller: copy ``RUN/model`` to
``python/hybridmpm/models/control/SCENE/`` and write its model card
``python/hybridmpm/models/control/SCENE.md`` from the run's ``control.json``
and ``log.jsonl`` and, when given, the benchmark results.

    python benchmarks/release/ship_control.py --scene water2d --run runs/control-water2d \
        --data-cmd "hybridmpm generate-control water2d --cases 800" --bench benchmarks/results/control.json
"""

from __future__ import annotations

import argparse
import json
import shutil
from pathlib import Path

import numpy as np

from hybridmpm.bench.harness import write_file, write_json
from hybridmpm.control.diffusion import SAMPLE_STEPS

DEST = Path(__file__).resolve().parents[2] / "python" / "hybridmpm" / "models" / "control"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scene", required=True)
    ap.add_argument("--run", required=True, type=Path)
    ap.add_argument("--data-cmd", required=True, help="the command that made the training cases")
    ap.add_argument("--train-cmd", default=None, help="the training command (default: inferred)")
    ap.add_argument("--bench", type=Path, default=None, help="bench_control.py results (JSON) to quote")
    ap.add_argument("--note", default="")
    ap.add_argument(
        "--sample-steps", type=int, default=None, help="DDIM steps the shipped model samples with (control.json sample_steps; default SAMPLE_STEPS)"
    )
    a = ap.parse_args()
    model = a.run / "model"
    meta = json.loads((model / "control.json").read_text())
    log = [json.loads(line) for line in (a.run / "log.jsonl").read_text().splitlines() if line.strip()]
    cfg = meta["config"]
    dest = DEST / a.scene
    if dest.exists():
        shutil.rmtree(dest)
    dest.mkdir(parents=True)
    for f in sorted(model.iterdir()):
        shutil.copy2(f, dest / f.name)
    if a.sample_steps is not None:
        meta["sample_steps"] = int(a.sample_steps)
        write_json(dest / "control.json", meta, indent=1, sort_keys=True)
    steps = int(meta.get("sample_steps", SAMPLE_STEPS))
    size = sum(f.stat().st_size for f in dest.iterdir())
    train_cmd = a.train_cmd or f"hybridmpm train-control {a.scene} --steps {meta['steps']}"
    lines = [
        f"# Model card: diffusion controller `control/{a.scene}/`",
        "",
        "Fluid ControlNet (paper Sec. 3.2, App. B; docs/control.md): a sketch and the fluid state → a plan of every particle's motion over",
        f"`T_ctr` = {cfg['frames']} frames, tracked by MPM through `hybridmpm.control.controller.track_path`. Three ONNX graphs",
        "(`sketch_encoder`, `state_encoder`, `denoiser_head`) and `control.json`; served by numpy + onnxruntime.",
        "",
        "## Data",
        f"`{a.data_cmd}`: reverse-simulation cases (seeds below 5000; the benchmark holds out 5000+), MPM at r_p = 0.5714;",
        f"{cfg['extra'].get('cases')} training cases (each also mirrored in x), {cfg['extra'].get('valid_cases')} validation cases.",
        "",
        "## Config",
        f"state encoder: GNS latent {cfg['latent_state']} × {cfg['layers_state']} layers, R = {cfg['radius']} m; sketch encoder: hint block",
        f"(8 convolutions, 3 downsamplings) → 44-d + 8-channel local map; denoising head latent {cfg['latent_head']} × 1 layer, adaLN-Zero;",
        f"sample: {cfg['k_basis']} path B-spline coefficients × {cfg['dim']} dimensions per particle; cosine schedule, T = {meta['diffusion_steps']},",
        f"x0 prediction, DDIM with {steps} trailing step{'s' if steps > 1 else ''} at serving time. {meta['parameters']} parameters, {size / 1e6:.2f} MB on disk.",
        f"Prior: `{meta.get('prior', 'none')}` — "
        + (
            "the plan is sampled relative to the coarse free-motion rollout bent onto the sketch (`hybridmpm.control.prior`)."
            if meta.get("prior") == "free_sketch"
            else "the plan is sampled relative to every particle moved to its sketch target along a smoothstep."
        ),
        "",
        "## Training",
        f"{meta['steps']} steps in {meta['train_seconds'] / 60:.0f} min on one CPU thread (2-core machine, other jobs running): `{train_cmd}`.",
        "AdamW, lr 1e-3 → 1e-4 exponential, EMA of the weights exported, blank-sketch (uncontrolled) pairs with p = 0.15.",
        "",
        "| step | train loss | validation loss (EMA, t ∈ {10, 40, 70, 95}) | minutes |",
        "|---|---|---|---|",
    ]
    rows = log[:: max(1, len(log) // 8)]
    if rows[-1] is not log[-1]:
        rows.append(log[-1])
    for row in rows:
        loss = "–" if row.get("loss") is None else f"{row['loss']:.3f}"
        lines.append(f"| {row['step']} | {loss} | {row['valid']:.3f} | {row['seconds'] / 60:.1f} |")
    if a.bench and a.bench.exists():
        cases = [c for c in json.loads(a.bench.read_text())["cases"] if c["scene"] == a.scene and "diffusion" in c["methods"]]
        if cases:
            err = {m: np.mean([c["methods"][m]["grid_mass_error"] for c in cases]) for m in ("none", "constant", "pd", "diffusion")}
            better = np.mean([c["methods"]["diffusion"]["grid_mass_error"] < c["methods"]["constant"]["grid_mass_error"] for c in cases])
            lines += [
                "",
                f"## Errors ({len(cases)} held-out cases, `benchmarks/bench_control.py`)",
                f"Final-shape grid-mass error against X_1: diffusion {err['diffusion']:.3f}; constant force {err['constant']:.3f}; PD {err['pd']:.3f};",
                f"no control {err['none']:.3f}. Better than the constant force on {100 * better:.0f}% of the cases.",
            ]
            extra = {m: np.mean([c["methods"][m]["grid_mass_error"] for c in cases]) for m in ("diffusion_net", "prior") if m in cases[0]["methods"]}
            if extra:
                free = sum(not c["methods"]["diffusion"].get("network", True) for c in cases)
                lines.append(
                    f"In free flight, planned without the network: {free} of {len(cases)} cases"
                    + (f"; with the network on every case: {extra['diffusion_net']:.3f}" if "diffusion_net" in extra else "")
                    + (f"; its prior alone (no network): {extra['prior']:.3f}" if "prior" in extra else "")
                    + "."
                )
    if a.note:
        lines += ["", a.note]
    write_file(DEST / f"{a.scene}.md", "\n".join(lines) + "\n")
    print(f"shipped {a.scene}: {size / 1e6:.2f} MB -> {dest}")


if __name__ == "__main__":
    main()
