"""Simulator configurations: :func:`make_simulator` builds any of the three
simulators from plain settings (what the CLI and the service take), and
:func:`load_tuned` reads the configuration ``hybridmpm tune`` chose
(``hybridmpm simulate SCENE --solver auto``)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from hybridmpm.conventions import R_C
from hybridmpm.errors import InvalidInputError
from hybridmpm.limits import check_seed
from hybridmpm.models import shipped_default
from hybridmpm.scenes.core import Clusters, Scene
from hybridmpm.scenes.registry import registered_name
from hybridmpm.sim.base import Simulator
from hybridmpm.sim.hybrid import HybridSimulator
from hybridmpm.sim.mpm import MpmSimulator
from hybridmpm.sim.neural import NeuralSimulator
from hybridmpm.sim.realtime import RealtimeSimulator
from hybridmpm.sim.switching import SwitchingRule

#: Solver kinds :func:`make_simulator` builds; "default" is the scene's shipped default configuration
#: (:func:`default_settings`: one of "hybrid", "mpm" and "neural", chosen by the chart); "realtime" the scene's
#: default particles on the real-time ladder (:class:`~hybridmpm.sim.realtime.RealtimeSimulator`).
SOLVERS = ("default", "hybrid", "mpm", "neural", "realtime")
#: Default location of a tuned configuration, relative to the working directory.
TUNED_DIR = Path("tuned")
#: The rule settings :func:`make_simulator` takes (the rest of a rule's
#: :meth:`~hybridmpm.sim.switching.SwitchingRule.to_dict` are the defaults).
RULE_KEYS = ("safeguard", "r_c", "dwell", "audit_every", "audit_tol", "residual_tol", "audit_max")
#: Keys of a configuration (the chosen method) in the tuned file.
CONFIG_KEYS = ("key", "kind", "label", "r_p", "r_t", "r_c", "model", "role", "params", "safeguard", "audit_tol", "n_grid", "calibrated", "integrator")


def make_simulator(
    scene: Scene | str,
    solver: str = "hybrid",
    *,
    model: Any = None,
    r_c: float = R_C,
    r_p: float = 1.0,
    dwell: int | None = None,
    audit_every: int | None = None,
    audit_tol: float | None = None,
    safeguard: str | None = None,
    residual_tol: float | None = None,
    audit_max: int | None = None,
    seed: int = 0,
    threads: int = 0,
    nn_threads: int = 1,
    clusters: Clusters | None = None,
    n_grid: int | None = None,
    particles_per_cell: int | None = None,
    cheap: str = "neural",
    cheap_grid: int | None = None,
    cheap_particles: str | None = None,
    calibrated: bool = False,
    integrator: str | None = None,
) -> Simulator:
    """A simulator of ``scene`` by kind: "default" (the scene's shipped default
    configuration, :func:`default_settings`; only ``seed``, ``threads``,
    ``nn_threads`` and ``clusters`` may be given with it), "realtime" (MPM on the
    default's particles that picks, from the scene's real-time chart, the most
    accurate grid and integrator whose frame fits real time on this machine:
    :class:`~hybridmpm.sim.realtime.RealtimeSimulator`, docs/realtime.md; the
    same settings as "default"), "hybrid" (model, ``r_c``, ``dwell``,
    the MPM audit's ``audit_every`` and ``audit_tol``, the switching rule
    ``safeguard`` and the "error" rule's ``residual_tol`` and ``audit_max``;
    None: the defaults),
    "mpm" (at ``r_p``) or "neural" (the model alone after its MPM warm-up).
    ``model`` an ONNX path, a :class:`~hybridmpm.neural.GnsRuntime` or None
    (the scene's shipped model); ``threads`` MPM threads (0 = all cores);
    ``clusters`` an earlier simulator's ``scene.clusters`` (same scene and
    ``r_p``), which skips the k-means of the downsampling; ``n_grid`` and
    ``particles_per_cell`` run MPM on another grid of the same domain
    (:func:`~hybridmpm.scenes.resolution.on_grid`; None: the scene's);
    ``cheap`` the hybrid's cheap half ("neural", or "mpm-coarse": its
    classical twin, MPM on a ``cheap_grid`` grid, default half the scene's)
    and ``cheap_particles`` what the twin's coarse grid carries ("network":
    the network's ``r_p`` set, the default; "grid": the grid's own set,
    merged and split at each handover; :data:`~hybridmpm.sim.hybrid.TWIN_PARTICLES`);
    ``calibrated`` runs MPM on ``n_grid`` with the calibrated coarse material
    of the scene (:func:`~hybridmpm.scenes.resolution.calibrate`);
    ``integrator`` steps MPM with "explicit" substeps or the incompressible
    "projection" (:func:`~hybridmpm.scenes.resolution.with_integrator`,
    docs/large-step.md; None: the scene's).
    ``seed`` an integer in [0, 2^63) (the scene's initial condition and the
    k-means of the downsampling: :func:`~hybridmpm.scenes.resolution.kmeans_seed`).
    "default" takes a registered scene's default; a scene file (or spec) of
    your own has none, whatever its ``name`` (:func:`default_entry`), and runs
    plain MPM as given.
    Raises :class:`InvalidInputError` naming the bad setting (``solver``,
    ``seed`` outside [0, 2^63), checked before any work, ``r_p``, ``n_grid``
    or ``particles_per_cell`` for a network solver: it runs at its model's
    resolution)."""
    if solver not in SOLVERS:
        raise InvalidInputError(f"solver: must be one of {', '.join(SOLVERS)}, got {solver!r}", "solver")
    check_seed(seed)  # before any work: every generator it reaches (the scene's, k-means') takes it
    if solver in ("default", "realtime"):
        name = scene.name if isinstance(scene, Scene) else str(scene)
        for field, value, unset in (
            ("model", model, None), ("r_c", r_c, R_C), ("r_p", r_p, 1.0), ("dwell", dwell, None), ("audit_every", audit_every, None),
            ("audit_tol", audit_tol, None), ("safeguard", safeguard, None), ("residual_tol", residual_tol, None), ("audit_max", audit_max, None),
            ("n_grid", n_grid, None), ("particles_per_cell", particles_per_cell, None), ("cheap", cheap, "neural"), ("cheap_grid", cheap_grid, None),
            ("cheap_particles", cheap_particles, None), ("calibrated", calibrated, False), ("integrator", integrator, None),
        ):  # fmt: skip
            if value != unset:
                chart = 'the chart (docs/hybrid.md "Defaults per scene")' if solver == "default" else "its real-time chart (docs/realtime.md)"
                raise InvalidInputError(
                    f"{field}: the {solver} configuration of {name} is chosen by {chart}; name the solver (hybrid, mpm or neural) to set {field}",
                    field,
                )
        if solver == "realtime":
            settings = default_settings(scene)
            r_p = float(settings.get("r_p", 1.0)) if settings.get("solver") == "mpm" else 1.0
            return RealtimeSimulator(scene, r_p=r_p, seed=seed, threads=threads, clusters=clusters)
        return make_simulator(scene, seed=seed, threads=threads, nn_threads=nn_threads, clusters=clusters, **default_settings(scene))
    if solver != "mpm":
        for name, value, unset in (
            ("r_p", r_p, 1.0),
            ("n_grid", n_grid, None),
            ("particles_per_cell", particles_per_cell, None),
            ("calibrated", calibrated, False),
            ("integrator", integrator, None),
        ):
            if value != unset:
                raise InvalidInputError(f"{name}: applies to the mpm solver; the {solver} solver runs at its model's resolution", name)
    if cheap_particles is not None and (solver != "hybrid" or cheap != "mpm-coarse"):
        raise InvalidInputError("cheap_particles: applies to the hybrid whose cheap half is 'mpm-coarse' (the classical twin)", "cheap_particles")
    twin: dict[str, Any] = {} if cheap_particles is None else {"cheap_particles": cheap_particles}
    if solver == "mpm":
        return MpmSimulator(
            scene,
            r_p=r_p,
            seed=seed,
            threads=threads,
            clusters=clusters,
            n_grid=n_grid,
            particles_per_cell=particles_per_cell,
            calibrated=calibrated,
            integrator=integrator,
        )
    if solver == "neural":
        return NeuralSimulator(scene, model, seed=seed, mpm_threads=threads, nn_threads=nn_threads, clusters=clusters)
    return HybridSimulator(
        scene,
        model,
        # None: the shipped model's rule or the defaults (hybridmpm.sim.switching.make_rule)
        r_c=r_c,
        dwell=dwell,
        audit_every=audit_every,
        audit_tol=audit_tol,
        safeguard=safeguard,
        residual_tol=residual_tol,
        audit_max=audit_max,
        seed=seed,
        mpm_threads=threads,
        nn_threads=nn_threads,
        clusters=clusters,
        cheap=cheap,
        cheap_grid=cheap_grid,
        **twin,
    )


def default_entry(scene: Scene | str) -> dict[str, Any]:
    """The shipped default of ``scene`` (:func:`hybridmpm.models.shipped_default`) when it is a
    registered scene (:func:`hybridmpm.scenes.registered_name`: a registered name, or a scene the
    registry built), else empty: a default belongs to a registered scene, not to a name, so a scene
    file (or spec) of your own has none, whatever its ``name``."""
    name = registered_name(scene)
    return shipped_default(name) if name is not None else {}


def default_settings(scene: Scene | str) -> dict[str, Any]:
    """The :func:`make_simulator` keyword arguments of ``scene``'s shipped default
    configuration (:func:`hybridmpm.models.shipped_default`, chosen on validation
    seeds by ``benchmarks/release/ship_defaults.py``: the fastest candidate within
    its error budget against MPM at ``r_p``); a scene without one (a scene file of
    your own, whatever its ``name``: :func:`default_entry`) runs plain MPM as
    given, ``{"solver": "mpm"}``. Raises :class:`InvalidInputError` (``defaults``)
    when the package's ``models/defaults.json`` is corrupt."""
    entry = default_entry(scene)
    if not entry:
        return {"solver": "mpm"}
    try:
        return tuned_settings({"config": entry["config"]})
    except (KeyError, TypeError, ValueError) as e:  # package data (checked by shipped_default as far as its shape): a value it misses
        raise InvalidInputError(
            f"defaults: the default configuration of {registered_name(scene)} in the package's models/defaults.json is corrupt ({type(e).__name__}: {e}); "
            "reinstall hybridmpm",
            "defaults",
        ) from None


def tuned_path(scene: str, path: str | Path | None = None) -> Path:
    """Where the tuned configuration of ``scene`` lives (``tuned/SCENE.json`` by default)."""
    return Path(path) if path is not None else TUNED_DIR / f"{scene}.json"


def load_tuned(scene: str, path: str | Path | None = None) -> dict[str, Any]:
    """Read the tuned configuration of ``scene``. Raises
    :class:`InvalidInputError` (field ``tuned``) if the file is missing,
    malformed, or made for another scene."""
    p = tuned_path(scene, path)
    if not p.is_file():
        raise InvalidInputError(f"tuned: no tuned configuration at {p}; run `hybridmpm tune {scene} --error-budget E` first", "tuned")
    try:
        doc = json.loads(p.read_text())
        cfg = doc["config"]
        kind = cfg["kind"]
    except (ValueError, KeyError, TypeError) as e:
        raise InvalidInputError(f"tuned: {p} is not a tuned configuration ({e})", "tuned") from e
    if doc.get("scene") != scene:
        raise InvalidInputError(f"tuned: {p} was tuned for {doc.get('scene')!r}, not {scene!r}", "tuned")
    if kind not in ("mpm", "neural", "hybrid"):
        raise InvalidInputError(f"tuned: {p} has unknown solver kind {kind!r}", "tuned")
    if kind != "mpm" and not (cfg.get("model") and Path(cfg["model"]).is_file()):
        raise InvalidInputError(f"tuned: the model {cfg.get('model')!r} of {p} does not exist", "tuned")
    return dict(doc)


def tuned_settings(doc: dict[str, Any]) -> dict[str, Any]:
    """The :func:`make_simulator` keyword arguments of a tuned configuration
    (``solver``, and ``r_p``, ``n_grid``, ``integrator`` and ``calibrated`` where set, or ``model`` and ``r_c``, and the hybrid's
    rule: its ``rule`` (a :meth:`~hybridmpm.sim.switching.SwitchingRule.to_dict`), or in
    configurations tuned before that was written, ``safeguard`` and ``audit_tol`` where set).
    Raises :class:`InvalidInputError` naming a bad rule setting."""
    cfg = doc["config"]
    if cfg["kind"] == "mpm":
        # configurations tuned before grids were a knob ran on the scene's grid
        mpm: dict[str, Any] = {"solver": "mpm", "r_p": float(cfg["r_p"]), "n_grid": None if cfg.get("n_grid") is None else int(cfg["n_grid"])}
        if cfg.get("integrator"):  # a large step (docs/large-step.md); configurations chosen before it ran the scene's
            mpm["integrator"] = str(cfg["integrator"])
        return {**mpm, "calibrated": True} if cfg.get("calibrated") else mpm  # a calibrated coarse material (docs/correction.md)
    out: dict[str, Any] = {"solver": cfg["kind"], "model": cfg["model"]}
    if cfg["kind"] == "hybrid" and cfg.get("cheap", "neural") != "neural":
        out["cheap"] = str(cfg["cheap"])  # the classical twin (a default may be one)
        if cfg.get("cheap_particles"):
            out["cheap_particles"] = str(cfg["cheap_particles"])  # with the coarse grid's own particle set
    if cfg["kind"] == "hybrid" and cfg.get("rule"):
        rule = SwitchingRule.from_dict(cfg["rule"]).to_dict()
        out.update({k: rule[k] for k in RULE_KEYS if k in rule})
    elif cfg["kind"] == "hybrid":
        out["r_c"] = float(cfg["r_c"])
        # configurations tuned before the switching rules existed have neither: the defaults
        if cfg.get("safeguard"):
            out["safeguard"] = str(cfg["safeguard"])
        if cfg.get("audit_tol") is not None:
            out["audit_tol"] = float(cfg["audit_tol"])
    return out


__all__ = [
    "CONFIG_KEYS",
    "RULE_KEYS",
    "SOLVERS",
    "TUNED_DIR",
    "default_entry",
    "default_settings",
    "load_tuned",
    "make_simulator",
    "tuned_path",
    "tuned_settings",
]
