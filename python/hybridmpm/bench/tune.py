"""``hybridmpm tune``: the cheapest configuration within an error budget
("model no more than a scene needs", made automatic).

Runs the benchmark on *validation* seeds (not the held-out test seeds that
``hybridmpm bench`` reports on), then picks among every benchmarked
configuration (MPM at full resolution or at ``r_p``, each neural model alone,
the hybrid at every threshold ``r_c``) the one with the lowest mean latency
per frame whose error stays within the budget. Full-resolution MPM is the
reference (error 0), so some configuration always qualifies. The choice is
written as a JSON config that ``hybridmpm simulate SCENE --solver auto``
reads.
"""

from __future__ import annotations

import json
import math
import time
from pathlib import Path
from typing import Any

from hybridmpm.errors import InvalidInputError
from hybridmpm.metrics import ROLLOUT_METRICS
from hybridmpm.sim.config import CONFIG_KEYS
from hybridmpm.sim.switching import make_rule


def choose(rows: list[dict[str, Any]], budget: float, metric: str = "error_mean") -> dict[str, Any]:
    """The row with the lowest ``ms_mean`` among ``rows`` whose ``metric`` (a
    score of :data:`~hybridmpm.metrics.ROLLOUT_METRICS`: "error_mean",
    "error_last", "short_error", "sinkhorn", "ke_error", "front_rms") is ≤
    ``budget`` and whose rollouts never broke off (ties: the lower score). Rows
    are :func:`~hybridmpm.bench.report.aggregate` rows (any dicts with those
    keys). Raises :class:`InvalidInputError` (``error_budget``) for a negative
    or non-finite budget or when no row qualifies, (``metric``) for another
    metric or one no row measured (``front_rms`` off the dam break)."""
    if metric not in ROLLOUT_METRICS:
        raise InvalidInputError(f"metric: must be one of {', '.join(ROLLOUT_METRICS)}, got {metric!r}", "metric")
    if not (isinstance(budget, (int, float)) and math.isfinite(budget) and budget >= 0):
        raise InvalidInputError(f"error_budget: must be a finite number >= 0, got {budget!r}", "error_budget")
    if not any(math.isfinite(r.get(metric, math.nan)) for r in rows):
        raise InvalidInputError(f"metric: no configuration has a {metric} (not measured on this scene, or a benchmark made before it)", "metric")
    ok = [r for r in rows if math.isfinite(r.get(metric, math.nan)) and r[metric] <= budget and not r.get("failures") and math.isfinite(r["ms_mean"])]
    if not ok:
        best = min((r[metric] for r in rows if math.isfinite(r.get(metric, math.nan))), default=float("nan"))
        raise InvalidInputError(f"error_budget: no configuration has {metric} <= {budget:g} (the lowest is {best:.4g})", "error_budget")
    return min(ok, key=lambda r: (r["ms_mean"], r[metric]))


def write_tuned(
    path: Path, scene: str, budget: float, metric: str, chosen: dict[str, Any], rows: list[dict[str, Any]], seeds: list[int], settings: dict[str, Any]
) -> dict[str, Any]:
    """Write the tuned config (the chosen configuration, with a hybrid's switching
    rule as :meth:`~hybridmpm.sim.switching.SwitchingRule.to_dict` writes it; what
    it measured; every candidate) as JSON; returns it."""
    config = {k: chosen.get(k) for k in CONFIG_KEYS}
    if config["kind"] == "hybrid":
        config["rule"] = make_rule(config.get("safeguard"), r_c=config.get("r_c"), audit_tol=config.get("audit_tol")).to_dict()
    doc = {
        "scene": scene,
        "error_budget": float(budget),
        "metric": metric,
        "config": config,
        "measured": {k: chosen[k] for k in ("error_mean", "error_last", "ms_mean", "ms_median", "ms_p95", "mpm_share")},
        "validation_seeds": list(seeds),
        "settings": settings,
        "candidates": [
            {k: r.get(k) for k in ("key", "label", "error_mean", "error_last", "ms_mean", "failures")} for r in sorted(rows, key=lambda r: r["ms_mean"])
        ],
        "date": time.strftime("%Y-%m-%d %H:%M:%S %z"),
    }
    measured: dict[str, Any] = doc["measured"]  # type: ignore[assignment]
    measured[metric] = chosen.get(metric)  # the score it was chosen on
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(json.dumps(doc, indent=2))
    tmp.replace(path)
    return doc


#: The metrics a scene's default is held to (docs/hybrid.md "Defaults per scene"): the long-horizon
#: grid-mass error, right for sand, and the Sinkhorn divergence, fair to a chaotic flow.
DEFAULT_METRICS = ("error_mean", "sinkhorn")
#: A default's budget on each of :data:`DEFAULT_METRICS`, as a ratio to MPM at ``r_p``'s value on the
#: same validation seeds: 1.15, and 1.3 on the scenes of sand alone (deterministic, and where the coarse
#: grid's bias is largest).
DEFAULT_BUDGET = 1.15
DEFAULT_BUDGET_SAND = 1.3
SAND_SCENES = ("sand2d", "sand3d", "sand_ramps2d")


def default_budget(scene: str) -> float:
    """The ratio to MPM at ``r_p`` a default of ``scene`` may err by (:data:`DEFAULT_BUDGET`)."""
    return DEFAULT_BUDGET_SAND if scene in SAND_SCENES else DEFAULT_BUDGET


def choose_default(rows: list[dict[str, Any]], budget: float, metrics: tuple[str, ...] = DEFAULT_METRICS) -> dict[str, Any]:
    """A scene's default among benchmarked configurations: the row with the
    lowest ``ms_mean`` whose every score in ``metrics`` is at most ``budget``
    times MPM at ``r_p``'s (the row keyed ``mpm_rp``, same seeds) and whose
    rollouts never broke off. MPM at ``r_p`` itself always qualifies, and
    the fastest row within a budget is on the front of every metric it is
    held to, so the default follows the chart. ``rows``:
    :func:`~hybridmpm.bench.report.aggregate` rows. Raises
    :class:`InvalidInputError` (``rows``) without an ``mpm_rp`` row or one
    missing a score, (``error_budget``) for a budget below 1 or not finite."""
    if not (isinstance(budget, (int, float)) and math.isfinite(budget) and budget >= 1.0):
        raise InvalidInputError(f"error_budget: a ratio to MPM at r_p must be finite and >= 1, got {budget!r}", "error_budget")
    base = next((r for r in rows if r.get("key") == "mpm_rp"), None)
    if base is None or not all(math.isfinite(base.get(m, math.nan)) for m in metrics):
        raise InvalidInputError(f"rows: no MPM at r_p row with {', '.join(metrics)} (the baseline of a default)", "rows")

    def within(r: dict[str, Any]) -> bool:
        return not r.get("failures") and math.isfinite(r["ms_mean"]) and all(r.get(m, math.inf) <= budget * base[m] for m in metrics)

    return min((r for r in rows if within(r)), key=lambda r: (r["ms_mean"], r[metrics[0]]))
