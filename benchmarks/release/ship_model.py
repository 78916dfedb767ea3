"""Choose and ship a model: the smallest whose validation rollout error is within 10% of the best.

Reads two ``bench_neural.py`` results for the same candidates, one scored on
validation trajectories (for the choice) and one on test trajectories (for the
card), copies the chosen ``model.onnx`` to ``python/hybridmpm/models/<scene>.onnx``
with the scenes it serves stamped into its metadata, writes the model card
``<scene>.md`` and updates ``index.json``.

    python benchmarks/release/ship_model.py --scene water2d --valid benchmarks/results/neural_water2d_valid.json \
        --test benchmarks/results/neural_water2d_test.json --models-dir runs/models/water2d --serves dam_break2d
"""

from __future__ import annotations

import argparse
import csv
import json
from pathlib import Path

from hybridmpm.bench.harness import write_file, write_json

MODELS = Path(__file__).resolve().parents[2] / "python" / "hybridmpm" / "models"


def _core_hours(run: Path, step: int) -> float | None:
    """The training's CPU time up to ``step`` from the run's ``log.csv`` (copied beside the candidate), if it has one."""
    log = run / "log.csv"
    if not log.exists():
        return None
    with open(log, newline="") as f:
        rows = {int(r["step"]): r for r in csv.DictReader(f)}
    row = rows.get(step)
    return float(row["core_seconds"]) / 3600 if row and row.get("core_seconds") else None


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scene", required=True)
    ap.add_argument("--valid", required=True, type=Path)
    ap.add_argument("--test", required=True, type=Path)
    ap.add_argument("--models-dir", required=True, type=Path)
    ap.add_argument("--serves", nargs="*", default=[], help="other scenes the model serves")
    ap.add_argument("--tolerance", type=float, default=0.10)
    ap.add_argument("--note", default="", help="a sentence added to the card (e.g. how the candidates were chosen)")
    ap.add_argument("--how", default=None, help="how the run was made, for the card's training line (default: the sweep or train_long.sh)")
    a = ap.parse_args()
    import onnx

    from hybridmpm.neural import fused
    from hybridmpm.sim.neural import RELAX_ITERATIONS
    from hybridmpm.train.gns.train import TrainConfig

    valid = json.loads(a.valid.read_text())
    test_all = json.loads(a.test.read_text())
    test = {r["model"]: r for r in test_all["models"]}
    rows = valid["models"]
    best = min(r["rollout_mean"] for r in rows)
    ok = [r for r in rows if r["rollout_mean"] <= (1 + a.tolerance) * best]
    chosen = min(ok, key=lambda r: (r["meta"].get("parameters", 0), r["ms_per_frame"]))
    src = a.models_dir / chosen["model"] / "model.onnx"
    proto = onnx.load(str(src))
    for p in proto.metadata_props:
        if p.key == "hybridmpm":
            meta = json.loads(p.value)
            meta["scenes"] = [a.scene, *a.serves]
            meta["name"] = chosen["model"]
            p.value = json.dumps(meta, sort_keys=True)
    MODELS.mkdir(exist_ok=True)
    dst = MODELS / f"{a.scene}.onnx"
    onnx.save(proto, str(dst))
    fused.write_fused(dst)  # models/fused/: the graph with the fused edge kernels, for serving without the onnx package
    t = test[chosen["model"]]
    data_meta = json.loads((Path(valid["data"]) / "metadata.json").read_text())
    train_cfg = json.loads((a.models_dir / chosen["model"] / "train_config.json").read_text())
    if a.how is not None:
        how_trained = a.how
    elif meta["steps"] <= 4000:
        how_trained = "(`benchmarks/train_models.sh`: the candidates at an equal budget of 4000 steps)."
    else:
        how_trained = (
            "(`benchmarks/train_long.sh`: the configuration chosen in the 4000-step sweep of `benchmarks/train_models.sh`, resumed; "
            "the learning rate decays over the full step count, so the resumed run restarts from a higher rate)."
        )
    # the run's own command (train_config.json), its options that differ from the defaults included
    data = train_cfg.get("data", valid["data"])
    run_steps = train_cfg.get("steps", meta["steps"])
    train_command = " ".join(
        [
            f"hybridmpm train {train_cfg.get('scene', a.scene)} --data {' '.join(data) if isinstance(data, list) else data}",
            f"--latent {meta['latent']} --layers {meta['layers']} --r-t {meta['r_t']} --radius {meta['radius']} --steps {run_steps}",
            *([f"--noise-std {train_cfg['noise_std']}"] if train_cfg.get("noise_std", TrainConfig.noise_std) != TrainConfig.noise_std else []),
            *([f"--ema {train_cfg['ema']}"] if train_cfg.get("ema") else []),
            *([f"--unroll {train_cfg['unroll']} --unroll-after {train_cfg['unroll_after']}"] if train_cfg.get("unroll", 1) > 1 else []),
            *([f"--wall-reach {train_cfg['wall_reach']:g}"] if train_cfg.get("wall_reach", 1.0) != 1.0 else []),
            *([f"--grid {train_cfg['grid']} --grid-width {train_cfg['grid_width']} --grid-levels {train_cfg['grid_levels']}"] if train_cfg.get("grid") else []),
            *([f"--seed {train_cfg['seed']}"] if train_cfg.get("seed") else []),
            "--threads 1",
        ]
    )
    branch = meta.get("grid_branch")
    core_h = _core_hours(a.models_dir / chosen["model"], meta["steps"])
    lines = [
        f"# Model card: `{a.scene}.onnx` ({chosen['model']})",
        "",
        (
            f"GNS (paper App. A) with a grid branch ({branch['grid']}^{meta['dim']} grid, U-Net width {branch['width']}, {branch['levels']} levels; "
            "docs/neural.md, The grid branch)"
            if branch
            else "GNS (paper App. A)"
        )
        + f" for `{a.scene}`"
        + (f", also serving {', '.join(f'`{s}`' for s in a.serves)}" if a.serves else "")
        + ".",
        f"Chosen by `benchmarks/release/ship_model.py`: the fewest parameters among the candidates whose validation rollout error is within "
        f"{a.tolerance:.0%} of the best ({best:.3f}) among {len(rows)} candidate(s). {a.note}".rstrip(),
        "",
        "## Data",
        f"`hybridmpm generate {data_meta.get('scene', a.scene)} --trajectories {sum(data_meta['trajectories'].values())} --r-p {data_meta['r_p']} --out {valid['data']}` "
        f"({data_meta['trajectories']['train']} training trajectories of {data_meta['frames']} frames, MPM at r_p = {data_meta['r_p']:.4f}); "
        f"train.npz sha256 `{data_meta['sha256']['train'][:16]}…`.",
        "",
        "## Config",
        f"latent {meta['latent']}, L = {meta['layers']} message-passing layers, R = {meta['radius']} m, r_t = {meta['r_t']} frames per step, "
        f"r_p = {meta['r_p']:.4f}, T_in = {meta['t_in']}, {meta['parameters']} parameters, training noise {train_cfg['noise_std']} m/step, "
        f"batch {train_cfg['batch']} windows, Adam lr {train_cfg['lr']} → decayed ×0.1.",
        "",
        "## Training",
        f"{meta['steps']} steps in {meta['train_seconds']:.0f} s on one CPU thread (2-core machine"
        + (f"; {core_h:.3f} core-hours" if core_h is not None else "")
        + "): "
        + (f"the step-{meta['steps']} snapshot of " if meta["steps"] != run_steps else "")
        + f"`{train_command}` {how_trained}",
        "",
        "## Errors (grid-mass error against full-resolution MPM, docs/design.md)",
        f"Network rollouts as `NeuralSimulator` runs them: predictions clipped to the domain and density-relaxed ({RELAX_ITERATIONS} iterations, the default).",
        f"- test split ({test_all['seeds']} trajectories), {test_all['frames']}-frame rollout: mean {t['rollout_mean']:.3f}, last frame {t['rollout_last']:.3f}",
        f"- test split, one-step (from MPM-at-r_p history): {t['one_step']:.3f}",
        f"- validation rollout (selection): {chosen['rollout_mean']:.3f}",
        f"- floor: MPM at r_p on the same test seeds: {test_all['reference']['mpm_rp_mean']:.3f}",
        *(
            [f"- the trivial model (MPM at r_p's particles held still after the warm-up) on the same test seeds: {test_all['reference']['still_mean']:.3f}"]
            if "still_mean" in test_all["reference"]
            else []
        ),
        "",
        "## Cost",
        f"{t['ms_per_frame']:.2f} ms per frame in the test rollouts (graph + onnxruntime, one thread, / r_t); "
        f"step at 2.3k particles {t['timing_2300']['step_ms']:.2f} ms, at 4k {t['timing_4096']['step_ms']:.2f} ms; "
        f"MPM at full resolution {test_all['reference']['mpm_full_ms_2t']:.2f} ms/frame (2 threads) in the same run.",
    ]
    write_file(dst.with_suffix(".md"), "\n".join(lines) + "\n")
    index_path = MODELS / "index.json"
    index = json.loads(index_path.read_text()) if index_path.exists() else {}
    for s in [a.scene, *a.serves]:
        index[s] = dst.name
    write_json(index_path, dict(sorted(index.items())), indent=2)
    print(f"shipped {chosen['model']} as {dst} ({dst.stat().st_size / 1e3:.0f} kB) for {[a.scene, *a.serves]}")


if __name__ == "__main__":
    main()
