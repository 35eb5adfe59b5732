"""research/cut_in_event_proposals.py: its proposals over the uniforms are densities whose importance weights are
exact, the premise of every figure of that study (research/cut-in-notes.md, "What 5,000 simulations can and cannot
do")."""

from __future__ import annotations

import sys

import numpy as np
import pytest

from conftest import REPO, load_script

SHAPE = (4, 2)  # T steps, M objects


@pytest.fixture(scope="module")
def study():
    yield load_script(REPO / "research" / "cut_in_event_proposals.py")
    del sys.modules["cut_in_event_proposals"]


def proposals(study):
    rng = np.random.default_rng(3)
    table = rng.uniform(0.01, 1.0, size=(*SHAPE, 3, study.NB)) * (study.WIDTH > 0)
    events = study.Events(table, (0.1, 0.6, 0.3))
    rho = np.zeros_like(table)
    rho[1:3, 0] = 0.05 * table[1:3, 0]  # a few coordinates inflated, each tail rate <= 0.4
    product = study.Product(rho)
    return {"events": events, "product": product, "both": study.Mixed(product, events)}


@pytest.mark.parametrize("family", ["events", "product", "both"])
def test_each_proposal_weighs_its_draws_so_that_tail_events_keep_their_pem_probability(study, family):
    """E_q[1 / q] = 1 and E_q[1{u in bin} / q] = the bin's width under the PEMs (the uniforms' density is 1), for
    every coordinate the proposal inflates, within 5 standard errors of 400,000 draws."""
    q = proposals(study)[family]
    u = q.sample(400_000, SHAPE, np.random.default_rng(11))
    assert u.shape == (400_000, *SHAPE, 3) and (u >= 0).all() and (u < 1).all()
    w = np.exp(-q.log_density(u))
    assert abs(w.mean() - 1.0) < 5 * w.std() / np.sqrt(w.size)
    bins = study.bin_index(u)
    checked = 0
    for t, m, c in [(1, 0, 1), (2, 0, 0), (1, 0, 2)]:
        for b in np.flatnonzero(study.WIDTH[c] > 0):
            hit = w * (bins[:, t, m, c] == b)
            if (bins[:, t, m, c] == b).sum() < 200:  # too rare under q to test at this size
                continue
            assert abs(hit.mean() - study.WIDTH[c, b]) < 5 * hit.std() / np.sqrt(w.size) + 1e-12, (t, m, c, b)
            checked += 1
    assert checked >= 10


def test_a_forced_event_lies_in_its_bin_and_is_counted_once(study):
    """A proposal that forces one event: every draw holds it, and its weight is 1 / (beta0 + beta1 pi / width)."""
    table = np.zeros((*SHAPE, 3, study.NB))
    table[2, 1, 1, 6] = 1.0  # step 2, object 1, range error in (0.9999, 0.99999)
    q = study.Events(table, (0.2, 0.8, 0.0))
    u = q.sample(2000, SHAPE, np.random.default_rng(5))
    held = study.bin_index(u)[:, 2, 1, 1] == 6
    assert 0.75 < held.mean() < 0.85  # 0.8 forced, and the PEMs' share lands there with probability 9e-5
    w = np.exp(-q.log_density(u))
    assert study.WIDTH[1, 6] == pytest.approx(9e-5, rel=1e-12)
    np.testing.assert_allclose(w[held], 1.0 / (0.2 + 0.8 / 9e-5), rtol=1e-9)
    np.testing.assert_allclose(w[~held], 1.0 / 0.2, rtol=1e-12)
