"""Training curves of GNS runs: rollout error of each snapshot against training step and core-hours.

For every run directory (``hybridmpm train`` output with ``snapshots/``, on by
default, and ``log.csv``), every ``--every``-th snapshot is scored by
``bench_neural.accuracy`` on the first ``--seeds`` trajectories of a split
(``valid`` by default: this is for choosing a checkpoint): the network alone,
after the MPM warm-up, over a ``--frames`` rollout, grid-mass error (docs/design.md)
against full-resolution MPM, with MPM at ``r_p`` on the same initial
conditions as the floor. The run's own validation one-step loss and wall time
come from its ``log.csv`` (core-hours: its ``core_seconds``, the CPU time of the training processes).

Writes ``OUT.md`` (one table per run, and each run's best snapshot), ``OUT.json``
and ``OUT.png`` (rollout error against step and against core-hours; one-step
validation loss against step).

    python benchmarks/training_curves.py --data data/water2d_rp --runs runs/water2d_a runs/water2d_b --every 5 --out benchmarks/results/curves_water2d
"""

from __future__ import annotations

import argparse
import csv
from pathlib import Path

import numpy as np
from bench_neural import accuracy

from hybridmpm.bench.harness import write_results


def snapshots(run: Path, every: int) -> list[Path]:
    """Every ``every``-th snapshot directory of ``run`` (by step), always including the last."""
    snaps = sorted(p.parent for p in (run / "snapshots").glob("step_*/model.onnx"))
    if not snaps:
        raise SystemExit(f"{run}: no snapshots/step_*/model.onnx (train with snapshots, the default)")
    picked = snaps[::every]
    if picked[-1] != snaps[-1]:
        picked.append(snaps[-1])
    return picked


def log_rows(run: Path) -> dict[int, dict[str, str]]:
    """``log.csv`` rows by step (a resumed run's repeated steps: the last row wins)."""
    with open(run / "log.csv", newline="") as f:
        return {int(r["step"]): r for r in csv.DictReader(f)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", required=True, type=Path, help="the runs' dataset (hybridmpm generate)")
    ap.add_argument("--runs", nargs="+", required=True, type=Path)
    ap.add_argument("--every", type=int, default=1, help="score every N-th snapshot (the last always)")
    ap.add_argument("--seeds", type=int, default=3)
    ap.add_argument("--frames", type=int, default=100)
    ap.add_argument("--split", default="valid", choices=["valid", "test"])
    ap.add_argument("--out", required=True, type=Path)
    a = ap.parse_args()
    if a.every < 1:
        raise SystemExit("--every: must be >= 1")
    result: dict = {"data": str(a.data), "split": a.split, "seeds": a.seeds, "frames": a.frames, "runs": {}}
    floor = None
    for run in a.runs:
        dirs = snapshots(run, a.every)
        per_model, ref = accuracy(dirs, a.data, a.seeds, a.frames, a.split)
        floor = float(np.mean(ref["mpm_rp_mean"]))
        logs = log_rows(run)
        rows = []
        for d in dirs:
            step = int(d.name.split("_")[1])
            m = per_model[d.name]
            lg = logs.get(step, {})
            rows.append(
                {
                    "step": step,
                    "wall_h": float(lg["elapsed_s"]) / 3600 if "elapsed_s" in lg else None,
                    "core_h": float(lg["core_seconds"]) / 3600 if lg.get("core_seconds") else None,
                    "val_one_step": float(lg["val_one_step"]) if "val_one_step" in lg else None,
                    "rollout_mean": float(np.mean(m["rollout_mean"])),
                    "rollout_last": float(np.mean(m["rollout_last"])),
                    "one_step": float(np.mean(m["one_step"])),
                }
            )
        result["runs"][str(run)] = {"mpm_rp_mean": floor, "still_mean": float(np.mean(ref["still_mean"])), "snapshots": rows}
    lines = [
        f"# Training curves on `{a.data.name}` ({a.split} split)",
        "",
        f"Network alone after the MPM warm-up, {a.frames}-frame rollouts, mean over the first {a.seeds} {a.split} "
        "trajectories; grid-mass error against full-resolution MPM.",
    ]
    for run, r in result["runs"].items():
        best = min(r["snapshots"], key=lambda s: s["rollout_mean"])
        lines += [
            "",
            f"## `{run}`",
            "",
            f"MPM at r_p on the same trajectories: {r['mpm_rp_mean']:.3f}; its particles held still after the warm-up "
            f"(the trivial model): {r['still_mean']:.3f}. Best snapshot: step {best['step']}, "
            f"{best['rollout_mean']:.3f} ({best['rollout_mean'] / r['mpm_rp_mean']:.2f}× MPM at r_p).",
            "",
            "| step | wall h | core h | val one-step loss | rollout error mean | last | one-step error |",
            "|---|---|---|---|---|---|---|",
        ]
        for s in r["snapshots"]:
            wall = f"{s['wall_h']:.2f}" if s["wall_h"] is not None else "—"
            core = f"{s['core_h']:.3f}" if s.get("core_h") is not None else "—"
            v1 = f"{s['val_one_step']:.3f}" if s["val_one_step"] is not None else "—"
            lines.append(f"| {s['step']} | {wall} | {core} | {v1} | {s['rollout_mean']:.3f} | {s['rollout_last']:.3f} | {s['one_step']:.3f} |")
    fig = plot(result, floor)
    write_results(a.out.parent, a.out.name, doc=result, markdown="\n".join(lines), figures={f"{a.out.name}.png": fig}, dpi=120)
    print("\n".join(lines))


def plot(result: dict, floor: float | None):
    """Rollout error against step and training cost, and the validation one-step loss, per run (the figure)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(1, 3, figsize=(13, 3.8))
    for run, r in result["runs"].items():
        s = r["snapshots"]
        name = Path(run).name
        ax[0].plot([x["step"] for x in s], [x["rollout_mean"] for x in s], "o-", ms=3, label=name)
        # core-hours (CPU time of the training process) where the log has them, else wall hours
        wall = [(x["core_h"] if x.get("core_h") is not None else x["wall_h"], x["rollout_mean"]) for x in s if x["wall_h"] is not None]
        if wall:
            ax[1].plot(*zip(*wall), "o-", ms=3, label=name)
        v1 = [(x["step"], x["val_one_step"]) for x in s if x["val_one_step"] is not None]
        if v1:
            ax[2].plot(*zip(*v1), "o-", ms=3, label=name)
    for k in (0, 1):
        if floor is not None:
            ax[k].axhline(floor, color="k", ls="--", lw=1, label="MPM at r_p")
            ax[k].axhline(1.5 * floor, color="k", ls=":", lw=1, label="1.5× MPM at r_p")
        still = [r["still_mean"] for r in result["runs"].values() if "still_mean" in r]
        if still:
            ax[k].axhline(float(np.mean(still)), color="grey", ls="-.", lw=1, label="particles held still")
        ax[k].set_ylabel("rollout grid-mass error (mean)")
    ax[0].set_xlabel("training step")
    ax[1].set_xlabel("training cost [core-hours; wall hours for logs without core_seconds]")
    ax[2].set_xlabel("training step")
    ax[2].set_ylabel("validation one-step loss")
    ax[0].legend(fontsize=7)
    fig.tight_layout()
    return fig


if __name__ == "__main__":
    main()
