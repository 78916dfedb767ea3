#!/usr/bin/env python3
"""The diffusion controller's behavioural checks and latency:

    python benchmarks/bench_control_checks.py --scenes water2d,sand2d --out benchmarks/results/control_checks

Per scene, on held-out cases (seeds 5000+, as bench_control.py):

* **latency** — sketch → field (the plan: state encoding, sketch encoding,
  the DDIM steps, one onnxruntime thread; the free-motion prior's MPM
  rollout on a second thread) p50/p95 over ``--repeats`` plans on
  each of 5 start states, and the whole controlled episode (plan + T_ctr
  MPM frames, one MPM thread), median;
* **flipped arrow** — each arrow case is also run with the arrow reversed:
  the cosine between the fluid's centroid displacement and the *original*
  arrow (target ≤ −0.5), raw and relative to the uncontrolled run;
* **blank sketch** — mean ‖a‖ with no sketch over mean ‖a‖ with the drawn
  one (target ≤ 0.2). With no sketch the controller applies no force by
  design, so this is 0; the model's own unconditional plan (classifier-free
  guidance's blank branch), tracked, is reported beside it;
* **random sketches** — ``--random`` sketches of every direction and size,
  strokes off the domain included: no NaN, every particle in the domain,
  ‖a‖ ≤ a_max, CFL substeps ≤ 2× the uncontrolled run's;
* **determinism** — same seed, state and sketch twice: bitwise-equal plan
  and trajectory; another seed: a different plan (its spread is reported).

Writes OUT.json and OUT.md. Time the latency on a quiet machine.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
from tqdm import tqdm

from hybridmpm.bench.harness import script_argv, write_results
from hybridmpm.control import A_MAX, Controller, Sketch, control_episode
from hybridmpm.control.prior import free_motion_of
from hybridmpm.conventions import G
from hybridmpm.train.control.cases import make_case


def _centroid_shift(ep) -> np.ndarray:  # type: ignore[no-untyped-def]
    f = ep.rollout.fluid_positions
    return f[-1, :, :2].mean(0) - f[0, :, :2].mean(0)


def _cos(a: np.ndarray, b: np.ndarray) -> float:
    return float(a @ b / max(np.linalg.norm(a) * np.linalg.norm(b), 1e-12))


def random_sketch(rng: np.random.Generator) -> Sketch:
    if rng.random() < 0.5:
        start = rng.uniform(-0.3, 1.3, 2)
        ang, length = rng.uniform(0, 2 * np.pi), 10 ** rng.uniform(-2, 0.2)
        end = np.clip(start + length * np.array([np.cos(ang), np.sin(ang)]), -0.99, 1.99)
        if np.linalg.norm(end - start) < 1e-3:
            end = start + 0.01
        return Sketch.arrow(start, end)
    radii = np.sort(10 ** rng.uniform(-2.3, 0.0, 2))[::-1]
    return Sketch.oval(rng.uniform(-0.2, 1.2, 2), np.maximum(radii, 0.005), float(rng.uniform(0, np.pi)))


def _unconditional_path(case: object, controller: Controller, frames: int) -> np.ndarray:
    """The model's own blank-sketch plan (classifier-free guidance's unconditional branch), float64 [F, N, D]."""
    sim = case.simulator()  # type: ignore[attr-defined]
    p, model = sim.particles, controller.model
    x, v, pt = p.fluid(sim.positions), sim.velocities, p.particle_type[: p.num_fluid]
    free = free_motion_of(sim, model.frames - 1) if model.needs_free else None
    return model.sample(x, v, pt, None, seed=controller.seed, steps=controller.steps, free=free).path[: frames + 1]


def check_scene(scene: str, args: argparse.Namespace) -> dict:
    model = None if args.model_root is None else Path(args.model_root) / scene
    ctl = lambda seed=0, frames=100: Controller.for_scene(scene, "diffusion", model=model, seed=seed, frames=frames)  # noqa: E731
    out: dict = {"scene": scene}
    cases = [make_case(scene, args.first_seed + i, "arrow" if i % 2 == 0 else "oval", tracking=False) for i in range(args.cases)]
    frames = len(cases[0].path) - 1
    # latency
    plans, episodes = [], []
    for case in cases[:5]:
        sim = case.simulator()
        c = ctl()
        c.plan(sim, case.sketch)  # warm-up
        for _ in range(args.repeats):
            plans.append(c.plan(sim, case.sketch).seconds * 1e3)
        sim = case.simulator()
        t0 = time.perf_counter()
        control_episode(sim, case.sketch, ctl(frames=frames))
        episodes.append((time.perf_counter() - t0) * 1e3)
    out["plan_ms_p50"], out["plan_ms_p95"] = float(np.percentile(plans, 50)), float(np.percentile(plans, 95))
    out["episode_ms_median"] = float(np.median(episodes))
    out["particles"] = [int(c.target.shape[0]) for c in cases[:5]]
    # flipped arrows, blank sketches, determinism
    flips, flips_rel, e_drawns, e_blanks, e_unconds, spread = [], [], [], [], [], []
    deterministic = True
    for i, case in enumerate(tqdm(cases, desc=f"{scene} checks")):
        drawn = control_episode(case.simulator(), case.sketch, ctl(seed=i, frames=frames))
        blank = control_episode(case.simulator(), None, ctl(seed=i, frames=frames))
        e_drawns.append(drawn.metrics["effort_mean_g"])
        e_blanks.append(blank.metrics["effort_mean_g"])
        uncond = control_episode(case.simulator(), None, Controller("oracle", frames=frames, oracle_path=_unconditional_path(case, ctl(seed=i), frames)))
        e_unconds.append(uncond.metrics["effort_mean_g"])
        if case.kind == "arrow":
            sk = case.sketch
            flipped = Sketch.arrow(sk.start, sk.start - sk.vector)
            ep = control_episode(case.simulator(), flipped, ctl(seed=i, frames=frames))
            flips.append(_cos(_centroid_shift(ep), sk.vector))
            flips_rel.append(_cos(_centroid_shift(ep) - _centroid_shift(blank), sk.vector))
        if i < 4:
            again = control_episode(case.simulator(), case.sketch, ctl(seed=i, frames=frames))
            other = ctl(seed=i + 1000).plan(case.simulator(), case.sketch)
            deterministic &= bool(np.array_equal(again.plan.path, drawn.plan.path) and np.array_equal(again.rollout.positions, drawn.rollout.positions))
            spread.append(float(np.abs(other.path - drawn.plan.path).mean()))
    out.update(
        flip_cos_mean=float(np.mean(flips)), flip_cos_max=float(np.max(flips)), flip_cos_rel_mean=float(np.mean(flips_rel)), flips=len(flips),
        # ratios of the means over the cases: a case in free flight costs next to nothing drawn (its plan is the parabola),
        # so per-case ratios would divide by ~0
        blank_effort_ratio=float(np.mean(e_blanks) / np.mean(e_drawns)), unconditional_effort_ratio=float(np.mean(e_unconds) / np.mean(e_drawns)),
        flip_cos=[float(c) for c in flips], effort_drawn_g=e_drawns, effort_unconditional_g=e_unconds,
        deterministic=deterministic, seed_spread_m=float(np.mean(spread)),
    )  # fmt: skip
    # random sketches
    rng = np.random.default_rng(args.random_seed)
    bad, worst_a, worst_sub = [], 0.0, 0.0
    base = cases[0]
    free = control_episode(base.simulator(), None, Controller("none", frames=frames))
    sub0 = float(np.max(free.rollout.substeps))
    for j in tqdm(range(args.random), desc=f"{scene} random sketches"):
        sk = random_sketch(rng)
        case = cases[j % len(cases)]
        ep = control_episode(case.simulator(), sk, ctl(seed=j, frames=frames))
        pos = ep.rollout.positions
        amax = ep.plan.applied.effort()["effort_max_g"] * G  # the largest |a| handed out [m/s²]
        worst_a = max(worst_a, amax)
        worst_sub = max(worst_sub, float(np.max(ep.rollout.substeps)) / sub0)
        if not np.isfinite(pos).all() or (pos < 0).any() or (pos > 1).any() or amax > A_MAX * (1 + 1e-6) or ep.rollout.failure is not None:
            bad.append({"sketch": sk.to_json(), "failure": ep.rollout.failure, "a_max": amax})
    out.update(random=args.random, random_bad=len(bad), random_bad_examples=bad[:3], random_max_a_g=worst_a / 9.8, random_max_substeps_ratio=worst_sub)
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scenes", default="water2d,sand2d")
    ap.add_argument("--cases", type=int, default=20)
    ap.add_argument("--first-seed", type=int, default=5000)
    ap.add_argument("--repeats", type=int, default=20)
    ap.add_argument("--random", type=int, default=200)
    ap.add_argument("--random-seed", type=int, default=12345)
    ap.add_argument("--model-root", default=None)
    ap.add_argument("--out", default="benchmarks/results/control_checks")
    args = ap.parse_args(argv)
    rows = [check_scene(s, args) for s in args.scenes.split(",")]
    out = Path(args.out)
    lines = [
        "| scene | particles | plan ms p50 / p95 (1 ORT thread) | episode ms (median) | flipped arrow cos (mean / worst; vs no control) | blank / drawn effort (means over the cases) | the model's unconditional plan tracked / drawn effort (means over the cases) | random sketches bad | max ‖a‖/g | max substeps / uncontrolled | bitwise deterministic | seed spread (m) |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        lines.append(
            f"| {r['scene']} | {min(r['particles'])}–{max(r['particles'])} | {r['plan_ms_p50']:.0f} / {r['plan_ms_p95']:.0f} | {r['episode_ms_median']:.0f} "
            f"| {r['flip_cos_mean']:.2f} / {r['flip_cos_max']:.2f}; {r['flip_cos_rel_mean']:.2f} ({r['flips']} arrows) "
            f"| {r['blank_effort_ratio']:.2f} "
            f"| {r['unconditional_effort_ratio']:.2f} | {r['random_bad']} of {r['random']} | {r['random_max_a_g']:.1f} "
            f"| {r['random_max_substeps_ratio']:.2f} | {'yes' if r['deterministic'] else 'NO'} | {r['seed_spread_m']:.2e} |"
        )
    text = "\n".join(lines) + "\n"
    write_results(out.parent, out.name, doc={"scenes": rows}, markdown=text, argv=script_argv(__file__, argv))
    print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
