"""The hybrid's switching rules (docs/hybrid.md "Switching rules"): the paper's
score alone, the score with the MPM audit, and the error rule (an audit whose
interval adapts, brought forward by the density residual)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from hybridmpm.conventions import G
from hybridmpm.errors import InvalidInputError
from hybridmpm.models import shipped_model
from hybridmpm.neural import GnsRuntime
from hybridmpm.scenes import make_scene
from hybridmpm.sim import Frame, HybridSimulator, MpmSimulator, rollout


def frames_of(sim: HybridSimulator, frames: int) -> list[Frame]:
    recs: list[Frame] = []
    rollout(sim, frames, on_frame=recs.append)
    return recs


@pytest.fixture(scope="module")
def water_model() -> GnsRuntime:
    return GnsRuntime(shipped_model("water2d"))


def test_the_paper_rule_is_the_score_without_the_audit_bit_for_bit(water_model):
    scene = make_scene("water2d", seed=1001)
    paper = frames_of(HybridSimulator(scene, water_model, safeguard="paper", mpm_threads=1), 200)
    no_audit = frames_of(HybridSimulator(scene, water_model, safeguard="audit", audit_every=0, mpm_threads=1), 200)
    assert all(np.isnan(f.audit) for f in paper)
    assert [f.solver for f in paper] == [f.solver for f in no_audit] and {"neural", "mpm"} <= {f.solver for f in paper}
    assert np.array_equal(np.stack([f.positions for f in paper]), np.stack([f.positions for f in no_audit]))


def test_the_error_rule_doubles_its_audit_interval_while_the_network_agrees(water_model):
    # Tolerance out of reach and no residual trigger: every audit passes, so the interval doubles up to audit_max: audits at network steps 0, 2, 6, 14,
    # then every 8th. The score is not consulted: the network keeps the flow through the splash.
    scene = make_scene("water2d", seed=1000)
    sim = HybridSimulator(scene, water_model, safeguard="error", audit_tol=1e6, residual_tol=1e6, audit_max=8, r_c=0.99, mpm_threads=1)
    frames = frames_of(sim, 200)
    neural = [i for i, f in enumerate(frames) if f.solver == "neural"]
    assert neural == list(range(neural[0], len(frames)))  # one stint: no switch back for a low score
    assert min(f.score for f in frames[neural[0] :]) < 0.99  # ...though the score fell below r_c
    audited = [k for k, i in enumerate(neural) if np.isfinite(frames[i].audit)]
    expected = [0, 2, 6, 14] + list(range(22, len(neural), 8))
    assert audited == expected and sim.stats.audits == len(expected)


def test_the_density_residual_brings_the_audit_forward(water_model):
    # The residual is the relaxation's correction as an acceleration: recomputed here from the
    # network's raw and relaxed predictions, it must match last_residual. A step whose residual
    # exceeds residual_tol and twice the residual of the stint's last passing audit is audited,
    # whatever the schedule; with audit_max out of reach nothing else is audited but the schedule's
    # steps 0, 2, 6, 14, ... of a stint.
    from hybridmpm.sim.switching import RESIDUAL_GROWTH

    scene = make_scene("water2d", seed=1002)
    sim = HybridSimulator(scene, water_model, safeguard="error", audit_tol=1e6, residual_tol=0.3, audit_max=1024, mpm_threads=1)
    seen: list[float] = []
    orig = sim.half.propose

    def spy(checks=None):
        p = orig(checks)
        corr = sim.particles.fluid(p.positions).astype(np.float64) - sim.particles.fluid(p.predicted)
        seen.append(float(np.sqrt(np.mean(np.sum(corr**2, axis=1)))) / sim.dt_step**2 / G)
        return p

    sim.half.propose = spy  # type: ignore[method-assign]
    ref, k, interval, since, last = 0.0, 0, 1, 0, "mpm"
    triggered = scheduled_only = 0
    for _ in range(100):
        f = sim.advance()
        if f.solver != "neural":
            last = f.solver
            continue
        if last != "neural":
            ref, k, interval, since = 0.0, 0, 1, 0  # a new stint
        r = sim.last_residual
        assert r == pytest.approx(seen[-1], rel=1e-9)
        audited = bool(np.isfinite(f.audit))
        if k > 0 and r > max(0.3, RESIDUAL_GROWTH * ref):
            assert audited
            triggered += 1
        else:
            assert audited == (k == 0 or since + 1 >= interval)
            scheduled_only += audited
        if audited:
            ref, interval, since = r, 2 * interval, 0  # every audit passes (tolerance out of reach)
        else:
            since += 1
        k += 1
        last = "neural"
    assert triggered >= 1 and scheduled_only >= 1


def test_an_error_rule_that_rejects_every_step_is_mpm_at_r_p_bit_for_bit(water_model):
    # Every stint is audited at its first step, where MPM holds the state (no conversion): a
    # tolerance nothing meets leaves the run exactly MPM at r_p, the network tried after each backoff.
    scene = make_scene("water2d", seed=1003)
    sim = HybridSimulator(scene, water_model, safeguard="error", audit_tol=1e-9, dwell=2, mpm_threads=1)
    frames = frames_of(sim, 160)
    assert all(f.solver == "mpm" for f in frames) and sim.stats.fallbacks["audit"] == sim.stats.audits >= 3
    mpm = rollout(MpmSimulator(scene, r_p=water_model.r_p, r_t=sim.r_t, threads=1), 160).positions[1:]
    assert np.array_equal(np.stack([f.positions for f in frames]), mpm)


def test_the_error_rule_keeps_its_schedule_across_a_state_restore(water_model):
    scene = make_scene("water2d", seed=1004)
    sim = HybridSimulator(scene, water_model, safeguard="error", mpm_threads=1)
    rollout(sim, 120)
    st = sim.state()
    a = frames_of(sim, 160)
    sim.restore(st)
    b = frames_of(sim, 160)
    assert [f.solver for f in a] == [f.solver for f in b]
    assert np.array_equal(np.stack([f.positions for f in a]), np.stack([f.positions for f in b]))
    np.testing.assert_array_equal([f.audit for f in a], [f.audit for f in b])
    with pytest.raises(InvalidInputError, match="state.interval"):
        sim.restore({**st, "interval": -1})
    with pytest.raises(InvalidInputError, match="state.residual_ref"):
        sim.restore({**st, "residual_ref": float("nan")})


def test_bad_rule_parameters_name_the_field(water_model):
    scene = make_scene("water2d", seed=0)
    for kw, field in [
        ({"safeguard": "complexity"}, "safeguard"),
        ({"residual_tol": 0.0}, "residual_tol"),
        ({"residual_tol": float("nan")}, "residual_tol"),
        ({"audit_max": 0}, "audit_max"),
        ({"audit_max": 2.5}, "audit_max"),
        ({"audit_max": 10**6}, "audit_max"),
    ]:
        with pytest.raises(InvalidInputError, match=field):
            HybridSimulator(scene, water_model, **kw)


def test_simulate_takes_the_rule_and_reports_it(tmp_path):
    from hybridmpm.cli import main

    hybrid = ["simulate", "water2d", "--solver", "hybrid", "--seed", "1000", "--frames", "60"]
    assert main([*hybrid, "--safeguard", "error", "--audit-max", "4", "--out", str(tmp_path), "--quiet"]) == 0
    s = json.loads((tmp_path / "summary.json").read_text())
    assert (s["safeguard"], s["audit_max"]) == ("error", 4) and s["audits"] >= 1
    assert main(["simulate", "water2d", "--solver", "hybrid", "--frames", "8", "--residual-tol", "-1", "--out", str(tmp_path / "bad"), "--quiet"]) == 2


def test_each_scene_runs_the_rule_shipped_with_its_model(water_model):
    """models/switching.json holds a valid rule per listed scene; the hybrid with
    the shipped model runs it unless told otherwise, and any other model runs the defaults."""
    from hybridmpm.conventions import AUDIT_TOL, SAFEGUARD, SAFEGUARDS
    from hybridmpm.models import shipped_models, shipped_switching

    table = json.loads((shipped_model("water2d").parent / "switching.json").read_text())
    assert set(table) <= set(shipped_models())
    for scene in shipped_models():
        rule = shipped_switching(scene)
        assert rule == {k: table[scene][k] for k in ("safeguard", "audit_tol")} if scene in table else rule == {}
        if rule:
            assert rule["safeguard"] in SAFEGUARDS and 0 < rule["audit_tol"] <= 100
    listed = sorted(table)[0]
    sim = HybridSimulator(listed, seed=0, mpm_threads=1)
    assert (sim.safeguard, sim.audit_tol) == (table[listed]["safeguard"], table[listed]["audit_tol"])
    assert HybridSimulator(listed, seed=0, mpm_threads=1, audit_tol=0.7).audit_tol == 0.7
    other = HybridSimulator(listed, shipped_model(listed), seed=0, mpm_threads=1)  # a model given: the defaults
    assert (other.safeguard, other.audit_tol) == (SAFEGUARD, AUDIT_TOL)
    unlisted = [s for s in shipped_models() if s not in table and s.endswith("2d")]
    if unlisted:
        sim = HybridSimulator(unlisted[0], seed=0, mpm_threads=1)
        assert (sim.safeguard, sim.audit_tol) == (SAFEGUARD, AUDIT_TOL)


def test_a_rule_round_trips_through_its_dict_and_the_shipped_table_reads_as_rules(tmp_path):
    """Each rule's to_dict is what models/switching.json and tune store: from_dict of it gives the
    same rule (settings, not counters); the shipped table's entries read as the rules they name;
    make_rule takes the shipped rule's settings only for that rule; a tuned configuration of a hybrid
    carries its rule to make_simulator's settings."""
    from hybridmpm.bench.tune import write_tuned
    from hybridmpm.models import shipped_switching
    from hybridmpm.sim.config import load_tuned, tuned_settings
    from hybridmpm.sim.switching import RULES, AuditRule, ErrorRule, PaperRule, SwitchingRule, make_rule

    rules = [
        PaperRule(r_c=0.7, dwell=3),
        AuditRule(audit_every=2, audit_tol=0.4, delta=8),
        ErrorRule(audit_tol=2.0, residual_tol=0.25, audit_max=8, accel_floor=0.5),
    ]
    assert sorted(r.name for r in rules) == sorted(RULES)
    for rule in rules:
        d = rule.to_dict()
        assert d["safeguard"] == rule.name and json.loads(json.dumps(d)) == d
        back = SwitchingRule.from_dict(d)
        assert type(back) is type(rule) and back == rule and back.to_dict() == d
        assert back != type(rule)()  # the settings are compared, not just the kind
    table = json.loads((shipped_model("water2d").parent / "switching.json").read_text())
    for scene, entry in table.items():
        rule = SwitchingRule.from_dict(shipped_switching(scene))
        assert (rule.name, rule.audit_tol) == (entry["safeguard"], entry["audit_tol"])  # type: ignore[attr-defined]
    shipped = {"safeguard": "error", "audit_tol": 2.0}
    assert make_rule(shipped=shipped) == ErrorRule(audit_tol=2.0)
    assert make_rule("error", shipped=shipped, audit_max=4) == ErrorRule(audit_tol=2.0, audit_max=4)
    assert make_rule("audit", shipped=shipped) == AuditRule()  # another rule: the shipped tolerance is not its
    assert make_rule("audit", residual_tol=0.3) == AuditRule()  # another rule's setting: checked, not used
    for bad, field in (({"safeguard": "complexity"}, "safeguard"), ({"audit_tol": -1}, "audit_tol"), ({"gain": 1.0}, "gain")):
        with pytest.raises(InvalidInputError, match=field):
            SwitchingRule.from_dict(bad)
    # a hybrid's tuned configuration: its rule, written by tune, read back as make_simulator's settings
    row = {"key": "hybrid_err2", "kind": "hybrid", "label": "", "r_p": 0.5714, "r_t": 4, "r_c": 0.8, "model": str(shipped_model("water2d")),
           "role": "hybrid", "params": 0, "safeguard": "error", "audit_tol": 2.0, "n_grid": None,
           "error_mean": 0.5, "error_last": 0.6, "ms_mean": 1.0, "ms_median": 1.0, "ms_p95": 1.0, "mpm_share": 0.5}  # fmt: skip
    doc = write_tuned(tmp_path / "water2d.json", "water2d", 1.0, "error_mean", row, [row], [2000], {})
    assert load_tuned("water2d", tmp_path / "water2d.json") == doc and doc["config"]["rule"] == ErrorRule(audit_tol=2.0).to_dict()
    settings = tuned_settings(doc)
    assert make_rule(**{k: settings[k] for k in ("safeguard", "r_c", "dwell", "audit_tol", "residual_tol", "audit_max")}) == ErrorRule(audit_tol=2.0)
