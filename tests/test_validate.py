"""``pemviz validate`` and ``pemviz tables``: numbers against exact answers, and their bad-input behaviour."""

from __future__ import annotations

import csv
import math

import numpy as np
import pytest

from pemviz.cli import main as cli_main
from pemviz.commands.tables import log_mean_and_se
from pemviz.commands.validate import ExactAnswer, RunRecord, exact_answer, relative_error, summarise
from pemviz.config import PRESETS, ExperimentConfig
from pemviz.engine import Experiment, failure_steps
from pemviz.scenarios.toy import ToyParams, toy_problem

REDUCED = ("--k", "4", "--ce-epochs", "150", "--pretrain-epochs", "300")


def test_log_mean_and_se_equal_numpy_and_stay_exact_below_float_range():
    x = np.array([1e-15, 3e-15, 2e-15, 6e-15])
    lm, lse = log_mean_and_se(np.log(x))
    assert math.exp(lm) == pytest.approx(x.mean(), rel=1e-12)
    assert math.exp(lse) == pytest.approx(x.std(ddof=1) / 2.0, rel=1e-12)
    lm, lse = log_mean_and_se(np.log(x) - 1000.0)  # 1e-450: no float64 holds it, the logs do
    assert lm == pytest.approx(math.log(x.mean()) - 1000.0, abs=1e-12)
    assert log_mean_and_se([-math.inf, -math.inf]) == (-math.inf, -math.inf)


def test_relative_error_and_summary_by_hand():
    lt = math.log(1e-21)
    assert relative_error(math.log(1.5e-21), lt) == pytest.approx(0.5, rel=1e-9)
    assert relative_error(-math.inf, lt) == 1.0
    recs = [RunRecord("toy", "m", s, math.log(v), 10, 100, 5.0, 40.0, 39.0, 1200, 1.0)
            for s, v in enumerate([0.6e-21, 0.9e-21, 1.2e-21, 4e-21])]  # fmt: skip
    (s,) = summarise(recs, {"toy": ExactAnswer(lt, "closed form")})
    assert s.median_rel_error == pytest.approx((0.2 + 0.4) / 2, rel=1e-9)  # errors 0.4, 0.1, 0.2, 3
    assert s.within_2x == 3 and s.n_seeds == 4
    assert math.exp(s.median_mu_hat) == pytest.approx(math.sqrt(0.9e-21 * 1.2e-21), rel=1e-9)  # median of logs


def test_exact_answers_of_the_toys():
    assert exact_answer("toy").log_p_fail == pytest.approx(math.log(1e-21), rel=1e-12)
    assert exact_answer("toy-1e-30").log_p_fail == pytest.approx(math.log(1e-30), rel=1e-9)


def test_failure_steps_are_the_first_step_below_the_safe_distance():
    pb = toy_problem(ToyParams(10, 5, 3, 0.9))
    from pemviz.detectors import ConstantDetector

    batch = pb.simulate(200, ConstantDetector(0.3), pb.target, np.random.default_rng(0))
    steps = failure_steps(pb, batch)
    failed = pb.failed(batch)
    assert np.all(steps[failed] == 8) and np.all(steps[~failed] == batch.n_steps)  # distance 2 at step 8


def test_improved_preset_weights_of_a_toy_failure_are_exact():
    # with the window and weights up to the failure, every failing toy rollout has the same weight
    # prod over the window of p / q(miss): the estimate's only noise is the failure count.
    pb = toy_problem(ToyParams(10, 5, 3, 0.9))
    cfg = ExperimentConfig(**PRESETS["improved"], n_stages=3, ce_epochs=100, pretrain_epochs=200, seed=1)
    res = Experiment(cfg, problem=pb).run()
    e = res.final.estimate
    assert e.n_failures > 10
    assert e.ess == pytest.approx(e.n_failures, rel=1e-9)


def test_tables_reduced_run_recovers_the_toy_1e_minus_3(tmp_path):
    # the CI version of `pemviz tables`: the toy's 1e-3 case within 30 % (issue 6, acceptance 6)
    out = tmp_path / "t"
    assert cli_main(["tables", "--problem", "toy-1e-3", "--reps", "3", *REDUCED, "--mc-large", "2000",
                     "--naive-large", "300", "--extra", "improved", "--jobs", "1", "--out", str(out)]) == 0  # fmt: skip
    rows = {row["method"]: row for row in csv.DictReader((out / "tables.csv").open())}
    assert set(rows) >= {"MC_100", "MC_2000", "naive-50_100", "naive-50_300", "adaptive_100", "r_agm"}
    for name in ("adaptive_100", "adaptive_100 (improved)"):
        assert math.exp(float(rows[name]["log_mu_hat_mean"])) == pytest.approx(1e-3, rel=0.3)
    assert float(rows["MC_100"]["mean_failures"]) < 1.0
    assert (out / "tables.md").read_text().count("| r_") == 3
    assert (out / "tables.rrd").stat().st_size > 10_000


def test_validate_reduced_run_prints_the_table_with_the_truth(tmp_path, capsys):
    args = ["validate", "--problems", "toy-1e-3", "--seeds", "3", "--presets", "paper", *REDUCED, "--out", str(tmp_path)]
    assert cli_main(args) == 0
    assert "| toy-1e-3 | 1.000e-03 | adaptive (paper) | 3 |" in capsys.readouterr().out
    rows = {row["method"]: row for row in csv.DictReader((tmp_path / "validate.csv").open())}
    assert float(rows["adaptive (paper)"]["median_rel_error"]) <= 0.3
    assert int(rows["mc"]["simulations"]) == int(rows["adaptive (paper)"]["simulations"]) == 100 + 400 + 100


@pytest.mark.parametrize(
    "args, message",
    [
        (("validate", "--problems", "nope"), "--problems 'nope'"),
        (("validate", "--presets", "fast"), "--presets 'fast'"),
        (("tables", "--problem", "nope"), "--problem 'nope'"),
        (("tables", "--reps", "1"), "--reps must be >= 2"),
        (("validate", "--n", "1"), "n_per_stage (N) = 1 is invalid"),
    ],
)
def test_bad_input_is_one_line_and_writes_nothing(tmp_path, capsys, args, message):
    assert cli_main([*args, "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err
    assert message in err and len(err.strip().splitlines()) == 1
    assert not (tmp_path / "o").exists()
