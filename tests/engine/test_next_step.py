"""The `next:` line after a run that is not reliable: the cheapest route that would decide it, with its rollouts and
its time on this machine (pemviz.sinks.console.next_step), checked on hand-made estimates and configs with real
numbers; every flag it names is one `pemviz run` accepts."""

from __future__ import annotations

import dataclasses
import math
import re
import types

import pemviz.scenarios.registry  # noqa: F401 (registers each scenario's cost factor, as a run does)
import pytest
from pemviz.cli import build_parser
from pemviz.commands.run import config_from_args
from pemviz.config import ExperimentConfig
from pemviz.core.estimate import Estimate, Reference
from pemviz.engine.cost import duration_text, mc_rollouts
from pemviz.engine.events import FinalEstimate
from pemviz.sinks.console import MC_AFFORDABLE, final_lines, next_step, plain_rollout_seconds

CUT_IN_REFERENCE = Reference(866, 10_000_000, "plain Monte Carlo, shipped PEMs")


def made(log_mu: float, verdict: str = "unreliable", n: int = 2100, khat: float = 1.2) -> Estimate:
    """An estimate of 40 failures at mu_hat = e^log_mu with a heavy k-hat (no terms kept: no lower bound)."""
    return Estimate(n, 40, log_mu, 30.0, 30.0, 2.0, (log_mu - 0.5, log_mu + 0.5), khat, 0.0, verdict, "k-hat")


def counted(n: int, failures: int, log_ci: tuple[float, float], verdict: str, reason: str) -> Estimate:
    """A plain Monte Carlo estimate: ``failures`` in ``n`` rollouts, every weight 1, with its interval (nats)."""
    log_mu = math.log(failures / n) if failures else -math.inf
    return Estimate(n, failures, log_mu, 0.0, 0.0, float(failures), log_ci, math.nan, 0.0, verdict, reason, True)


def mc_count(p: float) -> int:
    """The rollouts plain Monte Carlo needs for a 20 % relative half-width: ceil(1.96^2 (1 - p) / (0.04 p))."""
    return math.ceil(1.96**2 * (1 - p) / (0.04 * p))


def mc_cap(n: float) -> int:
    """The `--max-sims` named for plain Monte Carlo: 1.2 times its rollouts (the exact Clopper-Pearson interval the run
    stops on is a little wider than the normal approximation behind them)."""
    return math.ceil(1.2 * n)


def plain_rate(s: float) -> str:
    """How a plain rollout's seconds after a run of another method read: ``~0.16 ms a plain rollout (...)``."""
    return f"~{s * 1e3:.2g} ms a plain rollout (this run's speed, by the cost model)"


FLAG = r"--[a-z][a-z-]*(?: (?!--)[\w.]+)?"
FRAGMENT = re.compile(rf"{FLAG}(?: {FLAG})*")


def fragments(advice: str) -> list[list[str]]:
    """The command fragments of a `next:` line: runs of ``--flag [value]`` tokens."""
    return [m.group(0).split() for m in FRAGMENT.finditer(advice)]


def assert_valid_flags(advice: str) -> None:
    """Every fragment parses as `pemviz run` flags; each that switches to plain Monte Carlo builds a valid config."""
    parser = build_parser("run", full=False)
    assert fragments(advice), advice
    for tokens in fragments(advice):
        args = parser.parse_args(["run", *tokens, "--no-record"])  # an unknown flag or bad value exits 2
        if "--method" in tokens:
            config_from_args(args)


def test_mc_rollouts_is_the_binomial_count_for_a_20_percent_half_width():
    for p in (0.3, 3e-4, 8.66e-5):
        assert mc_rollouts(math.log(p)) == mc_count(p)
    assert mc_rollouts(math.log(1.984e-15)) == pytest.approx(mc_count(1.984e-15), rel=1e-12)  # 4.8e16: float64's ulp
    assert mc_rollouts(math.log(8.66e-5)) == 1_108_911  # about 96 / p
    assert mc_rollouts(-800.0) == math.inf  # p below float64's range


