"""The methods ``hybridmpm bench`` compares (paper Fig. 5, Fig. 8, Table 2).

A :class:`Method` is one configuration of a solver: MPM at full resolution
(the reference), MPM at ``r_p``, a neural model alone, or the hybrid at a
threshold ``r_c``. :func:`methods_for` lists those that exist for a scene:
the neural variants (full resolution ``r_p = r_t = 1``, spatial-only,
temporal-only) only where a model was trained for them
(:func:`hybridmpm.models.variant_models`).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, fields
from pathlib import Path
from typing import Any

from hybridmpm.conventions import AUDIT_TOL, R_C, SAFEGUARD
from hybridmpm.errors import InvalidInputError
from hybridmpm.models import shipped_default, shipped_model, shipped_switching, variant_models
from hybridmpm.models.calibrated import fit_name, shipped_calibrations
from hybridmpm.mpm.params import INTEGRATORS
from hybridmpm.neural.base import open_model
from hybridmpm.scenes import scene_spec
from hybridmpm.scenes.resolution import with_integrator

#: Hybrid thresholds of the sweep (paper Table 2).
R_C_SWEEP = tuple(round(0.1 * i, 1) for i in range(10))
#: Audit tolerances [g] of the "error" rule's sweep (docs/hybrid.md "Switching rules").
ERROR_TOL_SWEEP = (0.5, 1.0, 2.0, 3.0, 5.0)

#: Coarser grids of plain MPM, as fractions of the scene's grid (2D: 96², 64²
#: of 128²; 3D: 48³, 32³ of 64³), each at r_p = 1 and at the model's r_p:
#: with the scene's grid they make the classical front every method is judged against.
GRID_FRACTIONS = (0.75, 0.5)

#: Method kinds.
KINDS = ("mpm", "neural", "hybrid")

#: Neural roles by resolution: (r_p == 1, r_t == 1) -> role.
_ROLE = {(True, True): "full", (False, True): "spatial", (True, False): "temporal", (False, False): "lowres"}
ROLE_LABEL = {
    "full": "neural r_p = r_t = 1",
    "spatial": "neural spatial-only",
    "temporal": "neural temporal-only",
    "lowres": "neural",
}


@dataclass(frozen=True)
class Method:
    """One benchmarked configuration.

    ``key`` unique id (file names, CSV); ``kind`` "mpm", "neural" or
    "hybrid"; ``model`` the ONNX file (neural and hybrid) or None; ``r_p``
    spatial and ``r_t`` temporal downsampling; ``r_c`` the hybrid threshold
    (None otherwise); ``role`` "reference", "mpm_rp", "mpm_grid" (MPM on a
    coarser grid), "full", "spatial", "temporal", "lowres" (the shipped
    model), "size" (another network size) or "hybrid"; ``params`` network
    parameters (0 for MPM); ``safeguard`` the hybrid's switching rule
    (:data:`~hybridmpm.conventions.SAFEGUARDS`; None: the default) and
    ``audit_tol`` its audit tolerance [g] (None: the default); ``n_grid``
    the grid MPM runs on (None: the scene's;
    :func:`~hybridmpm.scenes.resolution.on_grid`, 2 particles per cell per
    axis); ``cheap`` the hybrid's cheap half ("neural", or "mpm-coarse": the
    classical twin, MPM on half the grid, :mod:`hybridmpm.sim.coarse`);
    ``calibrated`` MPM on ``n_grid`` with the calibrated coarse material of
    the scene (:func:`~hybridmpm.scenes.resolution.calibrate`);
    ``cheap_particles`` what the classical twin's coarse grid carries (None:
    the hybrid's particle set; "grid": its own, two per cell per axis,
    :class:`~hybridmpm.sim.coarse.CoarseOwnHalf`); ``integrator`` what steps
    plain MPM (None: the scene's, the explicit step; "projection": the large
    step of docs/large-step.md, role "large_step").
    """

    key: str
    kind: str
    label: str
    r_p: float = 1.0
    r_t: int = 1
    r_c: float | None = None
    model: str | None = None
    role: str = "reference"
    params: int = 0
    safeguard: str | None = None
    audit_tol: float | None = None
    n_grid: int | None = None
    cheap: str = "neural"
    calibrated: bool = False
    cheap_particles: str | None = None
    integrator: str | None = None

    def config(self) -> dict[str, Any]:
        """The configuration as a plain dict (``hybridmpm tune`` writes it)."""
        return asdict(self)


def neural_role(r_p: float, r_t: int) -> str:
    """ "full", "spatial", "temporal" or "lowres" for a model's resolution."""
    return _ROLE[(r_p >= 1.0, r_t == 1)]


def _model_info(path: Path, field: str = "model") -> tuple[float, int, int]:
    """``(r_p, r_t, parameters)`` of the model file ``path``; a file :func:`~hybridmpm.neural.base.open_model`
    refuses is an :class:`InvalidInputError` naming ``field`` (the argument that gave it)."""
    try:
        m = open_model(path)
    except InvalidInputError as e:
        if field == "model":
            raise
        raise InvalidInputError(f"{field}: {e}", field) from None
    params = int(m.meta.get("parameters", m.meta.get("params", 0)) or 0)
    return m.r_p, m.r_t, params


