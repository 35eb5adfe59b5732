"""``method = "tilt"``: the scenario's own tilted proposal (:class:`pemviz.estimators.tilt.CommittorTilt`).

- On the toy braking model, with a deliberately poor committor (:mod:`pemviz.scenarios.toy.tilt`), the estimates
  average to the exact answer 1e-3 (the weights p / q are exact whatever V is).
- On the cut-in (:mod:`pemviz.scenarios.cut_in.tilt`), a batch's log p - log q is each rollout's importance log weight,
  every step's weight is bounded by the defensive share (w <= 1 / eps), the run counts the look-aheads' steps in its
  simulations, and the same seed gives the same rollouts.
- A scenario without a tilted proposal is refused in one line; the cut-in runs the tilt by default.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
from pemviz.config import ExperimentConfig
from pemviz.engine.experiment import Experiment
from pemviz.scenarios.problems import build_problem


def test_the_toys_tilt_with_a_poor_committor_is_unbiased():
    """40 seeds of 2,000 rollouts: the mean of mu_hat / p within 4 standard errors of 1 (exact p = 1e-3), and the
    poor committor visibly poor: the estimates vary (relative variance a rollout > 1; the exact committor gives 0)."""
    problem = build_problem("toy-1e-3")

    def ratio_of(seed: int) -> float:
        cfg = dataclasses.replace(ExperimentConfig.of(method="tilt", seed=seed), n_per_stage=2000)
        return math.exp(Experiment(cfg, problem=problem).run().final.estimate.log_mu_hat - problem.exact_log_p)

    ratio = np.array([ratio_of(s) for s in range(40)])
    se = ratio.std(ddof=1) / math.sqrt(ratio.size)
    assert abs(ratio.mean() - 1.0) <= 4 * se, (ratio.mean(), se)
    assert ratio.var(ddof=1) * 2000 > 1.0


def test_the_toys_tilt_detector_is_the_pem_outside_the_window():
    """Outside the window (beyond the braking distance, or stopped) q is p itself; inside, q(miss) > p(miss)."""
    from pemviz.scenarios.toy.simulator import ToyDetector, ToyParams
    from pemviz.scenarios.toy.tilt import ToyTiltDetector

    params = ToyParams(total=10, braking=5, safe=3, p_detect=0.9)
    obs = np.array([[8.0, 0.0], [5.0, 1.0], [5.0, 0.0], [3.0, 0.0]])
    q, p = ToyTiltDetector(params).detect_logit(obs), ToyDetector(params).detect_logit(obs)
    np.testing.assert_allclose(q[:2], p[:2], rtol=0, atol=1e-12)
    assert np.all(q[2:] < p[2:])


@pytest.fixture(scope="module")
def cut_in():
    from pemviz.pem import load_pem
    from pemviz.scenarios.cut_in import tilt as tilt_module
    from pemviz.scenarios.cut_in.problem import cut_in_problem

    tilt_module._SOLVED.clear()  # solved here, not reused from another test's run
    problem = cut_in_problem(load_pem())
    tilt = problem.tilt()
    solve_steps = tilt.solve()
    return problem, tilt, solve_steps


def test_a_cut_in_tilt_batch_carries_its_weights(cut_in):
    """log p - log q of the batch summed over the steps is the stage's log weight (to 1e-9 nats); no step's weight
    exceeds log(1 / eps); the same seed draws the same rollouts."""
    problem, tilt, solve_steps = cut_in
    assert solve_steps > 50_000  # the beam's look-aheads: about 146,000 one-car steps
    batch, log_w, steps = tilt.stage(120, np.random.default_rng(3))
    assert steps > 0
    with np.errstate(invalid="ignore"):
        step_w = batch.log_p - batch.log_q
    np.testing.assert_allclose(step_w.sum(axis=1), log_w, rtol=0, atol=1e-9)
    assert step_w.max() <= math.log(1.0 / tilt.eps) + 1e-12
    again, log_w2, _ = tilt.stage(120, np.random.default_rng(3))
    assert np.array_equal(again.detected, batch.detected) and np.array_equal(log_w2, log_w)


def test_the_cut_ins_committor_ranks_splitting_particles_as_a_function_of_the_state(cut_in):
    """``ams_score = "committor"`` on the cut-in: two AMS iterations of 30 particles ranked by -log V of the tilt
    solved above (reused: no solve counted, its look-aheads counted); every particle's prefix scores, its branch's
    included, equal those of its events replayed and scored afresh, bit for bit; V is scored in the tilt's window
    only, and lies in (0, 1]."""
    from pemviz.estimators.ams import SCORE_FLOOR, run_ams, running_score

    problem, tilt, _ = cut_in
    sp = run_ams(problem, 30, 10, seed=0, max_iterations=2, score="committor")
    scorer = sp.scorer
    assert scorer.reused and scorer.solve_steps == 0 and scorer.steps > 0
    assert sp.iterations == 2 and sp.n_simulations > 30 + 20
    graded = scorer.rescore(sp.particles)
    np.testing.assert_array_equal(running_score(problem, sp.particles, graded), sp.running)
    w0, w1 = tilt.window
    assert np.isinf(graded[:, :w0]).all() and np.isinf(graded[:, w1:]).all()
    scored = graded[np.isfinite(graded)]
    assert scored.size > 30 and (scored >= 0.0).all() and (sp.running[:, -1] >= SCORE_FLOOR).sum() >= 25


def test_the_cut_in_runs_the_tilt_by_default_and_counts_its_look_aheads(monkeypatch):
    """``pemviz run --scenario cut-in``'s settings name the tilt; a small run's simulations are its rollouts plus its
    look-aheads' steps over T, the solve's included; a second run of the same scene and PEMs in the process reuses the
    solved proposal, says so, gives the same estimate bit for bit and counts no solve."""
    from pemviz.cli import build_parser
    from pemviz.commands.run import config_from_args
    from pemviz.engine import experiment
    from pemviz.scenarios.cut_in import tilt as tilt_module

    # each doubtful run times plain rollouts for its advice, which no line here reads: 20, not 1,000 (a sixth of it)
    monkeypatch.setattr(experiment, "PLAIN_PROBE", 20)

    cfg = config_from_args(build_parser("run").parse_args(["run", "--scenario", "cut-in"]))
    assert (cfg.method, cfg.n_per_stage) == ("tilt", 7_280)  # the cut-in record's run_defaults
    from pemviz.estimators import build_estimator
    from pemviz.scenarios.problems import problem_for

    tilt_module._SOLVED.clear()
    small = cfg.replace(n_per_stage=60)
    problem = problem_for(small)
    est = build_estimator(small, problem)
    final = Experiment(small, problem=problem).run().final
    assert final.n_simulations > 60 + 1_000  # the solve alone is about 1,464 rollout-equivalents
    assert est.n_simulations == 0  # a fresh estimator has simulated nothing
    assert final.prepared.startswith("the scenario's proposal solved by this run (1,")
    again = Experiment(small, problem=problem_for(small)).run().final  # the PEMs loaded again: the same weights
    assert again.prepared.startswith("the scenario's proposal reused")
    assert again.estimate == final.estimate
    solve = final.n_simulations - again.n_simulations
    assert 1_000 < solve < 2_000
    capped = small.replace(rel_error=0.01, max_sims=61)  # a precision target, capped below the first batch's cost
    with_target = Experiment(capped, problem=problem).run().final
    assert with_target.n_simulations == again.n_simulations  # it counts the look-aheads too, and adds no batch
    room = small.replace(rel_error=0.01, max_sims=again.n_simulations + 300)  # room for about 190 rollouts more
    grown = Experiment(room, problem=problem).run().final
    assert again.n_simulations + 150 < grown.n_simulations <= room.stop.max_sims  # batches added, look-aheads counted
    other = small.replace(scenario_params=(("cut_in_gap_m", 19.0),))
    assert (
        Experiment(other, problem=problem_for(other))
        .run()
        .final.prepared.startswith("the scenario's proposal " "solved")
    )


def test_a_scenario_without_a_tilt_is_refused():
    from pemviz.estimators.tilt import CommittorTilt

    with pytest.raises(ValueError, match="has no tilted proposal of its own"):
        CommittorTilt(build_problem("crowd"), 10, False)


def test_pemviz_run_refuses_the_tilt_on_the_crowd_in_one_line(capsys):
    from pemviz.cli import main

    assert main(["run", "--scenario", "crowd", "--method", "tilt", "--no-record"]) != 0
    err = capsys.readouterr().err.strip()
    assert err == (
        "pemviz run: error: method tilt: the crowd problem has no tilted proposal of its own; use " "adaptive or mc"
    )


def test_the_console_names_the_cross_entropy_settings_only_for_a_method_with_stages(capsys):
    from pemviz.cli import main

    assert main(["run", "--method", "mc", "--n", "40", "--no-record"]) == 0
    header = capsys.readouterr().out.splitlines()[0]
    assert header.endswith("metric classic, N=40 seed=0") and "sigma" not in header
    assert main(["run", "--n", "20", "--n-final", "40", "--stages", "1", "--no-record"]) == 0
    header = capsys.readouterr().out.splitlines()[0]
    assert header.endswith("metric classic, K=1 N=20 N_e=40 sigma=0.95 alpha=0.1 seed=0")