def test_duration_text_reads_in_seconds_minutes_hours_days_years():
    assert [duration_text(s) for s in (0.84, 42.0, 588.0, 3780.0, 11_160.0, 86_400 * 12, 9.6e12)] == [
        "0.8 s",
        "42 s",
        "9.8 min",
        "63 min",
        "3.1 h",
        "12 days",
        "3.0e+05 years",
    ]
    assert duration_text(5.24e10) == "1,660 years"


def test_an_unknown_p_names_plain_monte_carlo_with_its_count_and_this_run_s_time():
    """p from the run's own mu_hat (no exact answer, no reference): the count printed is ceil(1.96^2 (1 - p) /
    (0.04 p)), --max-sims 1.2 times it, and the time that count times a plain rollout's seconds: the run's measured
    seconds a simulation (6.3 s / 2100 = 3 ms) scaled by the cost model (plain_rollout_seconds); the sampler's own
    route keeps the run's 3 ms."""
    p = 3e-4
    cfg = ExperimentConfig.of()
    advice = next_step(made(math.log(p)), cfg, n_simulations=2100, wall_s=6.3)
    n, plain = mc_count(p), plain_rollout_seconds(cfg, 6.3 / 2100)
    assert n == 320_038 and mc_cap(n) == 384_046
    assert plain < 6.3 / 2100  # a plain rollout costs less than a simulation of the adaptive run, fits included
    assert advice.startswith(
        f"plain Monte Carlo decides it: --method mc --rel-error 0.2 --max-sims {mc_cap(n)} (p ~ "
        f"3.00e-04, this run's mu_hat: {n:,} rollouts for a 20 % interval, "
    )
    assert f"~{duration_text(n * plain)} at {plain_rate(plain)})" in advice
    assert "an upper estimate" in advice and "stops early where p is larger" in advice
    assert "more budget (--n 400: 5,100 simulations, ~15 s)" in advice  # 5,100 x 3 ms
    assert_valid_flags(advice)


def test_a_known_p_sizes_plain_monte_carlo_on_the_reference_with_the_measured_time():
    e = made(math.log(4.2e-12), khat=3.06)
    cfg = ExperimentConfig.of(scenario="cut-in")
    advice = next_step(e, cfg, None, CUT_IN_REFERENCE, 2100, 7.0)
    n, plain = mc_count(866 / 10_000_000), plain_rollout_seconds(cfg, 7.0 / 2100)
    assert f"--method mc --rel-error 0.2 --max-sims {mc_cap(n)} (p ~ 8.66e-05, the reference: {n:,} rollouts" in advice
    assert f"~{duration_text(n * plain)} at {plain_rate(plain)})" in advice
    assert "more budget (--n 400: 5,100 simulations, ~17 s)" in advice  # the sampler's own: 5,100 x 3.3 ms
    assert "upper estimate" not in advice  # the reference is no estimate of this run
    assert "k-hat 3.06 > 0.7" in advice
    assert_valid_flags(advice)


def test_a_probed_plain_rollout_times_plain_monte_carlo_at_its_own_speed():
    """With the engine's probe (a plain rollout's seconds measured after the run), plain Monte Carlo's time is its
    rollouts times that, and the line says it was measured; the sampler's own route keeps the run's speed."""
    e = made(math.log(4.2e-12), khat=3.06)
    advice = next_step(e, ExperimentConfig.of(scenario="cut-in"), None, CUT_IN_REFERENCE, 2100, 7.0, plain_s=2.3e-4)
    n = mc_count(866 / 10_000_000)
    assert (
        f"{n:,} rollouts for a 20 % interval, ~{duration_text(n * 2.3e-4)} at ~0.23 ms a plain rollout (measured "
        "here after the run))" in advice
    )
    assert "more budget (--n 400: 5,100 simulations, ~17 s)" in advice


