#!/usr/bin/env python3
"""Peer benchmark: Taichi (CPU backend) running the same MLS-MPM scenes as hybridmpm.

Standalone: needs only ``taichi`` (1.7.x) and ``numpy``.  Each (scene, variant,
threads) combination runs in its own subprocess, because ``ti.init`` cannot be
re-run reliably with a different thread count inside one process.

Variants
--------
serial  -- the strongest Taichi CPU variant: the p2g particle loop is scattered
           serially without atomics (``ti.loop_config(serialize=True)`` and plain
           read-modify-write), grid update and g2p run in parallel.
atomic  -- the textbook variant (mpm88 style): parallel p2g with atomic adds.

Physics (meant to match hybridmpm's work per substep): domain [0,1]^D, n cells
per dim, dx = 1/n, grid nodes 0..n, quadratic B-splines, MLS-MPM/APIC (Hu et al.
2018, mpm88 style), slip walls 3 cells thick, gravity -9.8 along y.
Water: tau = K J (J-1) I.  Sand: Drucker-Prager return mapping in log strain
(Klar et al. 2016) on F = U Sigma V^T after g2p.  The sand Kirchhoff stress
tau = U (2 mu eps + lambda tr(eps) I) U^T is evaluated right after the return
mapping in g2p (where U and eps are already at hand) and stored per particle;
p2g reads it.  This is exactly the tau of the stored F, with one SVD per
particle per substep (no second SVD in p2g).  log(Sigma) is taken of
max(Sigma, 1e-6) as a guard against degenerate F.

Kernel layout (the tightest found on a 2-core CPU):
* one kernel launch per substep (``--launch substep``), holding p2g, grid update
  and g2p as three separate top-level loops (Taichi runs them in order with a
  barrier in between; the serial variant's p2g loop runs on one thread);
  ``--launch stage`` uses one launch per stage instead;
* dense (n+1)^D grid, SoA: momentum, mass, and the updated velocity read by g2p;
* the grid clear is fused into the grid update: the pass visits every node, and
  nodes that received mass get their velocity written and momentum/mass zeroed
  (the grid is all zero outside p2g).  Massless nodes keep a stale, finite
  velocity that g2p can only read with weight exactly 0;
* the grid update is parallel over the leading D-1 index dims and serial
  (contiguous) over the last, which avoids a div/mod per node;
* water-only and sand-only scenes compile only their constitutive branch.

Timing: per (scene, variant, threads): build + JIT compile, warm up
``--warmup`` frames (default 5), then time ``--frames`` frames (default 40)
one by one with ``ti.sync()`` before reading the clock.  A frame is 2.5 ms of
simulated time (``substeps`` substeps).  Reported: median, p95 and min wall ms
per frame and median microseconds per substep.  Sanity: after all frames the
particle centroid's y must have decreased, no NaN, all particles inside.

Usage::

    python benchmarks/taichi_peer.py --bench-scene water2d --bench-out runs/bench/water2d   # the peer line of a bench report
    python benchmarks/taichi_peer.py [--scenes water2d,sand2d,water3d_4k,water3d_32k]
        [--threads 1,2] [--variants serial,atomic] [--frames 40] [--json out.json]
        [--positions scene.npz] [--md results.md] [--launch substep|stage]

``--positions`` loads an ``.npz`` with keys ``positions [N,D] float32``,
``material [N] int (0 = water, 1 = sand)``, ``n_grid`` and ``substeps`` and runs
that scene instead of the built-in ones.
"""

from __future__ import annotations

import argparse
import itertools
import json
import math
import os
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

from hybridmpm.bench.harness import load_average, round_robin, script_argv, write_results

FRAME_DT = 2.5e-3
RHO = 1000.0
WATER_K = 4.0e5
SAND_E = 3.5e5
SAND_NU = 0.3
SAND_FRICTION_DEG = 30.0
GRAVITY = 9.8

WATER, SAND = 0, 1

