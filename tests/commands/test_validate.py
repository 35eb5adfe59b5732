"""``pemviz validate`` and ``pemviz tables`` on the command line: numbers against exact answers, bad input.

The library under them is tested in test_validation.py and test_paper_tables.py."""

from __future__ import annotations

import csv
import math

import numpy as np
import pytest
from pemviz.cli import main as cli_main
from pemviz.config import ExperimentConfig
from pemviz.engine.experiment import Experiment
from pemviz.presets import PRESETS
from pemviz.scenarios.toy import ToyParams
from pemviz.scenarios.toy.problem import toy_problem

REDUCED = ("--k", "4", "--ce-epochs", "150", "--pretrain-epochs", "300")


def test_default_sampler_weights_of_a_toy_failure_are_exact():
    # with the window and weights up to the failure, every failing toy rollout of one batch has the same weight
    # prod over the window of p / q(miss): the estimate's only noise is the failure count.
    pb = toy_problem(ToyParams(10, 5, 3, 0.9))
    cfg = ExperimentConfig.of(final_estimate="fresh", n_stages=3, ce_epochs=100, pretrain_epochs=200, seed=1)
    res = Experiment(cfg, problem=pb).run()
    e = res.final.estimate
    assert e.n_failures > 10
    assert e.ess == pytest.approx(e.n_failures, rel=1e-9)


def test_tables_reduced_run_recovers_the_toy_1e_minus_3(tmp_path):
    # the CI version of `pemviz tables`: the toy's 1e-3 case within 30 %
    out = tmp_path / "t"
    assert (
        cli_main(
            [
                "tables",
                "--problem",
                "toy-1e-3",
                "--reps",
                "3",
                *REDUCED,
                "--mc-large",
                "2000",
                "--naive-large",
                "300",
                "--extra",
                "paper",
                "--jobs",
                "1",
                "--out",
                str(out),
            ]
        )
        == 0
    )
    rows = {row["method"]: row for row in csv.DictReader((out / "tables.csv").open())}
    assert set(rows) >= {"MC_100", "MC_2000", "naive-50_100", "naive-50_300", "adaptive_100", "r_agm"}
    for name in ("adaptive_100", "adaptive_100 (paper)"):
        assert math.exp(float(rows[name]["log_mu_hat_mean"])) == pytest.approx(1e-3, rel=0.3)
    assert float(rows["MC_100"]["mean_failures"]) < 1.0
    assert (out / "tables.md").read_text().count("| r_") == 6  # 3 metrics x (state-ce, paper)
    assert (out / "tables.rrd").stat().st_size > 10_000


def test_validate_reduced_run_prints_the_table_with_the_truth(tmp_path, capsys):
    args = [
        "validate",
        "--problems",
        "toy-1e-3",
        "--seeds",
        "3",
        "--presets",
        "paper",
        *REDUCED,
        "--out",
        str(tmp_path),
    ]
    assert cli_main(args) == 0
    assert "| toy-1e-3 | 1.000e-03 | adaptive (paper) | 3 |" in capsys.readouterr().out
    rows = {row["method"]: row for row in csv.DictReader((tmp_path / "validate.csv").open())}
    assert float(rows["adaptive (paper)"]["median_rel_error"]) <= 0.3
    assert int(rows["mc"]["simulations"]) == int(rows["adaptive (paper)"]["simulations"]) == 100 + 400 + 100


def test_validate_takes_a_shipped_pem_by_name_as_run_does(tmp_path):
    # `--pem gbt` once answered "no such file" here while `pemviz run --pem gbt` ran; the toy's truth is 1e-3 in
    # closed form whatever the PEM, and the run records the PEM it was given
    out = tmp_path / "v"
    assert (
        cli_main(
            [
                "validate",
                "--problems",
                "toy-1e-3",
                "--pem",
                "gbt",
                "--seeds",
                "1",
                "--presets",
                "",
                "--baselines",
                "mc",
                "--out",
                str(out),
            ]
        )
        == 0
    )
    (row,) = csv.DictReader((out / "validate.csv").open())
    assert (row["problem"], row["method"], float(row["truth"])) == ("toy-1e-3", "mc", 1e-3)
    assert '[\\"pem\\", \\"gbt\\"]' in (out / "runs.jsonl").read_text()


