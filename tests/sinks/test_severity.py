"""The exceedance curve P(min gap < x): hand-computed events, the braking scenario's exact points, a run that targets a
level, the miss bound the exact points rest on, and what the console and the JSON say."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from pemviz.config import ExperimentConfig
from pemviz.core.severity import SeverityScale, level_events
from pemviz.engine.events import RolloutsSampled
from pemviz.engine.experiment import Experiment
from pemviz.pem import load_pem
from pemviz.scenarios.braking import truth, truth_known
from pemviz.scenarios.braking.simulator import BrakingParams, braking_step, lead_speeds
from pemviz.scenarios.problems import problem_for

EXACT_1_5 = 2.9992e-17
"""P(min gap < 1.5 m) of the braking scenario under the shipped PEM, by enumeration (``benchmarks/severity.py
--exact``: bracket width 0.09 %)."""
EXACT_1_0 = 4.6704e-19
"""P(min gap < 1 m), the same way (bracket width 0.11 %)."""
EXACT_0_5 = 5.0523e-21
"""P(min gap < 0.5 m), the same way on the cell bound (``truth_cells.cell_miss_bound``; bracket width 0.02 %)."""
EXACT_CONTACT = 8.0581e-33
"""P(min gap < 0 m), contact, the same way (bracket width < 1e-9)."""


def test_level_events_by_hand():
    # three rollouts of 5 steps: one fails at step 1 and reaches 1 m at step 3, one fails at step 2 and stays above
    # 1 m, one never fails although its signal goes below 1.5 (the event needs the failure too)
    s = np.array([[3.0, 1.9, 1.6, 0.9, 0.5], [3.0, 2.5, 1.8, 1.2, 1.1], [3.0, 1.4, 3.0, 3.0, 3.0]])
    failed = np.array([True, True, False])
    fail_step = np.array([1, 2, 5])
    hit, step = level_events(s, failed, fail_step, np.array([1.5, 1.0, 0.0]))
    assert hit.tolist() == [[True, True, False], [True, False, False], [False, False, False]]
    # decided at the later of the failure step and the first step below the level
    assert step.tolist() == [[3, 3, 5], [3, 5, 5], [5, 5, 5]]


def test_severity_scale_refuses_levels_out_of_order():
    with pytest.raises(ValueError, match="strictly descending"):
        SeverityScale("d", "gap", "m", (1.0, 1.5))


def test_the_known_points_come_from_the_enumeration_at_that_crash_gap():
    pem = load_pem()
    for gap, p in ((1.5, EXACT_1_5), (1.0, EXACT_1_0), (0.5, EXACT_0_5), (0.0, EXACT_CONTACT)):
        log_p = truth_known.known_log_failure_probability(pem.logit_at_gap, BrakingParams(crash_gap_m=gap))
        assert log_p is not None and math.exp(log_p) == pytest.approx(p, rel=1e-4)
    assert truth_known.known_log_failure_probability(pem.logit_at_gap, BrakingParams(crash_gap_m=0.25)) is None


@pytest.mark.parametrize("gap, log_prune", [(0.5, -62.0), (0.0, -90.0)])
def test_the_kept_points_below_1_m_lie_in_a_coarser_enumeration_s_bracket(gap, log_prune):
    # the kept answers come from 2,000 x 400 cells and drop thresholds to -70 / -100 nats; a bound on 800 x 160 cells
    # and a higher threshold is another enumeration (other sequences dropped) whose bracket must hold them
    pem = load_pem()
    ex = truth.braking_exact(pem.logit_at_gap, BrakingParams(crash_gap_m=gap), log_prune=log_prune, bound_grid=161)
    kept = truth_known.known_log_failure_probability(pem.logit_at_gap, BrakingParams(crash_gap_m=gap))
    assert ex.log_p_fail <= kept <= ex.log_p_fail_upper
    assert ex.relative_width < 0.5


@pytest.fixture(scope="module")
def default_curve():
    cfg = ExperimentConfig.of(seed=0)
    return Experiment(cfg, problem=problem_for(cfg)).run().final


def test_the_default_run_reports_each_known_point_within_x1_5_inside_its_interval(default_curve):
    final = default_curve
    curve = final.severity
    assert [pt.level for pt in curve.points] == [2.0, 1.5, 1.0, 0.5, 0.0]
    assert curve.points[0].estimate is final.estimate  # the margin's point is the run's own estimate
    for pt, exact in zip(curve.points[1:3], (EXACT_1_5, EXACT_1_0), strict=False):
        assert pt.reached, pt.estimate.reason
        assert abs(pt.estimate.log_mu_hat - math.log(exact)) < math.log(1.5)
        assert pt.estimate.covers(math.log(exact))
    # deeper points have fewer events: the curve never rises
    counts = [pt.estimate.n_failures for pt in curve.points]
    assert counts == sorted(counts, reverse=True) and counts[-1] == 0
    assert not curve.points[-1].reached  # contact: no rollout of the default run touches the lead


def targeted_run_agrees(margin: float, exact: float):
    """A run of seed 1 that targets ``margin`` (its own proposal, fitted to those failures): reliable, within x1.5 of
    the enumeration's ``exact`` with its interval holding it; returns its final event."""
    cfg = ExperimentConfig.of(seed=1, margin=margin)
    final = Experiment(cfg, problem=problem_for(cfg)).run().final
    assert final.estimate.verdict == "reliable"
    assert final.estimate.covers(math.log(exact))
    assert abs(final.estimate.log_mu_hat - math.log(exact)) < math.log(1.5)
    return final