# name -> (dim, n_grid, particles per dim, origin, substeps, material)
SCENES = {
    "water2d": (2, 128, 64, (0.1, 0.1), 16, WATER),
    "sand2d": (2, 128, 64, (0.1, 0.1), 16, SAND),
    "water3d_4k": (3, 64, 16, (0.3, 0.1, 0.3), 8, WATER),
    "water3d_32k": (3, 64, 32, (0.25, 0.1, 0.25), 8, WATER),
}
DEFAULT_SCENES = list(SCENES)
WORKER_TAG = "@@TAICHI_PEER_RESULT@@"


# --------------------------------------------------------------------------- #
# Scene construction (pure numpy)
# --------------------------------------------------------------------------- #
def lattice(dim: int, n_grid: int, per_dim: int, origin) -> np.ndarray:
    """Particles at spacing dx/2: origin + (i + 0.5) * spacing per dimension."""
    spacing = 0.5 / n_grid
    idx = np.indices((per_dim,) * dim).reshape(dim, -1).T  # C order: last dim fastest
    pos = np.asarray(origin, dtype=np.float64) + (idx + 0.5) * spacing
    return pos.astype(np.float32)


def load_scene(name: str | None, positions_file: str | None):
    """Returns (label, positions [N,D] f32, material [N] i32, n_grid, substeps)."""
    if positions_file is not None:
        data = np.load(positions_file)
        pos = np.ascontiguousarray(data["positions"], dtype=np.float32)
        if pos.ndim != 2 or pos.shape[1] not in (2, 3):
            raise ValueError(f"positions must be [N,2] or [N,3], got {pos.shape}")
        if "material" in data:
            mat = np.ascontiguousarray(data["material"], dtype=np.int32).reshape(-1)
        else:
            mat = np.zeros(pos.shape[0], dtype=np.int32)
        if mat.shape[0] != pos.shape[0]:
            raise ValueError("material and positions disagree in length")
        if not np.all((mat == WATER) | (mat == SAND)):
            raise ValueError("material must be 0 (water) or 1 (sand)")
        n_grid = int(np.asarray(data["n_grid"]).reshape(-1)[0])
        substeps = int(np.asarray(data["substeps"]).reshape(-1)[0])
        label = os.path.splitext(os.path.basename(positions_file))[0]
        return label, pos, mat, n_grid, substeps
    if name is None:
        raise ValueError("a scene name or a positions file is needed")
    dim, n_grid, per_dim, origin, substeps, material = SCENES[name]
    pos = lattice(dim, n_grid, per_dim, origin)
    mat = np.full(pos.shape[0], material, dtype=np.int32)
    return name, pos, mat, n_grid, substeps


