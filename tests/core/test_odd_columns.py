"""Over an ODD each drawn parameter is added to the observations as a column named after it: a simulator that
already reports a column of that name (a user's AEB reporting its current ``speed_mps`` while the ODD draws its start
``speed_mps``) is refused in one line, instead of two columns of one name that the map and the rollout file read."""

from __future__ import annotations

import numpy as np
import pytest
from pemviz.core.odd_rollouts import WithParameters


class _Batched:
    observation_names = ("gap_m", "speed_mps")

    def observation(self):
        return np.array([[30.0, 17.0], [30.0, 16.0]])


def test_a_parameter_named_as_an_observation_column_is_refused():
    with pytest.raises(ValueError, match=r"drawn parameter 'speed_mps' .* already reports a column 'speed_mps'"):
        WithParameters(_Batched(), np.array([[17.0], [16.0]]), ("speed_mps",))


def test_a_parameter_of_its_own_name_ends_the_observations():
    sim = WithParameters(_Batched(), np.array([[17.0], [16.0]]), ("speed0_mps",))
    assert sim.observation_names == ("gap_m", "speed_mps", "speed0_mps")
    np.testing.assert_array_equal(sim.observation(), [[30.0, 17.0, 17.0], [30.0, 16.0, 16.0]])
