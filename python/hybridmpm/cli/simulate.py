"""The ``hybridmpm`` command line: simulate a scene (``simulate``, ``--solver auto`` reading what ``tune`` chose) and compare two trajectories (``evaluate``)."""

from __future__ import annotations

import argparse
import json
import platform
import time
from pathlib import Path
from typing import Any

import numpy as np

from hybridmpm.cli.common import check_frames_made, latency_ms, out_dir, parse_seed, write_json
from hybridmpm.conventions import AUDIT_EVERY, AUDIT_MAX, AUDIT_TOL, R_C, RESIDUAL_TOL, SAFEGUARD, SAFEGUARDS
from hybridmpm.errors import InvalidInputError
from hybridmpm.mpm.params import INTEGRATORS
from hybridmpm.trajectory import Trajectory


def _simulate(args: argparse.Namespace) -> int:
    """``hybridmpm simulate``: one simulator (:func:`hybridmpm.sim.make_simulator`),
    one :func:`~hybridmpm.sim.rollout`, then the files. A rollout that broke off before
    the frames asked for still writes its files (the frames made), then fails
    (:func:`~hybridmpm.cli.common.check_frames_made`: exit status 2, one line on stderr)."""
    # import time: loaded by this command only
    import hybridmpm
    from hybridmpm.cli.export import PARAMS_KEY, params_json, write_exports
    from hybridmpm.metrics import dam_break_geometry, grid_mass_error, json_scores, rollout_metrics
    from hybridmpm.render import plot_timeline, render_gif
    from hybridmpm.scenes import make_scene
    from hybridmpm.sim import NEURAL, make_simulator, reference, rollout, warmup_frames

    scene = make_scene(args.scene, seed=args.seed)
    frames = args.frames if args.frames is not None else scene.frames
    default: dict[str, Any] | None = None
    if args.solver == "auto":
        _apply_tuned(args, scene.name)
    elif args.solver == "default":
        default = _apply_default(args, scene)
    elif args.solver == "realtime" and _given(args):
        raise InvalidInputError(
            f"solver: {_given(args)[0]} sets a configuration of its own; real-time mode picks its grid and integrator from the scene's "
            "real-time chart (docs/realtime.md): add --solver mpm to set it",
            "solver",
        )
    for key, value in _CONFIG_DEFAULTS.items():  # what the flags not given (None) mean
        if getattr(args, key) is None:
            setattr(args, key, value)
    if frames < 1:
        raise InvalidInputError(f"frames: must be >= 1, got {frames}", "frames")
    exports = list(dict.fromkeys(args.export or []))
    if "usd" in exports:  # before the run: a missing extra is an error now, not after minutes of simulation
        from hybridmpm.render.usd import require_pxr

        require_pxr("export")
    out = out_dir(args.out)
    sim = make_simulator(
        scene, args.solver, model=args.model, r_c=args.r_c, r_p=args.r_p, dwell=args.dwell, audit_every=args.audit_every, audit_tol=args.audit_tol,
        safeguard=args.safeguard, residual_tol=args.residual_tol, audit_max=args.audit_max, seed=args.seed, threads=args.threads,
        nn_threads=max(1, args.threads) if args.solver == "neural" else 1, n_grid=args.n_grid, particles_per_cell=args.particles_per_cell,
        calibrated=args.calibrated, integrator=args.integrator, **({"cheap": args.cheap, "cheap_grid": args.cheap_grid} if args.solver == "hybrid" else {}), cheap_particles=args.cheap_particles,
    )  # fmt: skip
    label = f"{scene.name} [{args.solver}" + (f" r_c={args.r_c:g}]" if args.solver == "hybrid" else "]")
    ro = rollout(sim, frames, progress=None if args.quiet else label)
    low = sim.scene
    per_frame = ro.frame_seconds()
    steps = ro.stats["steps"]
    total = max(1, sum(steps.values()))
    summary: dict = {
        "scene": scene.name, "solver": args.solver, "seed": args.seed, "frames": ro.frames_done, "frames_asked": frames,
        "particles": low.num_particles, "particles_full_resolution": scene.num_particles, "boundary_particles": low.num_boundary,
        "dim": low.dim, "n_grid": low.params.resolved_n_grid(), "integrator": low.params.integrator, "dt_frame": low.dt_frame, "r_p": float(low.info.get("r_p", 1.0)), "r_t": sim.r_t,
        "wall_ms_per_frame": latency_ms(per_frame), "share_of_frames": {k: v / total for k, v in steps.items()}, **ro.stats,
        "failure": ro.failure, "events": [{"step": k, "frame": k * sim.r_t, "event": e} for k, e in ro.events],
        "threads": args.threads, "version": hybridmpm.__version__, "python": platform.python_version(), "machine": platform.machine(),
    }  # fmt: skip
    if ro.failure:
        summary["failure_detail"] = ro.failure_detail
    track = ro.bodies
    if track is not None and track.mass is not None:  # each rigid body: as given, its mass and its centre of mass at the first and last stored frame
        summary["bodies"] = [
            {"shape": b.shape, "density": b.density, "mass": float(m), "center_start": c[0].tolist(), "center_end": c[-1].tolist()}
            for b, m, c in zip(track.shapes, track.mass, np.moveaxis(track.center, 1, 0))
        ]
    # which cheap half ran and on what share of frames (a fallback to MPM counts as MPM); None: no cheap half
    cheap_kind = getattr(sim, "cheap_kind", None) if args.solver == "hybrid" else None
    summary["cheap_half"] = cheap_kind
    summary["cheap_share"] = float(ro.share(cheap_kind)) if cheap_kind is not None else None
    if default is not None:  # --solver default: the chart's choice, or (a scene without one) plain MPM as given
        summary["configuration"] = "default"
        summary["default"] = (
            {k: default.get(k) for k in ("label", "config", "ratios_to_mpm_rp", "cheap_share", "validation_seeds", "budget")} if default else None
        )
    if args.solver == "realtime":  # the rung it ended on and every change of rung
        summary["realtime"] = {**sim.realtime_info(), "history": list(sim.changes)}  # type: ignore[attr-defined]
    if args.solver in ("mpm", "realtime"):
        subs = ro.substeps[1:]
        summary["substeps_total"] = int(subs.sum())
        summary["substeps_per_frame"] = {"min": int(subs.min()), "median": float(np.median(subs)), "max": int(subs.max())} if len(subs) else None
        summary["realtime_factor"] = float(low.dt_frame / np.median(per_frame)) if len(per_frame) else None
    else:
        model = sim.model  # type: ignore[attr-defined]
        summary["model"] = str(model.path)
        summary["warmup_mpm_frames"] = warmup_frames(model)
        summary["neural_steps"] = steps.get(NEURAL, 0)
    if args.solver == "hybrid":
        summary.update(
            {"safeguard": sim.safeguard, "r_c": sim.r_c, "delta": sim.delta, "dwell": sim.dwell, "audit_every": sim.audit_every,  # type: ignore[attr-defined]
             "audit_tol": sim.audit_tol, "residual_tol": sim.residual_tol, "audit_max": sim.audit_max,  # type: ignore[attr-defined]
             "cheap": sim.cheap, "cheap_kind": sim.cheap_kind}  # type: ignore[attr-defined]
        )  # fmt: skip
        if sim.cheap_kind != NEURAL:  # type: ignore[attr-defined]
            summary["cheap_grid"] = sim.neural.n_grid  # type: ignore[attr-defined]
            summary["cheap_particles"] = args.cheap_particles or "network"
    err = None
    if args.baseline:
        # MPM at r_p (the shipped network's r_p, the scene's grid) from the same start: what the run is judged against
        base_sim = make_simulator(scene, "mpm", r_p=_shipped_r_p(scene.name), seed=args.seed, threads=args.threads)
        base_ro = rollout(base_sim, ro.frames_done, progress=None if args.quiet else f"{scene.name} [MPM at r_p]")
        summary["baseline"] = {"solver": "mpm", "r_p": float(base_sim.scene.info.get("r_p", 1.0)), "wall_ms_per_frame": latency_ms(base_ro.frame_seconds())}
    if args.reference:
        t0 = time.perf_counter()
        ref_ro = reference(scene, ro.frames_done, stride=sim.r_t, threads=args.threads)
        ref, n = ref_ro.fluid_positions, len(ro.positions)
        ref_ms = (time.perf_counter() - t0) / max(1, ro.frames_done) * 1e3
        err = grid_mass_error(ro.fluid_positions, ref[:n], scene.params.resolved_n_grid())  # the reference's grid
        # every score of a chaotic flow (docs/benchmarks.md "Metrics for a chaotic flow") on the stored frames
        scores = rollout_metrics(
            ro.fluid_positions, ref[:n], (ro.frame_index - ro.frame_index[0]) * scene.dt_frame, scene.params.resolved_n_grid(), errors=err,
            pred_weights=None if ro.masses is None else ro.masses[: ro.num_fluid], ref_weights=None if ref_ro.masses is None else ref_ro.masses[: ref_ro.num_fluid], dam_break=dam_break_geometry(scene.info),
        )  # fmt: skip
        summary["reference"] = {
            "solver": "mpm", "r_p": 1.0, "particles": scene.num_particles, "wall_ms_per_frame_mean": ref_ms,
            "grid_mass_error": {"mean": float(err.mean()), "last": float(err[-1])}, "metrics": json_scores(scores), "metric_seconds": scores["seconds"],
        }  # fmt: skip
        if args.baseline:
            b = base_ro.fluid_positions
            berr = grid_mass_error(b, ref[: len(b)], scene.params.resolved_n_grid())
            summary["baseline"]["grid_mass_error"] = {"mean": float(berr.mean()), "last": float(berr[-1])}
    ro.extras[PARAMS_KEY] = params_json(low.params)  # walls, grid, obstacles: what hybridmpm export needs
    ro.save(out / "trajectory.npz")
    write_json(out / "summary.json", summary)
    title = f"{scene.name} ({args.solver}" + (f", r_c = {args.r_c:g})" if args.solver == "hybrid" else ")")
    if args.solver == "hybrid":
        plot_timeline(out / "timeline.png", ro.dt_frame, ro.solver, ro.score, args.r_c, err, title=title)
    if not args.no_render:
        render_gif(
            ro.positions, ro.particle_type, out / "render.gif", dt_frame=ro.dt_frame, title=title, frame_solver=ro.solver if args.solver == "hybrid" else None,
            bodies=ro.bodies,
        )  # fmt: skip
    if exports:
        write_exports(out / "export", exports, ro, low.params, mesh_format=args.mesh_format, solver=ro.extras["solver"])
    if not args.quiet:
        ms = summary["wall_ms_per_frame"]
        line = f"{scene.name}: {ro.frames_done} frames, {low.num_particles} particles"
        line += f" (r_p {summary['r_p']:g})" if summary["r_p"] < 1 else ""
        line += f" on a {summary['n_grid']}^{low.dim} grid" if summary["n_grid"] != scene.params.resolved_n_grid() else ""
        line += f", {args.solver} median {ms['median']:.2f} ms/frame (p95 {ms['p95']:.2f})" if ms["median"] is not None else ""
        if args.solver == "hybrid":
            cheap = sim.cheap_kind  # type: ignore[attr-defined]
            line += f", {cheap} {100 * ro.share(cheap):.0f}% of steps, {ro.stats['switches']} switches"
        if err is not None:
            sc = summary["reference"]["metrics"]
            line += f"; grid-mass error vs full-res MPM mean {err.mean():.3f}, last {err[-1]:.3f}" + "".join(
                f", {k} {sc[k]:.3g}" for k in ("short_error", "sinkhorn", "ke_error", "front_rms") if sc[k] is not None
            )
        if "bodies" in summary:
            up = 1  # gravity acts along -y in 2D and 3D
            line += "; bodies' centre heights " + ", ".join(
                f"{b['shape']} {b['density'] or b['mass']:g}{' kg/m^3' if b['density'] else ' kg'} {b['center_start'][up]:.3f} -> {b['center_end'][up]:.3f} m"
                for b in summary["bodies"]
            )
        if ro.failure:
            line += f"; broke off: {ro.failure} ({ro.failure_detail})"
        print(line + f" -> {out}/")
        if args.baseline:
            print(_baseline_line(summary, default))
    # fewer frames than asked (the rollout broke off): what was made is written above, and the command fails
    check_frames_made("simulate", ro.frames_done, frames, ro.failure, ro.failure_detail, kept=f"{out}/")
    return 0