# --------------------------------------------------------------------------- #
# Worker: one (scene, variant, threads) in a fresh process
# --------------------------------------------------------------------------- #
def run_worker(cfg: dict) -> dict:
    import taichi as ti

    threads = int(cfg["threads"])
    variant = cfg["variant"]
    launch = cfg["launch"]
    serial = variant == "serial"
    ti.init(
        arch=ti.cpu,
        cpu_max_num_threads=threads,
        default_fp=ti.f32,
        default_ip=ti.i32,
        random_seed=0,
        debug=False,
        log_level=ti.WARN,
    )

    label, pos_np, mat_np, n_grid, substeps = load_scene(cfg["scene"], cfg["positions"])
    N, D = pos_np.shape
    has_water = bool(np.any(mat_np == WATER))
    has_sand = bool(np.any(mat_np == SAND))
    mixed = has_water and has_sand

    # ---- constants (Python floats, baked into the kernels) ----
    dx = 1.0 / n_grid
    inv_dx = float(n_grid)
    dt = FRAME_DT / substeps
    p_vol = (dx * 0.5) ** D
    p_mass = RHO * p_vol
    stress_coef = -dt * p_vol * 4.0 * inv_dx * inv_dx
    apic_coef = 4.0 * inv_dx * inv_dx
    mu = SAND_E / (2.0 * (1.0 + SAND_NU))
    lam = SAND_E * SAND_NU / ((1.0 + SAND_NU) * (1.0 - 2.0 * SAND_NU))
    sin_phi = math.sin(math.radians(SAND_FRICTION_DEG))
    if D == 2:
        alpha = sin_phi / math.sqrt(2.0)
    else:
        alpha = math.sqrt(2.0 / 3.0) * 2.0 * sin_phi / (3.0 - sin_phi)
    dp_coef = (D * lam + 2.0 * mu) / (2.0 * mu) * alpha
    n_nodes = n_grid + 1  # nodes 0..n
    gvec = [0.0] * D
    gvec[1] = -GRAVITY
    grav_dt = [g * dt for g in gvec]
    f32 = ti.f32

    # ---- fields ----
    x = ti.Vector.field(D, f32, shape=N)
    v = ti.Vector.field(D, f32, shape=N)
    C = ti.Matrix.field(D, D, f32, shape=N)
    Jp = ti.field(f32, shape=N) if has_water else None
    Fp = ti.Matrix.field(D, D, f32, shape=N) if has_sand else None
    taup = ti.Matrix.field(D, D, f32, shape=N) if has_sand else None
    matp = ti.field(ti.i32, shape=N) if mixed else None
    # Dense grid of (n+1)^D nodes (indices 0..n per dim), SoA: momentum, mass,
    # and the updated node velocity that g2p reads.
    grid_shape = (n_nodes,) * D
    grid_mv = ti.Vector.field(D, f32, shape=grid_shape)
    grid_m = ti.field(f32, shape=grid_shape)
    grid_v = ti.Vector.field(D, f32, shape=grid_shape)
    # 3^D stencil offsets (integer and float), unrolled at compile time
    stencil_nodes = [(off, tuple(float(c) for c in off)) for off in itertools.product(range(3), repeat=D)]

    @ti.func
    def weights(Xp):
        base = ti.cast(Xp - 0.5, ti.i32)
        fx = Xp - ti.cast(base, f32)
        w = [0.5 * (1.5 - fx) ** 2, 0.75 - (fx - 1.0) ** 2, 0.5 * (fx - 0.5) ** 2]
        return base, fx, w

    @ti.func
    def water_tau_diag(p):
        J = Jp[p]
        return WATER_K * J * (J - 1.0)

    @ti.func
    def p2g_body():
        ti.loop_config(serialize=serial)
        for p in range(N):
            Xp = x[p] * inv_dx
            base, fx, w = weights(Xp)
            affine = p_mass * C[p]
            if ti.static(has_sand and not has_water):
                affine += stress_coef * taup[p]
            elif ti.static(has_water and not has_sand):
                s = stress_coef * water_tau_diag(p)
                for d in ti.static(range(D)):
                    affine[d, d] += s
            else:
                if matp[p] == SAND:
                    affine += stress_coef * taup[p]
                else:
                    s = stress_coef * water_tau_diag(p)
                    for d in ti.static(range(D)):
                        affine[d, d] += s
            mv = p_mass * v[p]
            for off, off_f in ti.static(stencil_nodes):
                dpos = (ti.Vector(off_f, f32) - fx) * dx
                weight = 1.0
                for d in ti.static(range(D)):
                    weight *= w[off[d]][d]
                node = base + ti.Vector(off)
                if ti.static(serial):
                    grid_mv[node] = grid_mv[node] + weight * (mv + affine @ dpos)
                    grid_m[node] = grid_m[node] + weight * p_mass
                else:
                    grid_mv[node] += weight * (mv + affine @ dpos)
                    grid_m[node] += weight * p_mass

    @ti.func
    def grid_body():
        # Visits every node of the dense grid.  Invariant: grid_mv/grid_m are
        # all zero outside p2g, so only nodes that received mass are written
        # (velocity out, momentum/mass cleared for the next p2g): the grid clear
        # is fused into this pass.  Nodes without mass keep a stale but finite
        # grid_v, which g2p can only read with weight exactly 0.
        # Parallel over the leading D-1 index dims, serial (contiguous) over the
        # last one (avoids a div/mod index decomposition per node).
        for J in ti.grouped(ti.ndrange(*((n_nodes,) * (D - 1)))):
            for k in range(n_nodes):
                i = ti.Vector([J[d] for d in ti.static(range(D - 1))] + [k])
                m = grid_m[i]
                if m > 0.0:
                    vel = grid_mv[i] / m + ti.Vector(grav_dt, f32)
                    for d in ti.static(range(D)):
                        if i[d] < 3 and vel[d] < 0.0:
                            vel[d] = 0.0
                        if i[d] > n_grid - 3 and vel[d] > 0.0:
                            vel[d] = 0.0
                    grid_v[i] = vel
                    grid_mv[i] = ti.Vector.zero(f32, D)
                    grid_m[i] = 0.0

    @ti.func
    def sand_update(p, new_C):
        F = (ti.Matrix.identity(f32, D) + dt * new_C) @ Fp[p]
        U, sig, V = ti.svd(F, f32)
        eps = ti.Vector.zero(f32, D)
        for d in ti.static(range(D)):
            eps[d] = ti.log(ti.max(sig[d, d], 1e-6))
        tr = eps.sum()
        eps_hat = eps - tr / D
        if tr > 0.0:
            eps = ti.Vector.zero(f32, D)
        else:
            eh_norm = eps_hat.norm()
            dgamma = eh_norm + dp_coef * tr
            if dgamma > 0.0:
                eps = eps - dgamma / eh_norm * eps_hat
        sig_new = ti.Matrix.zero(f32, D, D)
        tau_diag = ti.Matrix.zero(f32, D, D)
        tr_new = eps.sum()
        for d in ti.static(range(D)):
            sig_new[d, d] = ti.exp(eps[d])
            tau_diag[d, d] = 2.0 * mu * eps[d] + lam * tr_new
        Fp[p] = U @ sig_new @ V.transpose()
        taup[p] = U @ tau_diag @ U.transpose()

    @ti.func
    def g2p_body():
        for p in range(N):
            Xp = x[p] * inv_dx
            base, fx, w = weights(Xp)
            new_v = ti.Vector.zero(f32, D)
            B = ti.Matrix.zero(f32, D, D)
            for off, off_f in ti.static(stencil_nodes):
                dpos = (ti.Vector(off_f, f32) - fx) * dx
                weight = 1.0
                for d in ti.static(range(D)):
                    weight *= w[off[d]][d]
                gv = grid_v[base + ti.Vector(off)]
                new_v += weight * gv
                B += weight * gv.outer_product(dpos)
            new_C = apic_coef * B
            v[p] = new_v
            C[p] = new_C
            x[p] += dt * new_v
            if ti.static(has_water and not has_sand):
                Jp[p] *= 1.0 + dt * new_C.trace()
            elif ti.static(has_sand and not has_water):
                sand_update(p, new_C)
            else:
                if matp[p] == SAND:
                    sand_update(p, new_C)
                else:
                    Jp[p] *= 1.0 + dt * new_C.trace()

    @ti.kernel
    def p2g():
        p2g_body()

    @ti.kernel
    def grid_update():
        grid_body()

    @ti.kernel
    def g2p():
        g2p_body()

    @ti.kernel
    def substep_kernel():
        # one launch per substep; the three stages are separate top-level
        # (offloaded) loops, executed in order with a barrier between them
        p2g_body()
        grid_body()
        g2p_body()

    def frame():
        if launch == "substep":
            for _ in range(substeps):
                substep_kernel()
        else:
            for _ in range(substeps):
                p2g()
                grid_update()
                g2p()

    # ---- init state ----
    t_init0 = time.perf_counter()
    x.from_numpy(pos_np)
    v.fill(0.0)
    C.fill(0.0)
    if Jp is not None:
        Jp.fill(1.0)
    if Fp is not None and taup is not None:
        eye = np.broadcast_to(np.eye(D, dtype=np.float32), (N, D, D)).copy()
        Fp.from_numpy(eye)
        taup.fill(0.0)
    if matp is not None:
        matp.from_numpy(mat_np)
    grid_mv.fill(0.0)
    grid_m.fill(0.0)
    grid_v.fill(0.0)
    y0 = float(pos_np[:, 1].astype(np.float64).mean())

    warmup = int(cfg["warmup"])
    n_frames = int(cfg["frames"])
    frame()  # JIT compile (first frame)
    ti.sync()
    t_compile = time.perf_counter() - t_init0
    for _ in range(warmup - 1):
        frame()
    ti.sync()

    times = []
    for _ in range(n_frames):
        t0 = time.perf_counter()
        frame()
        ti.sync()
        times.append(time.perf_counter() - t0)

    pos_end = x.to_numpy().astype(np.float64)
    finite = bool(np.all(np.isfinite(pos_end)))
    y1 = float(pos_end[:, 1].mean()) if finite else float("nan")
    inside = bool(finite and np.all(pos_end > dx) and np.all(pos_end < 1.0 - dx))
    times_ms = np.asarray(times) * 1e3
    med = float(np.median(times_ms))
    return {
        "scene": label,
        "variant": variant,
        "threads": threads,
        "dim": D,
        "particles": N,
        "n_grid": n_grid,
        "substeps": substeps,
        "launch": launch,
        "frames_timed": n_frames,
        "frames_total": max(warmup, 1) + n_frames,
        "median_ms": med,
        "mean_ms": float(times_ms.mean()),
        "p95_ms": float(np.percentile(times_ms, 95)),
        "min_ms": float(times_ms.min()),
        "us_per_substep": med * 1e3 / substeps,
        "compile_and_first_frame_s": t_compile,
        "centroid_y_start": y0,
        "centroid_y_end": y1,
        "finite": finite,
        "inside_domain": inside,
        "sane": bool(finite and inside and y1 < y0),
        "taichi_version": ".".join(map(str, ti.__version__)),
    }


