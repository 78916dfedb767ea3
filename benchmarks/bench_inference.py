"""Where a network step's time goes, per scene, and what it achieves.

For every shipped model (``hybridmpm.models``) on a state of its own scene
(a rollout of the network alone from the seed, after the MPM warm-up):

* **breakdown** of one network step (median over repeats, one onnxruntime
  thread): each stage of the ONNX graph (onnxruntime's profiler; node-name
  prefixes ``hybridmpm.train.gns.onnx_graph.STAGES``; graphs of torch's exporter,
  given with ``--baseline``, are grouped by operator type instead), the
  checks and history update of :class:`~hybridmpm.sim.NeuralSimulator`, the
  clipping, density relaxation and next step's radius graph of its
  prediction (``hybridmpm.graph.relax_then_graph``, one call), and the rest
  of ``advance()`` (Python overhead: the step timed with the network and the
  relaxation replaced by their cached results, less the checks); what the
  step takes beyond the parts is listed as unattributed (the network's
  inputs built around the ONNX run: feeds). The radius graph of the state
  alone (Rust cell list, with the edge geometry) is timed for reference: the
  step gets it from the relaxation;
* **cost per frame**: the network alone (``advance()`` / ``r_t``) against
  MPM at ``r_p`` (``MpmSimulator`` at the model's ``r_p``, ``--mpm-threads``,
  from the frame of the network's state, restored to it at each burst),
  same run, interleaved in bursts (each callable ``--burst`` times back to
  back, the first call of a burst not counted: a rollout's steady state), as a
  ratio;
* **GFLOP/s** on a block of ``--particles`` (≥ 2 000) particles at the
  model's spacing: dense-layer FLOPs (``hybridmpm.bench.cost.gnn_flops``)
  over the onnxruntime time, 1 and 2 threads.

``--ops`` adds onnxruntime's per-operator cost at the model width (ns per
row of ``latent`` floats, ``E`` rows): what bounds a 16-wide network here.
``--baseline DIR`` times the ``.onnx`` files of DIR in the same run,
interleaved with the shipped ones ("before and after"), unfused; ``--baseline-rev REV``
takes them from a git revision (94de7d8: the graphs of torch's exporter;
807d7d7: graphs of the current layout, so the plain graph against the fused
kernels). Graphs of an earlier compiled layout are refused by ``GnsRuntime``
(their training runs export them again).

    python benchmarks/bench_inference.py --baseline-rev 807d7d7 --ops --out benchmarks/results/inference

The simulator is driven through its public API (``propose``, ``commit``,
``state``, ``restore``, ``advance``), except for its failure check
(``_failure``), which has no public entry of its own and is timed alone, and
the stand-ins for the network and the relaxation that leave the simulator's
own work to time (the ``radius_graph`` and ``relax_then_graph`` of
``hybridmpm.sim.neural`` replaced during that call).

Check the load first (``uptime``); every figure that is compared is a ratio
within this run.
"""

from __future__ import annotations

import argparse
import collections
import itertools
import json
import os
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from hybridmpm.bench.cost import gnn_flops
from hybridmpm.bench.harness import write_file, write_results
from hybridmpm.graph import radius_graph, relax_then_graph
from hybridmpm.models import shipped_model
from hybridmpm.neural import GnsRuntime
from hybridmpm.scenes import lattice, make_scene
from hybridmpm.sim import MpmSimulator, NeuralSimulator, Proposal
from hybridmpm.train.gns.onnx_graph import STAGES

SCENES = ("water2d", "dam_break2d", "sand2d", "sand_ramps2d", "water_ramps2d", "water_sand2d", "water3d", "sand3d")


#: Pause after a run of spinning onnxruntime threads, so that their busy-wait
#: (tens of ms) does not land on the next timed callable [s].
SETTLE_S = 0.15


#: Calls of a callable back to back per turn of :func:`_interleaved` (``--burst``).
BURST = 4


