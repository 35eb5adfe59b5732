"""The panel charts' y limits without a browser: one rule (:func:`pemviz.app.plots.robust_range`) fits the log10 mu_hat
per stage chart, the controller chart and the q(detect) per gap bin charts to the values that matter; a value off
the range is drawn at the edge, ringed and counted in the title, every value inside it at its place; a gap bin of
too few states is not joined into its stage's line, and a bin crowded with standing states is named with its count."""

from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from pemviz.app import charts, explain_charts, plots
from pemviz.app.plots import STAGE_RULES, AxisRange, robust_range
from pemviz.app.runs import PanelRun
from pemviz.config import ExperimentConfig
from pemviz.core.proposal_view import proposal_view
from pemviz.core.rollouts import RolloutBatch
from pemviz.engine.events import RolloutsSampled
from pemviz.scenarios.braking.drawing import BrakingDrawing
from pemviz.scenarios.braking.panel import GAP_BINS_M

LN10 = math.log(10.0)


def handle() -> SimpleNamespace:
    """A stand-in for viser's uPlot handle: the fill functions only assign its attributes."""
    return SimpleNamespace(title="", series=(), data=(), scales={}, bands=())


def labels(plot) -> list[str]:
    return [s["label"] for s in plot.series]


def y_limits(plot) -> tuple[float, float]:
    return plot.scales["y"]["range"]


def assert_drawn_in_place(raw: np.ndarray, drawn: np.ndarray, lo: float, hi: float) -> None:
    """Every finite value inside [lo, hi] is drawn exactly at its value, one below / above at that edge, and a
    missing value stays missing."""
    raw, drawn = np.asarray(raw, dtype=np.float64), np.asarray(drawn, dtype=np.float64)
    inside = np.isfinite(raw) & (raw >= lo) & (raw <= hi)
    np.testing.assert_array_equal(drawn[inside], raw[inside])
    np.testing.assert_array_equal(drawn[np.isfinite(raw) & (raw < lo)], lo)
    np.testing.assert_array_equal(drawn[np.isfinite(raw) & (raw > hi)], hi)
    assert np.all(np.isnan(drawn[~np.isfinite(raw)]))


# -- the rule on hand-made numbers ------------------------------------------------------------------
def test_two_stages_orders_of_magnitude_off_leave_the_log10_mu_hat_axis_and_are_counted():
    values = np.array([-40.0, -36.0, -15.1, -14.8, -14.7])
    r = robust_range(values, **STAGE_RULES["log10_mu_hat"])
    # the three that agree, padded by max(0.08 * 0.4, 0.05) = 0.05 (log10 probability) each side
    assert r.range == pytest.approx((-15.15, -14.65), abs=1e-12)
    assert (r.n_below, r.n_above, r.lowest) == (2, 0, -40.0)
    assert r.note() == "; 2 points off scale, drawn at the edge (lowest -40.0)"
    assert_drawn_in_place(values, r.drawn(values), r.lo, r.hi)
    np.testing.assert_array_equal(r.drawn(values), [-15.15, -15.15, -15.1, -14.8, -14.7])


def test_a_stage_that_is_no_majority_leaves_nothing_out():
    """Two stages 5 orders apart: neither is the rest's majority, so both stay on the axis."""
    r = robust_range(np.array([-20.0, -14.7]), **STAGE_RULES["log10_mu_hat"])
    assert r.n_off == 0 and r.lo < -20.0 and r.hi > -14.7
    # spread-out estimates (1 order apart at most) are all kept as well
    spread = np.array([-12.0, -13.0, -14.0, -14.5, -14.7, -14.7])
    r = robust_range(spread, **STAGE_RULES["log10_mu_hat"])
    assert r.n_off == 0 and r.range == pytest.approx((-14.7 - 0.08 * 2.7, -12.0 + 0.08 * 2.7))


def test_outliers_on_both_sides_leave_the_axis():
    values = np.array([-100.0, -40.0, -14.8, -14.75, -14.7, -14.6, 50.0])
    r = robust_range(values, min_gap=3.0, min_pad=0.05)
    assert r.range == pytest.approx((-14.85, -14.55)) and (r.n_below, r.n_above) == (2, 1)
    assert r.note() == "; 3 points off scale, drawn at the edge (lowest -100.0, highest 50.0)"