def test_the_engine_probes_a_plain_rollout_only_where_the_advice_needs_it():
    """:func:`pemviz.engine.experiment.plain_probe`: seconds a plain rollout after a run that is not reliable from
    another method; None after a reliable run or a plain Monte Carlo run (which measured its own)."""
    from pemviz.engine.experiment import plain_probe
    from pemviz.scenarios.problems import build_problem

    problem = build_problem("toy")
    s = plain_probe(problem, ExperimentConfig.of(method="adaptive"), made(math.log(1e-3)))
    assert s is not None and 0.0 < s < 0.1
    assert plain_probe(problem, ExperimentConfig.of(method="mc"), made(math.log(1e-3))) is None
    assert (
        plain_probe(problem, ExperimentConfig.of(), dataclasses.replace(made(math.log(1e-3)), verdict="reliable"))
        is None
    )


def test_the_probe_of_a_slow_simulator_stops_at_its_pilot():
    """A simulator whose rollouts cost 2 ms each (a per-rollout simulator, as highway-env's is) is timed on the pilot
    and twice the pilot alone: 1,000 of them would take 2 s, past the probe's budget of 1 s; a fast one is timed on
    the whole probe."""
    import time as clock

    from pemviz.engine import experiment
    from pemviz.scenarios.problems import build_problem

    problem = build_problem("toy")
    asked, simulate = [], problem.simulate

    def slow(n, *args, **kwargs):
        asked.append(n)
        clock.sleep(0.002 * n)
        return simulate(n, *args, **kwargs)

    s = experiment.plain_probe(
        dataclasses.replace(problem, simulate=slow), ExperimentConfig.of(method="adaptive"), made(math.log(1e-3))
    )
    assert asked == [experiment.PROBE_PILOT, 2 * experiment.PROBE_PILOT] and 0.002 <= s < 0.05
    counted = dataclasses.replace(problem, simulate=lambda n, *a, **k: asked.append(n) or simulate(n, *a, **k))
    asked.clear()
    experiment.plain_probe(counted, ExperimentConfig.of(method="adaptive"), made(math.log(1e-3)))
    assert asked == [experiment.PROBE_PILOT, 2 * experiment.PROBE_PILOT, experiment.PLAIN_PROBE]


def test_the_probe_of_a_scene_with_a_fixed_cost_per_batch_reaches_its_1000_rollouts():
    """A scene whose batch costs 0.15 s whatever its size plus 0.05 ms a rollout (a stack scene's steps: tracker and
    PEM calls per batched step) takes 0.2 s for 1,000 rollouts, 0.2 ms each. Its 50 rollouts alone (3 ms each)
    say 1,000 would take 3 s, past the budget: the probe used to stop there and the advice priced plain Monte Carlo
    15 times too high (a user's left turn on the stack: ~2 ms a rollout said, 0.2 ms measured)."""
    import time as clock

    from pemviz.engine import experiment
    from pemviz.scenarios.problems import build_problem

    problem = build_problem("toy")
    asked, simulate = [], problem.simulate

    def fixed_cost(n, *args, **kwargs):
        asked.append(n)
        clock.sleep(0.15 + 5e-5 * n)
        return simulate(n, *args, **kwargs)

    s = experiment.plain_probe(
        dataclasses.replace(problem, simulate=fixed_cost), ExperimentConfig.of(method="adaptive"), made(math.log(1e-3))
    )
    assert asked == [experiment.PROBE_PILOT, 2 * experiment.PROBE_PILOT, experiment.PLAIN_PROBE]
    assert 0.0002 <= s < 0.0006  # 0.2 s / 1,000 (+ the toy's own cost and a loaded machine's delays)