def _interleaved(fns: dict[str, Any], repeats: int, spinning: tuple[str, ...] = ()) -> dict[str, float]:
    """Median ms of each callable, run in turn (so that a noisy minute hits all),
    :data:`BURST` times back to back per turn with the first call of each burst
    not counted: it pays for what the previous callable left behind (caches,
    an MPM thread pool gone idle), which a rollout, calling the same step
    again and again, does not (with one call per turn the radius graph of a
    500-particle state measured 0.46 ms, against 0.08–0.13 in a loop of its
    own, and MPM at r_p on the dam break 2.0 against 1.1 ms per frame). The
    callables named in ``spinning`` are followed by a :data:`SETTLE_S` pause."""
    ts: dict[str, list[float]] = {k: [] for k in fns}
    for _ in range(repeats):
        for k, fn in fns.items():
            for i in range(BURST):
                t0 = time.perf_counter()
                fn()
                if i or BURST == 1:
                    ts[k].append(time.perf_counter() - t0)
            if k in spinning:
                time.sleep(SETTLE_S)
    return {k: float(np.median(v) * 1e3) for k, v in ts.items()}


def _profile(path: Path, history: np.ndarray, ptype: np.ndarray, graph: tuple, repeats: int, fused: bool | None = None) -> dict[str, float]:
    """Mean µs per run by stage (compiled graphs) or by operator (others), from onnxruntime's profiler."""
    nm = GnsRuntime(path, profile=True, fused=fused)
    feeds = nm.feeds(history, ptype, graph)
    for _ in range(repeats):
        nm.session_for(feeds).run(None, feeds)
    prof = nm.session.end_profiling()
    groups: dict[str, float] = collections.defaultdict(float)
    with open(prof) as fh:
        events = json.load(fh)
    os.remove(prof)
    for ev in events:
        if ev.get("cat") != "Node" or not ev.get("name", "").endswith("_kernel_time"):
            continue
        name = ev["name"][: -len("_kernel_time")].removeprefix("fused ").strip()
        stage = name.split("/")[0]
        groups[stage if stage in STAGES else f"op:{ev['args']['op_name']}"] += ev["dur"]
    return {k: v / repeats for k, v in sorted(groups.items(), key=lambda kv: -kv[1])}


def scene_state(scene: str, seed: int, steps: int) -> tuple[NeuralSimulator, dict[str, Any], Proposal]:
    """The network alone on ``scene`` after its warm-up and ``steps`` (≥ 1)
    network steps (failure checks on), the last one proposed and committed by
    hand; with the state before it and its proposal, so that
    ``sim.restore(before); sim.commit(last)`` comes back to this state with the
    radius graph the next step reuses, as in a rollout."""
    sim = NeuralSimulator(scene, shipped_model(scene), seed=seed, mpm_threads=1)
    while sim.warming_up:
        sim.advance()
    for _ in range(steps - 1):
        sim.advance()
    before = sim.state()
    last = sim.propose()
    assert last.failure is None, last.failure
    sim.commit(last)
    return sim, before, last