def test_without_min_gap_every_value_is_on_the_axis_as_before():
    """gamma and NLL keep every stage: their fall over the stages is what they show."""
    gamma = np.array([np.nan, 1.889, 0.0, 0.0, 0.0])
    r = plots.stage_range("gamma", [gamma])
    assert r.n_off == 0 and r.range == pytest.approx((-0.08 * 1.889, 1.889 * 1.08))
    assert plots.y_range("failure_rate", [np.array([0.0, 0.5])]) == (-0.05, 1.05)
    assert plots.y_range("nll", [np.array([63.0])]) == pytest.approx((63.0 - 6.3, 63.0 + 6.3))


@settings(max_examples=200, deadline=None)
@given(st.lists(st.floats(-1e6, 1e6), min_size=1, max_size=40), st.floats(0.0, 50.0))
def test_the_range_keeps_the_median_and_a_majority_and_counts_exactly_what_it_leaves_out(values, min_gap):
    v = np.array(values)
    r = robust_range(v, min_gap=min_gap)
    assert r.lo < r.hi and math.isfinite(r.lo) and math.isfinite(r.hi)
    inside = (v >= r.lo) & (v <= r.hi)
    assert inside.sum() > v.size / 2  # more than half of the values stay on the axis
    assert r.lo <= np.sort(v)[(v.size - 1) // 2] <= r.hi
    assert (r.n_below, r.n_above) == (int(np.sum(v < r.lo)), int(np.sum(v > r.hi)))
    assert_drawn_in_place(v, r.drawn(v), r.lo, r.hi)


def test_values_that_do_not_matter_do_not_set_the_range_but_are_counted():
    v = np.array([0.0, 0.0, -15.5, -14.7, -13.9])
    r = robust_range(v, np.array([False, False, True, True, True]), min_gap=3.0, min_pad=0.05)
    assert r.range == pytest.approx((-15.5 - 0.128, -13.9 + 0.128)) and (r.n_below, r.n_above) == (0, 2)
    assert robust_range(np.zeros(0), at_least=(0.0, 1.04)) == AxisRange(0.0, 1.04)


# -- the per-stage charts ----------------------------------------------------------------------------
def staged_run(
    run_id: int,
    log10_mu: list[float],
    failures: list[int],
    log10_ci: list[tuple[float, float]],
    exact_log10: float | None = None,
) -> PanelRun:
    """A real PanelRun whose stages carry the given log10 mu_hat, failure counts and 95 % interval (log10)."""
    run = PanelRun(run_id, ExperimentConfig.of())
    run.stages = [
        SimpleNamespace(
            stage=k,
            kind="ce",
            gamma=math.nan,
            estimate=SimpleNamespace(
                log10_mu_hat=mu,
                n_failures=f,
                n=100,
                nll_mean=math.nan,
                log_ci=(lo * LN10, hi * LN10),
                shown_log_ci=(lo * LN10, hi * LN10),
            ),
        )
        for k, (mu, f, (lo, hi)) in enumerate(zip(log10_mu, failures, log10_ci, strict=False))
    ]
    run.exact_log_p = None if exact_log10 is None else exact_log10 * LN10
    return run


def test_the_stage_chart_fits_the_stages_that_agree_and_draws_the_others_at_the_edge():
    mu = [-40.0, -36.0, -15.1, -14.8, -14.7]
    run = staged_run(1, mu, [1] * 5, [(m - 0.3, m + 0.3) for m in mu])
    plot = handle()
    plots.fill_stage_plot(plot, "log10_mu_hat", [run])
    lo, hi = y_limits(plot)
    assert (lo, hi) == pytest.approx((-15.15, -14.65))
    assert plot.title == "log10 mu_hat per stage"  # a short title, what it says of the chart below it
    assert plot.caption_text == "2 points off scale, drawn at the edge (lowest -40.0)"
    assert labels(plot) == ["stage", run.short_label, "2 below the scale (at the edge)"]
    assert_drawn_in_place(mu, plot.data[1], lo, hi)
    np.testing.assert_array_equal(plot.data[2], [lo, lo, np.nan, np.nan, np.nan])  # the rings, at the edge


def test_the_mu_hat_chart_ignores_the_interval_of_stages_without_failures_and_shows_the_exact_answer():
    """Stages 0-1 found no failure: their interval's upper bound is log10 1 = 0 and says nothing; before, it set the
    top of the axis (0.93) and the stages that matter were a flat line."""
    mu = [math.nan, math.nan, -14.69, -14.12, -14.73, -14.78]
    ci = [(-math.inf, 0.0), (-math.inf, 0.0), (-15.52, -13.86), (-14.81, -13.43), (-15.13, -14.34), (-14.94, -14.61)]
    run = staged_run(1, mu, [0, 0, 10, 49, 67, 81], ci, exact_log10=-14.702)
    plot = handle()
    plots.fill_stage_plot(plot, "log10_mu_hat", [run])
    charts.fill_mu_hat_plot(plot, [run])
    lo, hi = y_limits(plot)
    # the estimates and the bounds of stages 2-5 with a pad of 0.08 * (15.52 - 13.43) = 0.167
    assert (lo, hi) == pytest.approx((-15.52 - 0.1672, -13.43 + 0.1672))
    assert plot.caption_text.endswith("black: the exact answer; 2 points off scale, drawn at the edge (highest 0.0)")
    names = labels(plot)
    assert names[-1] == "2 above the scale (at the edge)" and "exact answer -14.702" in names
    high = np.array([s.estimate.log_ci[1] / LN10 for s in run.stages])  # the bounds as the run holds them (log10)
    drawn_high = plot.data[names.index(f"{run.short_label} 95 % high")]
    assert_drawn_in_place(high, drawn_high, lo, hi)
    assert drawn_high[0] == drawn_high[1] == hi
    assert_drawn_in_place(mu, plot.data[names.index(run.short_label)], lo, hi)
    low = plot.data[names.index(f"{run.short_label} 95 % low")]
    np.testing.assert_array_equal(low[2:], [s.estimate.log_ci[0] / LN10 for s in run.stages[2:]])
    assert np.all(np.isnan(low[:2]))
    np.testing.assert_array_equal(plot.data[-1], [hi, hi, np.nan, np.nan, np.nan, np.nan])
    assert plot.scales["x"]["range"] == (-0.5, 5.5)


def test_early_in_a_run_the_first_stage_with_failures_sets_the_mu_hat_axis():
    """Three stages without failures (upper bound 0 each) and the first with failures: the zeros are no minority,
    only the rule that they do not matter keeps them off the axis."""
    mu = [math.nan, math.nan, math.nan, -14.7]
    ci = [(-math.inf, 0.0)] * 3 + [(-15.5, -13.9)]
    run = staged_run(1, mu, [0, 0, 0, 4], ci)
    plot = handle()
    plots.fill_stage_plot(plot, "log10_mu_hat", [run])
    charts.fill_mu_hat_plot(plot, [run])
    assert y_limits(plot) == pytest.approx((-15.5 - 0.128, -13.9 + 0.128))
    assert plot.title == "log10 mu_hat per stage"
    assert plot.caption_text == (
        "log10 of each stage's mu_hat; band: its 95 % interval (a bound alone where no interval is backed); 3 points "
        "off scale, drawn at the edge (highest 0.0)"
    )


def test_before_any_failure_the_mu_hat_axis_is_the_exact_answer_with_room_never_a_single_value():
    """Stage 0 without failures and an exact answer: nothing but the exact answer to fit. A range of no width (lo =
    hi, as the first version of the rule gave) makes the browser's uPlot stall for seconds."""
    run = staged_run(1, [math.nan], [0], [(-math.inf, 0.0)], exact_log10=-14.702)
    plot = handle()
    plots.fill_stage_plot(plot, "log10_mu_hat", [run])
    assert y_limits(plot) == (-0.05, 1.05)  # no value yet
    charts.fill_mu_hat_plot(plot, [run])
    assert y_limits(plot) == pytest.approx((-14.702 - 0.05, -14.702 + 0.05))
    assert plot.caption_text.endswith("; 1 point off scale, drawn at the edge (highest 0.0)")
    for at_least, limits in (((3.0, 3.0), (-math.inf, math.inf)), ((20.0, 20.0), (-12.0, 12.0))):
        r = robust_range(np.zeros(0), at_least=at_least, limits=limits)
        assert r.hi - r.lo >= 1.0 - 1e-12, (at_least, limits, r)


def test_an_exact_answer_far_from_the_estimates_stays_on_the_axis():
    mu = [-20.0, -20.1, -19.9]
    run = staged_run(1, mu, [5, 5, 5], [(m - 0.2, m + 0.2) for m in mu], exact_log10=-14.7)
    plot = handle()
    plots.fill_stage_plot(plot, "log10_mu_hat", [run])
    charts.fill_mu_hat_plot(plot, [run])
    lo, hi = y_limits(plot)
    assert lo < -20.3 and hi == pytest.approx(-14.7) and "off scale" not in plot.caption_text


# -- the controller chart ----------------------------------------------------------------------------
def controller_explanation(accel: np.ndarray, gap: np.ndarray, command=None, applied=None) -> SimpleNamespace:
    """What :func:`explain_charts.fill_controller_plot` reads of an explanation: the controller's signals and the
    steps in contact (a gap of at most 0.7 m, the braking scenario's contact gap)."""
    n = accel.size
    none = np.zeros(n, bool)
    controller = SimpleNamespace(
        time_s=np.arange(n) * 0.05,
        accel_mps2=accel,
        gap_m=gap,
        brake_command=none if command is None else command,
        brake_applied=none if applied is None else applied,
    )
    return SimpleNamespace(controller=controller, contact=np.asarray(gap) <= 0.7)


def test_the_contact_steps_acceleration_is_drawn_at_the_edge_and_named():
    """One -110 m/s^2 step, the contact step (a = -v / dt), among accelerations in [-8, 3]."""
    accel = np.linspace(3.0, -8.0, 61)
    accel = np.insert(accel, 40, -110.0)
    gap = np.linspace(12.0, 0.8, accel.size)
    gap[40] = 0.6  # at most the contact gap
    applied = np.zeros(accel.size, bool)
    applied[30:35] = True
    plot = handle()
    explain_charts.fill_controller_plot(plot, controller_explanation(accel, gap, applied=applied), 40, "run 1 r0")
    names = labels(plot)
    assert names == [
        "t (s)",
        "acceleration (m/s^2)",
        "brake commanded",
        "brake applied",
        "acceleration off scale (1)",
        "now",
    ]
    # [-8, 3] padded by max(0.08 * 11, 1) = 1 m/s^2: about [-9, 4]
    bottom, top = -9.0, 4.0
    row = 0.07 * (top - bottom)
    assert y_limits(plot) == pytest.approx((bottom, top + 3 * row))
    assert plot.title == "controller"
    assert plot.caption_text.startswith("run 1 r0: the ego's acceleration (m/s^2)") and plot.caption_text.endswith(
        "; 1 step off scale, drawn at the edge: -110.0 m/s^2 at 2.00 s (contact: the ego stops within one step)"
    )
    assert_drawn_in_place(accel, plot.data[1], bottom, top)
    ring, now = plot.data[4], plot.data[5]
    assert np.flatnonzero(np.isfinite(ring)).tolist() == [40] and ring[40] == bottom
    assert now[40] == bottom  # the now marker at the contact step is on the chart
    np.testing.assert_array_equal(np.flatnonzero(np.isfinite(plot.data[3])), np.arange(30, 35))
    assert np.all(plot.data[3][30:35] == top + row)  # the brake dots just above the curve


def test_a_contact_step_near_full_braking_still_leaves_the_axis():
    """Braking to -26 m/s^2, then contact at a low speed: -76.85 m/s^2 is within twice the braking's spread of it,
    but a contact step does not set the range (the default run, seed 3)."""
    accel = np.r_[np.full(40, 1.5), np.linspace(1.0, -3.7, 15), [-9.2, -9.2, -22.0, -25.96, -76.85], np.zeros(10)]
    gap = np.full(accel.size, 3.0)
    gap[59:] = 0.46
    plot = handle()
    explain_charts.fill_controller_plot(plot, controller_explanation(accel, gap), 0, "r")
    bottom = -25.96 - 0.08 * (1.5 + 25.96)
    assert y_limits(plot)[0] == pytest.approx(bottom)
    assert plot.title == "controller" and plot.caption_text.endswith(
        "; 1 step off scale, drawn at the edge: -76.8 m/s^2 at 2.95 s (contact: the ego stops within one step)"
    )
    assert_drawn_in_place(accel, plot.data[1], bottom, y_limits(plot)[1])


def test_a_lone_spike_leaves_the_controller_axis_even_before_contact():
    accel = np.r_[np.linspace(-8.0, 3.0, 60), -110.0]
    plot = handle()
    explain_charts.fill_controller_plot(plot, controller_explanation(accel, np.full(accel.size, 5.0)), 0, "r")
    assert y_limits(plot)[0] == pytest.approx(-9.0)
    assert plot.caption_text.endswith("; 1 step off scale, drawn at the edge: -110.0 m/s^2 at 3.00 s")


def test_the_emergency_brake_stays_on_the_controller_axis():
    """Full braking (27.5 m/s^2 at low speed) is the controller's own action: drawn at its place, nothing off scale."""
    accel = np.r_[np.full(50, 1.5), np.linspace(1.0, -3.7, 10), [-9.2, -9.2, -22.0, -27.5, -27.5, -27.5], np.zeros(5)]
    plot = handle()
    explain_charts.fill_controller_plot(plot, controller_explanation(accel, np.full(accel.size, 3.0)), 0, "r")
    bottom = -27.5 - 0.08 * 29.0
    assert y_limits(plot)[0] == pytest.approx(bottom) and "off scale" not in plot.caption_text
    np.testing.assert_array_equal(plot.data[1], accel)
    assert "acceleration off scale" not in " ".join(labels(plot))


# -- q(detect) per gap bin ---------------------------------------------------------------------------
def view_record(gap: np.ndarray, q_detect: np.ndarray, stage: int = 1) -> tuple[PanelRun, object]:
    """A real PanelRun holding one CE stage whose rollouts visited ``gap`` [N, T] (metres), each step detected
    with probability ``q_detect`` [N, T] under the sampler and 0.993 under the PEM (every step detected)."""
    n, t = gap.shape
    detected = np.ones((n, t), bool)
    log_q, log_p = np.log(q_detect), np.full((n, t), math.log(0.993))
    view = proposal_view(gap, detected, log_q, log_p, GAP_BINS_M)
    obs = np.stack([gap, np.zeros_like(gap), np.zeros_like(gap)], axis=-1)
    batch = RolloutBatch(obs, detected, log_p, log_q, ("gap_m", "ego_speed_mps", "lead_speed_mps"))
    r = np.ones(n)
    record = PanelRun(1, ExperimentConfig.of())
    record.proposal_axis = BrakingDrawing().proposal_axis()  # the gap's bins, standing states checked
    record.events = [RolloutsSampled(stage, "ce", batch, r, {"classic": r}, r < 0, np.zeros(n))]
    record.proposal_views = {stage: ("ce", view)}
    return record, view


def test_a_bin_of_few_states_is_not_drawn_as_a_spike_but_as_a_hollow_ring_with_its_count():
    rng = np.random.default_rng(0)
    gap = rng.uniform(3.0, 9.0, size=(40, 50))
    gap[0, :3] = 0.7  # three states in the 0.5-1 m bin
    q = np.full(gap.shape, 0.5)
    q[0, :3] = 0.02  # a mean of 0.02 there: a spike if joined into the line
    record, view = view_record(gap, q)
    assert view.n_states[1] == 3 and view.q_mean[1] == pytest.approx(0.02)
    m = {charts.PROB: handle(), charts.LOG_ODDS: handle()}
    charts.fill_marginal_plots(m, record)
    plot = m[charts.PROB]
    names = labels(plot)
    assert plot.caption_text.endswith("; 1 bin of under 20 states hollow")
    line = plot.data[names.index("stage 1")]
    assert np.isnan(line[1])  # not joined into the stage's line
    full = view.n_states >= charts.MIN_BIN_STATES
    np.testing.assert_array_equal(line[full], view.q_mean[full])  # every other bin at its place
    ring = plot.data[names.index("stage 1, bins under 20 states")]
    assert np.flatnonzero(np.isfinite(ring)).tolist() == [1] and ring[1] == pytest.approx(0.02)  # not invented
    assert y_limits(plot) == (0.0, 1.04)
    # the log-odds chart: the few states' median (log 0.98 / 0.02 = 3.9 nats) neither draws nor sets the range
    odds = m[charts.LOG_ODDS]
    assert np.isnan(odds.data[labels(odds).index("stage 1")][1])
    assert y_limits(odds) == pytest.approx((-6.4, 2.4))


def test_a_bin_crowded_with_standing_states_keeps_its_value_and_says_why():
    """The braking scenario's spike: rollouts that stopped in time stand at one gap for the rest of the episode
    (q = p = 0.993 there) and outnumber the moving states of that bin."""
    n, t = 40, 60
    gap = np.tile(np.linspace(9.0, 4.5, t), (n, 1))  # moving through 4.5-9 m: about 6.7 states per bin per rollout
    q = np.full((n, t), 0.5)
    gap[:20, 30:] = 6.2  # half the rollouts stand at 6.2 m from step 30 on
    q[:20, 31:] = 0.993
    share = charts.unchanged_share(gap, GAP_BINS_M)
    b = 12  # 6.0-6.5 m
    in_bin = (gap >= 6.0) & (gap < 6.5)
    assert share[b] == pytest.approx(20 * 29 / in_bin.sum())  # all but the first standing step repeat
    assert np.all(np.nan_to_num(np.delete(share, b)) == 0.0)
    record, view = view_record(gap, q)
    assert charts.standing_bins(view.n_states, share).tolist() == [b]
    m = {charts.PROB: handle(), charts.LOG_ODDS: handle()}
    charts.fill_marginal_plots(m, record)
    plot = m[charts.PROB]
    assert f"6-6.5 m {share[b]:.0%} of {int(view.n_states[b]):,}" in plot.caption_text
    names = labels(plot)
    line = plot.data[names.index("stage 1")]
    assert line[b] == pytest.approx(view.q_mean[b]) and line[b] > 0.8  # the real value, not hidden
    ring = plot.data[names.index("stage 1, mostly standing states")]
    assert np.flatnonzero(np.isfinite(ring)).tolist() == [b]


def test_a_median_beyond_12_nats_is_drawn_at_the_edge_of_the_log_odds_chart():
    gap = np.tile(np.linspace(9.0, 3.0, 60), (30, 1))
    q = np.full(gap.shape, 0.5)
    q[gap < 4.0] = 1.0 - 1e-7  # log q(miss) / q(detect) = -16.1 nats
    record, view = view_record(gap, q)
    m = {charts.PROB: handle(), charts.LOG_ODDS: handle()}
    charts.fill_marginal_plots(m, record)
    odds = m[charts.LOG_ODDS]
    lo, hi = y_limits(odds)
    assert lo == -12.0 and hi == pytest.approx(2.4)
    n_low = int(np.sum(view.q_log_odds < -12.0))
    assert n_low == 2 and odds.caption_text.endswith(
        f"; {n_low} medians off scale, drawn at the edge (lowest -16.1 nats)"
    )
    line = odds.data[labels(odds).index("stage 1")]
    assert_drawn_in_place(view.q_log_odds, line, lo, hi)


def test_a_run_with_a_retry_names_each_final_batch_once_in_the_legend():
    """K 3 and a retry: stages 1-3 and the final batch 4, then the stages once more (6-8) and their final batch 9.
    Each stage drawn is one legend entry of its own; the two final batches are told apart by their stage."""
    gap = np.tile(np.linspace(9.0, 3.0, 60), (30, 1))
    record, view = view_record(gap, np.full(gap.shape, 0.5))
    record.proposal_views = {
        0: ("pretrain", view),
        **{k: ("ce", view) for k in (1, 2, 3, 6, 7, 8)},
        4: ("final", view),
        5: ("pretrain", view),
        9: ("final", view),
    }
    m = {charts.PROB: handle(), charts.LOG_ODDS: handle()}
    charts.fill_marginal_plots(m, record)
    for plot in m.values():
        names = labels(plot)
        stages = [n for n in names if n.startswith(("stage ", "final batch")) and "%" not in n and "," not in n]
        assert stages == [
            "stage 1",
            "stage 2",
            "stage 3",
            "final batch (stage 4)",
            "stage 6",
            "stage 7",
            "stage 8",
            "final batch (stage 9)",
        ]
        assert len(set(names)) == len(names), names  # no legend entry twice
        assert "final batch (stage 9) 10 %" in names  # the newest stage's band
    # a run without a retry keeps the one final batch's short name
    record.proposal_views = {1: ("ce", view), 2: ("final", view)}
    charts.fill_marginal_plots(m, record)
    assert "final batch" in labels(m[charts.PROB]) and "final batch (stage 2)" not in labels(m[charts.PROB])
