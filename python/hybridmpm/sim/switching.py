"""The hybrid's switching rules as types: which solver takes the next step (docs/hybrid.md "Switching rules").

A rule decides, step by step, whether the hybrid's cheap half (:mod:`hybridmpm.sim.cheap`) keeps the
flow or MPM on the scene's grid takes it. Every rule shares the complexity score ``s(t)`` (paper
Sec. 3.1.2, Eq. 1; :func:`~hybridmpm.sim.safeguard.complexity_score` with window ``delta`` and
``accel_floor``), the threshold ``r_c`` and the way back to the cheap half (``dwell`` steps, doubled
per failure since the cheap half's last healthy stint: the backoff, up to 2^:data:`MAX_BACKOFF`);
``r_c <= 0`` switches every rule off (the cheap half alone, with only its failure fallbacks; the
paper's Table 2 reads r_c = 0 as neural) and ``r_c > 1`` runs MPM only, whatever the rule:

* :class:`PaperRule` (``"paper"``): ``s(t) < r_c`` hands the next step to MPM (the paper's rule);
* :class:`AuditRule` (``"audit"``, the default): as the paper's, and every ``audit_every``-th step of a
  cheap stint, its first included, MPM takes the same step from the same state; the cheap step is kept
  only if the two agree within ``audit_tol`` [g] (the MPM audit, not in the paper: ``s(t)`` cannot see
  a network that is smooth but wrong);
* :class:`ErrorRule` (``"error"``): the cheap half's error alone, the score only reported. The audit
  runs at a stint's first step and then at an interval that doubles after each audit within
  ``audit_tol`` (up to ``audit_max`` steps); the density residual (the RMS correction the density
  relaxation applied, as an acceleration in g) above ``residual_tol`` and :data:`RESIDUAL_GROWTH` × that
  of the stint's last passing audit brings the audit forward. Back on MPM, the cheap half takes over
  again after the backoff's ``dwell·2^k`` steps, whatever the score.

Each rule holds its settings (dataclass fields; :meth:`SwitchingRule.to_dict` and
:meth:`SwitchingRule.from_dict` are the form ``models/switching.json`` and ``hybridmpm tune`` store)
and its counters (:meth:`SwitchingRule.state` for checkpoints). :func:`make_rule` builds one from plain
settings as the CLI and :func:`~hybridmpm.sim.make_simulator` take them.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass, fields
from typing import Any, ClassVar

import numpy as np

from hybridmpm.conventions import AUDIT_EVERY, AUDIT_MAX, AUDIT_TOL, DELTA, R_C, RESIDUAL_TOL, SAFEGUARD, SAFEGUARDS, G
from hybridmpm.errors import InvalidInputError
from hybridmpm.scenes.particles import ParticleSet
from hybridmpm.sim.base import check_count, reading_state
from hybridmpm.sim.cheap import Proposal
from hybridmpm.sim.safeguard import ACCEL_FLOOR, complexity_score

#: Default dwell (steps of s ≥ r_c on MPM before the cheap half takes over again); docs/hybrid.md "Choices measured".
DWELL = 5
#: After a failure fallback the dwell doubles per failure since the cheap half's last healthy stint
#: (2·dwell steps without failure), up to 2**MAX_BACKOFF.
MAX_BACKOFF = 6
#: "error" rule: a density residual this many times that of the last passing audit (and above
#: ``residual_tol``) brings the next audit forward.
RESIDUAL_GROWTH = 2.0


def _finite(v: Any) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)


def _integer(v: Any, lo: int, hi: int | None = None) -> bool:
    return isinstance(v, int) and not isinstance(v, bool) and v >= lo and (hi is None or v <= hi)


def _checked(name: str, ok: bool, msg: str, value: Any) -> Any:
    if not ok:
        raise InvalidInputError(f"{name}: {msg}, got {value!r}", name)
    return value


#: Every rule's settings: name -> the check that returns the value as the rule keeps it
#: (raises :class:`InvalidInputError` naming the setting).
SETTINGS: dict[str, Callable[[Any], Any]] = {
    "r_c": lambda v: float(_checked("r_c", _finite(v), "must be a finite number", v)),
    "delta": lambda v: _checked("delta", _integer(v, 1), "must be an integer >= 1", v),
    "dwell": lambda v: _checked("dwell", _integer(v, 1), "must be an integer >= 1", v),
    "accel_floor": lambda v: float(_checked("accel_floor", _finite(v) and v >= 0, "must be >= 0 [m/s²]", v)),
    "audit_every": lambda v: _checked("audit_every", _integer(v, 0), "must be an integer >= 0 (0 = no audit)", v),
    "audit_tol": lambda v: float(_checked("audit_tol", _finite(v) and v > 0, "must be > 0 [g]", v)),
    "residual_tol": lambda v: float(_checked("residual_tol", _finite(v) and v > 0, "must be > 0 [g]", v)),
    "audit_max": lambda v: _checked("audit_max", _integer(v, 1, 1024), "must be an integer in [1, 1024] [network steps]", v),
}


@dataclass
class SwitchingRule:
    """The settings and counters every rule shares (module doc); :class:`PaperRule`,
    :class:`AuditRule` and :class:`ErrorRule` are the rules. Counters: ``calm`` MPM steps in a row
    that would hand back, ``strikes`` failures since the last healthy stint, ``run`` steps of the
    current cheap stint. Raises :class:`InvalidInputError` naming a setting out of range."""

    #: The rule's name (``safeguard``).
    name: ClassVar[str] = ""

    r_c: float = R_C
    delta: int = DELTA
    dwell: int = DWELL
    accel_floor: float = ACCEL_FLOOR

    def __post_init__(self) -> None:
        for f in fields(self):
            setattr(self, f.name, SETTINGS[f.name](getattr(self, f.name)))
        self.calm = self.strikes = self.run = 0

    # ------------------------------------------------------------ settings
    @property
    def active(self) -> bool:
        """Whether the rule switches at all (``r_c > 0``; else the cheap half alone)."""
        return self.r_c > 0.0

    @property
    def mpm_only(self) -> bool:
        """``r_c > 1``: the score can never reach it, so MPM runs every step."""
        return self.r_c > 1.0

    @property
    def by_score(self) -> bool:
        """Whether ``s(t)`` decides the switches (every rule but the error rule, which uses it only for MPM alone)."""
        return True

    def to_dict(self) -> dict[str, Any]:
        """The rule as ``models/switching.json`` and ``hybridmpm tune`` store it: ``safeguard`` and every setting."""
        return {"safeguard": self.name, **{f.name: getattr(self, f.name) for f in fields(self)}}

    @staticmethod
    def from_dict(d: Mapping[str, Any]) -> SwitchingRule:
        """The rule a :meth:`to_dict` (or any part of one: missing settings take their defaults) describes
        (:func:`make_rule`). Raises :class:`InvalidInputError` naming a bad or unknown setting."""
        return make_rule(**dict(d))

    # ------------------------------------------------------------ decisions
    def score(self, trajectory: np.ndarray, dt_step: float) -> float:
        """``s(t)`` of the hybrid's trajectory float [T, N, D] (fluid positions, one ``dt_step`` [s] apart), nan while the rule is off."""
        return complexity_score(trajectory, dt_step, self.delta, self.accel_floor) if self.active else float("nan")

    def residual(self, proposal: Proposal, particles: ParticleSet, dt_step: float) -> float:
        """What the rule reads of a proposal besides an audit (the error rule's density residual [g]); nan where it reads nothing."""
        return float("nan")

    def audit_due(self, residual: float) -> bool:
        """Whether MPM audits this cheap step (its ``residual`` from :meth:`residual`)."""
        return False

    def audited(self, error: float, residual: float) -> bool:
        """Record an audit of ``error`` [g]; returns whether the cheap step passes."""
        return True

    def not_audited(self) -> None:
        """A cheap step passed without an audit."""

    def kept(self) -> None:
        """A cheap step was kept: a stint of ``2·dwell`` of them forgives the earlier failures."""
        self.run += 1
        if self.run >= 2 * self.dwell:
            self.strikes = 0

    def failed(self) -> None:
        """A cheap step was rejected (a failure or an audit): one more strike for the backoff."""
        self.strikes += 1

    def stays(self, score: float) -> bool:
        """After a kept cheap step scoring ``score``: whether the cheap half takes the next step."""
        return not (self.active and self.by_score and not score >= self.r_c)

    def fell_back(self) -> None:
        """MPM took over: the calm count starts again."""
        self.calm = 0

    def returns(self, score: float, first: bool) -> bool:
        """On MPM after the warm-up, with no forcing: count the step scoring ``score`` and say whether
        the cheap half may take over (``first``: it never ran and nothing switched yet, so one calm
        step suffices; else ``dwell·2^k``, k the strikes, capped at :data:`MAX_BACKOFF`)."""
        ok = (not self.active) or (score >= self.r_c if self.by_score else True)
        self.calm = self.calm + 1 if ok else 0
        need = 1 if first else self.dwell * 2 ** min(self.strikes, MAX_BACKOFF)
        return self.calm >= need

    def took_over(self) -> None:
        """The cheap half took over: a new stint."""
        self.run = 0

    # ------------------------------------------------------------ checkpoint
    def state(self) -> dict[str, Any]:
        """The counters (picklable); the keys of the hybrid's state they have always had."""
        return {"calm": self.calm, "strikes": self.strikes, "neural_run": self.run}

    def prepare_restore(self, state: Mapping[str, Any]) -> Callable[[], None]:
        """Validate the counters of a :meth:`state` (within a hybrid's state); returns their commit.
        Raises :class:`InvalidInputError` (field ``state.<counter>``)."""
        with reading_state("hybrid"):
            calm, strikes, run = (check_count(f"state.{k}", state[k]) for k in ("calm", "strikes", "neural_run"))

        def commit() -> None:
            self.calm, self.strikes, self.run = calm, strikes, run

        return commit


