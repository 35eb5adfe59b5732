"""The uniform-space proposals of ``research/uniform_space_proposals.py`` weigh their rollouts exactly: the mean
importance weight of rollouts drawn from a strongly tilted proposal is 1 (E_h[1 / h] = 1 over the unit cube), for the
product and the mixture family, within 4 standard errors."""

from __future__ import annotations

import numpy as np
import pytest

from conftest import REPO, load_script

study = load_script(REPO / "research" / "uniform_space_proposals.py")


@pytest.mark.parametrize("family", ["product", "mixture"])
def test_the_weights_of_a_tilted_proposal_average_to_one(family: str) -> None:
    problem, make, n_steps, _ = study.crossing_setup()
    proposal = study.UniformProposal(problem, make, n_steps, family, eps=0.1)
    rng = np.random.default_rng(0)
    fake = rng.integers(0, study.N_BINS, (60, proposal.n_coords))  # "failures": random bins ...
    fake[:, 40:52] = study.N_BINS - 1  # ... and twelve coordinates always in their top bin (a strong tilt)
    assert proposal.fit(fake, np.zeros(60)) >= 1
    _, bins, log_w = proposal.draw(3000, np.random.default_rng(1))
    assert (bins[:, 40:52] == study.N_BINS - 1).mean() > 0.05  # the draws follow the tilt (uniform: 0.02)
    w = np.exp(log_w)
    assert abs(w.mean() - 1.0) <= 4.0 * w.std() / np.sqrt(w.size), (w.mean(), w.std())