#: Settings that choose a solver's configuration: with the default configuration (chosen by the chart) each one given is refused,
#: whatever its value. Their flags default to None (not given), so an explicit value equal to the default (``--r-p 1.0``) is seen.
_CONFIG_FLAGS = (
    "model", "r_c", "r_p", "dwell", "audit_every", "audit_tol", "safeguard", "residual_tol", "audit_max", "n_grid", "particles_per_cell", "cheap",
    "cheap_grid", "cheap_particles", "calibrated", "tuned", "integrator",
)  # fmt: skip
#: What a configuration flag not given means (the others mean None: the solver's default).
_CONFIG_DEFAULTS: dict[str, Any] = {"r_c": R_C, "r_p": 1.0, "cheap": "neural", "calibrated": False}


def _given(args: argparse.Namespace, keys: tuple[str, ...] = _CONFIG_FLAGS) -> list[str]:
    """The configuration flags of ``keys`` given on the command line (whatever their value), as ``--flag``."""
    return ["--" + key.replace("_", "-") for key in keys if getattr(args, key, None) is not None]


def _apply_default(args: argparse.Namespace, scene: Any) -> dict[str, Any]:
    """``--solver default`` (the default): take the shipped default configuration of ``scene``
    (a :class:`~hybridmpm.scenes.Scene`) when it is a registered scene
    (:func:`hybridmpm.sim.default_settings`); returns its entry (empty for a scene without one, a scene
    file whatever its name: plain MPM as given). A configuration flag given (any value) is refused, naming it."""
    # import time: loaded by this command only
    from hybridmpm.sim import default_settings
    from hybridmpm.sim.config import default_entry

    given = _given(args)
    if given:
        flag = given[0]
        raise InvalidInputError(
            f'solver: {flag} sets a configuration of its own; the default of {scene.name} is chosen by the chart (docs/hybrid.md "Defaults per scene"): '
            f"add --solver hybrid, mpm or neural to use {flag}",
            "solver",
        )
    for key, value in default_settings(scene).items():
        setattr(args, key, value)
    entry = default_entry(scene)
    if not args.quiet:
        r = entry.get("ratios_to_mpm_rp", {})
        print(
            f"default: {entry['label']} (on validation seeds: {r.get('time')}x MPM at r_p's time, {r.get('error_mean')}x its error)"
            if entry
            else f"default: no default was chosen for {scene.name}; plain MPM on the scene as given"
        )
    return entry