def test_a_max_time_that_plain_monte_carlo_does_not_fit_says_so_and_what_is_left():
    cfg = ExperimentConfig.of(scenario="cut-in", rel_error=0.1, max_time_s=60.0)
    n, plain = mc_count(866 / 10_000_000), plain_rollout_seconds(cfg, 1e-3)  # 1,108,911 rollouts, this run at 1 ms
    assert n * plain > 60.0  # plain Monte Carlo does not fit in the minute
    e = made(math.log(4.2e-12))
    # the sampler has time left in the minute: within it, only its own precision target, with its verdict
    left = next_step(e, cfg, None, CUT_IN_REFERENCE, 2100, 2.1)
    assert left.startswith(
        f"plain Monte Carlo does not fit in --max-time 60 (p ~ 8.66e-05, the reference: {n:,} "
        f"rollouts for a 20 % interval, ~{duration_text(n * plain)} at "
        f"{plain_rate(plain)})"
    )
    assert (
        "within it only a precision target (--rel-error 0.1 --max-sims 60000 --max-time 60: final batches up to "
        "60,000 simulations, ~60 s) is left, with its verdict" in left
    )
    assert_valid_flags(left)
    # this run used the minute: no route within it decides
    none = next_step(e, cfg, None, CUT_IN_REFERENCE, 60_000, 60.0)
    plain = plain_rollout_seconds(cfg, 1e-3, 60_000)  # this run's 60,000 simulations took the minute
    assert "no route within --max-time 60 s would decide it" in none
    assert f"plain Monte Carlo would, given ~{duration_text(n * plain)} " in none
    assert f"--method mc --rel-error 0.2 --max-sims {mc_cap(n)} --max-time {math.ceil(n * plain)})" in none
    assert_valid_flags(none)


def test_braking_s_p_is_too_rare_for_plain_monte_carlo_and_says_so():
    e = Estimate(
        100,
        0,
        -math.inf,
        math.nan,
        math.nan,
        0.0,
        (-math.inf, math.log(0.03)),
        math.nan,
        0.0,
        "unreliable",
        "no failure",
    )
    advice = next_step(e, ExperimentConfig.of(method="mc"), math.log(1.984e-15), None, 100, 0.01)
    assert advice.startswith(
        "p ~ 1.98e-15, the exact answer: 4.8e+16 rollouts for a 20 % interval, ~1.5e+05 years "
        "at this run's 0.1 ms a rollout: too rare for plain Monte Carlo; an importance-sampling "
        "method (--method adaptive), with its verdict"
    )
    assert mc_count(1.984e-15) > MC_AFFORDABLE
    assert_valid_flags(advice)


def test_a_plain_monte_carlo_run_is_told_how_many_rollouts_and_how_long():
    e = counted(20_000, 1, (math.log(1.27e-6), math.log(2.79e-4)), "doubtful", "only 1 failure")
    advice = next_step(e, ExperimentConfig.of(method="mc", n_per_stage=20_000), None, CUT_IN_REFERENCE, 20_000, 4.2)
    n = mc_count(866 / 10_000_000)  # timed at the run's own measured 4.2 s / 20,000 rollouts
    assert advice == (
        f"more rollouts: --rel-error 0.2 --max-sims {mc_cap(n)} samples until the interval is within "
        f"20 % (p ~ 8.66e-05, the reference: {n:,} rollouts for a 20 % interval, "
        f"~{duration_text(n * 4.2 / 20_000)} at this run's 0.21 ms a rollout)"
    )
    assert_valid_flags(advice)