def mpm_grid_methods(scene: str, r_p: float, seed: int = 0, fractions: tuple[float, ...] = GRID_FRACTIONS) -> tuple[list[Method], dict[int, str]]:
    """Plain MPM on coarser grids of ``scene`` (``fractions`` of its grid),
    each at ``r_p = 1`` and at ``r_p``: the methods, and per grid the scene
    refuses (checked on ``seed``'s initial condition) the reason, e.g. an
    obstacle thinner than two cells of it."""
    spec = scene_spec(scene, seed=seed)
    n0 = spec.params.resolved_n_grid()
    out: list[Method] = []
    refused: dict[int, str] = {}
    for frac in fractions:
        n = int(round(n0 * float(frac)))
        try:
            spec.on_grid(n)
        except InvalidInputError as e:
            refused[n] = str(e)
            continue
        out.append(Method(f"mpm_g{n}", "mpm", f"MPM {n}^{spec.dim}", 1.0, 1, role="mpm_grid", n_grid=n))
        if r_p < 1.0:
            out.append(Method(f"mpm_g{n}_rp", "mpm", f"MPM {n}^{spec.dim}, r_p = {r_p:.3g}", r_p, 1, role="mpm_grid", n_grid=n))
    return out, refused


def large_step_methods(scene: str, r_p: float, seed: int = 0, fractions: tuple[float, ...] = GRID_FRACTIONS) -> tuple[list[Method], dict[str, str]]:
    """Plain MPM stepped by each large-step integrator (every one of
    :data:`~hybridmpm.mpm.params.INTEGRATORS` but the explicit step; today the
    pressure projection, docs/large-step.md) where ``scene`` allows it: on the
    scene's grid at ``r_p = 1`` (key ``mpm_projection``) and at ``r_p``
    (``mpm_rp_projection``), and on each coarser grid of ``fractions`` the
    scene holds at ``r_p = 1`` (``mpm_g<n>_projection``), all of role
    "large_step". Returns the methods, and per integrator the scene refuses
    (checked on ``seed``'s initial condition: obstacles, bodies, another
    material) the reason."""
    spec = scene_spec(scene, seed=seed)
    built = spec.build()
    grids = [m.n_grid for m in mpm_grid_methods(scene, 1.0, seed, fractions)[0]]
    out: list[Method] = []
    refused: dict[str, str] = {}
    for integrator in INTEGRATORS[1:]:
        try:
            with_integrator(built, integrator)
        except InvalidInputError as e:
            refused[integrator] = str(e)
            continue
        role = "large_step"
        out.append(Method(f"mpm_{integrator}", "mpm", f"MPM full resolution, {integrator}", role=role, integrator=integrator))
        if r_p < 1.0:
            out.append(Method(f"mpm_rp_{integrator}", "mpm", f"MPM r_p = {r_p:.3g}, {integrator}", r_p, role=role, integrator=integrator))
        for n in grids:
            out.append(Method(f"mpm_g{n}_{integrator}", "mpm", f"MPM {n}^{spec.dim}, {integrator}", role=role, n_grid=n, integrator=integrator))
    return out, refused


