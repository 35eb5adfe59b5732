"""pemviz.studies.validation: exact answers, run records on disk, summaries, equal budgets."""

from __future__ import annotations

import math

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from pemviz.config import ExperimentConfig
from pemviz.core.estimate import relative_error
from pemviz.scenarios.problems import PROBLEMS, build_problem
from pemviz.studies.exact_answers import ExactAnswer, exact_answer
from pemviz.studies.validation import (
    DEFAULT_PROBLEMS,
    Job,
    RunRecord,
    job_key,
    markdown_table,
    methods_for,
    read_finished,
    read_records,
    record_to_json,
    run_jobs,
    summaries_csv,
    summarise,
)


def test_relative_error_and_summary_by_hand():
    lt = math.log(1e-21)
    assert relative_error(math.log(1.5e-21), lt) == pytest.approx(0.5, rel=1e-9)
    assert relative_error(-math.inf, lt) == 1.0
    recs = [
        RunRecord(
            "toy",
            "m",
            s,
            math.log(v),
            10,
            100,
            5.0,
            40.0,
            39.0,
            1200,
            1.0,
            log_ci_lo=math.log(v / 1.6),
            log_ci_hi=math.log(v * 1.6),
            verdict=verdict,
        )
        for s, (v, verdict) in enumerate(
            [(0.6e-21, "reliable"), (0.9e-21, "doubtful"), (1.2e-21, "reliable"), (4e-21, "unreliable")]
        )
    ]
    (s,) = summarise(recs, {"toy": ExactAnswer(lt, "closed form")})
    assert s.median_rel_error == pytest.approx((0.2 + 0.4) / 2, rel=1e-9)  # errors 0.4, 0.1, 0.2, 3
    assert s.within_2x == 3 and s.n_seeds == 4
    assert s.covered == 2 and s.reliable == 2  # 0.6e-21 * 1.6 < 1e-21 and 4e-21 / 1.6 > 1e-21 miss the truth
    assert math.exp(s.median_mu_hat) == pytest.approx(math.sqrt(0.9e-21 * 1.2e-21), rel=1e-9)  # median of logs
    assert "| toy | 1.000e-21 | m | 4 |" in markdown_table([s])
    assert summaries_csv([s]).splitlines()[1].startswith(f"toy,{lt!r},1e-21,m,4,")


def test_a_run_with_no_failure_and_the_trivial_interval_is_counted_apart_not_as_covering():
    """[0, 1] (no failure, no bound) holds every p and says nothing: not counted as covering, reported apart; a
    real upper bound with no failure (plain Monte Carlo's [0, 3/n]) and a real interval still count."""
    lt = math.log(1e-3)

    def record(seed: int, log_mu: float, lo: float, hi: float, failures: int) -> RunRecord:
        return RunRecord(
            "toy-1e-3", "m", seed, log_mu, failures, 1000, 1.0, 5.0, 5.0, 1000, 1.0, log_ci_lo=lo, log_ci_hi=hi
        )

    trivial = record(0, -math.inf, -math.inf, 0.0, 0)
    assert trivial.says_nothing and not trivial.covers(lt)
    rule_of_three = record(1, -math.inf, -math.inf, math.log(3e-3), 0)
    real = record(2, math.log(1.1e-3), math.log(0.8e-3), math.log(1.4e-3), 11)
    assert rule_of_three.covers(lt) and real.covers(lt) and not (rule_of_three.says_nothing or real.says_nothing)
    (s,) = summarise([trivial, rule_of_three, real], {"toy-1e-3": ExactAnswer(lt, "closed form")})
    assert (s.covered, s.said_nothing, s.n_seeds) == (2, 1, 3)
    assert "| 2/3 (1 no failure: [0, 1]) |" in markdown_table([s])
    assert summaries_csv([s]).splitlines()[1].endswith(",1")


def test_exact_answers_of_the_toys():
    assert exact_answer("toy").log_p_fail == pytest.approx(math.log(1e-21), rel=1e-12)
    assert exact_answer("toy-1e-30").log_p_fail == pytest.approx(math.log(1e-30), rel=1e-9)
    assert exact_answer("toy-1e-3").log_p_fail == pytest.approx(math.log(1e-3), rel=1e-12)
    with pytest.raises(ValueError, match="unknown problem 'nope'"):
        exact_answer("nope")


def test_named_problems_carry_their_exact_answer():
    assert set(DEFAULT_PROBLEMS) <= set(PROBLEMS)
    toy = build_problem("toy-1e-3")
    assert toy.name == "toy-1e-3" and toy.exact_log_p == pytest.approx(math.log(1e-3), rel=1e-12)
    assert build_problem("toy-1e-3") is toy  # built once per process
    with pytest.raises(ValueError, match="use one of toy, "):
        build_problem("nope")


