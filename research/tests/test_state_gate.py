"""The gated state proposal's fit rules (``research/state_gate.py``) against independent truths: the tempering
exponent of two weights in closed form, and the gate, logit shift and error scale that generated synthetic events."""

from __future__ import annotations

import math

import numpy as np
from pemviz.core.diagnostics import effective_sample_size

from conftest import REPO, load_script

study = load_script(REPO / "research" / "state_gate.py")


def test_tempering_of_two_weights_is_the_closed_form_exponent():
    # w = (1, e^-c): Kish's ESS of w^beta is (1 + u)^2 / (1 + u^2), u = e^(-beta c); ESS 1.5 at u^2 - 4 u + 1 = 0
    c = 10.0
    beta = study.tempering(np.array([0.0, -c]), 1.5)
    assert abs(beta - (-math.log(2.0 - math.sqrt(3.0)) / c)) < 1e-5
    assert study.tempering(np.array([0.0, -c]), 1.0) == 1.0  # the weights themselves reach ESS 1
    assert study.tempering(np.array([0.0, -c]), 5.0) < 1e-5  # at most the two weights' own count: flat weights


def test_tempered_weights_reach_the_asked_ess():
    lw = np.random.default_rng(3).standard_normal(200) * 8.0
    beta = study.tempering(lw, 20.0)
    assert 0.0 < beta < 1.0
    assert abs(effective_sample_size(beta * lw) - 20.0) < 0.01


def _events(n: int, seed: int):
    """Rows whose column 1 is uniform on [0, 1); inside [0.4, 0.6) the detection's logit is the PEM's (3) minus 2
    and the first error component's scale 5 times the PEM's (standard normal errors)."""
    rng = np.random.default_rng(seed)
    rows = np.column_stack([np.full(n, 7.0), rng.random(n), rng.standard_normal(n)])
    inside = (rows[:, 1] >= 0.4) & (rows[:, 1] < 0.6)
    logit_p = np.full(n, 3.0)
    detected = rng.random(n) < 1.0 / (1.0 + np.exp(-(logit_p - 2.0 * inside)))
    z = rng.standard_normal((n, 2))
    z[inside, 0] *= 5.0
    return rows, detected, logit_p, z, inside


def test_the_gate_shift_and_scale_of_synthetic_events_are_found():
    rows, detected, logit_p, z, inside = _events(40_000, 5)
    gate = study.fit_error_gate(rows, detected, logit_p, z, np.full(len(rows), 1.0 / len(rows)), "normal", None, 1)
    assert gate is not None and gate.bounds[0][0] == 1
    _, lo, hi = gate.bounds[0]
    assert abs(lo - 0.4) < 0.02 and abs(hi - 0.6) < 0.02
    assert abs(gate.logit_shift + 2.0) <= 0.25  # the grid's step
    assert abs(math.exp(gate.log_scale[0]) - 5.0) <= 0.5 and gate.log_scale[1] == 0.0
    a, b = gate.shift(rows)
    assert not a.any() and np.array_equal(b[:, 0] > 0, gate.inside(rows))
    assert (gate.inside(rows) == inside).mean() > 0.98


def test_events_like_the_pem_s_give_no_gate():
    rng = np.random.default_rng(6)
    n = 5_000
    rows, logit_p = rng.random((n, 2)), np.full(n, 3.0)
    detected = rng.random(n) < 1.0 / (1.0 + np.exp(-logit_p))
    z = rng.standard_t(3.0, (n, 2))
    gate = study.fit_error_gate(rows, detected, logit_p, z, np.full(n, 1.0 / n), "student-t", np.array([3.0, 3.0]))
    assert gate is None


def test_the_gated_proposal_weighs_its_rollouts_exactly():
    """Rollouts of the crossing drawn with a fixed gate (pedestrians 10-14 m away: detections' logit - 0.5, range
    errors' scale x 1.2): their mean importance weight is 1 within 4 standard errors, and the gate moved them."""
    gate = study.ErrorGate(((0, 10.0, 14.0),), -0.5, np.array([math.log(1.2), 0.0]), 0.0)
    restore = study.install(True, 1, None, True, gate)
    try:
        seen, _, _ = study.draw(0, ["--k", "1", "--n", "50", "--n-final", "1500"])
    finally:
        restore()
    from pemviz.estimators.state_glm import StateGLM

    assert "noise_shift_of" not in StateGLM.__dict__  # undone
    w = np.exp(np.asarray(seen[-1].log_weight))
    assert (np.abs(np.log(w)) > 1e-9).mean() > 0.9  # almost every rollout's weight moved by the gate
    assert abs(w.mean() - 1.0) <= 4.0 * w.std() / np.sqrt(w.size), (w.mean(), w.std())


def test_a_mixture_of_gates_weighs_its_rollouts_exactly():
    """Rollouts of the crossing drawn from the PEM (a tenth) and two gates (pedestrians 10-14 m and 20-26 m away):
    their mixture's importance weights average to 1 within 4 standard errors."""
    gates = (
        study.ErrorGate(((0, 10.0, 14.0),), -0.5, np.array([math.log(1.2), 0.0]), 0.0),
        study.ErrorGate(((0, 20.0, 26.0),), 0.5, np.array([0.0, math.log(1.3)]), 0.0),
    )
    restore = study.install(True, 1, None, True, gates[0], gates)
    try:
        seen, _, _ = study.draw(1, ["--k", "1", "--n", "50", "--n-final", "1500"])
    finally:
        restore()
    w = np.exp(np.asarray(seen[-1].log_weight))
    assert abs(w.mean() - 1.0) <= 4.0 * w.std() / np.sqrt(w.size), (w.mean(), w.std())
    assert w.std() > 0.05  # the gates moved the weights
