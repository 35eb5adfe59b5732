"""The cut-in over an operating design domain of its start gap: the batched twin's per-rollout gaps against the
highway-env simulator started at each gap, the translation check that refuses a support, the problem's rollouts, and
the run's defaults."""

from __future__ import annotations

import argparse
import dataclasses

import numpy as np
import pytest
from pemviz.core.odd import ODD, parse_distribution
from pemviz.scenarios.cut_in.batched import BatchedCutIn, translation_error
from pemviz.scenarios.cut_in.scenario import OBSERVATION_NAMES, CutInParams

from .test_cut_in_batched import highway_env_replay, random_inputs

P = CutInParams()
GAPS = np.array([19.5, 20.0, 20.73, 21.5])


def test_per_rollout_gaps_match_highway_env_started_at_each_gap():
    """Rollout i of a batch with ``gap_shift_m`` = its gap - 20 m gives the observations and object rows of the
    highway-env simulator started at that gap (to 1e-9 m: the two round the same motion differently)."""
    n_steps = 60
    detected, noise = random_inputs(P, len(GAPS), seed=3)
    detected, noise = detected[:, :n_steps], noise[:, :n_steps]
    sim = BatchedCutIn(P, len(GAPS), gap_shift_m=GAPS - P.cut_in_gap_m)
    # highway-env started at each gap, its whole run on rollout i's inputs (step t's rows are recorded before step t)
    refs = [
        highway_env_replay(dataclasses.replace(P, cut_in_gap_m=float(gap)), detected[i : i + 1], noise[i : i + 1])
        for i, gap in enumerate(GAPS)
    ]
    for t in range(n_steps):
        if t == 30:  # a snapshot keeps the per-rollout gaps' state; restoring it changes nothing
            sim.restore(sim.snapshot())
        obs, objs = sim.observation(), sim.objects()
        for i, (gap, (ref_obs, ref_objs)) in enumerate(zip(GAPS, refs, strict=True)):
            np.testing.assert_allclose(obs[i], ref_obs[0, t], rtol=0, atol=1e-9, err_msg=f"gap {gap}, step {t}")
            np.testing.assert_allclose(objs[i], ref_objs[0, t], rtol=0, atol=1e-9, err_msg=f"gap {gap}, step {t}")
        sim.step(detected[:, t], noise[:, t])


def test_no_shift_is_the_plain_twin_bit_for_bit():
    detected, noise = random_inputs(P, 6, seed=5)
    a, b = BatchedCutIn(P, 6), BatchedCutIn(P, 6, gap_shift_m=np.zeros(6))
    for t in range(P.n_steps):
        assert np.array_equal(a.observation(), b.observation()) and np.array_equal(a.objects(), b.objects())
        a.step(detected[:, t], noise[:, t])
        b.step(detected[:, t], noise[:, t])


def test_translation_error_is_rounding_near_the_setting_and_infinite_where_the_traffic_changes():
    assert translation_error(P, 21.5) < 1e-12
    assert translation_error(P, 15.0) < 1e-12
    assert translation_error(P, 40.0) == np.inf  # the cut-in vehicle now meets other traffic: not a translation


def test_bad_shift_is_refused():
    with pytest.raises(ValueError, match=r"gap_shift_m must be finite float64 \[3\]"):
        BatchedCutIn(P, 3, gap_shift_m=np.zeros(2))
    with pytest.raises(ValueError, match="gap_shift_m must be finite"):
        BatchedCutIn(P, 2, gap_shift_m=np.array([0.0, np.nan]))


def _problem(text: str):
    from pemviz.config import ExperimentConfig
    from pemviz.scenarios.cut_in.odd import cut_in_odd_problem

    odd = ODD((("cut_in_gap_m", parse_distribution(text)),))
    return cut_in_odd_problem(ExperimentConfig.of(scenario="cut-in", method="mc"), P, odd)


def test_a_support_where_the_traffic_is_not_moved_is_refused_in_one_line():
    said = r"cut_in_gap_m~uniform\(20, 40\): from a start gap of 35 m the traffic is not the one from 20 m"
    with pytest.raises(ValueError, match=said) as info:
        _problem("uniform(20, 40)")
    assert "\n" not in str(info.value)


def test_rollouts_carry_their_gaps_and_start_where_they_say():
    problem = _problem("uniform(19.5, 21.5)")
    assert problem.tilt is None and problem.reference is None and problem.odd is not None
    batch = problem.simulate(50, problem.target, problem.target, np.random.default_rng(0))
    names = tuple(batch.observation_names)
    gaps = batch.observations[:, :, names.index("cut_in_gap_m")]
    assert np.all((gaps >= 19.5) & (gaps <= 21.5)) and np.all(gaps == gaps[:, :1])  # constant in time
    assert np.unique(gaps[:, 0]).size == 50
    assert names[: len(OBSERVATION_NAMES)] == OBSERVATION_NAMES


def _args(**kw: object) -> argparse.Namespace:
    from pemviz.cli import build_parser

    return build_parser().parse_args(["run", *[str(x) for pair in kw.items() for x in pair]])


@pytest.mark.parametrize(
    "param, method, n",
    [("cut_in_gap_m~uniform(19.5, 21.5)", "mc", 100_000), ("cut_in_gap_m=21", "tilt", 7_280)],
)
def test_over_an_odd_the_cut_in_runs_plain_monte_carlo_by_default(param: str, method: str, n: int):
    from pemviz.commands.run import config_from_args

    cfg = config_from_args(_args(**{"--scenario": "cut-in", "--param": param}))
    assert (cfg.method, cfg.n_per_stage) == (method, n)
    cfg = config_from_args(_args(**{"--scenario": "cut-in", "--param": param, "--method": "adaptive"}))
    assert cfg.method == "adaptive"