# --------------------------------------------------------------------------- #
# Driver
# --------------------------------------------------------------------------- #
def markdown_table(rows: list[dict]) -> str:
    multi = any(len(r.get("repeat_medians_ms", [])) > 1 for r in rows)
    head = "| scene | variant | threads | particles | substeps | median ms/frame | p95 ms/frame | min ms/frame | µs/substep (median) | load avg |"
    rule = "|---|---|---:|---:|---:|---:|---:|---:|---:|---:|"
    if multi:
        head += " medians of all passes |"
        rule += "---|"
    out = [head + " sanity: centroid y start → end |", rule + "---|"]
    for r in rows:
        if "error" in r:
            out.append(f"| {r['scene']} | {r['variant']} | {r['threads']} | | | ERROR | | | | |" + (" |" if multi else "") + f" {r['error'][:80]} |")
            continue
        ok = "ok" if r["sane"] else "FAILED"
        line = (
            f"| {r['scene']} | {r['variant']} | {r['threads']} | {r['particles']} | {r['substeps']} | "
            f"{r['median_ms']:.2f} | {r['p95_ms']:.2f} | {r['min_ms']:.2f} | {r['us_per_substep']:.0f} | "
            f"{r.get('loadavg_1min', float('nan')):.1f} |"
        )
        if multi:
            line += " " + ", ".join(f"{m:.1f}" for m in r.get("repeat_medians_ms", [])) + " |"
        line += f" {ok} ({r['centroid_y_start']:.4f} → {r['centroid_y_end']:.4f}, {r['frames_total']} frames) |"
        out.append(line)
    return "\n".join(out)