@dataclass
class PaperRule(SwitchingRule):
    """``s(t) < r_c`` hands the next step to MPM; ``dwell`` calm steps hand it back (paper Sec. 3.1.2)."""

    name: ClassVar[str] = "paper"


@dataclass
class AuditRule(SwitchingRule):
    """The paper's rule plus the MPM audit: every ``audit_every``-th step of a cheap stint (its first
    included; 0: never) MPM takes the same step, and the cheap step is kept only within ``audit_tol`` [g]."""

    name: ClassVar[str] = "audit"

    audit_every: int = AUDIT_EVERY
    audit_tol: float = AUDIT_TOL

    def audit_due(self, residual: float) -> bool:
        return self.active and self.audit_every > 0 and self.run % self.audit_every == 0

    def audited(self, error: float, residual: float) -> bool:
        return error <= self.audit_tol


@dataclass
class ErrorRule(SwitchingRule):
    """The cheap half's error alone (module doc): an audit at a stint's first step, then at an interval
    that doubles up to ``audit_max`` after each audit within ``audit_tol`` [g] (and falls to 1 after one
    beyond), brought forward by a density residual above ``residual_tol`` [g] and
    :data:`RESIDUAL_GROWTH` × the last passing audit's. Counters besides the shared ones: ``interval``,
    ``since_audit``, ``residual_ref`` [g]."""

    name: ClassVar[str] = "error"

    audit_tol: float = AUDIT_TOL
    residual_tol: float = RESIDUAL_TOL
    audit_max: int = AUDIT_MAX

    def __post_init__(self) -> None:
        super().__post_init__()
        self.interval, self.since_audit, self.residual_ref = 1, 0, 0.0

    @property
    def by_score(self) -> bool:
        return self.mpm_only

    def residual(self, proposal: Proposal, particles: ParticleSet, dt_step: float) -> float:
        """The density residual [g]: RMS over fluid particles of (kept − predicted) / dt_step²."""
        if proposal.positions is None:
            return float("nan")
        corr = particles.fluid(proposal.positions).astype(np.float64) - particles.fluid(proposal.predicted)
        rms = float(np.sqrt(np.mean(np.sum(corr * corr, axis=1)))) if len(corr) else 0.0
        return rms / (dt_step * dt_step) / G

    def audit_due(self, residual: float) -> bool:
        trigger = max(self.residual_tol, RESIDUAL_GROWTH * self.residual_ref)
        return self.active and (self.run == 0 or residual > trigger or self.since_audit + 1 >= self.interval)

    def audited(self, error: float, residual: float) -> bool:
        ok = error <= self.audit_tol
        self.since_audit = 0
        self.interval = min(2 * self.interval, self.audit_max) if ok else 1
        # a residual the audit passed is the cheap half's own level: only growth beyond it is news
        self.residual_ref = residual if ok else 0.0
        return ok

    def not_audited(self) -> None:
        self.since_audit += 1

    def took_over(self) -> None:
        super().took_over()
        self.interval, self.since_audit, self.residual_ref = 1, 0, 0.0

    def state(self) -> dict[str, Any]:
        return {**super().state(), "interval": self.interval, "since_audit": self.since_audit, "residual_ref": self.residual_ref}

    def prepare_restore(self, state: Mapping[str, Any]) -> Callable[[], None]:
        shared = super().prepare_restore(state)
        with reading_state("hybrid"):
            # absent from states written before the rule existed: a new stint's schedule
            interval = max(1, check_count("state.interval", state.get("interval", 1)))
            since_audit = check_count("state.since_audit", state.get("since_audit", 0))
            ref = state.get("residual_ref", 0.0)
            if not (_finite(ref) and ref >= 0):
                raise InvalidInputError("state.residual_ref: must be a finite number >= 0 [g]", "state.residual_ref")

        def commit() -> None:
            shared()
            self.interval, self.since_audit, self.residual_ref = interval, since_audit, float(ref)

        return commit