def breakdown(scene: str, seed: int, steps: int, repeats: int, mpm_threads: int, baseline: Path | None) -> dict[str, Any]:
    sim, before, last = scene_state(scene, seed, steps)
    model = sim.model
    hist, ptype = sim.history, sim.particles.particle_type
    assert hist is not None
    graph = radius_graph(hist[-1], model.radius)
    n, e = hist.shape[1], len(graph[0])
    paths = {"shipped": model.path}
    if baseline is not None and (baseline / model.path.name).is_file():
        paths["baseline"] = baseline / model.path.name
    sessions = {k: GnsRuntime(p, fused=None if k == "shipped" else False) for k, p in paths.items()}  # a baseline as it was: unfused
    feeds = {k: s.feeds(hist, ptype, graph) for k, s in sessions.items()}
    proposal = sim.propose()

    def checks() -> None:
        sim.failure_of(proposal.predicted)
        np.concatenate([hist[1:], proposal.predicted[None]])

    domain = np.asarray(model.meta["bounds"], np.float32)  # what the simulator clips to
    bounds = (domain[:, 0], domain[:, 1]) if sim.clamp else None
    movable = np.ascontiguousarray(sim.particles.fluid_mask)

    def relaxation() -> Any:
        # what advance() does with the prediction: clip, relax, clip and the next
        # step's radius graph, one call (the graph alone without relaxation)
        if sim.relax:
            return relax_then_graph(proposal.predicted, movable, model.radius, sim.rest_density, sim.relax, bounds=bounds)
        return radius_graph(proposal.predicted if bounds is None else np.clip(proposal.predicted, *bounds), model.radius)

    # the full step from the same state each time: the state before the last step and
    # that step committed again (its proposal holds the graph the next step reuses)
    models = {1: model, 2: GnsRuntime(model.path, threads=2)}

    def restore() -> None:
        sim.restore(before)
        sim.commit(last)

    def step(threads: int) -> None:
        sim.model = models[threads]
        restore()
        sim.advance()
        sim.model = model

    restore_ms = _interleaved({"restore": restore}, repeats)["restore"]

    # the same step with the network and the radius graph replaced by their cached
    # results: what is left is the simulator's own work (checks, clamp, history, Python)
    import hybridmpm.sim.neural as neural_module

    cached = model.predict(hist, ptype, graph=graph)
    relaxed = relaxation()

    class _Cached:
        radius = model.radius

        def predict(self, *args: Any, **kwargs: Any) -> Any:
            return cached

    def stubbed_step() -> None:
        real = neural_module.radius_graph, neural_module.relax_then_graph
        sim.model = _Cached()  # type: ignore[assignment]
        neural_module.radius_graph = lambda *a, **k: relaxed  # type: ignore[assignment]
        neural_module.relax_then_graph = lambda *a, **k: relaxed  # type: ignore[assignment]
        try:
            restore()
            sim.advance()
        finally:
            sim.model = model
            neural_module.radius_graph, neural_module.relax_then_graph = real

    # MPM at r_p from the frame of the network's state (sand's cost changes as it flows), back to
    # it at the start of each burst (the first, uncounted call): both are timed at the same point
    mpm = MpmSimulator(sim.scene, r_t=1, threads=mpm_threads)
    for _ in range(max(5, sim.step_index * sim.r_t)):
        mpm.advance()
    mpm_state, mpm_calls = mpm.state(), itertools.count()

    def mpm_frame() -> None:
        if BURST > 1 and next(mpm_calls) % BURST == 0:
            mpm.restore(mpm_state)
        mpm.advance()

    fns = {
        "radius_graph": lambda: radius_graph(hist[-1], model.radius),
        **{f"onnx_{k}": (lambda s=s, f=f: s.session_for(f).run(None, f)) for (k, s), f in zip(sessions.items(), feeds.values())},
        "checks_clamp_history": checks,
        "relaxation": relaxation,
        "advance": lambda: step(1),
        "simulator_own": stubbed_step,
        "mpm_rp_frame": mpm_frame,
        "advance_2t": lambda: step(2),
    }
    # the graphs' A/B on their own, back to back: in the loop below, the first ONNX run after another
    # kind of work (the radius graph, a pause) came out up to 1.3x slower than the same run after an
    # ONNX run, which biased the comparison against whichever graph ran first
    onnx = {k: fns.pop(k) for k in list(fns) if k.startswith("onnx_")}
    ms = {**_interleaved(onnx, repeats), **_interleaved(fns, repeats, spinning=("advance_2t",))}
    ms["advance"] -= restore_ms
    ms["advance_2t"] -= restore_ms
    ms["simulator_own"] -= restore_ms
    # advance() builds the graph of its prediction (for the next step) with the relaxation:
    # "relaxation" includes it; the radius graph alone is timed for reference
    python_ms = ms["simulator_own"] - ms["checks_clamp_history"]
    lat, layers = int(model.meta["latent"]), int(model.meta["layers"])
    flops = gnn_flops(lat, layers, model.dim, n, e, t_in=model.t_in)
    out: dict[str, Any] = {
        "scene": scene, "particles": n, "edges": e, "latent": lat, "layers": layers, "r_t": model.r_t, "r_p": model.r_p,
        "ms": ms, "python_overhead_ms": python_ms, "mflop_step": flops / 1e6,
        # the step less every part timed: the network's inputs built around the ONNX run
        # (the in-edge table, degrees, feeds) and what the parts' separate timing misses
        "unattributed_ms": ms["advance"] - ms["onnx_shipped"] - ms["checks_clamp_history"] - ms["relaxation"] - python_ms,
        "gflops_onnx": flops / ms["onnx_shipped"] / 1e6,
        "network_ms_per_frame": ms["advance"] / model.r_t, "mpm_rp_ms_per_frame": ms["mpm_rp_frame"],
        "ratio_network_to_mpm_rp": ms["advance"] / model.r_t / ms["mpm_rp_frame"],
        "network_2t_ms_per_frame": ms["advance_2t"] / model.r_t, "ratio_network_2t_to_mpm_rp": ms["advance_2t"] / model.r_t / ms["mpm_rp_frame"],
        "stages_us": _profile(paths["shipped"], hist, ptype, graph, repeats),
    }  # fmt: skip
    if "baseline" in paths:
        out["baseline_stages_us"] = _profile(paths["baseline"], hist, ptype, graph, repeats, fused=False)
        out["speedup_onnx"] = ms["onnx_baseline"] / ms["onnx_shipped"]
    return out