def test_the_plain_monte_carlo_after_the_stages_is_advised_as_plain_monte_carlo():
    """The default sampler's answer is the plain rollouts after its stages (--plain-fallback): with no failure in
    144,000 of them (a scene that cannot fail) the line named --n 400 (the retry the run had already drawn); with 2
    failures it called the plain count "an upper estimate" of heavy-tailed weights. Now: more plain rollouts."""
    config = ExperimentConfig.of(scenario="crossing")  # the default sampler: adaptive, N = 100
    none = counted(144_000, 0, (-math.inf, math.log(3 / 144_000)), "unreliable", "rule of three")
    advice = next_step(none, config, None, None, 151_200, 15.12)  # 0.1 ms a simulation
    n = mc_count(3 / 144_000)
    assert advice == (
        f"more plain rollouts (--method mc --n 1440000, ~{duration_text(144.0)}) lower the bound ten-fold; "
        f"p < 2.08e-05 here, so a 20 % interval needs at least {n:,} rollouts, ~{duration_text(n * 1e-4)}; the "
        "stages before them saw no failure either"
    )
    assert_valid_flags(advice)
    two = counted(10_000, 2, (math.log(2.42e-5), math.log(7.22e-4)), "doubtful", "only 2 failures")
    advice = next_step(two, config, None, None, 17_200, 1.72, plain_s=1e-4)
    n = mc_count(2e-4)
    assert advice.startswith(f"more rollouts: --method mc --rel-error 0.2 --max-sims {mc_cap(n)} samples until")
    assert "upper estimate" not in advice and "--n 400" not in advice
    assert_valid_flags(advice)


def test_a_heavy_tailed_tiny_mu_hat_gets_plain_monte_carlo_capped_not_called_too_rare():
    """mu_hat 3.8e-11 from weights with k-hat 4.4 (the cut-in at a 19.5 m gap) is usually far too low: plain Monte
    Carlo capped at MC_AFFORDABLE rollouts decides p wherever p >= 1.96^2 / (0.04 cap + 1.96^2), stopping early."""
    e = made(math.log(3.8e-11), khat=4.38)
    advice = next_step(e, ExperimentConfig.of(scenario="cut-in"), None, None, 2100, 7.0)
    assert advice.startswith("p is not known (p ~ 3.80e-11, this run's mu_hat: 2.5e+12 rollouts")
    assert "--method mc --rel-error 0.2 --max-sims 100000000: up to 100,000,000 rollouts" in advice
    assert "decides it where p >= 9.6e-07, stopping early where p is larger" in advice
    assert "too rare" not in advice
    assert_valid_flags(advice)


@pytest.mark.parametrize("backed", [True, False])
def test_a_run_that_backs_no_interval_caps_plain_monte_carlo_at_its_lower_bound(backed):
    """Estimate.interval_backed / log_lower_bound, read with getattr: where the interval is not backed, the 95 % lower
    bound of p sizes --max-sims (p >= it whatever the weights' tail), mu_hat the count expected."""
    e = types.SimpleNamespace(
        verdict="doubtful",
        n=8221,
        n_failures=2824,
        log_mu_hat=math.log(1.76e-2),
        khat=-2.3,
        log_ci=(-5.0, -3.0),
        interval_backed=backed,
        log_lower_bound=math.log(5.21e-3),
    )
    cfg = ExperimentConfig.of()
    advice = next_step(e, cfg, n_simulations=8221, wall_s=15.2)
    n, floor, plain = mc_count(1.76e-2), mc_count(5.21e-3), plain_rollout_seconds(cfg, 15.2 / 8221, 8221)
    cap = mc_cap(floor if not backed else n)
    assert f"--method mc --rel-error 0.2 --max-sims {cap} (p ~ 1.76e-02, this run's mu_hat: {n:,} rollouts" in advice
    assert f"~{duration_text(n * plain)} at {plain_rate(plain)}" in advice
    assert (
        f"; up to {floor:,} at its 95 % lower bound p >= 5.21e-03, ~{duration_text(floor * plain)}" in advice
    ) is not backed
    assert_valid_flags(advice)


