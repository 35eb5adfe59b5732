"""The velocity prior of a new track measured on a stopped car (benchmarks/track_prior.py, the guide's *A new track
on a stopped car*): a prior sure of the ego's speed shows it moving for over a second; the library's default std does
not, and leaves a car that moves with the ego unbiased."""

from __future__ import annotations

import numpy as np
from pemviz.stack.tracker import TrackerParams

from conftest import REPO, load_script

prior = load_script(REPO / "benchmarks" / "track_prior.py")
N = 400


def median_estimates(std_mps: float, speed_mps: float) -> np.ndarray:
    """The median velocity estimate (m/s) after each 0.1 s step, [20], ego prior, seed 0."""
    return np.nanmedian(prior.velocity_errors(prior.EGO_MPS, std_mps, speed_mps, N, 0), axis=1) + speed_mps


def test_a_prior_sure_of_the_ego_s_speed_shows_a_stopped_car_moving_and_the_default_does_not():
    sure = median_estimates(5.0, 0.0)
    assert sure[4] > 13.0 and sure[9] > 4.0  # 0.5 s and 1.0 s after first seen: the symptom the guide quotes
    assert prior.settling_time(np.abs(sure)) > 1.0
    default = median_estimates(TrackerParams().init_speed_std_x_mps, 0.0)
    assert default[4] < 10.0 and abs(default[9]) < 2.0
    assert prior.settling_time(np.abs(default)) <= 1.2
    moving = median_estimates(TrackerParams().init_speed_std_x_mps, prior.EGO_MPS)
    assert np.all(np.abs(moving[2:] - prior.EGO_MPS) < 1.5)  # no bias on a car that moves with the ego


def test_settling_time_is_the_first_step_from_which_the_error_stays_within_tolerance():
    steps = prior.STEPS
    err = np.full(steps, 5.0)
    err[7:] = 1.0
    err[3] = 0.0  # within once, then off again: not settled there
    assert prior.settling_time(err) == 7 * prior.DT
    assert prior.settling_time(np.zeros(steps)) == 0.0 and prior.settling_time(np.full(steps, 3.0)) == np.inf