@pytest.mark.parametrize(
    "args, message",
    [
        (("validate", "--problems", "nope"), "--problems 'nope'"),
        # a registered scene without an exact answer (a user's own, or the crossing): say so, and what to do instead
        (
            ("validate", "--problems", "toy,crossing"),
            "--problems 'crossing': the crossing scenario has no exact answer to compare with (its Scenario record's "
            "exact=True and its problem's exact_log_p); check it against plain Monte Carlo instead: pemviz run "
            "--scenario crossing --method mc",
        ),
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


# -- the opt-in sampler improvements (pemviz.config) -----------------------------------------------------------
def test_paper_preset_leaves_every_improvement_off():
    cfg = ExperimentConfig.of(**PRESETS["paper"])
    assert (cfg.adaptive.proposal_inputs, cfg.adaptive.proposal_window, cfg.weights_until_failure) == (
        "gap",
        False,
        False,
    )
    assert (
        cfg.adaptive.smoothing_at_failure,
        cfg.adaptive.elite_ties,
        cfg.adaptive.pretrain_cap,
        cfg.adaptive.defensive,
    ) == (None, "all", None, 0.0)
    assert cfg.adaptive.final_estimate == "fresh"


@pytest.mark.parametrize(
    "field, value",
    [
        ("proposal_inputs", "speed"),
        ("defensive", 1.0),
        ("pretrain_cap", 1.5),
        ("elite_ties", "some"),
        ("smoothing_at_failure", 0.0),
        ("proposal_window", 1),
    ],
)
def test_improvement_fields_reject_bad_values(field, value):
    from pemviz.config import ConfigError

    with pytest.raises(ConfigError, match=field):
        ExperimentConfig.of(**{field: value})


def test_ce_update_with_an_all_true_step_mask_is_the_paper_update():
    import torch
    from pemviz.core.sampling import Proposal
    from pemviz.estimators.ce_fit import FitOptions, ce_update

    rng = np.random.default_rng(0)
    gaps = np.tile(np.linspace(12, 1, 30), (40, 1))
    detected = rng.random(gaps.shape) < 0.5
    log_p, log_q = np.log(np.where(detected, 0.99, 0.01)), np.full(gaps.shape, np.log(0.5))
    elite = np.arange(40) < 8
    params = []
    for mask in (None, np.ones(gaps.shape, bool)):
        torch.manual_seed(0)
        q = Proposal()
        ce_update(q, gaps, detected, log_p, log_q, elite, FitOptions(30), smoothing=0.1, step_mask=mask)
        params.append(torch.cat([p.detach().ravel() for p in q.parameters()]))
    torch.testing.assert_close(params[1], params[0], rtol=1e-9, atol=1e-10)  # the same sums, masked or not: ~1e-14


def test_state_proposal_reads_its_columns_and_holds_the_rest_for_the_curve():
    import torch
    from pemviz.core.sampling import StateProposal

    torch.manual_seed(0)
    q = StateProposal((0, 1), (12.0, 8.0), (12.3, 7.7))
    obs = np.array([[5.0, 3.0, 0.0], [5.0, 7.7, 9.0]])
    assert q.features(obs[None]).shape == (1, 2, 2)
    logit = q.detect_logit(obs)
    assert logit[0] != logit[1]  # the speed matters
    assert q.curve(np.array([5.0]))[0] == pytest.approx(
        1.0 / (1.0 + math.exp(-q.detect_logit(np.array([[5.0, 7.7]]))[0]))
    )


def test_tables_recording_holds_fig4_as_the_mean_of_the_stage_3_curves(tmp_path):
    rr = pytest.importorskip("rerun")
    pytest.importorskip("datafusion", reason="rerun-sdk[catalog] reads recordings back")
    out = tmp_path / "t"
    assert (
        cli_main(
            [
                "tables",
                "--problem",
                "toy-1e-3",
                "--reps",
                "2",
                "--k",
                "3",
                "--ce-epochs",
                "30",
                "--pretrain-epochs",
                "50",
                "--extra",
                "",
                "--mc-large",
                "200",
                "--jobs",
                "1",
                "--out",
                str(out),
            ]
        )
        == 0
    )
    with rr.server.Server(datasets={"t": [str(out / "tables.rrd")]}) as server:
        client = server.client()  # keep it alive while reading
        table = client.get_dataset("t").reader(index="gap_mm").to_arrow_table()

    def series(entity: str) -> np.ndarray:
        return np.array([x[0] for x in table.column(f"/{entity}:Scalars:scalars").to_pylist() if x is not None])

    reps = [series(f"curves/adaptive_100/rep_{r:02d}/stage_03") for r in range(2)]
    np.testing.assert_allclose(series("fig4/classic"), (reps[0] + reps[1]) / 2, rtol=1e-12)
    assert series("fig4/pem").size == reps[0].size == toy_problem(ToyParams(10, 5, 3, 0.9)).curve_grid.size


def test_every_named_problem_has_its_exact_answer_for_validate():
    from pemviz.scenarios.problems import PROBLEMS, build_problem
    from pemviz.studies.exact_answers import exact_answer

    for name in PROBLEMS:
        assert exact_answer(name).log_p_fail == pytest.approx(build_problem(name).exact_log_p, rel=1e-9), name