def _shipped_r_p(scene: str) -> float:
    """``r_p`` of the scene's shipped network (MPM at ``r_p`` is the baseline every configuration is judged against); 1 without one."""
    # import time: loaded by this command only
    from hybridmpm.models import shipped_model, shipped_models
    from hybridmpm.neural.base import read_header

    return float(read_header(shipped_model(scene)).r_p) if scene in shipped_models() else 1.0


def _baseline_line(summary: dict[str, Any], default: dict[str, Any] | None) -> str:
    """This run's time and error as ratios to MPM at ``r_p``'s (``--baseline``), and the plain-MPM front's error at that time."""
    base, ms = summary["baseline"], summary["wall_ms_per_frame"]["median"]
    bms = base["wall_ms_per_frame"]["median"]
    line = f"against MPM at r_p = {base['r_p']:.3g} (same start): time {ms / bms:.2f}x" if ms and bms else "against MPM at r_p: time n/a"
    if "reference" in summary and "grid_mass_error" in base:
        line += f", error {summary['reference']['grid_mass_error']['mean'] / base['grid_mass_error']['mean']:.2f}x"
    if summary.get("cheap_half"):
        line += f", cheap half ({summary['cheap_half']}) on {100 * summary['cheap_share']:.0f}% of steps"
    if default:
        t = (default.get("ratios_to_mpm_rp") or {}).get("time")
        plain = [c["ratios"] for c in default.get("candidates", []) if c["key"].startswith("mpm_") and c["ratios"].get("time") is not None]
        front = [c["error_mean"] for c in plain if t is not None and c["time"] <= t * 1.000001 and c.get("error_mean") is not None]
        if front:
            line += f"; the plain-MPM front at its time on the validation seeds errs {min(front):.2f}x MPM at r_p"
    return line