def test_splitting_and_tilt_keep_their_own_advice_with_counts_and_times():
    e = Estimate(100, 0, -math.inf, math.nan, math.nan, 0.0, (-math.inf, 0.0), math.nan, 0.0, "unreliable", "died")
    ams = next_step(e, ExperimentConfig.of(method="ams"), None, None, 170, 0.2)
    assert ams == (
        "more particles (--n 400, ~0.8 s), or particles ranked by the nominal look-ahead (--ams-score lookahead: "
        "where the robustness is flat every particle ties and the run dies out); "
        "the verdict says whether to trust the result"
    )
    assert_valid_flags(ams)
    cut_in = next_step(e, ExperimentConfig.of(method="ams"), None, None, 170, 0.2, committor=True)
    assert "or particles ranked by the scenario's learned committor (--ams-score committor)" in cut_in
    assert "lookahead" not in cut_in
    tilt = next_step(
        made(math.log(9.15e-5), khat=1.72),
        ExperimentConfig.of(method="tilt", scenario="cut-in"),
        None,
        CUT_IN_REFERENCE,
        12_995,
        6.5,
    )
    assert tilt.startswith(
        f"plain Monte Carlo decides it: --method mc --rel-error 0.2 --max-sims "
        f"{mc_cap(mc_count(866 / 10_000_000))} ("
    )
    assert "or more tilted batches (--rel-error 0.2 --max-sims 100000: up to 100,000 simulations, ~50 s)" in tilt
    assert_valid_flags(tilt)


def test_final_lines_time_the_advice_with_the_run_s_own_seconds_a_simulation():
    e = made(math.log(3e-4))
    lines = final_lines(FinalEstimate(e, 2100, 6.3), ExperimentConfig.of())
    advice = next(line for line in lines if line.startswith("next: "))
    assert advice == "next: " + next_step(e, ExperimentConfig.of(), None, None, 2100, 6.3)
    plain = plain_rollout_seconds(ExperimentConfig.of(), 6.3 / 2100)  # the event's 6.3 s / 2100 simulations
    assert f"~{duration_text(mc_count(3e-4) * plain)} at {plain_rate(plain)}" in advice
    assert "more budget (--n 400: 5,100 simulations, ~15 s)" in advice  # 5,100 x the event's 3 ms


def test_a_plain_rollout_s_seconds_are_the_run_s_scaled_by_the_cost_model_s_ratio():
    """After a run of another method, a plain rollout's seconds are the run's measured seconds a simulation times the
    cost model's seconds of a plain rollout (a large plain batch's, a rollout) over its seconds of one of the run's
    simulations (its whole plan's, over its planned simulations); a plain Monte Carlo run's are its own."""
    from pemviz.engine.cost import N_STEPS, run_cost, stage_cost
    from pemviz.estimators import run_plan

    ratios = []
    for cfg in (
        ExperimentConfig.of(method="adaptive", scenario="braking"),
        ExperimentConfig.of(method="tilt", scenario="cut-in"),
    ):
        plain = stage_cost(cfg.replace(method="mc"), "final", 100_000, N_STEPS).seconds / 100_000
        run = run_cost(cfg, run_plan(cfg), N_STEPS).seconds / cfg.n_simulations
        ratios.append(plain / run)
        assert 0.0 < plain / run < 1.0, cfg.method  # a plain rollout is cheaper than a fitted or tilted simulation
        assert plain_rollout_seconds(cfg, 3e-3) == pytest.approx(3e-3 * plain / run, rel=1e-12), cfg.method
        assert plain_rollout_seconds(cfg, 0.5) == pytest.approx(0.5 * plain / run, rel=1e-12), cfg.method
        assert plain_rollout_seconds(cfg, None) is None
    assert ratios[0] != pytest.approx(ratios[1], rel=0.1)  # each method's own ratio, not one factor for all
    for scenario in ("braking", "cut-in"):
        mc = ExperimentConfig.of(method="mc", scenario=scenario)
        assert plain_rollout_seconds(mc, 2.1e-4) == 2.1e-4 and plain_rollout_seconds(mc, 3e-3) == 3e-3


