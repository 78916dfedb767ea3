"""Neural simulator: cost and accuracy of each trained model, against MPM in the same run.

For every model directory (``hybridmpm train`` output: ``model.onnx``, and
``checkpoint.pt``/``best.pt`` for the torch comparison):

* **inference cost per step** on lattice blocks of ~2.3k and ~4k particles at
  the model's particle spacing: graph build (Rust radius graph), onnxruntime
  (1 thread) and torch eager (1 thread, no grad) in the same run, medians;
* **accuracy on the test split** (the first ``--seeds`` test trajectories of
  the dataset, rebuilt from ``scenes.json`` at full resolution): grid-mass
  error (docs/design.md) against full-resolution MPM over a ``--frames`` rollout
  (mean and last) and one-step (each step predicted from the MPM-at-r_p
  history, compared with full-resolution MPM ``r_t`` frames later); MPM at
  ``r_p`` itself is reported as the floor;
* **cost per frame** of the rollouts (neural step incl. graph build / ``r_t``)
  against MPM at full resolution on the same initial conditions (2 threads
  and 1 thread), measured in the same run.

Writes ``OUT.md``, ``OUT.json`` and ``OUT.png`` (error against cost per frame).

    python benchmarks/bench_neural.py --data data/water2d_rp --models runs/models/water2d/* --out benchmarks/results/neural_water2d
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

from hybridmpm.bench.harness import write_results


def _median_ms(fn, repeats: int) -> float:
    fn()
    ts = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        ts.append(time.perf_counter() - t0)
    return float(np.median(ts) * 1e3)


def timing(model_dir: Path, n: int, repeats: int) -> dict:
    import torch

    from hybridmpm import radius_graph
    from hybridmpm.neural import GnsRuntime
    from hybridmpm.scenes import lattice
    from hybridmpm.train.gns.model import GnsConfig, GnsModel

    nm = GnsRuntime(model_dir / "model.onnx", threads=1)
    spacing = 0.5 / 128 / np.sqrt(nm.r_p) if nm.dim == 2 else 0.5 / 64 / np.cbrt(nm.r_p)
    side = int(np.ceil(n ** (1 / nm.dim)))
    x = lattice([0.2] * nm.dim, [0.2 + side * spacing] * nm.dim, spacing)[:n]
    rng = np.random.default_rng(0)
    hist = np.stack([x + k * rng.normal(0, 2e-4, x.shape).astype(np.float32) for k in range(nm.t_in)]).astype(np.float32)
    ptype = np.full(len(x), 5, np.int64)
    s, r, disp, dist = radius_graph(hist[-1], nm.radius)
    out = {"particles": len(x), "edges": int(len(s))}
    out["graph_ms"] = _median_ms(lambda: radius_graph(hist[-1], nm.radius), repeats)
    feeds = nm.feeds(hist, ptype, (s, r, disp, dist))  # compiled graphs also take the edge geometry
    out["onnx_ms"] = _median_ms(lambda: nm.session_for(feeds).run(None, feeds), repeats)
    ckpt = model_dir / "checkpoint.pt"
    if ckpt.exists():
        state = torch.load(ckpt, weights_only=False)
        model = GnsModel(GnsConfig.from_dict(state["gns_config"])).eval()
        best = model_dir / "best.pt"
        model.load_state_dict(torch.load(best, weights_only=True) if best.exists() else state["model"])
        torch.set_num_threads(1)
        args = (torch.from_numpy(hist), torch.from_numpy(ptype), torch.from_numpy(s), torch.from_numpy(r))
        with torch.no_grad():
            out["torch_ms"] = _median_ms(lambda: model(*args), max(3, repeats // 4))
        out["onnx_speedup_vs_torch"] = out["torch_ms"] / out["onnx_ms"]
    out["step_ms"] = out["graph_ms"] + out["onnx_ms"]
    out["graph_share"] = out["graph_ms"] / out["step_ms"]
    return out


def accuracy(model_dirs: list[Path], data: Path, seeds: int, frames: int, split: str = "test") -> tuple[dict, dict]:
    from hybridmpm.bench.run import held_still
    from hybridmpm.metrics import grid_mass_error
    from hybridmpm.neural import GnsRuntime
    from hybridmpm.scenes import SceneSpec
    from hybridmpm.sim import MpmSimulator, NeuralSimulator, rollout, warmup_frames

    scenes = json.loads((data / "scenes.json").read_text())
    test = sorted(k for k, v in scenes.items() if v["split"] == split)[:seeds]
    per_model: dict[str, dict[str, list[float]]] = {d.name: {"rollout_mean": [], "rollout_last": [], "one_step": [], "ms_per_frame": []} for d in model_dirs}
    ref_stats: dict[str, list[float]] = {"mpm_full_ms_2t": [], "mpm_full_ms_1t": [], "mpm_rp_ms_1t": [], "mpm_rp_mean": [], "mpm_rp_last": [], "still_mean": []}
    models = {d.name: GnsRuntime(d / "model.onnx", threads=1) for d in model_dirs}
    for tid in test:
        info = scenes[tid]
        full = SceneSpec.from_dict(info["spec"]).build()
        n_grid = full.params.resolved_n_grid()
        for threads, key in ((0, "mpm_full_ms_2t"), (1, "mpm_full_ms_1t")):
            ro = rollout(MpmSimulator(full, threads=threads), frames)
            ref_stats[key].append(float(ro.seconds.sum()) / frames * 1e3)
        ref_a = ro.fluid_positions
        r_p = next(iter(models.values())).r_p
        mpm_rp = MpmSimulator(full, r_p=r_p, seed=info["seed"], threads=1)
        low = mpm_rp.scene
        ro = rollout(mpm_rp, frames)
        ref_stats["mpm_rp_ms_1t"].append(float(ro.seconds.sum()) / frames * 1e3)
        low_a = ro.fluid_positions
        e = grid_mass_error(low_a, ref_a, n_grid)
        ref_stats["mpm_rp_mean"].append(float(e.mean()))
        ref_stats["mpm_rp_last"].append(float(e[-1]))
        # the trivial model: MPM at r_p's particles held still after the networks' warm-up
        still = held_still(low_a, np.arange(len(low_a)), warmup_frames(next(iter(models.values()))))
        ref_stats["still_mean"].append(float(grid_mass_error(still, ref_a, n_grid).mean()))
        for name, nm in models.items():
            res = rollout(NeuralSimulator(full, nm, seed=info["seed"], detect_failures=False, mpm_threads=1), frames)
            pos = res.fluid_positions
            k = res.frame_index
            keep = k <= frames
            e = grid_mass_error(pos[keep], ref_a[k[keep]], n_grid)
            m = per_model[name]
            m["rollout_mean"].append(float(e.mean()))
            m["rollout_last"].append(float(e[-1]))
            net = res.solver == "neural"
            m["ms_per_frame"].append(float(np.median(res.seconds[net]) * 1e3 / nm.r_t))
            # one-step: history from MPM at r_p, compared with full-resolution MPM r_t frames later
            errs = []
            pt = low.particle_type()
            for t in range((nm.t_in - 1) * nm.r_t, frames - nm.r_t + 1, nm.r_t):
                hist = mpm_rp.particles.pad(low_a[t - (nm.t_in - 1) * nm.r_t : t + 1 : nm.r_t])
                _, nxt, _ = nm.predict(hist, pt)
                errs.append(float(grid_mass_error(nxt[: low.num_particles], ref_a[t + nm.r_t], n_grid)[0]))
            m["one_step"].append(float(np.mean(errs)))
    return per_model, ref_stats


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", required=True, type=Path)
    ap.add_argument("--models", nargs="+", required=True, type=Path)
    ap.add_argument("--seeds", type=int, default=3)
    ap.add_argument("--frames", type=int, default=100)
    ap.add_argument("--repeats", type=int, default=20)
    ap.add_argument("--split", default="test", choices=["valid", "test"], help="trajectories to score (valid: for choosing a model)")
    ap.add_argument("--out", required=True, type=Path)
    a = ap.parse_args()
    dirs = [d for d in a.models if (d / "model.onnx").exists()]
    per_model, ref = accuracy(dirs, a.data, a.seeds, a.frames, a.split)
    rows = []
    for d in dirs:
        meta = json.loads((d / "summary.json").read_text()) if (d / "summary.json").exists() else {}
        t23, t4 = timing(d, 2300, a.repeats), timing(d, 4096, a.repeats)
        m = per_model[d.name]
        rows.append({"model": d.name, "meta": meta, "timing_2300": t23, "timing_4096": t4, **{k: float(np.mean(v)) for k, v in m.items()}})
    refm = {k: float(np.mean(v)) for k, v in ref.items()}
    doc = {"split": a.split, "seeds": a.seeds, "frames": a.frames, "data": str(a.data), "reference": refm, "models": rows}
    lines = [
        f"# Neural simulator on `{a.data.name}`: cost and accuracy against MPM",
        "",
        f"Accuracy: mean over the first {a.seeds} {a.split} trajectories, {a.frames}-frame rollouts, grid-mass error (docs/design.md) against full-resolution MPM.",
        "Timing: medians; onnxruntime and torch one thread each; graph = Rust radius graph.",
        "",
        "| model | params | train steps / s | rollout error mean | last | one-step error | neural ms/frame (rollouts) | step ms @2.3k: graph + onnx = total (torch) | @4k | onnx vs torch @2.3k |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        t, t4 = r["timing_2300"], r["timing_4096"]
        torch_s = f"{t['torch_ms']:.1f}" if "torch_ms" in t else "—"
        speed = f"{t['onnx_speedup_vs_torch']:.2f}×" if "onnx_speedup_vs_torch" in t else "—"
        lines.append(
            f"| {r['model']} | {r['meta'].get('parameters', '?')} | {r['meta'].get('steps', '?')} / {r['meta'].get('train_seconds', '?')} | "
            f"{r['rollout_mean']:.3f} | {r['rollout_last']:.3f} | {r['one_step']:.3f} | {r['ms_per_frame']:.2f} | "
            f"{t['graph_ms']:.2f} + {t['onnx_ms']:.2f} = {t['step_ms']:.2f} ({torch_s}), {t['edges']} edges | {t4['step_ms']:.2f} | {speed} |"
        )
    lines += [
        "",
        f"MPM on the same initial conditions: full resolution {refm['mpm_full_ms_2t']:.2f} ms/frame (2 threads), "
        f"{refm['mpm_full_ms_1t']:.2f} (1 thread); at r_p {refm['mpm_rp_ms_1t']:.2f} (1 thread), grid-mass error "
        f"{refm['mpm_rp_mean']:.3f} mean, {refm['mpm_rp_last']:.3f} last (the floor of any model at this r_p); "
        f"its particles held still after the warm-up (the trivial model): {refm['still_mean']:.3f} mean.",
    ]
    fig = plot(rows, refm, a.frames, a.data.name)
    write_results(a.out.parent, a.out.name, doc=doc, markdown="\n".join(lines), figures={f"{a.out.name}.png": fig}, dpi=120)
    print("\n".join(lines))


def plot(rows: list[dict], refm: dict, frames: int, title: str):  # type: ignore[no-untyped-def]
    """Each model's rollout error against its cost per frame, with MPM's (the figure)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 4))
    for r in rows:
        ax.scatter(r["ms_per_frame"], r["rollout_mean"], s=30)
        ax.annotate(r["model"], (r["ms_per_frame"], r["rollout_mean"]), fontsize=7, xytext=(4, 3), textcoords="offset points")
    ax.scatter(refm["mpm_full_ms_2t"], 0.0, marker="s", c="k")
    ax.annotate("MPM full (2 threads)", (refm["mpm_full_ms_2t"], 0.0), fontsize=7, xytext=(4, 3), textcoords="offset points")
    ax.scatter(refm["mpm_rp_ms_1t"], refm["mpm_rp_mean"], marker="D", c="grey")
    ax.annotate("MPM r_p (1 thread)", (refm["mpm_rp_ms_1t"], refm["mpm_rp_mean"]), fontsize=7, xytext=(4, 3), textcoords="offset points")
    ax.set_xscale("log")
    from matplotlib.ticker import NullFormatter, ScalarFormatter

    ax.xaxis.set_major_formatter(ScalarFormatter())
    ax.xaxis.set_minor_formatter(NullFormatter())
    ax.set_ylim(bottom=-0.05)
    ax.set_xlabel("cost per frame [ms] (neural: graph + onnxruntime step / r_t)")
    ax.set_ylabel(f"grid-mass error, {frames}-frame rollout (mean)")
    ax.set_title(title, fontsize=9)
    fig.tight_layout()
    return fig


if __name__ == "__main__":
    main()