def _apply_tuned(args: argparse.Namespace, scene: str) -> None:
    """``--solver auto``: take solver, model, r_p and r_c from the configuration
    ``hybridmpm tune`` wrote (``--tuned``, default tuned/SCENE.json)."""
    # import time: loaded by this command only
    from hybridmpm.sim import load_tuned, tuned_settings

    given = _given(args, ("model", "r_p", "n_grid", "particles_per_cell", "calibrated"))
    if given:
        raise InvalidInputError(f"solver: --solver auto takes the model, r_p, grid and r_c from the tuned configuration; drop {'/'.join(given)}", "solver")
    doc = load_tuned(scene, args.tuned)
    for key, value in tuned_settings(doc).items():
        setattr(args, key, value)
    cfg = doc["config"]
    if not args.quiet:
        m = doc["measured"]
        print(
            f"auto: {cfg['label']} (tuned for error <= {doc['error_budget']:g}: measured {m['error_mean']:.3f}, "
            f"{m['ms_mean']:.2f} ms/frame on validation seeds)"
        )


def _evaluate(args: argparse.Namespace) -> int:
    """``hybridmpm evaluate``: the comparison is sized from both files' headers (their positions'
    shapes: at most the shorter one's frames are compared) against the memory budget before either
    file is read (:func:`hybridmpm.metrics.check_evaluate_size`), then :func:`hybridmpm.metrics.evaluate`."""
    # import time: loaded by this command only
    from hybridmpm.metrics import check_evaluate_size, evaluate
    from hybridmpm.trajectory import trajectory_headers

    shapes = [h.shape for h in (trajectory_headers(p).get("positions") for p in (args.pred, args.ref)) if h is not None]
    if len(shapes) == 2 and all(len(s) == 3 for s in shapes):  # anything else: Trajectory.load names what is wrong
        check_evaluate_size(min(shapes[0][0], shapes[1][0]), shapes[0][1], shapes[1][1], shapes[1][2], f"{Path(args.pred).name} and {Path(args.ref).name}")
    pred = Trajectory.load(args.pred)
    ref = Trajectory.load(args.ref)
    geometry = None
    if args.scene is not None:  # the dam break's geometry: its front against Martin & Moyce
        from hybridmpm.metrics import dam_break_geometry
        from hybridmpm.scenes import scene_spec

        geometry = dam_break_geometry(scene_spec(args.scene, seed=0).info)
    result = evaluate(pred, ref, n_grid=args.n_grid, dam_break=geometry)
    result["pred"]["path"] = str(Path(args.pred))
    result["ref"]["path"] = str(Path(args.ref))
    out = Path(args.out) if args.out is not None else Path(args.pred).parent / "metrics.json"
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.with_name(out.name + ".tmp")
    tmp.write_text(json.dumps(result, indent=2))
    tmp.replace(out)
    if not args.quiet:
        gme = result["grid_mass_error"]
        lines = [
            f"{result['frames_compared']} frames compared (pred every {pred.dt_frame * 1e3:g} ms, ref every {ref.dt_frame * 1e3:g} ms; "
            f"{result['pred']['particles']} vs {result['ref']['particles']} fluid particles)",
            f"grid-mass error (n_grid {result['n_grid']}): mean {gme['mean']:.4g}, last {gme['last']:.4g}",
        ]
        for key, label in (("position_mse_rollout", "rollout"), ("position_mse_one_step", "one-step")):
            m = result[key]
            lines.append(f"{label} position MSE: " + (f"mean {m['mean']:.4g} m², last {m['last']:.4g} m²" if m else f"n/a ({result[key + '_reason']})"))
        sc = result["metrics"]
        lines.append(
            "chaotic-flow scores: " + ", ".join(f"{k} {sc[k]:.4g}" if sc[k] is not None else f"{k} n/a" for k in ("short_error", "sinkhorn", "ke_error"))
            + (f", front_rms {sc['front_rms']:.4g}" if sc["front_rms"] is not None else "")
        )  # fmt: skip
        lines.append(f"-> {out}")
        print("\n".join(lines))
    return 0


