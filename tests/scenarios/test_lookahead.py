"""The braking look-ahead (conditional Monte Carlo below 6 m): its enumeration against every detection sequence of a
short scene, and a run that targets contact against the exact answer, with its rollout file re-estimated."""

from __future__ import annotations

import dataclasses
import itertools
import json
import re

import numpy as np
import pytest
from pemviz.cli import main
from pemviz.pem.store import load_pem
from pemviz.scenarios.braking.batched import replay
from pemviz.scenarios.braking.lookahead import log_exceedance_after, start_steps
from pemviz.scenarios.braking.simulator import BrakingParams
from scipy.special import log_expit, logsumexp


def brute_force(p: BrakingParams, logit_at_gap, prefix: np.ndarray, level: float) -> float:
    """log P(min gap < level | the detections ``prefix``), over every detection sequence of the remaining steps,
    each replayed from the start (:func:`replay`, the batched simulator): independent of the enumeration's pruning."""
    k = p.n_steps - prefix.size
    suffixes = np.array(list(itertools.product([False, True], repeat=k)), dtype=bool)
    seqs = np.concatenate([np.tile(prefix, (suffixes.shape[0], 1)), suffixes], axis=1)
    gaps = replay(p, seqs)[:, :, 0]
    logit = logit_at_gap(gaps[:, prefix.size :])
    log_prob = np.where(suffixes, log_expit(logit), log_expit(-logit)).sum(axis=1)
    fails = gaps.min(axis=1) < level
    return float(logsumexp(log_prob[fails])) if fails.any() else -np.inf


def short_scene_against_brute_force(level: float, **changes) -> tuple[np.ndarray, np.ndarray]:
    """The enumeration's and the brute force's log P [6] on a 64-step scene (``changes`` to its parameters): the ego
    reaches the lead at about step 61 when it never detects it; from step 50 (gap 4.6 m) every one of the 2^14
    sequences is replayed. Prefixes with detections shift the phase that contact needs."""
    base = BrakingParams()
    p = dataclasses.replace(base, n_steps=64, lead_speed_profile_mps=base.lead_speed_profile_mps[:64], **changes)
    logit = load_pem().logit_at_gap
    rng = np.random.default_rng(7)
    prefixes = [np.zeros(50, bool)] + [np.concatenate([np.zeros(36, bool), rng.random(14) < 0.3]) for _ in range(5)]
    detected = np.zeros((len(prefixes), p.n_steps), dtype=bool)
    for i, pre in enumerate(prefixes):
        detected[i, :50] = pre
    start = np.full(len(prefixes), 50)
    got = log_exceedance_after(p, logit, detected, start, level)
    want = np.array([brute_force(p, logit, pre, level) for pre in prefixes])
    assert np.array_equal(np.isinf(got), np.isinf(want)), (got, want)
    return got, want


@pytest.mark.parametrize("level", [0.0, 0.5, 1.0, 2.0])
def test_the_enumeration_equals_every_detection_sequence_of_a_short_scene(level):
    got, want = short_scene_against_brute_force(level)
    finite = np.isfinite(want)
    assert finite.sum() >= 2  # the check compares real probabilities
    np.testing.assert_allclose(got[finite], want[finite], rtol=0, atol=1e-9)  # nats


@pytest.mark.parametrize(
    "level, changes, n_finite",
    [
        (0.0, {"actuation_lag_steps": 0}, 5),  # each detection's brake at once: the two children part at once
        (1.0, {"actuation_lag_steps": 0}, 6),
        (0.5, {"latched_brake": True}, 1),  # once braking, always: only the prefix without detections can fail
        (0.5, {"actuation_lag_steps": 0, "latched_brake": True}, 1),
        (0.5, {"braking_distance_m": 4.0}, 6),  # above 4 m a detection changes nothing: one child, not two
    ],
)
def test_the_enumeration_of_other_controllers_equals_every_detection_sequence(level, changes, n_finite):
    # the enumeration shares the controller's commands between the branches of one detection only where the
    # one-step actuation lag makes them share the next state; these controllers take the other paths
    got, want = short_scene_against_brute_force(level, **changes)
    finite = np.isfinite(want)
    assert finite.sum() == n_finite
    np.testing.assert_allclose(got[finite], want[finite], rtol=0, atol=1e-9)  # nats


def test_start_steps_are_the_first_below_the_gap():
    gaps = np.array([[9.0, 7.0, 5.9, 3.0], [9.0, 8.0, 7.0, 6.5], [5.0, 4.0, 3.0, 2.0]])
    assert start_steps(gaps, 6.0).tolist() == [2, 4, 0]


def test_a_run_that_targets_contact_is_right_and_its_file_re_estimates_to_it(tmp_path, capsys):
    """`pemviz run --margin 0 --seed 0 --plain-fallback 0` at the default budget: within x1.5 of the exact 8.058e-33
    with the exact answer inside its interval, capped at doubtful; before the look-ahead the same run gave 3.9e-33 (ESS
    1.4). (Without the flag, plain Monte Carlo follows the doubtful stages: a million rollouts with no failure at
    8e-33, the same answer.)"""
    out = tmp_path / "contact.parquet"
    argv = ["run", "--margin", "0", "--seed", "0", "--plain-fallback", "0", "--no-record", "--save-rollouts", str(out)]
    assert main([*argv, "--json", str(tmp_path / "result.json")]) == 0  # in this process: the command, not its start
    stdout = capsys.readouterr().out
    doc = json.loads((tmp_path / "result.json").read_text())
    log_mu, (lo, hi), exact = doc["estimate"]["log_p"], doc["estimate"]["log_ci95"], doc["exact"]["log_p"]
    assert exact == pytest.approx(np.log(8.0581e-33), abs=1e-4)
    assert doc["estimate"]["verdict"] == "doubtful"
    # a doubtful run backs no interval: its 95 % lower bound alone, which holds (no upper end)
    assert doc["estimate"]["interval"] == "lower_bound95" and hi is None
    assert abs(log_mu - exact) < np.log(1.5) and lo <= exact and lo == doc["estimate"]["log_lower_bound95"]
    # no stage's row claims more: stage 5 of seed 1 said reliable at x0.68 with the exact answer outside its interval
    rows = [ln for ln in stdout.splitlines() if re.match(r"\s+\d+\s+(pretrain|ce|final)\s", ln)]
    assert len(rows) == 12 and not any(re.search(r"\sreliable\s+[0-9.]+$", ln) for ln in rows), rows
    assert "look-ahead: each rollout weighs up to the state" in stdout
    assert main(["estimate", str(out), "--no-record"]) == 0
    line = next(ln for ln in capsys.readouterr().out.splitlines() if ln.startswith("mu_hat = ") and "CI" in ln)
    run_line = next(ln for ln in stdout.splitlines() if ln.startswith("mu_hat = ") and "CI" in ln)
    assert line.split(",")[0] == run_line.split(",")[0]


def test_rollouts_of_another_scene_are_refused():
    p = BrakingParams(crash_gap_m=0.0)
    detected = np.zeros((2, p.n_steps), dtype=bool)
    start = np.array([52, p.n_steps])
    gap = replay(p, detected)[:, :, 0]
    logit = load_pem().logit_at_gap
    log_exceedance_after(p, logit, detected, start, 0.0, observed_gap_m=gap[[0, 1], [52, 99]])  # its own: accepted
    with pytest.raises(ValueError, match="not of this scene's parameters"):
        log_exceedance_after(p, logit, detected, start, 0.0, observed_gap_m=gap[[0, 1], [52, 99]] + 0.01)
