"""The gate mixture's estimate stage (``research/gate_mixture.py``) against independent truths: each rollout's log
weight is the direct likelihood ratio of the PEM against the defensive mixture of the PEM and the gates, computed
from the gates' definition; the weights average to 1 under the mixture; and the gates fitted to splitting's failures
of the crossing make failures more frequent than the PEM does."""

from __future__ import annotations

import math

import numpy as np
from pemviz.core.detector_noise import standard_log_density
from pemviz.core.features import with_state
from pemviz.estimators.base import weighted_steps_mask
from pemviz.scenarios.crossing.scene import OBJECT_NAMES
from scipy.special import log_expit, logsumexp

from conftest import REPO, load_script

study = load_script(REPO / "research" / "gate_mixture.py")
gate = study.state_gate

GATES = (
    gate.ErrorGate(((0, 10.0, 14.0),), -0.5, np.array([math.log(1.2), 0.0]), 0.0),
    gate.ErrorGate(((0, 20.0, 26.0), (1, -np.inf, 1.0)), 0.5, np.array([0.0, math.log(1.3)]), 0.0),
    gate.ErrorGate(((0, 15.0, 30.0),), -2.0, np.array([math.log(2.0), 0.0]), 0.0),
)


def _direct_log_weight(pb, batch, gates, share: float, n: int) -> np.ndarray:
    """log p(x) - log(s' p(x) + sum_j n_j / n q_j(x)) [N] from the gates' definition: inside gate j (and the window,
    at the steps the weights count) q_j's detection logit is the PEM's plus c_j and its errors' scale exp(b_j) times
    the PEM's; s' = round(s n) / n and the n_j split the rest evenly, as the rollouts were drawn."""
    b = with_state(batch, pb.features(batch, None))
    rows = np.asarray(b.object_rows, dtype=np.float64)
    det = np.asarray(b.detected, bool)
    flat = rows.reshape(-1, rows.shape[-1])
    own = np.ascontiguousarray(flat[:, : len(OBJECT_NAMES)])
    t = pb.target
    logit = np.asarray(t.detect_logit(own), dtype=np.float64).reshape(det.shape)
    loc, log_scale = t.noise_params(own)
    noise = np.asarray(b.noise, dtype=np.float64)
    z = ((noise.reshape(-1, noise.shape[-1]) - loc) * np.exp(-log_scale)).reshape(noise.shape)
    counted = weighted_steps_mask(pb, batch, True)[:, :, None] & (rows[..., 0] < pb.window) & np.isfinite(logit)
    finite = np.where(np.isfinite(logit), logit, 0.0)
    sign = np.where(det, 1.0, -1.0)
    n_p = int(round(share * n))
    sizes = np.diff(np.round(np.linspace(0, n - n_p, len(gates) + 1)).astype(int))
    terms = [np.full(batch.n, math.log(n_p / n))]
    for g, m in zip(gates, sizes, strict=True):
        inside = counted & g.inside(flat).reshape(counted.shape)
        d = np.where(inside, log_expit(sign * (finite + g.logit_shift)) - log_expit(sign * finite), 0.0)
        wide = standard_log_density(t.noise_family, t.noise_df, z * np.exp(-g.log_scale)) - g.log_scale
        e = (wide - standard_log_density(t.noise_family, t.noise_df, z)).sum(-1)
        terms.append(math.log(m / n) + (d + np.where(inside & det, e, 0.0)).sum(axis=(1, 2)))
    return -logsumexp(np.vstack(terms), axis=0)


def test_each_weight_is_the_direct_likelihood_ratio_of_the_pem_against_the_mixture():
    pb = study.problem([])
    restore = gate.install(True, 2, None, True, GATES[0], GATES)
    try:
        seen, _, _ = gate.draw(3, ["--state-share", "0.2", "--k", "1", "--n", "20", "--n-final", "400"])
    finally:
        restore()
    ev = seen[-1]
    got = np.asarray(ev.log_weight, dtype=np.float64)
    want = _direct_log_weight(pb, ev.batch, GATES, 0.2, 400)
    assert got.dtype == np.float64 and np.max(np.abs(got - want)) < 1e-10
    assert np.std(want) > 0.05 and np.max(want) <= -math.log(0.2) + 1e-12  # moved, and bounded by 1 / s


def test_the_estimate_stage_counts_its_rollouts_and_its_verdict_is_not_capped():
    final, simulated, ev = study.estimate(4, GATES, [], 0.1, 20, 1500)
    assert simulated == 100 + 20 + 1500  # pretraining, the one CE stage, the final batch
    e = final.estimate
    assert "never fitted to a failure" not in e.reason
    from pemviz.estimators.state import StateCrossEntropy

    assert "verdict_cap" not in StateCrossEntropy.__dict__  # the patch undone
    assert final.n_simulations == simulated and ev.kind == "final" and ev.batch.n == 1500


def test_the_mixture_weights_have_mean_one_under_the_mixture():
    restore = gate.install(True, 2, None, True, GATES[0], GATES)
    try:
        seen, _, _ = gate.draw(5, ["--state-share", "0.1", "--k", "1", "--n", "20", "--n-final", "2000"])
    finally:
        restore()
    w = np.exp(np.asarray(seen[-1].log_weight, dtype=np.float64))
    assert abs(w.mean() - 1.0) <= 4.0 * w.std() / math.sqrt(w.size), (w.mean(), w.std())
    assert w.max() <= 10.0 + 1e-9  # at most 1 / s


def test_gates_fitted_to_splitting_s_failures_make_failures_more_frequent():
    """A pilot of 60 particles finds failures; the gates fitted to them, drawn from alone, fail more often than the
    PEM's 3e-4 (the reference) by far."""
    pb = study.problem([])
    pilot = study.pilot(pb, 11, 60, 6)
    assert pilot.rows.shape[0] >= 20 and pilot.families >= 1
    assert pilot.cost > 60 and pilot.rows.shape[:3] == pilot.detected.shape
    gates = gate.mixture_of_gates(pb, pilot.rows, pilot.detected, pilot.z, 2, 2)
    assert gates
    # failures of weight 0 do not count: weights on two failures fit what those two alone fit
    w = np.zeros(pilot.rows.shape[0])
    w[[0, -1]] = (0.25, 0.75)
    two = (pilot.rows[[0, -1]], pilot.detected[[0, -1]], pilot.z[[0, -1]])
    alone = gate.mixture_of_gates(pb, *two, 2, 1, weights=np.array([0.25, 0.75]), given=gates)
    got = gate.mixture_of_gates(pb, pilot.rows, pilot.detected, pilot.z, 2, 1, weights=w, given=gates)
    assert alone and repr(got) == repr(alone)
    restore = gate.install(True, 2, None, True, gates[0], gates)
    try:
        seen, _, _ = gate.draw(6, ["--state-share", "0.1", "--k", "1", "--n", "20", "--n-final", "500"])
    finally:
        restore()
    assert np.asarray(seen[-1].failed).mean() > 0.003  # ten times the PEM's rate at least