def markdown(meta: dict, rows: list[dict]) -> str:
    """The report: the table of :func:`markdown_table` and how the Taichi side is built."""
    lines = [
        "# Taichi CPU peer benchmark (MLS-MPM)",
        "",
        f"- taichi {meta['taichi_version']}",
        f"- kernel launches: {meta['launch']}; warm-up {meta['warmup']} frames, {meta['frames']} timed frames "
        "per row, each row in its own process; "
        f"{meta['repeats']} pass(es) over the matrix, each row shows the pass with the lowest median",
        "- frame = 2.5 ms simulated time; ms are wall-clock per frame (`ti.sync()` before each clock read)",
        "- load avg = 1-minute load average when the row started: the machine is shared and noisy "
        "(expect ±30% or worse on medians; min ms/frame is the least disturbed figure)",
        "",
        markdown_table(rows),
        "",
        "## How the Taichi side is built",
        "",
        "- `serial`: p2g particle loop under `ti.loop_config(serialize=True)` with plain "
        "read-modify-write (the generated LLVM IR has no atomics); grid update and g2p parallel. "
        "`atomic`: textbook parallel p2g with `+=` (float atomic adds, which x86 lowers to CAS loops).",
        "- One kernel launch per substep (three top-level loops inside, run in order). Dense "
        "(n+1)^D grid in SoA (momentum, mass, velocity); the grid clear is fused into the grid "
        "update (only nodes that received mass are written and zeroed).",
        "- Sand: the Kirchhoff stress τ = U(2μ ε + λ tr ε I)Uᵀ is computed right after the "
        "Drucker–Prager return mapping in g2p, from the same SVD, and stored per particle; p2g "
        "reads it (one SVD per particle per substep). ε = log max(Σ, 1e-6).",
        "- The sanity column is the particle centroid's y before the run and after all warm-up + timed frames (no NaN, all particles inside the domain).",
        "",
    ]
    return "\n".join(lines)