def test_records_round_trip_through_the_runs_file_and_a_torn_line_is_skipped(tmp_path):
    job = Job("toy-1e-3", "mc", (("method", "mc"), ("n_per_stage", 50)), 3)
    other = Job("toy-1e-3", "mc", (("method", "mc"), ("n_per_stage", 60)), 3)
    rec = RunRecord("toy-1e-3", "mc", 3, -math.inf, 0, 50, 0.0, math.nan, math.nan, 50, 0.1, gammas=(1.5, 0.25))
    path = tmp_path / "runs.jsonl"
    path.write_text(record_to_json(job, rec) + "\n" + record_to_json(other, rec)[:-7], encoding="utf-8")
    (back,) = read_finished(path, [job]).values()
    assert back.log_mu_hat == -math.inf and math.isnan(back.nll_mean) and back.gammas == (1.5, 0.25)
    assert read_finished(path, [other]) == {}  # its line is torn
    assert read_finished(tmp_path / "missing.jsonl", [job]) == {}
    ((key, again),) = read_records(path)  # every setting's records, the torn line skipped
    assert key == job_key(job) and record_to_json(job, again) == record_to_json(job, back)  # NaN != NaN: the lines


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(st.lists(st.binary(max_size=80), max_size=6))
def test_read_records_skips_any_foreign_line_and_keeps_the_records_around_it(tmp_path, junk):
    job = Job("toy-1e-3", "mc", (("method", "mc"),), 1)
    rec = RunRecord("toy-1e-3", "mc", 1, -3.5, 2, 50, 4.0, 1.0, 1.0, 50, 0.1, gammas=(0.0,), khat=0.2)
    line = record_to_json(job, rec).encode()
    path = tmp_path / "runs.jsonl"
    path.write_bytes(b"\n".join([line, *(j.replace(b"\n", b" ").replace(b"\r", b" ") for j in junk), line]) + b"\n")
    assert read_records(path) == [(job_key(job), rec), (job_key(job), rec)]  # no junk line reads as a record


def test_run_jobs_resumes_from_the_runs_file_with_the_same_numbers(tmp_path):
    jobs = [Job("toy-1e-3", "mc", (("method", "mc"), ("n_per_stage", 2000)), seed) for seed in (0, 1)]
    path = tmp_path / "runs.jsonl"
    first = run_jobs(jobs[:1], runs_file=path)
    seen = []
    both = run_jobs(jobs, on_record=seen.append, runs_file=path)
    assert [r.seed for r in seen] == [1]  # seed 0 was read back, not run again
    assert record_to_json(jobs[0], both[0]) == record_to_json(jobs[0], first[0])  # NaN != NaN: compare the lines
    assert both[1].n == 2000 and both[1].n_failures == pytest.approx(2, abs=6)  # p_fail 1e-3
    assert both[1].log_mu_hat == run_jobs(jobs[1:])[0].log_mu_hat  # same seed, same estimate


def test_baselines_get_the_first_presets_simulation_budget():
    methods = dict(methods_for(["paper", "quick"], ["mc", "naive50"], {"n_stages": 3}))
    assert list(methods) == ["adaptive (paper)", "adaptive (quick)", "mc", "naive50"]
    # the paper's budget at K = 3: 100 pretraining rollouts + 3 stages x N = 100 + a final batch of 100
    assert methods["mc"] == {"method": "mc", "n_per_stage": 500}
    assert methods["naive50"] == {"method": "naive50", "n_per_stage": 500}
    assert methods["adaptive (quick)"] == {
        "n_stages": 3,
        "ce_epochs": 200,
        "pretrain_rollouts": 50,
        "pretrain_epochs": 200,
        "learning_rate": 2e-2,
        "plain_fallback": 0,
    }  # the quick preset, K = 3, its stages alone (no plain Monte Carlo past the budget)


def test_the_main_truth_of_a_shipped_pem_is_the_kept_enumeration_not_recomputed():
    from pemviz.pem import load_pem
    from pemviz.scenarios.braking.truth_known import KNOWN_BRAKING_LOG_P, pem_fingerprint

    answer = exact_answer("main")
    assert answer.log_p_fail == KNOWN_BRAKING_LOG_P[pem_fingerprint(load_pem().logit_at_gap)] == -33.85370929668962
    assert "kept" in answer.source and answer.table is None  # no enumeration ran (it has a refinement table)


def test_a_runs_key_holds_every_config_field_so_a_changed_default_reruns_the_run():
    # the same run, its default given or not: one key; another value of that field: another key; the key names the
    # default's value, so a pemviz with other defaults finds no finished run under it
    bare = Job("toy", "adaptive (state-ce)", (), 0)
    explicit = Job("toy", "adaptive (state-ce)", (("uniforms", ExperimentConfig.of().uniforms),), 0)
    other = Job("toy", "adaptive (state-ce)", (("uniforms", "iid"),), 0)
    assert job_key(bare) == job_key(explicit) != job_key(other)
    assert '["uniforms", "array-rqmc"]' in job_key(bare) and '["seed"' not in job_key(bare)