def test_a_run_that_targets_1_m_agrees_with_the_enumeration():
    targeted_run_agrees(1.0, EXACT_1_0)


def test_a_run_that_targets_0_5_m_agrees_with_the_enumeration_on_the_cell_bound():
    final = targeted_run_agrees(0.5, EXACT_0_5)
    contact = final.severity.points[-1]
    assert contact.level == 0.0 and contact.exact_log_p == pytest.approx(math.log(EXACT_CONTACT), abs=1e-4)


def _remaining_misses_against_bound(margin: float) -> tuple[int, int]:
    """(rollout-steps where the miss bound exceeds the misses a sampled failure still made, rollout-steps checked)
    over the failures of a run that targets ``margin``."""
    cfg = ExperimentConfig.of(seed=0, margin=margin, n_final=300, plain_fallback=0)  # the sampler's failures
    pb = problem_for(cfg)
    got = []
    Experiment(
        cfg, [lambda e: got.append(e) if isinstance(e, RolloutsSampled) and e.kind == "final" else None], problem=pb
    ).run()
    ev = got[-1]
    p = BrakingParams(crash_gap_m=margin)
    start, vl = truth.branching_start(p), lead_speeds(p)
    bound = truth.exact_bound(p, start, 401 if margin >= truth.MISS_BOUND_MIN_GAP_M else 161)
    rows = np.flatnonzero(ev.failed)
    gap = pb.signal_arrays(ev.batch)["d"][rows]
    det = ev.batch.detected.reshape(ev.batch.n, ev.batch.n_steps, -1)[rows, :, 0]
    fail = np.argmax(gap < margin, axis=1)
    miss = ~det & (gap < p.braking_distance_m)
    after = np.concatenate([np.cumsum(miss[:, ::-1], axis=1)[:, ::-1], np.zeros((rows.size, 1), int)], axis=1)
    left_at_fail = np.take_along_axis(after, fail[:, None], axis=1)[:, 0]
    g, v, i, b = (np.full(rows.size, x, dtype=float) for x in (start.gap_m, start.speed_mps, start.integral, 0))
    b = np.full(rows.size, start.pending)
    bad = checked = 0
    for t in range(start.step, int(fail.max())):
        live = t < fail
        bad += int((live & (bound(t, g, v, b) > after[:, t] - left_at_fail)).sum())
        checked += int(live.sum())
        g, v, i, b = braking_step(p, vl[t], g, v, i, b, det[:, t])
    return bad, checked


@pytest.mark.parametrize("margin", [1.0, 0.5, 0.0])
def test_the_miss_bound_never_asks_more_misses_than_a_sampled_failure_made(margin):
    # at 1 m the node table (miss_bound), below it the cell bound (cell_miss_bound), where the node table fails
    bad, checked = _remaining_misses_against_bound(margin)
    assert checked > (1000 if margin > 0 else 500) and bad == 0  # contact: 585 rollout-steps


def test_the_miss_bound_is_refused_below_1_m_where_failures_break_it():
    p = BrakingParams(crash_gap_m=0.5)
    with pytest.raises(ValueError, match="not a bound"):
        truth.miss_bound(p, truth.branching_start(p))


def test_console_and_json_show_the_curve(tmp_path, capsys):
    from pemviz.cli import main

    out = tmp_path / "r.json"
    assert main(["run", "--no-record", "--json", str(out)]) == 0
    text = capsys.readouterr().out
    assert "severity: P(min gap < x), from the same rollouts" in text
    assert "gap < 1.5 m" in text and "exact 2.999e-17" in text
    assert (
        "gap < 0 m                     not reached by this run (0 of 1,800 rollouts): pemviz run --margin 0 "
        "targets it" in text
    )
    doc = json.loads(out.read_text())
    points = doc["severity"]["points"]
    assert [p["level"] for p in points] == [2.0, 1.5, 1.0, 0.5, 0.0]
    assert points[0]["p"] == doc["estimate"]["p"] and points[1]["exact"]["p"] == pytest.approx(EXACT_1_5, rel=1e-4)
    assert points[-1]["n_events"] == 0 and points[-1]["p"] == 0.0


def test_a_level_some_rollouts_reach_without_a_backed_estimate_says_so_and_gives_its_bound():
    # "not reached" means no rollout reached the level; a level that some reach but whose weights back no estimate
    # says "not estimated" and prints the 95 % lower bound those weights do back
    import numpy as np
    from pemviz.core.estimate import estimate
    from pemviz.core.severity import SeverityCurve, SeverityPoint, SeverityScale

    rng = np.random.default_rng(0)
    log_w = rng.normal(-40.0, 4.0, 1800)
    failed = np.arange(1800) < 9  # 9 failures: doubtful
    e = estimate(log_w, failed, np.zeros(1800))
    scale = SeverityScale("d", "gap", "m", levels=(0.5,), margin=2.0, target_flag="margin")
    full = estimate(log_w, np.arange(1800) < 900, np.zeros(1800))
    rows = dict(SeverityCurve(scale, (SeverityPoint(2.0, full), SeverityPoint(0.5, e))).rows())
    text = rows[scale.level_text(0.5)]
    assert e.verdict != "reliable" and e.log_lower_bound > -np.inf
    assert text.startswith(f"reached by 9 of 1,800 rollouts, not estimated (ESS {e.ess:.1f}, {e.verdict}): p >= ")
    assert "(95 % lower bound), no upper bound; pemviz run --margin 0.5 targets it" in text
    assert "not reached" not in text