# --------------------------------------------------------------------------- #
# Peer line of a `hybridmpm bench` report
# --------------------------------------------------------------------------- #
def bench_peer(scene_name: str, seed: int, frames: int | None, warmup: int, threads: int = 0, timed_frames: int = 200) -> dict[str, Any]:
    """Time ``timed_frames`` frames (after ``warmup``) of ``scene_name``/``seed``
    in our MPM and in Taichi, each with ``threads`` threads (0 = all cores).
    Returns ``ms_mean``, ``ms_median``, ``ms_p95`` (Taichi), ``ours_ms_mean``,
    ``ours_ms_median``, ``particles``, ``substeps``, ``threads``, ``taichi``
    and ``arch``. Raises :class:`HybridMpmError` if Taichi is missing or its
    run fails."""
    import importlib.util
    import tempfile
    from pathlib import Path

    from hybridmpm.errors import HybridMpmError
    from hybridmpm.scenes import make_scene
    from hybridmpm.sim import MpmSimulator, rollout

    try:
        found = importlib.util.find_spec("taichi") is not None
    except ValueError:  # a module set to None in sys.modules
        found = False
    if not found:
        raise HybridMpmError("peer: Taichi is not installed; pip install 'hybridmpm[bench]'")
    scene = make_scene(scene_name, seed=seed)
    n = min(int(timed_frames), int(frames or scene.frames))
    threads = threads or os.cpu_count() or 1
    ro = rollout(MpmSimulator(scene, threads=threads), warmup + n)
    wall, subs = ro.frame_seconds(after=warmup), ro.substeps[1 + warmup :]
    substeps = max(1, int(round(float(np.mean(subs)))))

    with tempfile.TemporaryDirectory() as tmp:
        npz = Path(tmp) / f"{scene_name}_seed{seed}.npz"
        np.savez(
            npz,
            positions=np.asarray(scene.positions, np.float32),
            material=np.asarray(scene.material, np.int32),
            n_grid=scene.params.resolved_n_grid(),
            substeps=substeps,
        )
        out = Path(tmp) / "taichi.json"
        cmd = [
            sys.executable,
            os.path.abspath(__file__),
            "--positions",
            str(npz),
            "--variants",
            "serial",
            "--threads",
            str(threads),
            "--frames",
            str(n),
            "--warmup",
            str(max(1, warmup)),
            "--json",
            str(out),
        ]
        proc = subprocess.run(cmd, capture_output=True, text=True, timeout=1800)
        if not out.is_file():
            raise HybridMpmError(f"peer: the Taichi run failed: {(proc.stderr or proc.stdout).strip()[-500:]}")
        res = json.loads(out.read_text())["results"][0]
    if "error" in res:
        raise HybridMpmError(f"peer: the Taichi run failed: {res['error']}")
    ours = np.asarray(wall) * 1e3
    return {
        "scene": scene_name, "seed": int(seed), "particles": int(res["particles"]), "substeps": substeps, "threads": int(threads),
        "frames_timed": n, "ms_mean": float(res["mean_ms"]),
        "ms_median": float(res["median_ms"]), "ms_p95": float(res["p95_ms"]), "ours_ms_mean": float(ours.mean()),
        "ours_ms_median": float(np.median(ours)), "taichi": res.get("taichi_version", "?"), "arch": "cpu, serial p2g", "sane": bool(res.get("sane")),
    }  # fmt: skip


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--scenes", default=",".join(DEFAULT_SCENES))
    ap.add_argument("--threads", default="1,2")
    ap.add_argument("--variants", default="serial,atomic")
    ap.add_argument("--frames", type=int, default=40)
    ap.add_argument("--warmup", type=int, default=5)
    ap.add_argument("--json", default=None, help="write all results to this JSON file (FILE.json)")
    ap.add_argument("--positions", default=None, help=".npz scene (positions, material, n_grid, substeps)")
    ap.add_argument(
        "--launch",
        choices=["substep", "stage"],
        default="substep",
        help="kernel launches: substep = one launch per substep holding the three stages as separate top-level loops (default); stage = one launch per stage",
    )
    ap.add_argument(
        "--repeats",
        type=int,
        default=1,
        help="run every combination this many times (whole matrix per pass) and report, per row, the pass with the lowest median (default 1)",
    )
    ap.add_argument("--md", default=None, help="write a markdown report (table + machine info) here (FILE.md)")
    ap.add_argument("--timeout", type=float, default=600.0, help="per-subprocess timeout, s")
    ap.add_argument(
        "--bench-scene",
        default=None,
        help="registered scene: time it against hybridmpm's MPM and write BENCH_OUT/peer_taichi.json (the line `hybridmpm bench` puts in report.md)",
    )
    ap.add_argument("--bench-out", default=None, help="with --bench-scene: the bench directory (default runs/bench/SCENE)")
    ap.add_argument("--seed", type=int, default=1000, help="with --bench-scene: the scene's seed (default 1000, the first held-out seed)")
    ap.add_argument("--_worker", dest="worker_config", default=None, help=argparse.SUPPRESS)  # internal: one measurement in a child process
    args = ap.parse_args(argv)

    if args.bench_scene is not None:
        out = args.bench_out or os.path.join("runs", "bench", args.bench_scene)
        res = bench_peer(args.bench_scene, args.seed, None, 24, threads=0)
        write_results(out, "peer_taichi", doc=res, argv=script_argv(__file__, argv))
        print(f"peer taichi: {res['ms_mean']:.2f} ms/frame against ours {res['ours_ms_mean']:.2f} -> {out}/peer_taichi.json")
        return 0

    if args.worker_config is not None:
        res = run_worker(json.loads(args.worker_config))
        print(WORKER_TAG + json.dumps(res), flush=True)
        return 0

    if args.positions is not None:
        scenes = [None]
    else:
        scenes = [s.strip() for s in args.scenes.split(",") if s.strip()]
        for s in scenes:
            if s not in SCENES:
                ap.error(f"unknown scene {s!r}; choose from {', '.join(SCENES)}")
    variants = [s.strip() for s in args.variants.split(",") if s.strip()]
    for vname in variants:
        if vname not in ("serial", "atomic"):
            ap.error(f"unknown variant {vname!r}")
    threads = [int(t) for t in args.threads.split(",") if t.strip()]

    def run_one(cfg: dict, label: str) -> dict:
        cmd = [sys.executable, os.path.abspath(__file__), "--_worker", json.dumps(cfg)]
        print(f"# running {label} / {cfg['variant']} / {cfg['threads']} thread(s) ...", file=sys.stderr, flush=True)
        load = load_average()[0]
        try:
            proc = subprocess.run(cmd, capture_output=True, text=True, timeout=args.timeout)
            lines = [l for l in proc.stdout.splitlines() if l.startswith(WORKER_TAG)]
            if proc.returncode != 0 or not lines:
                raise RuntimeError((proc.stderr or proc.stdout).strip().splitlines()[-1:] or ["no output"])
            r = json.loads(lines[-1][len(WORKER_TAG) :])
            r["loadavg_1min"] = load
            print(
                f"#   median {r['median_ms']:.2f} ms/frame, p95 {r['p95_ms']:.2f}, min {r['min_ms']:.2f}, "
                f"compile+first frame {r['compile_and_first_frame_s']:.1f} s, load {load:.1f}, "
                f"centroid y {r['centroid_y_start']:.4f} -> {r['centroid_y_end']:.4f}"
                f"{'' if r['sane'] else '  SANITY FAILED'}",
                file=sys.stderr,
                flush=True,
            )
        except Exception as e:  # keep going with the other combinations
            r = {"scene": label, "variant": cfg["variant"], "threads": cfg["threads"], "error": str(e)}
            print(f"#   ERROR: {e}", file=sys.stderr, flush=True)
        return r

    combos = [(scene, variant, k) for scene in scenes for variant in variants for k in threads]
    t_all = time.perf_counter()

    def run_combo(combo: tuple) -> dict:
        scene, variant, k = combo
        cfg = {
            "scene": scene,
            "positions": args.positions,
            "variant": variant,
            "threads": k,
            "frames": args.frames,
            "warmup": args.warmup,
            "launch": args.launch,
        }
        label = scene if scene is not None else os.path.splitext(os.path.basename(args.positions))[0]
        return run_one(cfg, label)

    # repeats round the combinations: noise bursts on a shared machine are correlated in time
    rows = []
    for runs in round_robin(combos, max(1, args.repeats), run_combo):
        ok = [r for r in runs if "error" not in r]
        if not ok:
            rows.append(runs[0])
            continue
        best = dict(min(ok, key=lambda r: r["median_ms"]))  # least disturbed run
        best["repeat_medians_ms"] = [r["median_ms"] for r in ok]
        best["sane"] = all(r["sane"] for r in ok) and len(ok) == len(runs)
        rows.append(best)

    print(markdown_table(rows))
    print(f"\n(total wall time {time.perf_counter() - t_all:.0f} s)", file=sys.stderr)
    versions = [r["taichi_version"] for r in rows if "taichi_version" in r]
    meta = {
        "taichi_version": versions[0] if versions else "unknown",
        "launch": args.launch,
        "warmup": args.warmup,
        "frames": args.frames,
        "repeats": args.repeats,
        "total_wall_s": time.perf_counter() - t_all,
    }
    if args.json:
        out = Path(args.json)
        write_results(out.parent, out.stem, doc={"meta": meta, "results": rows}, argv=script_argv(__file__, argv))
    if args.md:
        out = Path(args.md)
        write_results(out.parent, out.stem, markdown=markdown(meta, rows), argv=script_argv(__file__, argv))
    bad = [r for r in rows if "error" in r or not r.get("sane", False)]
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())