def methods_for(
    scene: str,
    *,
    r_cs: tuple[float, ...] = R_C_SWEEP,
    model: str | Path | None = None,
    variants: bool = True,
    extra_models: tuple[str | Path, ...] = (),
    error_tols: tuple[float, ...] = ERROR_TOL_SWEEP,
    grids: tuple[float, ...] = GRID_FRACTIONS,
    seed: int = 0,
    large_step: bool = True,
) -> list[Method]:
    """The methods of a benchmark of registered scene ``scene``.

    ``model`` the hybrid's network (default: the shipped model of the scene);
    its ``r_p`` is the resolution of "MPM at r_p". ``variants`` adds the
    shipped variants of the scene (:func:`hybridmpm.models.variant_models`),
    ``extra_models`` more ONNX files, each run alone; the hybrid at each
    ``r_cs`` (the "audit" rule), the paper's rule at ``r_c`` = 0.8, the
    "error" rule at each audit tolerance of ``error_tols`` [g], and the
    GNS hybrid under the rule shipped with the scene's model (key
    ``hybrid_default``; else the rule's defaults), its classical twin with MPM on half the grid as the cheap
    half (key ``hybrid_coarse``, the same rule; ``hybrid_coarse_own`` with the
    coarse grid's own particle set), and plain MPM on each coarser grid of ``grids`` (fractions of
    the scene's grid, at r_p = 1 and at the model's r_p; grids the scene
    refuses on ``seed``'s initial condition are left out:
    :func:`mpm_grid_methods`; with the calibrated coarse material where one
    was fitted for the scene and grid, key ``mpm_g<n>_cal``); with
    ``large_step``, plain MPM stepped by each large-step integrator the scene
    allows, on its grid and the same coarser grids (:func:`large_step_methods`).
    Raises
    :class:`InvalidInputError` (field ``r_c``) for thresholds outside [0, 1], ``model`` /
    ``extra_models`` for a model file that is missing, not a regular file (a FIFO, ``/dev/zero``),
    larger than :data:`~hybridmpm.files.MAX_MODEL_BYTES` or no model of hybridmpm.
    """

    for r in r_cs:
        if not (0.0 <= float(r) <= 1.0):
            raise InvalidInputError(f"r_c: thresholds must lie in [0, 1], got {r!r}", "r_c")
    main = Path(model) if model is not None else shipped_model(scene)
    r_p, r_t, params = _model_info(main)
    out = [
        Method("mpm_full", "mpm", "MPM full resolution", 1.0, 1, role="reference"),
        Method("mpm_rp", "mpm", f"MPM r_p = {r_p:.3g}", r_p, 1, role="mpm_rp"),
    ]
    out += mpm_grid_methods(scene, r_p, seed, grids)[0]
    out += [  # a calibrated coarse material: one more plain-MPM configuration, where one was fitted (docs/correction.md)
        Method(f"mpm_g{m.n_grid}_cal", "mpm", f"{m.label}, calibrated", role="mpm_grid", n_grid=m.n_grid, calibrated=True)
        for m in mpm_grid_methods(scene, r_p, seed, grids)[0]
        if m.r_p == 1.0 and fit_name(scene, int(m.n_grid or 0)) in shipped_calibrations()
    ]
    if large_step:
        out += large_step_methods(scene, r_p, seed, grids)[0]
    models: list[tuple[str, Path, str, str]] = []
    if variants:
        models += [(v["name"], v["path"], v["role"], "model") for v in variant_models(scene)]
    models += [(Path(p).stem, Path(p), "", "extra_models") for p in extra_models]
    for name, path, role, field in models:
        vr_p, vr_t, vparams = _model_info(path, field)
        role = role or neural_role(vr_p, vr_t)
        label = f"{ROLE_LABEL[role]} ({name})" if role in ROLE_LABEL else f"neural {name}"
        out.append(Method(f"neural_{name}", "neural", label, vr_p, vr_t, model=str(path), role=role, params=vparams))
    out.append(Method("neural", "neural", f"neural r_p = {r_p:.3g}, r_t = {r_t} (shipped)", r_p, r_t, model=str(main), role="lowres", params=params))
    for r in r_cs:
        out.append(Method(f"hybrid_rc{float(r):.1f}", "hybrid", f"hybrid r_c = {float(r):.1f}", r_p, r_t, float(r), str(main), "hybrid", params, "audit"))
    if r_cs:
        out.append(Method("hybrid_paper", "hybrid", f"hybrid, paper's rule (s(t) alone), r_c = {R_C:g}", r_p, r_t, R_C, str(main), "hybrid", params, "paper"))
    rule = shipped_switching(scene) if model is None else {}
    safeguard, tol0 = rule.get("safeguard", SAFEGUARD), rule.get("audit_tol", AUDIT_TOL)
    name = f"error rule, tol {float(tol0):g} g" if safeguard == "error" else ("s(t) + audit" if safeguard == "audit" else "s(t) alone")
    out.append(
        Method("hybrid_default", "hybrid", f"hybrid, GNS with its shipped rule ({name})", r_p, r_t, R_C, str(main), "hybrid", params, safeguard, float(tol0))
    )
    if mpm_grid_methods(scene, r_p, seed, (0.5,))[0]:  # the classical twin, where the scene holds on half its grid
        twin = dict(r_p=r_p, r_t=r_t, r_c=R_C, model=str(main), role="hybrid", params=0, safeguard=safeguard, audit_tol=float(tol0), cheap="mpm-coarse")
        out.append(Method("hybrid_coarse", "hybrid", f"hybrid, cheap half MPM on half the grid ({name})", **twin))
        out.append(
            Method("hybrid_coarse_own", "hybrid", f"hybrid, cheap half MPM on half the grid, its own particles ({name})", cheap_particles="grid", **twin)
        )
    for tol in error_tols:
        if not (0.0 < float(tol) <= 100.0):
            raise InvalidInputError(f"audit_tol: tolerances must lie in (0, 100] g, got {tol!r}", "audit_tol")
        out.append(
            Method(
                f"hybrid_err{float(tol):g}",
                "hybrid",
                f"hybrid, error rule, tol {float(tol):g} g",
                r_p,
                r_t,
                R_C,
                str(main),
                "hybrid",
                params,
                "error",
                float(tol),
            )
        )
    return out


def shipped_default_method(scene: str, methods: list[Method]) -> Method | None:
    """The configuration ``hybridmpm simulate SCENE`` runs by default
    (``models/defaults.json``: :func:`hybridmpm.models.shipped_default`) as one
    of ``methods``: the method with its key, appended to ``methods`` when none
    has it. None where the scene ships no default."""

    cfg = shipped_default(scene).get("config") or {}
    key = cfg.get("key")
    if not key:
        return None
    for m in methods:
        if m.key == key:
            return m
    names = {f.name for f in fields(Method)}
    m = Method(**{k: v for k, v in cfg.items() if k in names})
    methods.append(m)
    return m