def test_a_tilt_run_s_plain_rollout_seconds_divide_its_wall_time_not_its_look_aheads():
    # a tilt run reports its look-aheads in its simulations (1,623 for 100 rollouts on the cut-in): a plain rollout's
    # seconds are its wall time over the model's seconds of its plan, times the model's plain rollout
    from pemviz.engine.cost import N_STEPS, run_cost, stage_cost
    from pemviz.estimators import run_plan

    cfg = ExperimentConfig.of(method="tilt", scenario="cut-in")
    wall, reported = 2.8, 1623
    plain = stage_cost(cfg.replace(method="mc"), "final", 100_000, N_STEPS).seconds / 100_000
    model = run_cost(cfg, run_plan(cfg), N_STEPS).seconds
    got = plain_rollout_seconds(cfg, wall / reported, reported)
    assert got == pytest.approx(plain * wall / model, rel=1e-12)
    assert got > 10 * plain_rollout_seconds(cfg, wall / reported)  # dividing by the planned 100 instead: far too low


def test_a_splitting_run_s_advice_speaks_of_what_splitting_has():
    """AMS has no importance weights: its line never speaks of weights, and names a score the scene accepts (the
    look-ahead on a scene without a committor, which --ams-score committor would refuse)."""
    e = Estimate(
        100,
        4,
        math.log(3e-4),
        math.nan,
        math.nan,
        4.0,
        (math.log(1e-4), math.log(9e-4)),
        math.nan,
        0.0,
        "doubtful",
        "few families",
    )
    for committor in (None, False, True):
        ams = next_step(
            e, ExperimentConfig.of(method="ams", ams_score="lookahead"), None, None, 10_000, 5.0, committor=committor
        )
        assert "weight" not in ams and "splitting's estimate is skewed, most runs low" in ams, ams
        assert ("--ams-score committor" in ams) is bool(committor)
        assert_valid_flags(ams)
    adaptive = next_step(e, ExperimentConfig.of(), None, None, 10_000, 5.0)
    assert "heavy-tailed weights make this run's estimate usually too low" in adaptive


def test_the_rare_cut_in_s_default_says_no_method_shipped_answers_with_the_bound_it_has():
    """``pemviz run --scenario cut-in-rare``: plain Monte Carlo of 5,000 rollouts (about 15 s), then, not a method that
    cannot answer at about 1e-7, the line that none shipped can, with the run's Clopper-Pearson bound; the same
    scene with another start gap, or a scene a method answers, keeps its own route."""
    from pemviz.config import scene_defaults

    assert scene_defaults("cut-in-rare") == {"method": "mc", "n_per_stage": 5_000}
    config = ExperimentConfig.of(scenario="cut-in-rare", **scene_defaults("cut-in-rare"))
    upper = 1.0 - 0.05 ** (1.0 / 5_000)  # one-sided Clopper-Pearson with no failure in 5,000: 5.99e-4
    none = Estimate(5_000, 0, -math.inf, math.nan, math.nan, 0.0, (-math.inf, math.log(upper)), plain_mc=True)
    said = next_step(none, config, None, None, 5_000, 15.0) or ""
    assert said.startswith("no method shipped today answers at this scene's rarity: p is about 1e-7"), said
    assert said.endswith("the bound this run has: p < 5.99e-04 (95 %, 5,000 rollouts without a failure)"), said
    assert "--method adaptive" not in said and "--method" not in said
    tilted = next_step(made(math.log(4e-10), "unreliable"), config.replace(method="tilt"), None, None, 7280, 30.0)
    assert tilted is not None and tilted.startswith("no method shipped today answers")
    assert tilted.endswith("no bound either way from this run")  # made() keeps no terms: no lower bound
    moved = config.replace(scenario_params=(("cut_in_gap_m", 20.0),))  # the moderate gap: the tilt answers there
    assert "no method shipped" not in (next_step(none, moved, None, None, 5_000, 15.0) or "")
    cut_in = ExperimentConfig.of(scenario="cut-in", method="mc", n_per_stage=5_000)
    assert "no method shipped" not in (next_step(none, cut_in, None, None, 5_000, 15.0) or "")


