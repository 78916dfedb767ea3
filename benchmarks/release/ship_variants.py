"""Ship the variant networks that ``hybridmpm bench`` compares with the shipped
models: copy each trained ``model.onnx`` to
``python/hybridmpm/models/variants/<scene>/<name>.onnx`` (with a ``name`` in
its metadata), write ``variants/index.json`` and the cards in
``variants/README.md``.

    python benchmarks/release/ship_variants.py   # after benchmarks/train_variants.sh

Variants: ``runs/models/variants/<scene>/<role>_<config>/`` (train_variants.sh)
and, for water2d, two network sizes from the 4000-step sweep
(``runs/models/water2d/{L3x32_R15_rt2,L2x16_R10_rt2}``, train_models.sh).
"""

from __future__ import annotations

import json
from pathlib import Path

from hybridmpm.bench.harness import write_file, write_json

ROOT = Path(__file__).resolve().parents[2]
DST = ROOT / "python" / "hybridmpm" / "models" / "variants"
SIZES = {"water2d": ["L3x32_R15_rt2", "L2x16_R10_rt2"]}


def _candidates() -> list[tuple[str, str, str, Path]]:
    out = []
    for d in sorted((ROOT / "runs/models/variants").glob("*/*/model.onnx")):
        scene, name = d.parent.parent.name, d.parent.name
        out.append((scene, name, name.split("_", 1)[0], d.parent))
    for scene, names in SIZES.items():
        for n in names:
            d = ROOT / "runs/models" / scene / n
            if (d / "model.onnx").is_file():
                out.append((scene, f"size_{n}", "size", d))
    return out


def main() -> None:
    import onnx

    index: dict[str, list[dict]] = {}
    lines = [
        "# Variant networks (benchmarks only)",
        "",
        "Networks that `hybridmpm bench` runs alone beside the shipped model of a scene, to chart the paper's ablations "
        "(Fig. 5 a-c): the original neural physics at full resolution (`full`: r_p = r_t = 1), the spatial-only "
        "(`spatial`: r_p = 0.5714, r_t = 1) and temporal-only (`temporal`: r_p = 1, r_t = 4) reductions, and other "
        "network sizes (`size`). Same GNS as the shipped models (paper App. A), one CPU thread, 4000 optimiser steps "
        "(the shipped 2D models have 20000): they are the equal-budget comparison, not tuned to their best. "
        "The connectivity radius scales with the particle spacing (R = 0.0103 m at r_p = 0.5714, 0.0078 m at r_p = 1), "
        "so every variant sees about the same number of neighbours. Made by `benchmarks/train_variants.sh` and "
        "`benchmarks/train_models.sh`; shipped by `benchmarks/release/ship_variants.py`. The validation MSE is over 20 model "
        "steps (r_t frames each), so it does not compare across r_t; their errors against full-resolution MPM are in "
        "docs/benchmarks.md.",
        "",
        "| scene | name | role | r_p | r_t | latent × L | R [m] | parameters | steps | train time [s] | best validation rollout MSE [m², 20 model steps] | data |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for scene, name, role, d in _candidates():
        summ = json.loads((d / "summary.json").read_text())
        cfg = json.loads((d / "train_config.json").read_text())
        proto = onnx.load(str(d / "model.onnx"))
        meta = {}
        for p in proto.metadata_props:
            if p.key == "hybridmpm":
                meta = json.loads(p.value)
                meta["name"] = name
                meta.setdefault("scenes", [scene])
                p.value = json.dumps(meta, sort_keys=True)
        (DST / scene).mkdir(parents=True, exist_ok=True)
        onnx.save(proto, str(DST / scene / f"{name}.onnx"))
        index.setdefault(scene, []).append({"name": name, "role": role, "file": f"{scene}/{name}.onnx"})
        lines.append(
            f"| {scene} | {name} | {role} | {meta['r_p']:.4g} | {meta['r_t']} | {meta['latent']} × {meta['layers']} | {meta['radius']:.4g} | "
            f"{summ['parameters']} | {summ['steps']} | {summ['train_seconds']:.0f} | {summ['best_val_rollout_mse']:.3g} | `{cfg['data']}` |"
        )
    write_json(DST / "index.json", index, indent=2, sort_keys=True)
    write_file(DST / "README.md", "\n".join(lines) + "\n")
    print(f"{sum(len(v) for v in index.values())} variants -> {DST}")


if __name__ == "__main__":
    main()