def block_gflops(scene: str, particles: int, repeats: int, baseline: Path | None) -> dict[str, Any]:
    """GFLOP/s of the shipped model on a jittered lattice block of ``particles`` particles at its spacing, 1 and 2 threads."""
    model = GnsRuntime(shipped_model(scene))
    dx = 1.0 / make_scene(scene, seed=0).params.resolved_n_grid()  # the unit domain's grid spacing
    spacing = dx / 2 / model.r_p ** (1 / model.dim)  # the scenes seed 2^D particles per cell at full resolution
    side = int(np.ceil(particles ** (1 / model.dim)))
    lo = np.asarray(model.meta["bounds"], np.float64)[:, 0] + 0.1
    x = lattice(list(lo), list(lo + side * spacing), spacing)[:particles].astype(np.float32)
    rng = np.random.default_rng(0)
    hist = np.stack([x + rng.normal(0, 0.05 * spacing, x.shape).astype(np.float32) for _ in range(model.t_in)])
    ptype = np.full(len(x), int(model.meta["particle_types"][0]), np.int64)
    graph = radius_graph(hist[-1], model.radius)
    flops = gnn_flops(int(model.meta["latent"]), int(model.meta["layers"]), model.dim, len(x), len(graph[0]), t_in=model.t_in)
    paths = {"shipped": model.path}
    if baseline is not None and (baseline / model.path.name).is_file():
        paths["baseline"] = baseline / model.path.name
    fns = {}
    for k, p in paths.items():
        # a graph of torch's exporter (ScatterND sums only) is exact on one thread only
        # (GnsRuntime would run it on one anyway): no 2-thread figure for it
        exact_on_two = "in_edges" in GnsRuntime(p).input_names
        for t in (1, 2) if exact_on_two else (1,):
            nm = GnsRuntime(p, threads=t, fused=None if k == "shipped" else False)  # 2 threads spin (GnsRuntime's default)
            f = nm.feeds(hist, ptype, graph)
            session = nm.session_for(f)
            fns[f"{k}_{t}t"] = lambda s=session, f=f: s.run(None, f)
    ms = _interleaved(fns, repeats, spinning=tuple(k for k in fns if k.endswith("_2t")))
    return {
        "scene": scene, "particles": len(x), "edges": len(graph[0]), "mean_degree": len(graph[0]) / len(x), "mflop_step": flops / 1e6,
        "ms": ms, "gflops": {k: flops / v / 1e6 for k, v in ms.items()},
    }  # fmt: skip


