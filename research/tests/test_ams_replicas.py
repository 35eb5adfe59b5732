"""Splitting from independent replicas (research/ams_replicas.py): the study's intervals by hand (pemviz's own, its
streams, unbiasedness, coverage and verdict: tests/estimators/test_ams_replicas.py)."""

from __future__ import annotations

import numpy as np

from conftest import REPO, load_script

study = load_script(REPO / "research" / "ams_replicas.py")


def test_intervals_by_hand():
    """p = (1, 2, 3, 4): mean 2.5, s = 1.2910, se = 0.6455, t_{3, 0.975} = 3.1824: Student-t [0.4458, 4.5542];
    the log-scale one 2.5 exp(-+ 3.1824 x 0.6455 / 2.5) = [1.0992, 5.6859]."""
    iv = study.intervals(np.array([1.0, 2.0, 3.0, 4.0]))
    np.testing.assert_allclose(iv["t"], (0.4458, 4.5542), atol=2e-4)
    np.testing.assert_allclose(iv["log-t"], (1.0992, 5.6859), atol=2e-4)
    lo, hi = iv["boot-t"]
    assert lo < 2.5 < hi
