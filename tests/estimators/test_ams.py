"""Adaptive multilevel splitting (``method = "ams"``) against exact answers, and the snapshot/restore capability it
branches with."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
from pemviz.config import ConfigError, ExperimentConfig
from pemviz.engine.events import RunFinished
from pemviz.engine.experiment import Experiment
from pemviz.envs import BrakingEnv
from pemviz.estimators import build_estimator
from pemviz.estimators.ams import SCORE_FLOOR, run_ams, running_score
from pemviz.scenarios import branch
from pemviz.scenarios.braking.batched import BatchedBraking
from pemviz.scenarios.braking.problem import braking_problem
from pemviz.scenarios.braking.simulator import BrakingParams, BrakingScenario
from pemviz.scenarios.problems import build_problem
from pemviz.scenarios.toy import ToyBraking, ToyParams
from pemviz.scenarios.toy.problem import toy_problem
from pemviz.scenarios.toy.simulator import toy_log_failure_probability

from conftest import run_cli


def ratios(problem, n: int, k: int, seeds: range) -> np.ndarray:
    """p_hat / p over the seeds."""
    return np.array(
        [math.exp(run_ams(problem, n, k, seed=s).estimate().log_mu_hat - problem.exact_log_p) for s in seeds]
    )


def assert_unbiased(x: np.ndarray) -> None:
    se = x.std(ddof=1) / math.sqrt(x.size)
    assert abs(x.mean() - 1.0) <= 3.0 * se, f"mean p_hat / p = {x.mean():.3f} +- {se:.3f}"
    assert se < 0.15  # the test has power: a bias of 50 % would show


def test_ams_is_unbiased_on_the_small_toy():
    """toy (10, 5, 3, 0.9), p = 1e-3 exactly: mean of p_hat over 400 seeds of N = 20, k = 2 (measured 1.03 +- 0.08)."""
    pb = build_problem("toy-1e-3")
    assert pb.exact_log_p == pytest.approx(math.log(1e-3))
    assert_unbiased(ratios(pb, 20, 2, range(400)))


def test_ams_is_unbiased_with_a_distance_dependent_detector():
    """p(d) from 0.95 at the obstacle to 0.5 at the start; exact answer by the product formula
    (pemviz.scenarios.braking.truth)."""
    params = ToyParams(30, 12, 3, lambda d: 0.95 - 0.015 * np.asarray(d))
    pb = toy_problem(params)
    assert pb.exact_log_p == toy_log_failure_probability(params) and pb.exact_log_p < math.log(1e-6)
    assert_unbiased(ratios(pb, 50, 5, range(300)))


def test_ams_on_a_rare_toy_relative_error():
    """toy (30, 12, 3, 0.9), p = 1e-10: unbiased over 300 seeds (N = 50, k = 5: measured 1.00 +- 0.06 over 800
    seeds), and one run's relative error is typically of order 1 at this N (median over the seeds < 1)."""
    pb = toy_problem(ToyParams(30, 12, 3, 0.9))
    assert pb.exact_log_p == pytest.approx(math.log(1e-10))
    x = ratios(pb, 50, 5, range(300))
    assert_unbiased(x)
    assert float(np.median(np.abs(x - 1.0))) < 1.0