def test_pemviz_run_cut_in_rare_ends_with_the_line_and_the_bound_its_run_has(capsys):
    """``pemviz run --scenario cut-in-rare`` as a user runs it (here at 200 rollouts, not its 5,000): plain Monte Carlo,
    then the line that no method shipped answers, with the bound the run printed (the rule of three, 3 / n: 1.50e-02
    at 200; the scene's guide quotes 6.00e-04, its default's 5,000); no method advised that cannot answer there."""
    from pathlib import Path

    from pemviz.cli import main

    assert main(["run", "--scenario", "cut-in-rare", "--n", "200", "--seed", "0", "--no-record"]) == 0
    out = capsys.readouterr().out
    assert "no failure seen in 200 rollouts: p < 1.50e-02 (95%, rule of three" in out
    (said,) = [line for line in out.splitlines() if line.startswith("next: ")]
    assert said.startswith("next: no method shipped today answers at this scene's rarity: p is about 1e-7"), said
    assert said.endswith("the bound this run has: p < 1.50e-02 (95 %, 200 rollouts without a failure)"), said
    assert "--method" not in said
    guide = " ".join((Path(__file__).resolve().parents[2] / "docs" / "cut-in.md").read_text().split())
    assert f"the bound this run has: p < {3 / 5_000:.2e}`" in guide  # the default's 5,000 rollouts


def test_an_upper_estimate_blames_heavy_tails_only_where_the_weights_have_them():
    """The count sized on a run's own mu_hat is an upper estimate; the line says why mu_hat may be low: heavy-tailed
    weights where k-hat is above the verdict's threshold (or not fitted), and not where the fitted tail passed and the
    run is doubted on other grounds (``--param "gap0_m~uniform(1,3)"``: k-hat 0.00, ESS 1,175, doubtful over an ODD)."""
    cfg = ExperimentConfig.of()
    light = next_step(made(math.log(0.496), "doubtful", khat=0.0), cfg, n_simulations=2100, wall_s=3.8)
    assert "heavy-tailed" not in light, light
    assert (
        "an upper estimate: this run's estimate may be too low (doubtful; its weights' tail not heavy, k-hat 0.00)"
        in (light)
    )
    heavy = next_step(made(math.log(3e-4), "doubtful", khat=0.9), cfg, n_simulations=2100, wall_s=6.3)
    assert "an upper estimate: heavy-tailed weights make this run's estimate usually too low" in heavy
    unknown = next_step(made(math.log(3e-4), "doubtful", khat=math.nan), cfg, n_simulations=2100, wall_s=6.3)
    assert "heavy-tailed weights make this run's estimate usually too low" in unknown  # no tail fitted: not cleared


def test_a_run_over_an_odd_whose_stages_back_no_interval_says_no_plain_monte_carlo_followed(capsys):
    """Over an ODD the default sampler's stages run alone (no retry, no plain fallback): a run they leave `doubtful`
    says so and names plain Monte Carlo over the ODD (a user's overtaking scene ended at 6e-15, doubtful, with p
    about 3e-4, and nothing said that the fallback of the one-scene run had not run); a one-scene run does not."""
    from pemviz.cli import main
    from pemviz.sinks.console import ODD_STAGES_ALONE

    toy = ["run", "--scenario", "toy", "--param", "total=10", "--param", "safe=3", "--k", "1", "--n", "20"]
    assert main([*toy, "--param", "braking~choice(5, 6, 7)", "--n-final", "20", "--no-record"]) == 0
    out = capsys.readouterr().out
    assert re.search(r"k-hat [^:]*: doubtful \(", out), out  # the stages' verdict: 3 distinct failing rollouts
    assert f"stop: {ODD_STAGES_ALONE}" in out.splitlines()
    assert_valid_flags("--method mc --n 1000")  # the flags the line names
    assert main([*toy, "--param", "braking=5", "--n-final", "20", "--plain-fallback", "0", "--no-record"]) == 0
    assert ODD_STAGES_ALONE not in capsys.readouterr().out