def add_parsers(sub: Any) -> None:
    """Register this group's commands on the subparsers ``sub``."""
    from hybridmpm.scenes import DOMAINS  # import time: loaded when the parser is built

    sim = sub.add_parser("simulate", help="run a scene and write trajectory.npz, summary.json and render.gif")
    sim.add_argument(
        "scene", nargs="?", default="dam_break2d", help=f"a scene ({', '.join(sorted(DOMAINS))}) or a scene file (.toml/.json); default dam_break2d"
    )
    sim.add_argument(
        "--solver", default="default", choices=["default", "hybrid", "mpm", "neural", "realtime", "auto"],
        help="solver (default: the scene's default configuration, chosen by the chart: docs/hybrid.md \"Defaults per scene\"; hybrid: the paper's, "
        "neural, MPM while s(t) < r_c; realtime: MPM on the grid and integrator of its real-time chart that keep real time here, "
        "docs/realtime.md; auto: the configuration hybridmpm tune chose)",
    )  # fmt: skip
    sim.add_argument("--tuned", default=None, help="--solver auto: tuned configuration (default tuned/SCENE.json)")
    sim.add_argument("--model", default=None, help="ONNX model for --solver neural|hybrid (default: the shipped model for the scene)")
    sim.add_argument(
        "--cheap",
        default=None,
        choices=["neural", "mpm-coarse"],
        help="hybrid: its cheap half, the network (default) or MPM on a coarser grid with the same particles (the classical twin)",
    )
    sim.add_argument("--cheap-grid", type=int, default=None, help="hybrid --cheap mpm-coarse: the coarse grid (default half the scene's)")
    sim.add_argument(
        "--cheap-particles", default=None, choices=["network", "grid"],
        help="hybrid --cheap mpm-coarse: the particles its coarse grid carries, the network's r_p set (default) or the grid's own (merged and split at each handover)",
    )  # fmt: skip
    sim.add_argument("--r-c", type=float, default=None, help=f"hybrid threshold r_c (default {R_C:g}; 0 = no complexity trigger, > 1 = MPM only)")
    sim.add_argument("--dwell", type=int, default=None, help="hybrid: steps of s(t) >= r_c on MPM before the network takes over again")
    sim.add_argument("--audit-every", type=int, default=None, help=f"hybrid: network steps per MPM audit (default {AUDIT_EVERY}; 0 = no audit; docs/hybrid.md)")
    sim.add_argument("--audit-tol", type=float, default=None, help=f"hybrid: MPM audit tolerance in g (default {AUDIT_TOL:g})")
    sim.add_argument(
        "--safeguard", default=None, choices=list(SAFEGUARDS),
        help=f"hybrid: switching rule (default {SAFEGUARD}: s(t) and the MPM audit; paper: s(t) alone; error: an audit whose interval adapts, no s(t); docs/hybrid.md)",
    )  # fmt: skip
    sim.add_argument(
        "--residual-tol", type=float, default=None, help=f"hybrid, error rule: density residual in g that brings the audit forward (default {RESIDUAL_TOL:g})"
    )
    sim.add_argument("--audit-max", type=int, default=None, help=f"hybrid, error rule: longest interval between audits in network steps (default {AUDIT_MAX})")
    sim.add_argument(
        "--reference", action="store_true",
        help="also run full-resolution MPM and report the grid-mass error and the scores of a chaotic flow in summary.json (docs/benchmarks.md)",
    )  # fmt: skip
    sim.add_argument(
        "--export", nargs="+", default=None, choices=["ply", "vtu", "mesh", "usd"], metavar="{ply,vtu,mesh,usd}",
        help="also write to OUT/export/: point clouds frame_#####.ply|vtu (Blender, ParaView), surface meshes <material>_#####.<--mesh-format> "
        "(docs/mesh.md), one USD file run.usd (docs/usd.md; needs the usd extra); several at once: --export ply usd mesh",
    )  # fmt: skip
    sim.add_argument("--mesh-format", default="ply", choices=["ply", "obj", "glb"], help="--export mesh: file format (default ply)")
    sim.add_argument("--frames", type=int, default=None, help="frames of 2.5 ms (default: the scene's)")
    sim.add_argument("--out", default="runs/out", help="output directory (default: runs/out)")
    sim.add_argument("--seed", type=parse_seed, default=0, help="seed of the scene's random initial condition")
    sim.add_argument("--threads", type=int, default=0, help="solver threads (0 = all cores)")
    sim.add_argument("--r-p", type=float, default=None, help="spatial downsampling r_p in (0, 1]: cluster the initial particles (default 1)")
    sim.add_argument(
        "--n-grid", type=int, default=None, help="--solver mpm: run on this grid of the same domain (same blocks, obstacles, wall faces; default: the scene's)"
    )
    sim.add_argument(
        "--particles-per-cell",
        type=int,
        default=None,
        help="--solver mpm: particles per cell per axis of the lattice on --n-grid (1-4; default the scene's, 2)",
    )
    sim.add_argument(
        "--calibrated",
        action="store_true",
        default=None,
        help="--solver mpm --n-grid N: the calibrated coarse material fitted for the scene on that grid (docs/correction.md); refused where none was fitted",
    )
    sim.add_argument(
        "--integrator",
        default=None,
        choices=list(INTEGRATORS),
        help="--solver mpm: how a frame advances: explicit MLS-MPM substeps, or projection: incompressible APIC water at the flow's pace "
        "(water only, round free-slip obstacles and rigid bodies; docs/large-step.md; default: the scene's)",
    )
    sim.add_argument(
        "--baseline", action="store_true",
        help="also run MPM at r_p (the shipped network's r_p, the scene's grid) from the same start and print this run's time (and with --reference "
        "its error) as ratios to it",
    )  # fmt: skip
    sim.add_argument("--no-render", action="store_true", help="skip render.gif")
    sim.add_argument("--quiet", action="store_true", help="no progress bar or summary line")
    sim.set_defaults(func=_simulate)
    ev = sub.add_parser("evaluate", help="compare a predicted trajectory.npz with a reference one and write metrics.json")
    ev.add_argument("pred", help="predicted trajectory (.npz, as written by simulate)")
    ev.add_argument("ref", help="reference trajectory (.npz), e.g. full-resolution MPM from the same initial condition")
    ev.add_argument("--n-grid", type=int, default=None, help="grid of the grid-mass error (default: the reference's, else 128 in 2D / 64 in 3D)")
    ev.add_argument(
        "--scene", default=None, choices=sorted(DOMAINS),
        help="the registered scene both come from: for the dam break (dam_break2d, dam_break3d) adds the front against Martin & Moyce (1952)",
    )  # fmt: skip
    ev.add_argument("--out", default=None, help="metrics JSON to write (default: metrics.json next to PRED)")
    ev.add_argument("--quiet", action="store_true", help="no summary")
    ev.set_defaults(func=_evaluate)