def test_ams_counts_rollout_equivalents_and_reports_an_interval():
    pb = build_problem("toy-1e-3")
    r = run_ams(pb, 100, 10, seed=0)
    T = r.particles.n_steps
    assert r.steps > 100 * T and r.n_simulations == -(-r.steps // T)
    e = r.estimate()
    assert e.n == 100 and e.log_ci[0] < e.log_mu_hat < e.log_ci[1] and e.verdict in ("reliable", "doubtful")
    assert math.isnan(e.khat) and e.ess > 0
    # every particle's score is its classic robustness, the last column of its prefix scores
    np.testing.assert_array_equal(r.score, pb.robustness(r.particles, "classic"))


def test_running_score_is_the_running_min_of_the_operand():
    pb = build_problem("main")
    b = pb.simulate(5, pb.target, pb.target, np.random.default_rng(0))
    s = running_score(pb, b)
    np.testing.assert_allclose(s, np.minimum.accumulate(b.signal("gap_m") - 2.0, axis=1))


# -- snapshot / restore ---------------------------------------------------------------------------------------


def _run(sim, actions):
    out = []
    for a in actions:
        out.append(np.array(sim.observation(), dtype=np.float64).copy())
        sim.step(a)
    return np.array(out)


@pytest.mark.parametrize(
    "make", [lambda: BrakingScenario(BrakingParams()), lambda: ToyBraking(ToyParams())], ids=["highway-env", "toy"]
)
def test_restoring_a_snapshot_replays_the_rest_exactly(make):
    rng = np.random.default_rng(3)
    actions = rng.random(60) < 0.4
    whole = make()
    assert callable(whole.snapshot) and callable(whole.restore)
    full = _run(whole, actions)
    first = make()
    _run(first, actions[:25])
    snap = first.snapshot()
    _run(first, ~actions[25:40])  # the snapshotted simulator moves on; the snapshot must not
    for _ in range(2):  # a snapshot can be restored more than once
        other = make()
        other.restore(snap)
        np.testing.assert_array_equal(_run(other, actions[25:]), full[25:])


def test_batched_twin_snapshot_restore():
    rng = np.random.default_rng(4)
    actions = rng.random((100, 7)) < 0.3
    whole = BatchedBraking(n=7)
    full = _run(whole, actions)
    sim = BatchedBraking(n=7)
    _run(sim, actions[:40])
    snap = sim.snapshot()
    _run(sim, actions[40:60])
    other = BatchedBraking(n=7)
    other.restore(snap)
    np.testing.assert_array_equal(_run(other, actions[40:]), full[40:])
    with pytest.raises(ValueError, match="snapshot of 7 rollouts"):
        BatchedBraking(n=3).restore(snap)


def test_gym_env_snapshot_restore():
    env = BrakingEnv()
    env.reset(seed=5)
    accel = np.array([0.5])
    for _ in range(30):
        env.step(accel)
    snap = env.snapshot()
    after = [env.step(accel) for _ in range(20)]
    env.restore(snap)
    again = [env.step(accel) for _ in range(20)]
    for (o1, r1, _, _, i1), (o2, r2, _, _, i2) in zip(after, again, strict=False):
        np.testing.assert_array_equal(o1, o2)
        assert r1 == r2 and i1 == i2


@pytest.mark.parametrize("name", ["toy-1e-3", "main"])
def test_branched_rollouts_keep_their_parents_prefix(name):
    pb = build_problem(name)
    b = pb.simulate(20, pb.target, pb.target, np.random.default_rng(0))
    parent, at = np.arange(7) * 2, np.random.default_rng(1).integers(0, b.n_steps, 7)
    c = pb.branch(b, parent, at, pb.target, np.random.default_rng(2))
    for i in range(7):
        np.testing.assert_array_equal(c.observations[i, : at[i] + 1], b.observations[parent[i], : at[i] + 1])
        np.testing.assert_array_equal(c.detected[i, : at[i]], b.detected[parent[i], : at[i]])
    np.testing.assert_array_equal(c.log_p, c.log_q)  # continuations are drawn from the target


def test_snapshot_branching_on_highway_env_equals_the_batched_twin():
    """The generic branch (replay once per parent, snapshot, restore per child) on highway-env vehicles gives the
    batched twin's vectorised continuations bit for bit."""
    batched, highway = build_problem("main"), braking_problem(build_problem("main").target.pem, sim="highway-env")
    b = batched.simulate(5, batched.target, batched.target, np.random.default_rng(0))
    parent, at = np.array([0, 1, 1, 1, 4]), np.array([0, 30, 60, 60, 99])
    c = highway.branch(b, parent, at, highway.target, np.random.default_rng(2))
    d = batched.branch(b, parent, at, batched.target, np.random.default_rng(2))
    np.testing.assert_array_equal(c.observations, d.observations)
    np.testing.assert_array_equal(c.detected, d.detected)
    np.testing.assert_array_equal(c.log_p, d.log_p)


def test_branch_replays_a_simulator_without_snapshot_as_the_vectorised_toy_does():
    # branching replays the parent's detections up to the branching step (the scenario is deterministic given them),
    # so a simulator without snapshot/restore branches too, and gives the vectorised twin's rollouts bit for bit
    class Plain:
        observation_names = ("gap_m", "stopped")

        def __init__(self):
            self.sim = ToyBraking(ToyParams(10, 5, 3, 0.9))

        def reset(self):
            self.sim.reset()

        def observation(self):
            return self.sim.observation()

        def step(self, detected):
            self.sim.step(detected)

    pb = build_problem("toy-1e-3")
    b = pb.simulate(3, pb.target, pb.target, np.random.default_rng(0))
    parent, at = np.array([0, 2, 2]), np.array([2, 0, 5])
    replayed = branch(Plain, b, parent, at, pb.target, np.random.default_rng(1))
    twin = pb.branch(b, parent, at, pb.target, np.random.default_rng(1))
    np.testing.assert_array_equal(replayed.observations, twin.observations)
    np.testing.assert_array_equal(replayed.detected, twin.detected)
    np.testing.assert_array_equal(replayed.detected[0, :2], b.detected[0, :2])  # the replayed prefix


# -- wiring ---------------------------------------------------------------------------------------------------


def test_a_problem_without_branch_gives_one_clear_error():
    pb = dataclasses.replace(build_problem("toy-1e-3"), branch=None, name="custom")
    with pytest.raises(ValueError, match=r"^method ams needs a simulator with snapshot/restore; custom has none$"):
        build_estimator(ExperimentConfig.of(method="ams"), pb)


def test_config_checks_k_against_n():
    with pytest.raises(ConfigError, match=r"ams_killed \(k\) = 10 is invalid"):
        ExperimentConfig.of(method="ams", n_per_stage=10)
    with pytest.raises(ConfigError, match="ams_max_iterations"):
        ExperimentConfig.of(method="ams", ams_max_iterations=0)
    ExperimentConfig.of(method="mc", n_per_stage=5)  # k matters only to ams


def test_engine_runs_ams_in_stages_and_reports_rollout_equivalents():
    pb = build_problem("toy-1e-3")
    cfg = ExperimentConfig.of(method="ams", n_per_stage=100, ams_killed=10, seed=0)
    res = Experiment(cfg, problem=pb).run()
    assert isinstance(res, RunFinished)
    direct = run_ams(pb, 100, 10, seed=0)
    assert res.final.estimate.log_mu_hat == direct.estimate().log_mu_hat  # the engine adds nothing
    assert res.final.n_simulations == direct.n_simulations > 100
    assert [s.kind for s in res.stages] == ["ams"] * len(res.stages) and len(res.stages) >= 2


def test_cli_run_method_ams(tmp_path):
    rrd = tmp_path / "ams.rrd"  # one run prints and records (a run with --no-record differs only by its sinks)
    r = run_cli("run", "--method", "ams", "--save", str(rrd))
    assert r.returncode == 0, r.stderr
    assert "AMS" in r.stderr + r.stdout
    assert rrd.stat().st_size > 0
    r = run_cli("run", "--method", "ams", "--n", "5", "--no-record")
    assert r.returncode == 2 and "Traceback" not in r.stderr and "k must be a whole number in [1, N - 1]" in r.stderr


def test_ams_through_snapshots_of_single_simulators_equals_the_vectorised_toy():
    """The generic branch (ToyBraking snapshots) and the vectorised toy give the same AMS run for a seed."""
    pb = build_problem("toy-1e-3")
    params = ToyParams(10, 5, 3, 0.9)
    generic = dataclasses.replace(
        pb,
        branch=lambda parents, parent, at, target, rng: branch(
            lambda: ToyBraking(params), parents, parent, at, target, rng
        ),
    )
    for seed in range(3):
        a, b = run_ams(pb, 30, 3, seed=seed), run_ams(generic, 30, 3, seed=seed)
        assert a.iterations == b.iterations > 0
        assert a.estimate().log_mu_hat == b.estimate().log_mu_hat
        np.testing.assert_array_equal(a.particles.detected, b.particles.detected)


def test_initial_particles_may_arrive_in_chunks():
    """A streamed stage 0 (N above the engine's STREAM_ABOVE) reaches the estimator chunk by chunk."""
    pb = build_problem("toy-1e-3")
    est = build_estimator(ExperimentConfig.of(method="ams", n_per_stage=30, ams_killed=3), pb)
    plan = est.next_stage()
    assert (plan.stage, plan.n, plan.draw) == (0, 30, None)
    whole = pb.simulate(30, pb.target, pb.target, np.random.default_rng(0))
    for rows in (slice(0, 12), slice(12, 30)):
        part = whole.select(np.arange(30)[rows])
        np.testing.assert_array_equal(est.observe(part, pb.failed(part), None), 0.0)
    est.finish()
    assert est.ams.n == 30
    np.testing.assert_array_equal(est.ams.particles.detected, whole.detected)
    assert est.next_stage().draw is not None


# -- a graded score: the scenario's committor ------------------------------------------------------------------


def test_running_score_with_a_graded_score_by_hand():
    """The graded score where the operand holds (floored above 0), the robustness where it fails, the parent's
    prefix up to the branching step; then the running minimum."""
    pb = build_problem("toy-1e-3")  # G[0,8](d >= 3): the operand's robustness is d - 3
    b = pb.simulate(2, pb.target, pb.target, np.random.default_rng(0))
    d = b.signal("gap_m")
    graded = np.full(d.shape, np.inf)
    graded[0, 2], graded[1, 1] = 0.7, 0.0
    s = running_score(pb, b, graded)
    rho = d - 3.0
    want = np.minimum.accumulate(np.where(rho < 0, rho, np.maximum(graded, SCORE_FLOOR)), axis=1)
    np.testing.assert_array_equal(s, want)
    assert s[0, 2] == 0.7 and s[1, 1] == SCORE_FLOOR  # a V of 1 does not count as a failure
    prefix = np.full(d.shape, -5.0)
    s = running_score(pb, b, graded, prefix, np.array([0, 3]))
    assert (s[0] == -5.0).all() and (s[1, :4] == -5.0).all()


def test_committor_scored_ams_is_unbiased_with_a_poor_committor():
    """toy (10, 5, 3, 0.9), p = 1e-3 exactly, ranked by -log of a poor V that calls a stopped car (which cannot
    fail) likely to: the mean of p_hat over 400 seeds of N = 100, k = 10 (measured 1.04 +- 0.08 over seeds 0-199),
    and it is not the robustness's run (the score changes the particles kept)."""
    pb = build_problem("toy-1e-3")
    x = np.array(
        [
            math.exp(run_ams(pb, 100, 10, seed=s, score="committor").estimate().log_mu_hat - pb.exact_log_p)
            for s in range(400)
        ]
    )
    assert_unbiased(x)
    a, b = run_ams(pb, 100, 10, seed=3, score="committor"), run_ams(pb, 100, 10, seed=3)
    assert a.estimate().log_mu_hat != b.estimate().log_mu_hat


def test_engine_runs_committor_scored_ams_as_run_ams_does():
    pb = build_problem("toy-1e-3")
    cfg = ExperimentConfig.of(method="ams", n_per_stage=100, ams_killed=10, seed=2, ams_score="committor")
    res = Experiment(cfg, problem=pb).run()
    direct = run_ams(pb, 100, 10, seed=2, score="committor")
    assert res.final.estimate.log_mu_hat == direct.estimate().log_mu_hat
    assert res.final.n_simulations == direct.n_simulations


def test_committor_score_asked_of_a_scenario_without_one_gives_one_line():
    with pytest.raises(
        ValueError,
        match=r"^ams_score committor needs a scenario with a learned committor; crowd "
        r"has none: use ams_score robustness$",
    ):
        build_estimator(ExperimentConfig.of(method="ams", ams_score="committor"), build_problem("crowd"))
    r = run_cli("run", "--scenario", "crowd", "--method", "ams", "--ams-score", "committor", "--no-record")
    assert r.returncode == 2 and "Traceback" not in r.stderr and "has none: use ams_score robustness" in r.stderr
    r = run_cli("run", "--method", "ams", "--ams-score", "nope", "--no-record")
    assert r.returncode == 2 and "Traceback" not in r.stderr and "committor" in r.stderr


def test_an_extinct_run_says_why_where_its_estimate_is_printed():
    """A run whose every particle ties at the level ends with p_hat = 0; its summary gives the AMS's reason, not an
    importance sampler's."""
    from pemviz.estimators.ams import Splitting

    pb = build_problem("toy-1e-3")
    sp = Splitting(pb, 2, 10, np.random.default_rng(0), np.random.default_rng(1))
    b = pb.simulate(4, pb.target, pb.target, np.random.default_rng(0))
    sp.start(b, np.full((4, b.n_steps), 3.0))  # every particle scores 3 nats: they tie
    assert sp.stop.startswith("extinction") and sp.log_prod == -math.inf
    line = sp.estimate().summary()
    assert line.startswith("no failure seen in 4 rollouts: AMS: extinction: every particle ties at level 3: "), line
