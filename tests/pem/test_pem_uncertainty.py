"""p under the PEM's own uncertainty: the detections' likelihood ratio by hand, the shipped ensemble, and re-weighted
estimates against exact answers (the latched-brake scenario's closed form for every member and shift; the main
scenario's enumeration for the members the truth table keeps)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from pemviz.config import ConfigError, ExperimentConfig
from pemviz.core.detectors import ConstantDetector
from pemviz.core.reweight import ShiftedDetector, detection_log_ratios, with_pem
from pemviz.engine.experiment import Experiment
from pemviz.pem import load_pem
from pemviz.pem.ensemble import DEFAULT_MEMBERS, bootstrap_rows, ensemble_path, load_ensemble
from pemviz.scenarios.braking.problem import braking_problem
from pemviz.scenarios.braking.simulator import BrakingParams
from pemviz.scenarios.braking.truth_latched import latched_log_failure_probability
from pemviz.scenarios.problems import PEM_SHIFTS, problem_for, with_alternatives
from scipy.special import logit


class Invisible:
    """Rows whose first column is 0 are never detected (logit -inf), others at ``p``."""

    def __init__(self, p: float) -> None:
        self.p = p

    def detect_logit(self, rows):
        return np.where(rows[:, 0] > 0, logit(self.p), -np.inf)


def test_the_log_ratio_by_hand():
    # one rollout, 3 steps, 1 object: detected, missed, detected; the last step is not weighed
    rows = np.ones((1, 3, 1, 2))
    detected = np.array([[[True], [False], [True]]])
    mask = np.array([[True, True, False]])
    out = detection_log_ratios(
        ConstantDetector(0.5), [ConstantDetector(0.9), ConstantDetector(0.5)], rows, detected, mask
    )
    assert out[0, 0] == pytest.approx(math.log(0.9 / 0.5) + math.log(0.1 / 0.5), rel=1e-12)
    assert out[1, 0] == 0.0


def test_an_object_no_pem_can_detect_adds_nothing():
    rows = np.array([[[[0.0], [1.0]], [[0.0], [1.0]]]])  # [N=1, T=2, M=2, G=1]: object 0 invisible
    detected = np.array([[[False, True], [False, False]]])
    out = detection_log_ratios(Invisible(0.5), [Invisible(0.8)], rows, detected, np.ones((1, 2), bool))
    assert np.isfinite(out).all()
    assert out[0, 0] == pytest.approx(math.log(0.8 / 0.5) + math.log(0.2 / 0.5), rel=1e-12)


def test_a_shift_moves_every_logit_and_with_pem_swaps_the_pem():
    pem = load_pem()
    target = braking_problem(pem).target
    rows = np.array([[4.0, 0, 0, 0], [8.0, 0, 0, 0]])
    assert ShiftedDetector(target, 0.5).detect_logit(rows) == pytest.approx(target.detect_logit(rows) + 0.5)
    member = load_ensemble(ensemble_path("ml-nn"))[3]
    assert with_pem(target, member).detect_logit(rows) == pytest.approx(member.logit_at_gap(rows[:, 0]))
    with pytest.raises(TypeError):
        with_pem(ConstantDetector(0.5), member)


def test_the_shipped_ensemble_is_twenty_bootstrap_refits_reproducible_by_seed():
    members = load_ensemble(ensemble_path("ml-nn"))
    assert len(members) == DEFAULT_MEMBERS == 20
    assert [m.metadata["member"] for m in members] == list(range(20))
    assert members[0].metadata["bootstrap_seed"] == [2, 0]  # the recipe's seed, then the member
    rows = bootstrap_rows(37498, 2, 0)
    assert np.array_equal(rows, bootstrap_rows(37498, 2, 0)) and not np.array_equal(rows, bootstrap_rows(37498, 2, 1))
    assert len(np.unique(rows)) == pytest.approx(37498 * (1 - math.exp(-1)), rel=0.01)  # a bootstrap resample
    gaps = np.array([4.0])
    p4 = [float(m.prob_at_gap(gaps)[0]) for m in members]
    assert len(set(p4)) == 20  # twenty different fits


def _latched(config: ExperimentConfig):
    problem = with_alternatives(braking_problem(load_pem(), BrakingParams(latched_brake=True)), config)
    return Experiment(config, problem=problem).run().final.pem_spread


@pytest.mark.parametrize("seed", [0, 1])
def test_latched_members_and_shifts_against_their_closed_form(seed):
    spread = _latched(ExperimentConfig.of(seed=seed, pem_uncertainty=True))
    assert len(spread.members) == 20 and [a.label for a in spread.shifts] == [f"{d:+g}" for d in PEM_SHIFTS]
    alts = [*spread.members, *spread.shifts]
    for a in alts:  # the truth comes from the closed form, computed for each PEM here
        assert a.exact_log_p is not None
    pem = load_pem()
    for a, d in zip(spread.shifts, PEM_SHIFTS, strict=False):
        known = latched_log_failure_probability(
            lambda g: pem.logit_at_gap(g) + d,  # noqa: B023 (called within the iteration)
            BrakingParams(latched_brake=True),
        )
        assert a.exact_log_p == pytest.approx(known.log_p_fail, abs=1e-9)
    within = [a for a in alts if abs(a.estimate.log_mu_hat - a.exact_log_p) <= math.log(1.5)]
    covers = [a for a in alts if a.estimate.covers(a.exact_log_p)]
    assert len(within) >= 0.9 * len(alts) and len(covers) >= 0.9 * len(alts)
    # k-hat of nearly equal weights is noisy: some members say doubtful, none claims reliable when it is off
    trusted = [a for a in alts if a.estimate.verdict == "reliable"]
    assert len(trusted) >= 0.7 * len(alts)
    assert all(abs(a.estimate.log_mu_hat - a.exact_log_p) <= math.log(1.5) for a in trusted)
    assert all(math.isfinite(a.estimate.log_mu_hat) and math.isfinite(a.estimate.ess) for a in alts)


def test_main_scenario_members_the_truth_knows_are_within_x1_5():
    cfg = ExperimentConfig.of(seed=0, pem_uncertainty=True)
    spread = Experiment(cfg, problem=problem_for(cfg)).run().final.pem_spread
    known = [a for a in (*spread.members, *spread.shifts) if a.exact_log_p is not None]
    assert len(known) >= 5
    for a in known:
        assert abs(a.estimate.log_mu_hat - a.exact_log_p) <= math.log(1.5), a
        assert a.estimate.covers(a.exact_log_p), a
    # the run's own estimate is untouched by the re-weighting
    plain = Experiment(ExperimentConfig.of(seed=0), problem=problem_for(ExperimentConfig.of(seed=0))).run().final
    assert spread.nominal.log_mu_hat == plain.estimate.log_mu_hat


def test_console_shows_the_spread_and_the_shift(capsys):
    from pemviz.cli import main

    assert main(["run", "--no-record", "--pem-shift", "0.5", "--preset", "quick"]) == 0
    out = capsys.readouterr().out
    assert "PEM shifted by +0.5: p = " in out and "PEM uncertainty" not in out


def test_pem_shift_out_of_range_is_refused():
    with pytest.raises(ConfigError, match="PEM's logit shift"):
        ExperimentConfig.of(pem_shift=20.0)


def test_the_rollout_file_re_estimates_the_run_s_spread(tmp_path, capsys):
    from pemviz.cli import main

    path = tmp_path / "r.parquet"
    assert main(["run", "--no-record", "--pem-uncertainty", "--save-rollouts", str(path)]) == 0
    run = capsys.readouterr().out
    assert main(["estimate", str(path), "--pem-uncertainty", "--no-record"]) == 0
    est = capsys.readouterr().out

    def spread(text: str) -> list[str]:
        return [
            ln
            for ln in text.splitlines()
            if ln.startswith(("PEM uncertainty", "  members:", "  member ESS", "  exact members", "PEM shifted"))
        ]

    assert len(spread(run)) >= 7 and spread(est) == spread(run)