#: The rules by name (:data:`~hybridmpm.conventions.SAFEGUARDS`).
RULES: dict[str, type[SwitchingRule]] = {r.name: r for r in (AuditRule, ErrorRule, PaperRule)}
assert tuple(sorted(RULES)) == tuple(sorted(SAFEGUARDS))


def make_rule(safeguard: str | None = None, *, shipped: Mapping[str, Any] | None = None, **settings: Any) -> SwitchingRule:
    """The rule ``safeguard`` (one of :data:`~hybridmpm.conventions.SAFEGUARDS`) with ``settings``
    (None values: unset). ``shipped`` a rule dict chosen for the scene's model
    (:func:`~hybridmpm.models.shipped_switching`): its rule runs when ``safeguard`` is None, and its
    settings fill those not given when ``safeguard`` names the same rule. Unset settings take their
    defaults (``safeguard`` :data:`~hybridmpm.conventions.SAFEGUARD`). A setting of another rule
    (``residual_tol`` for the "audit" rule, say) is checked and not used: the CLI passes them all.
    Raises :class:`InvalidInputError` naming the setting that is out of range or unknown."""
    shipped = dict(shipped or {})
    name = safeguard if safeguard is not None else shipped.get("safeguard", SAFEGUARD)
    if name not in RULES:
        raise InvalidInputError(f"safeguard: must be one of {', '.join(map(repr, SAFEGUARDS))}, got {name!r}", "safeguard")
    base = {k: v for k, v in shipped.items() if k != "safeguard"} if shipped.get("safeguard") == name else {}
    merged = {**base, **{k: v for k, v in settings.items() if v is not None}}
    for key, value in merged.items():
        if key not in SETTINGS:
            raise InvalidInputError(f"{key}: not a setting of a switching rule (settings: {', '.join(SETTINGS)})", key)
        SETTINGS[key](value)
    rule = RULES[name]
    own = {f.name for f in fields(rule)}
    return rule(**{k: v for k, v in merged.items() if k in own})


__all__ = ["DWELL", "MAX_BACKOFF", "RESIDUAL_GROWTH", "RULES", "SETTINGS", "AuditRule", "ErrorRule", "PaperRule", "SwitchingRule", "make_rule"]