def op_costs(latent: int, rows: int, repeats: int) -> dict[str, float]:
    """ns per row of ``latent`` floats of single onnxruntime operators (one thread), chained 6 deep to amortise the run overhead."""
    import onnxruntime as ort
    from onnx import TensorProto, helper, numpy_helper

    rng = np.random.default_rng(0)
    w = numpy_helper.from_array(rng.normal(size=(latent, latent)).astype(np.float32), "W")
    b = numpy_helper.from_array(rng.normal(size=latent).astype(np.float32), "b")
    g = numpy_helper.from_array(np.ones(latent, np.float32), "g")
    idx = numpy_helper.from_array(rng.integers(0, rows // 10, rows).astype(np.int64), "idx")
    idx2 = numpy_helper.from_array(np.sort(rng.integers(0, rows // 10, rows)).astype(np.int64)[:, None], "idx2")

    def one(kind: str, x: str, i: int) -> tuple[list[Any], str]:
        o = f"o{i}"
        mk = helper.make_node
        if kind == "MatMul":
            return [mk("MatMul", [x, "W"], [o])], o
        if kind == "Gemm (bias)":
            return [mk("Gemm", [x, "W", "b"], [o])], o
        if kind == "Gemm+Relu":
            return [mk("Gemm", [x, "W", "b"], [f"t{i}"]), mk("Relu", [f"t{i}"], [o])], o
        if kind == "Relu":
            return [mk("Relu", [x], [o])], o
        if kind == "Add":
            return [mk("Add", [x, "x"], [o])], o
        if kind == "Add bias [L]":
            return [mk("Add", [x, "b"], [o])], o
        if kind == "Gather rows":
            return [mk("Gather", [x, "idx"], [f"t{i}"], axis=0), mk("Slice", [f"t{i}", "z0", "nrow", "z0"], [o])], o
        if kind == "ScatterND add":
            return [mk("ScatterND", [x, "idx2", x], [o], reduction="add")], o
        if kind == "LayerNormalization":
            return [mk("LayerNormalization", [x, "g", "b"], [o], axis=-1, epsilon=1e-5)], o
        if kind == "LayerNorm folded, one-column variance":
            return [
                mk("Mul", [x, x], [f"q{i}"]), mk("Gemm", [f"q{i}", "Kcol", "eps1"], [f"e{i}"]), mk("Sqrt", [f"e{i}"], [f"c{i}"]),
                mk("MatMul", [f"c{i}", "ones"], [f"s{i}"]), mk("Div", [x, f"s{i}"], [o]),
            ], o  # fmt: skip
        if kind == "LayerNorm folded, broadcast Div":
            return [
                mk("Mul", [x, x], [f"q{i}"]), mk("Gemm", [f"q{i}", "Kcol", "eps1"], [f"e{i}"]), mk("Sqrt", [f"e{i}"], [f"c{i}"]),
                mk("Div", [x, f"c{i}"], [o]),
            ], o  # fmt: skip
        raise ValueError(kind)

    kinds = [
        "MatMul",
        "Gemm (bias)",
        "Gemm+Relu",
        "Relu",
        "Add",
        "Add bias [L]",
        "Gather rows",
        "ScatterND add",
        "LayerNormalization",
        "LayerNorm folded, one-column variance",
        "LayerNorm folded, broadcast Div",
    ]
    x = rng.normal(size=(rows, latent)).astype(np.float32)
    depth = 6
    sessions = {}
    for kind in kinds:
        nodes, cur = [], "x"
        for i in range(depth):
            ns, cur = one(kind, cur, i)
            nodes += ns
        nodes.append(helper.make_node("Identity", [cur], ["y"]))
        consts = [
            w,
            b,
            g,
            idx,
            idx2,
            numpy_helper.from_array(np.full((latent, 1), 1.0 / latent, np.float32), "Kcol"),
            numpy_helper.from_array(np.array([1e-5], np.float32), "eps1"),
            numpy_helper.from_array(np.ones((1, latent), np.float32), "ones"),
            numpy_helper.from_array(np.array([0], np.int64), "z0"),
            numpy_helper.from_array(np.array([rows], np.int64), "nrow"),
        ]
        used = {i for nd in nodes for i in nd.input}
        graph = helper.make_graph(
            nodes, kind, [helper.make_tensor_value_info("x", TensorProto.FLOAT, [rows, latent])],
            [helper.make_tensor_value_info("y", TensorProto.FLOAT, None)], initializer=[c for c in consts if c.name in used],
        )  # fmt: skip
        proto = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 18)])
        proto.ir_version = 9
        o = ort.SessionOptions()
        o.intra_op_num_threads = 1
        sessions[kind] = ort.InferenceSession(proto.SerializeToString(), o, providers=["CPUExecutionProvider"])
    ms = _interleaved({k: (lambda s=s: s.run(None, {"x": x})) for k, s in sessions.items()}, repeats)
    ns_row = {k: v * 1e6 / depth / rows for k, v in ms.items()}
    ns_row["GFLOP/s of MatMul"] = 2 * latent * latent / ns_row["MatMul"]
    return ns_row


def _md(res: dict[str, Any]) -> str:
    lines = ["# Network inference: breakdown, cost per frame, GFLOP/s", ""]
    lines += [
        f"One onnxruntime thread unless stated; MPM at r_p with {res['mpm_threads'] or 'all'} threads. "
        f"Each callable runs in turn with the others, {res.get('burst', 1)} times back to back per turn, "
        + ("the first of each burst not counted (a rollout's steady state)." if res.get("burst", 1) > 1 else "every call counted."),
        "",
    ]
    lines += ["## Cost per frame (network alone, after warm-up, failure checks on) against MPM at r_p, same run", ""]
    lines += [
        "| scene | particles | edges | radius graph alone ms (not in the step) | ONNX ms | checks+history ms | relaxation + next graph ms | rest of advance() (Python) ms | unattributed ms | step ms | network ms/frame | MPM r_p ms/frame | ratio | network 2 threads ms/frame | ratio 2 threads | GFLOP/s (ONNX) |"
        + (" ONNX speedup vs baseline |" if res["baseline"] else "")
    ]
    lines += ["|---" * (16 + bool(res["baseline"])) + "|"]
    for r in res["scenes"]:
        m = r["ms"]
        row = (
            f"| {r['scene']} | {r['particles']} | {r['edges']} | {m['radius_graph']:.2f} | {m['onnx_shipped']:.2f} | {m['checks_clamp_history']:.2f} | "
            f"{m['relaxation']:.2f} | {r['python_overhead_ms']:.2f} | {r['unattributed_ms']:.2f} | {m['advance']:.2f} | {r['network_ms_per_frame']:.2f} | {r['mpm_rp_ms_per_frame']:.2f} | "
            f"{r['ratio_network_to_mpm_rp']:.2f} | {r['network_2t_ms_per_frame']:.2f} | {r['ratio_network_2t_to_mpm_rp']:.2f} | {r['gflops_onnx']:.1f} |"
        )
        if res["baseline"]:
            row += f" {r.get('speedup_onnx', float('nan')):.2f} |"
        lines.append(row)
    lines += ["", "## ONNX time by stage (µs per step, onnxruntime profiler; baseline graphs by operator)", ""]
    for r in res["scenes"]:
        st = ", ".join(f"{k} {v:.0f}" for k, v in r["stages_us"].items())
        lines.append(f"- **{r['scene']}**: {st}")
        if "baseline_stages_us" in r:
            lines.append(f"  - baseline: {', '.join(f'{k} {v:.0f}' for k, v in list(r['baseline_stages_us'].items())[:10])}")
    lines += ["", "## GFLOP/s on a block of particles (dense-layer FLOPs, `gnn_flops`)", ""]
    if any("baseline_1t" in b["ms"] and "baseline_2t" not in b["ms"] for b in res["blocks"]):
        lines += [
            "A baseline graph of torch's exporter sums with `ScatterND`, which loses updates on 2 onnxruntime threads: it has no 2-thread column.",
            "",
        ]
    keys = sorted({k for b in res["blocks"] for k in b["gflops"]})
    lines += ["| scene | particles | edges | MFLOP/step | " + " | ".join(f"{k} ms" for k in keys) + " | " + " | ".join(f"{k} GFLOP/s" for k in keys) + " |"]
    lines += ["|---" * (4 + 2 * len(keys)) + "|"]
    for b in res["blocks"]:
        lines.append(
            f"| {b['scene']} | {b['particles']} | {b['edges']} | {b['mflop_step']:.1f} | " + " | ".join(f"{b['ms'][k]:.2f}" for k in keys) + " | "
            + " | ".join(f"{b['gflops'][k]:.1f}" for k in keys) + " |"
        )  # fmt: skip
    if res.get("ops"):
        lines += ["", f"## onnxruntime operator cost at width {res['ops']['latent']} ({res['ops']['rows']} rows, ns per row, one thread)", ""]
        lines += ["| operator | ns/row |", "|---|---|"] + [f"| {k} | {v:.1f} |" for k, v in res["ops"]["ns_per_row"].items()]
    return "\n".join(lines) + "\n"


def main() -> None:
    global BURST
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scenes", nargs="+", default=list(SCENES), choices=SCENES)
    ap.add_argument("--seed", type=int, default=1000)
    ap.add_argument("--steps", type=int, default=3, help="network steps before the measured state")
    ap.add_argument("--repeats", type=int, default=40)
    ap.add_argument("--particles", type=int, default=2400, help="block size of the GFLOP/s measurement (>= 2000)")
    ap.add_argument("--mpm-threads", type=int, default=0, help="MPM at r_p threads (0: all, as hybridmpm bench)")
    ap.add_argument("--baseline", type=Path, default=None, help="a directory of .onnx files named as the shipped ones, timed in the same run")
    ap.add_argument("--baseline-rev", default=None, help="or a git revision: its shipped graphs (git show REV:python/hybridmpm/models/NAME.onnx)")
    ap.add_argument("--ops", action="store_true", help="also time single onnxruntime operators at the model width")
    ap.add_argument("--burst", type=int, default=BURST, help="calls back to back per turn, the first not counted (1: one call per turn, as before)")
    ap.add_argument("--out", type=Path, required=True, help="writes OUT.json and OUT.md")
    args = ap.parse_args()
    if args.burst < 1:
        ap.error("--burst: must be >= 1")
    if args.steps < 1:
        ap.error("--steps: must be >= 1")
    BURST = args.burst
    if args.baseline_rev is not None:
        import subprocess

        args.baseline = Path(tempfile.mkdtemp(prefix=f"hmpm_graphs_{args.baseline_rev}_"))
        for scene in args.scenes:
            name = shipped_model(scene).name
            blob = subprocess.run(["git", "show", f"{args.baseline_rev}:python/hybridmpm/models/{name}"], capture_output=True, check=True).stdout
            write_file(args.baseline / name, blob)
    res: dict[str, Any] = {
        "mpm_threads": args.mpm_threads,
        "baseline": args.baseline_rev or (str(args.baseline) if args.baseline else None), "burst": BURST, "scenes": [], "blocks": [],
    }  # fmt: skip
    for scene in args.scenes:
        r = breakdown(scene, args.seed, args.steps, args.repeats, args.mpm_threads, args.baseline)
        res["scenes"].append(r)
        print(f"{scene}: step {r['ms']['advance']:.2f} ms, {r['network_ms_per_frame']:.2f} ms/frame vs MPM r_p {r['mpm_rp_ms_per_frame']:.2f} "
              f"(ratio {r['ratio_network_to_mpm_rp']:.2f}; 2 threads {r['ratio_network_2t_to_mpm_rp']:.2f}), {r['gflops_onnx']:.1f} GFLOP/s", flush=True)  # fmt: skip
        b = block_gflops(scene, args.particles, max(10, args.repeats // 2), args.baseline)
        res["blocks"].append(b)
        print(f"  block of {b['particles']}: " + ", ".join(f"{k} {v:.1f} GFLOP/s" for k, v in b["gflops"].items()), flush=True)
    if args.ops:
        lat = int(GnsRuntime(shipped_model(args.scenes[0])).meta["latent"])
        res["ops"] = {"latent": lat, "rows": 20000, "ns_per_row": op_costs(lat, 20000, args.repeats)}
    write_results(args.out.parent, args.out.name, doc=res, markdown=_md(res))
    print(_md(res))


if __name__ == "__main__":
    main()
