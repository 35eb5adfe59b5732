"""The estimator, the threshold and the cross-entropy update against closed-form answers."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from pemviz.core.detectors import ConstantDetector, action_log_prob, defensive_logit
from pemviz.core.estimate import estimate, format_probability
from pemviz.core.sampling import (
    DISTINCT_FROM,
    Proposal,
    ProposalFormatError,
    StateProposal,
    fit_proposal,
    load_proposal,
    save_proposal,
)
from pemviz.estimators.base import quantile_threshold
from pemviz.estimators.ce_fit import FitOptions, ce_update, pretrain_proposal
from pemviz.scenarios import simulate


def test_estimate_equals_hand_computed_mean_of_failure_weights():
    log_w = np.log(np.array([1e-20, 3e-20, 5e-1, 7e-30]))
    failed = np.array([True, True, False, False])
    log_p = np.array([-40.0, -44.0, -1.0, -3.0])
    e = estimate(log_w, failed, log_p)
    assert e.n == 4 and e.n_failures == 2
    assert e.mu_hat == pytest.approx((1e-20 + 3e-20) / 4, rel=1e-12)
    assert e.ess == pytest.approx((4e-20) ** 2 / (1e-40 + 9e-40), rel=1e-12)  # 1.6
    assert e.nll_mean == pytest.approx(42.0)
    assert e.nll_lme == pytest.approx(-math.log((math.exp(-40) + math.exp(-44)) / 2), rel=1e-12)


def test_estimate_stays_exact_far_below_float64_range():
    e = estimate(np.array([-2000.0, -2001.0]), np.array([True, True]), np.array([-1.0, -1.0]))
    assert e.log_mu_hat == pytest.approx(-2000.0 + math.log(1 + math.exp(-1)) - math.log(2), abs=1e-12)
    assert e.mu_hat == 0.0  # underflows as a float, but the log is exact
    assert format_probability(e.log_mu_hat).endswith("e-869")


def test_estimate_without_failures_is_zero_with_zero_ess():
    e = estimate(np.zeros(5), np.zeros(5, bool), np.zeros(5))
    assert e.log_mu_hat == -math.inf and e.mu_hat == 0.0 and e.ess == 0.0 and math.isnan(e.nll_mean)


def test_quantile_threshold_is_the_fifth_smallest_of_100_at_sigma_095():
    r = np.random.default_rng(0).permutation(np.arange(100, dtype=float) + 1.0)
    assert quantile_threshold(r, 0.95) == 5.0
    assert quantile_threshold(r, 0.9) == 10.0
    assert quantile_threshold(r - 50.0, 0.95) == 0.0  # floored at the failure threshold


def test_format_probability_rounds_mantissa_and_exponent():
    assert format_probability(math.log(5.02e-15)) == "5.020e-15"
    assert format_probability(math.log(9.9996e-3)) == "1.000e-02"
    assert format_probability(-math.inf) == "0"


def test_action_log_prob_is_logsigmoid_of_plus_minus_logit():
    logit = np.array([0.0, 5.0, -30.0, 40.0])
    log_p_detect = -np.log1p(np.exp(-logit))  # exact also where p rounds to 1
    np.testing.assert_allclose(action_log_prob(logit, np.ones(4, bool)), log_p_detect, rtol=1e-12)
    p = 1 / (1 + np.exp(-logit[:3]))
    np.testing.assert_allclose(action_log_prob(logit[:3], np.zeros(3, bool)), np.log1p(-p), rtol=1e-9)
    assert action_log_prob(np.array([40.0]), np.array([False]))[0] == pytest.approx(-40.0, abs=1e-12)


class MissCounter:
    """Test-only simulator: the observation is the number of misses so far; no dynamics."""

    observation_names = ("misses",)

    def __init__(self) -> None:
        self.misses = 0

    def reset(self) -> None:
        self.misses = 0

    def observation(self) -> np.ndarray:
        return np.array([float(self.misses)])

    def step(self, detected: bool) -> None:
        self.misses += 0 if detected else 1


def test_importance_sampling_recovers_binomial_tail_probability():
    # 11 steps, failure = at least 6 misses in the first 10 actions (the 11th acts on nothing).
    p = 0.9
    exact = sum(math.comb(10, k) * (1 - p) ** k * p ** (10 - k) for k in range(6, 11))  # 1.47e-4
    target, sampler = ConstantDetector(p), ConstantDetector(0.4)
    batch = simulate(MissCounter, 8000, sampler, target, np.random.default_rng(0), 11)
    failed = batch.observations[:, -1, 0] >= 6
    e = estimate(batch.log_weight(), failed, batch.log_p[:, :10].sum(axis=1))
    assert e.n_failures > 2000
    assert e.mu_hat == pytest.approx(exact, rel=0.06)


def test_pretraining_fits_the_detection_rate():
    torch.manual_seed(0)
    gaps = np.tile(np.linspace(0, 12, 40), (50, 1))
    detected = np.arange(50)[:, None] < 45 + np.zeros((1, 40))  # exactly 90 % at every gap
    q = Proposal()
    pretrain_proposal(q, gaps, detected, FitOptions(800, 1e-2))
    np.testing.assert_allclose(q.curve(np.array([1.0, 6.0, 11.0])), 0.9, atol=0.01)


@pytest.mark.parametrize("weights", ["frozen", "recomputed"])
def test_ce_update_moves_the_proposal_to_the_elites_miss_rate_inside_10m(weights):
    torch.manual_seed(0)
    rng = np.random.default_rng(1)
    gaps = np.tile(np.linspace(12, 0.5, 40), (60, 1))
    inside = gaps < 10
    detected = np.where(inside, rng.random(gaps.shape) < 0.2, rng.random(gaps.shape) < 0.95)
    log_q = np.log(np.where(detected, 0.5, 0.5))
    log_p = np.where(detected, np.log(0.99), np.log(0.01))
    elite = np.zeros(60, bool)
    elite[:30] = True
    q = Proposal()
    ce_update(q, gaps, detected, log_p, log_q, elite, FitOptions(600, 1e-2), smoothing=0.0001, weights=weights)
    curve = q.curve(np.array([2.0, 5.0, 8.0, 11.5]))
    np.testing.assert_allclose(curve[:3], detected[:30][inside[:30]].mean(), atol=0.06)
    assert curve[3] > 0.85


def test_ce_update_refuses_an_empty_elite_set():
    with pytest.raises(ValueError, match="no elite"):
        z = np.zeros((3, 4))
        ce_update(Proposal(), z, z > 0, z, z, np.zeros(3, bool), FitOptions(500), smoothing=0.1)


def test_an_elite_set_with_no_step_to_fit_leaves_the_proposal_as_it_was():
    # the elites never entered the step mask (a small cut-in run whose CE stage found none inside the window):
    # nothing to fit, and no division by the zero steps
    from pemviz.estimators.ce_fit import fit_elite_steps

    q = Proposal()
    before = q.curve(np.array([1.0, 6.0, 11.0]))
    losses = fit_elite_steps(
        q, np.zeros(0), np.zeros(0, bool), np.zeros(0), -np.inf, FitOptions(50, 1e-2, tolerance=1e-4)
    )
    assert losses == []
    np.testing.assert_array_equal(q.curve(np.array([1.0, 6.0, 11.0])), before)


def test_training_loops_call_check_every_25_epochs_and_stop_when_it_raises():
    calls = []

    def check():
        calls.append(1)
        if len(calls) == 3:
            raise KeyboardInterrupt  # stands for the engine's Cancelled

    gaps = np.tile(np.linspace(0, 12, 10), (4, 1))
    with pytest.raises(KeyboardInterrupt):
        pretrain_proposal(Proposal(), gaps, gaps > 5, FitOptions(1000, check=check))
    assert len(calls) == 3  # epochs 0, 25, 50: stopped after ~50 of 1000 epochs


def test_weighted_step_subsample_keeps_the_ce_objective_in_expectation():
    """sum_j w_j f(s_j, a_j) over a systematic subsample of 40 of 600 steps: its mean over 4000 draws equals the
    full sum within 4 standard errors, and every draw carries the total weight exactly."""
    from pemviz.estimators.ce_fit import weighted_steps

    rng = np.random.default_rng(3)
    h = rng.normal(size=(30, 20, 2))
    detected = rng.random((30, 20)) < 0.4
    w = rng.lognormal(sigma=2.0, size=(30, 20)) * (rng.random((30, 20)) < 0.8)
    f = lambda x, a: np.sin(x[..., 0]) + x[..., 1] ** 2 + 3.0 * a  # noqa: E731  any function of (s, a)
    exact = float((w * f(h, detected)).sum())
    draws = []
    for seed in range(4000):
        rows, counts = weighted_steps(h, detected, w, 40, np.random.default_rng(seed))
        assert len(rows) <= 40 and counts.sum() == pytest.approx(w.sum(), rel=1e-12)
        draws.append(float((counts[:, 0] * f(rows, False) + counts[:, 1] * f(rows, True)).sum()))
    draws = np.array(draws)
    assert abs(draws.mean() - exact) < 4 * draws.std() / math.sqrt(draws.size)
    rows, counts = weighted_steps(h, detected, w, 10_000, np.random.default_rng(0))  # no subsample: every step
    assert counts.sum().item() == pytest.approx(w.sum(), rel=1e-12) and len(rows) == np.count_nonzero(w)


@pytest.mark.parametrize("fit, epochs, tolerance", [("lbfgs", 200, None), ("adam", 3000, 1e-5)])
def test_converging_fits_reach_the_elites_miss_rate_and_stop_early(fit, epochs, tolerance):
    torch.manual_seed(0)
    rng = np.random.default_rng(1)
    gaps = np.tile(np.linspace(12, 0.5, 40), (60, 1))
    inside = gaps < 10
    detected = np.where(inside, rng.random(gaps.shape) < 0.2, rng.random(gaps.shape) < 0.95)
    log_q = np.log(np.full(gaps.shape, 0.5))
    log_p = np.where(detected, np.log(0.99), np.log(0.01))
    elite = np.arange(60) < 30
    q = Proposal()
    losses = ce_update(
        q,
        gaps,
        detected,
        log_p,
        log_q,
        elite,
        FitOptions(epochs, 1e-2, fit=fit, tolerance=tolerance, max_rows=1_000),
        smoothing=0.0001,
    )
    assert len(losses) < epochs  # converged, then stopped
    curve = q.curve(np.array([2.0, 5.0, 8.0, 11.5]))
    np.testing.assert_allclose(curve[:3], detected[:30][inside[:30]].mean(), atol=0.06)
    assert curve[3] > 0.85


@pytest.mark.parametrize("rows", [7, 400])
def test_adam_gives_torch_optims_parameters(rows):
    """pemviz's Adam (imported without torch._dynamo) must not change any fit: the parameters torch.optim.Adam gives,
    to rounding (:data:`FIT_TOL`: torch may vectorise its element-wise update differently on another CPU)."""
    from pemviz.core.torch_fits import Adam
    from torch import nn

    fitted, start = [], None
    for make in (lambda ps: torch.optim.Adam(ps, lr=1e-2), lambda ps: Adam(list(ps), lr=1e-2)):
        torch.manual_seed(3)
        net = nn.Sequential(nn.Linear(3, 32), nn.ReLU(), nn.Linear(32, 2), nn.LogSoftmax(dim=-1)).double()
        start = torch.cat([p.detach().reshape(-1) for p in net.parameters()])
        x, w = torch.randn(rows, 3, dtype=torch.float64), torch.rand(rows, 2, dtype=torch.float64)
        opt = make(net.parameters())
        for _ in range(300):
            opt.zero_grad()
            (-(w * net(x)).sum()).backward()
            opt.step()
        fitted.append(torch.cat([p.detach().reshape(-1) for p in net.parameters()]))
    assert (fitted[0] - start).abs().max() > 0.1  # the fit moved the parameters
    torch.testing.assert_close(fitted[1], fitted[0], **FIT_TOL)


FIT_TOL = dict(rtol=1e-9, atol=1e-10)
"""How close a hand-backpropagated fit must come to autograd + torch.optim.Adam. The two sum each gradient over the
same 300 rows in different orders, so each gradient differs by a few ulps times the sum's condition number (~1e-14
relative here), and Adam divides every step by sqrt(v), carrying that difference into each parameter: after 200
steps the parameters (of order 1) agree to ~1e-13 on an AVX-512 CPU, and another CPU or BLAS build may sum in yet
another order. A wrong gradient (a missed term, a wrong sign or scale) moves them by more than 1e-3."""


def _torch_reference_fit(proposal, inputs, loss_of_log_q, epochs, lr):
    """The fit as torch does it: autograd through the network and torch.optim.Adam (the independent truth)."""
    opt = torch.optim.Adam(proposal.parameters(), lr=lr)
    for _ in range(epochs):
        opt.zero_grad()
        loss_of_log_q(proposal.forward(inputs)).backward()
        opt.step()
    return torch.cat([p.detach().reshape(-1) for p in proposal.parameters()])


@pytest.mark.parametrize("state", [False, True])
def test_fit_proposal_gives_autograd_and_torch_adams_parameters(state):
    """fit_proposal backpropagates by hand on one flat parameter tensor; it must fit what autograd and
    torch.optim.Adam fit (to :data:`FIT_TOL`), for the gap-only and the state proposal, the loss divided by a step
    count or not."""
    from pemviz.core.sampling import StateProposal, fit_proposal

    gen = torch.Generator().manual_seed(5)
    if state:

        def make():
            torch.manual_seed(1)
            return StateProposal((0, 1, 2), (12.0, 8.0, 1.0), (20.0, 8.0, 0.0))

        inputs = torch.rand(300, 3, generator=gen, dtype=torch.float64) * torch.tensor([12.0, 8.0, 1.0])
    else:

        def make():
            torch.manual_seed(1)
            return Proposal()

        inputs = torch.rand(300, generator=gen, dtype=torch.float64) * 12.0
    counts = torch.rand(300, 2, generator=gen, dtype=torch.float64)
    for per in (None, 417.0):
        ours, ref = make(), make()
        start = torch.cat([p.detach().reshape(-1) for p in ours.parameters()])
        losses = fit_proposal(ours, inputs, counts, 200, 1e-2, per=per, dtype=torch.float64)
        expected = _torch_reference_fit(
            ref,
            inputs,
            lambda lq, per=per: -(counts * lq).sum() if per is None else -(counts * lq).sum() / per,
            200,
            1e-2,
        )
        got = torch.cat([p.detach().reshape(-1) for p in ours.parameters()])
        assert (got - start).abs().max() > 0.1  # the fit moved the parameters
        torch.testing.assert_close(got, expected, **FIT_TOL)
        assert losses[-1] < losses[0]
        assert all(p.is_contiguous() and p._base is None for p in ours.parameters())  # own storage after the fit


FIT32_TOL = dict(rtol=0, atol=1e-5)
"""How close a float32 fit must come, after 50 steps, to autograd + torch.optim.Adam in float32 on the same network and
to the float64 fit: each gradient is a float32 sum over 300 rows (~1e-7 relative), carried by Adam's sqrt(v) into
every step; here they agree to ~1e-6. A wrong gradient moves them by more than 1e-3. Later the paths part: where a
parameter's gradient is near zero, Adam divides float32 rounding by sqrt(v) ~ eps and takes full steps on it, so
the float32 and float64 fits end in different, equally good parameters (the test compares their losses)."""


def test_a_float32_fit_gives_autograds_float32_parameters_and_keeps_them_float64():
    """The default fit of a tensor objective runs in float32: it fits what autograd and torch.optim.Adam fit on a
    float32 copy of the network, stays within a float32 fit's distance of the float64 fit, reaches as low a loss,
    and leaves the parameters float64."""
    from pemviz.core.sampling import StateProposal, fit_proposal

    gen = torch.Generator().manual_seed(5)

    def make():
        torch.manual_seed(1)
        return StateProposal((0, 1, 2), (12.0, 8.0, 1.0), (20.0, 8.0, 0.0))

    def params(proposal):
        return torch.cat([p.detach().reshape(-1) for p in proposal.parameters()])

    inputs = torch.rand(300, 3, generator=gen, dtype=torch.float64) * torch.tensor([12.0, 8.0, 1.0])
    counts = torch.rand(300, 2, generator=gen, dtype=torch.float64)
    ours, ref, wide = make(), make(), make()
    start = params(ours)
    fit_proposal(ours, inputs, counts, 50, 1e-2, per=417.0)
    fit_proposal(wide, inputs, counts, 50, 1e-2, per=417.0, dtype=torch.float64)
    ref.net.float()
    ref.scales = torch.as_tensor(ref.scales).float()
    expected = _torch_reference_fit(ref, inputs.float(), lambda lq: -(counts.float() * lq).sum() / 417.0, 50, 1e-2)
    got = params(ours)
    assert got.dtype == torch.float64 and all(p.dtype == torch.float64 for p in ours.parameters())
    assert all(p.is_contiguous() and p._base is None for p in ours.parameters())  # own storage after the fit
    assert (got - start).abs().max() > 0.1  # the fit moved the parameters
    torch.testing.assert_close(got, expected.double(), **FIT32_TOL)
    torch.testing.assert_close(got, params(wide), **FIT32_TOL)
    narrow, wide = make(), make()
    losses = fit_proposal(narrow, inputs, counts, 200, 1e-2, per=417.0)
    wide_losses = fit_proposal(wide, inputs, counts, 200, 1e-2, per=417.0, dtype=torch.float64)
    assert losses[-1] < losses[0] - 0.01  # nats per step: it learned
    assert losses[-1] == pytest.approx(wide_losses[-1], abs=1e-3)


def test_recomputed_weights_objective_matches_autograd():
    """The authors' loss (weights recomputed through the gradient) with its gradient written out must give autograd's
    loss and gradient, and fit what autograd fits on the same loss (to :data:`FIT_TOL`)."""
    from pemviz.core.sampling import fit_proposal
    from pemviz.estimators.ce_fit import recomputed_objective

    rng = np.random.default_rng(2)
    n, t_steps, m, k, alpha = 6, 40, 50, 39, 0.5
    inputs = torch.as_tensor(rng.uniform(0.0, 12.0, m))
    slot = rng.integers(0, m, (n, t_steps)) * 2 + (rng.random((n, t_steps)) < 0.8)
    mask = rng.random((n, t_steps)) < 0.9
    log_p = rng.uniform(-30.0, -5.0, n)
    objective = recomputed_objective(slot, log_p, mask, k, alpha)
    slot_t, lp_t, mask_t = torch.as_tensor(slot), torch.as_tensor(log_p), torch.as_tensor(mask, dtype=torch.float64)

    def reference_loss(log_q):
        log_q_now = log_q.reshape(-1)[slot_t] * mask_t
        scaled = alpha * (lp_t - log_q_now[:, :k].sum(dim=1))
        w = torch.exp(scaled - scaled.detach().max())
        return -(w * log_q_now.sum(dim=1)).sum()

    torch.manual_seed(4)
    ours = Proposal()
    torch.manual_seed(4)
    ref = Proposal()
    log_q = ref.forward(inputs).detach().requires_grad_(True)
    loss, grad = objective(log_q.detach())
    reference = reference_loss(log_q)
    reference.backward()
    assert loss.item() == pytest.approx(reference.item(), rel=1e-12)  # one sum of 6 x 40 terms, in another order
    torch.testing.assert_close(grad, log_q.grad, rtol=1e-12, atol=1e-15)
    fit_proposal(ours, inputs, objective, 150, 1e-2)
    expected = _torch_reference_fit(ref, inputs, reference_loss, 150, 1e-2)
    torch.testing.assert_close(torch.cat([p.detach().reshape(-1) for p in ours.parameters()]), expected, **FIT_TOL)


def test_a_saved_proposal_loads_with_the_same_curve_and_a_foreign_file_is_refused(tmp_path):
    torch.manual_seed(3)
    q = Proposal(h_scale=7.5)
    gaps = np.array([0.5, 3.0, 12.0, 40.0])
    saved = save_proposal(q, tmp_path / "q.proposal.pt")
    with torch.no_grad():
        next(q.parameters()).add_(1.0)  # the proposal moves on; the checkpoint must not
    loaded = load_proposal(saved)
    assert loaded.h_scale == 7.5 and not loaded.training
    torch.manual_seed(3)
    np.testing.assert_array_equal(loaded.curve(gaps), Proposal(h_scale=7.5).curve(gaps))  # the weights at saving
    foreign = tmp_path / "foreign.pt"
    torch.save({"format": "something-else", "version": 1}, foreign)
    with pytest.raises(ProposalFormatError, match="not a pemviz proposal checkpoint file"):
        load_proposal(foreign)
    with pytest.raises(FileNotFoundError, match="proposal checkpoint .* not found"):
        load_proposal(tmp_path / "missing.pt")


def test_the_exact_sampler_follows_its_network_and_every_change_of_its_parameters(tmp_path):
    # detect_logit is the float64 network's logit difference to the grids' rounding (24 bits: ~1e-6 of the logits'
    # scale); a row's logit is the same bits alone or in any batch; its cached weights follow an update under
    # no_grad, a fit (which swaps each parameter's storage) and load_state_dict; a checkpoint says it samples exactly
    q = StateProposal((0, 1, 2, 3), (12.0, 10.0, 10.0, 1.0), (10.0, 8.0, 8.0, 0.0))
    q.initialise(np.random.default_rng(0))
    obs = np.random.default_rng(0).uniform(0.0, 12.0, (500, 4))
    with torch.no_grad():
        net = q.forward(torch.as_tensor(obs))
    net = (net[:, 1] - net[:, 0]).numpy()
    z = q.detect_logit(obs)
    assert z.dtype == np.float64 and np.abs(z - net).max() < 1e-5 * max(1.0, np.abs(net).max())
    alone = np.concatenate([q.detect_logit(obs[i : i + 1]) for i in range(0, 500, 7)])
    np.testing.assert_array_equal(alone, z[::7])  # bit for bit: no row depends on the others
    np.testing.assert_array_equal(q.detect_logit(obs[::-1])[::-1], z)
    with torch.no_grad():
        q.net[4].bias[1] += 1.0
    np.testing.assert_allclose(q.detect_logit(obs) - z, 1.0, atol=1e-5)
    pretrain_proposal(q, obs[:, None, :], np.ones((500, 1), bool), FitOptions(30, 1e-2))  # every row detected
    fitted = q.detect_logit(obs)
    assert fitted.mean() > z.mean() + 1.0
    save_proposal(Proposal(h_scale=12.0), tmp_path / "q.pt")
    payload = torch.load(tmp_path / "q.pt", weights_only=True)
    assert payload["sample_precision"] == "exact"
    for old in ("float32", "float64"):  # written before sampling was exact: read, and sampled exactly
        torch.save({**payload, "sample_precision": old}, tmp_path / f"{old}.pt")
        load_proposal(tmp_path / f"{old}.pt")
    torch.save({**payload, "sample_precision": "float16"}, tmp_path / "half.pt")
    with pytest.raises(ProposalFormatError, match="sample_precision 'float16' is none of exact, float64, float32"):
        load_proposal(tmp_path / "half.pt")
    shift = torch.tensor([0.0, 0.5], dtype=torch.float64)  # the detect unit's bias: the logit moves by 0.5
    q.load_state_dict({k: v + shift if k == "net.4.bias" else v for k, v in q.state_dict().items()})
    np.testing.assert_allclose(q.detect_logit(obs) - fitted, 0.5, atol=1e-5)


def test_an_exact_fit_follows_autograds_float64_fit_and_repeats_bit_for_bit():
    # the exact fit's hand-written gradients against torch's float64 autograd fit of the same weighted
    # log-likelihood: after 40 Adam epochs the parameters agree to the grids' precision, and a second fit from the
    # same start gives the same bits
    rng = np.random.default_rng(1)
    obs = rng.uniform(0.0, 12.0, (700, 3))
    counts = torch.as_tensor(rng.uniform(0.0, 4.0, (700, 2)) * (rng.random((700, 1)) < 0.8))
    fits = []
    for dtype in ("exact", torch.float64, "exact"):
        q = StateProposal((0, 1, 2), (12.0, 10.0, 10.0), (10.0, 8.0, 8.0))
        q.initialise(np.random.default_rng(0))
        losses = fit_proposal(q, torch.as_tensor(obs), counts, 40, 1e-2, per=700.0, dtype=dtype)
        fits.append((losses, torch.cat([p.detach().reshape(-1) for p in q.parameters()]).numpy()))
    (exact_losses, exact_params), (ref_losses, ref_params), (again_losses, again_params) = fits
    np.testing.assert_allclose(exact_losses, ref_losses, rtol=1e-5)
    np.testing.assert_allclose(exact_params, ref_params, rtol=0, atol=1e-4)
    assert exact_losses[-1] < exact_losses[0] - 0.01  # it learnt something
    np.testing.assert_array_equal(again_params, exact_params)
    assert again_losses == exact_losses


def test_the_defensive_logit_is_the_mixtures_log_odds():
    # logit of (1 - eps) q + eps / 2 against the log-space formula, over logits from -800 to 800 (both outcomes keep
    # eps / 2 at least, so nothing under- or overflows)
    z = np.concatenate([np.linspace(-800.0, 800.0, 2001), [-1e-300, 0.0, 1e-300]])
    for eps in (0.01, 0.2, 0.9):
        a, half = math.log1p(-eps), math.log(eps / 2.0)
        expected = np.logaddexp(a - np.logaddexp(0.0, -z), half) - np.logaddexp(a - np.logaddexp(0.0, z), half)
        np.testing.assert_allclose(defensive_logit(z, eps), expected, rtol=1e-14, atol=1e-14)


def test_a_proposal_gives_each_row_the_logit_it_has_alone_among_repeated_rows():
    # the network runs once per distinct gap (by its bits) when many rows repeat: each row must still get the bits it
    # gets asked about alone (a batch of one row, below DISTINCT_FROM: the network itself), -0.0 apart from 0.0
    rng = np.random.default_rng(5)
    gaps = np.concatenate([rng.uniform(-2.0, 60.0, 40), [0.0, -0.0, 5e-324, 12.5]])
    states = np.column_stack([gaps, rng.normal(size=(gaps.size, 2))])
    states[-1, 1:] = [0.0, -0.0]  # the same gap with different states
    obs = states[rng.integers(0, gaps.size, 4 * DISTINCT_FROM)]
    for q in (Proposal(h_scale=20.0), StateProposal((0, 1, 2), (20.0, 5.0, 1.0), (50.0, 0.0, 0.0))):
        q.initialise(np.random.default_rng(4))
        got = q.detect_logit(obs)
        alone = np.array([q.detect_logit(row[None, :])[0] for row in obs])
        assert np.array_equal(got.view(np.int64), alone.view(np.int64))
        assert len(np.unique(got)) <= gaps.size < DISTINCT_FROM  # the repeated rows took the distinct path


def test_the_samplers_give_every_row_its_own_logit_and_defensive_mixture_from_distinct_rows():
    # the network runs NETWORK_BLOCK rows at a time and once per distinct row, and StageSamplers takes the defensive
    # mixture of each distinct row once: every row still gets the bits of the proposal asked about it alone, and the
    # defensive logit of those bits; a subclass with a logit of its own is asked for it (no distinct rows)
    from pemviz.core.detectors import StageSamplers
    from pemviz.core.sampling import NETWORK_BLOCK

    rng = np.random.default_rng(8)
    q = StateProposal((0, 1, 2), (20.0, 5.0, 1.0), (50.0, 0.0, 0.0))
    q.initialise(np.random.default_rng(2))
    many = np.column_stack([rng.uniform(0.0, 12.0, 3 * NETWORK_BLOCK + 5), rng.normal(size=(3 * NETWORK_BLOCK + 5, 2))])
    alone = np.array([q.detect_logit(row[None, :])[0] for row in many])
    assert np.array_equal(q.detect_logit(many).view(np.int64), alone.view(np.int64))  # all distinct, block by block
    pick = rng.integers(0, 400, 4 * DISTINCT_FROM)
    obs = many[pick]
    assert q.distinct_logit(obs)[1] is not None  # the repeated rows took the distinct path
    _, plain, defensive = StageSamplers(q, ConstantDetector(0.3), 10.0, 1.0, 0.1).logits(obs)
    near = (obs[:, 0] >= 1.0) & (obs[:, 0] < 10.0)
    assert np.array_equal(plain[near].view(np.int64), alone[pick][near].view(np.int64))
    assert np.array_equal(defensive[near].view(np.int64), defensive_logit(alone[pick][near], 0.1).view(np.int64))

    class Shifted(StateProposal):
        def detect_logit(self, obs):
            return super().detect_logit(obs) + 1.0

    s = Shifted((0, 1, 2), (20.0, 5.0, 1.0), (50.0, 0.0, 0.0))
    s.initialise(np.random.default_rng(2))
    logits, inverse = s.distinct_logit(obs)
    assert inverse is None and np.array_equal(logits, q.detect_logit(obs) + 1.0)


def test_two_different_rows_of_one_key_are_not_taken_for_one():
    from pemviz.core.sampling import _MIX, _distinct_rows

    # rows (a0, a1) and (c0, c1) whose mixed keys agree: c1 = (a0 * MIX) ^ a1 ^ (c0 * MIX) in uint64 arithmetic
    a0, c0 = np.array([10.0, 30.0]).view(np.uint64)
    for a1 in np.linspace(1.0, 2.0, 1000).view(np.uint64):
        with np.errstate(over="ignore"):  # uint64 products wrap, as the keys' do
            c1 = (a0 * _MIX) ^ a1 ^ (c0 * _MIX)
        if np.isfinite(np.array([c1]).view(np.float64)[0]):
            break
    pair = np.array([[a0, a1], [c0, c1]], dtype=np.uint64).view(np.float64)
    x = pair[np.arange(2 * DISTINCT_FROM) % 2]
    assert _distinct_rows(x) is None  # one key, two rows: no sharing
    assert _distinct_rows(np.ascontiguousarray(x[:, :1]))[0].size == 2  # the first column alone: two values


@pytest.mark.parametrize("n, k", [(256, 1), (1000, 3), (8192, 2)])
def test_distinct_rows_are_numpy_s_unique_rows(n, k):
    from pemviz.core.sampling import _distinct_rows

    rng = np.random.default_rng(n)
    kinds = rng.normal(size=(n // 3, k)) * 50
    kinds[1] = np.nextafter(kinds[0], np.inf)  # rows one ulp apart are two rows
    x = np.ascontiguousarray(kinds[rng.integers(0, kinds.shape[0], n)])
    x[:2] = kinds[:2]
    first, inverse = _distinct_rows(x)
    unique = np.unique(x.view(np.uint64), axis=0)
    assert first.size == unique.shape[0] < 3 * n // 4
    assert np.array_equal(x[first][inverse].view(np.uint64), x.view(np.uint64))
    assert np.unique(x[first].view(np.uint64), axis=0).shape[0] == first.size  # each representative once
    assert _distinct_rows(rng.normal(size=(n, k))) is None  # all distinct: declined


def test_the_samplers_keep_the_logits_of_rows_unchanged_since_the_last_step_and_ask_about_the_others():
    # rows with the bits they had at the last ask (cars at rest) keep their logits: every row still gets the bits of
    # the proposal asked about it alone, the network is asked only about the changed rows, a fit forgets what was kept,
    # and a proposal with a logit of its own (not row by row) is asked about every row
    from pemviz.core.detectors import StageSamplers

    rng = np.random.default_rng(11)
    q = StateProposal((0, 1, 2), (20.0, 5.0, 1.0), (50.0, 0.0, 0.0))
    q.initialise(np.random.default_rng(3))
    first = np.column_stack([rng.uniform(0.0, 12.0, 600), rng.normal(size=(600, 2))])
    second = first.copy()
    moved = rng.random(600) < 0.5
    second[moved, 0] += 0.25  # half the rows move (some into or out of the window), half stay
    second[0, 1] = -0.0 if first[0, 1] == 0.0 else 0.0  # a sign of zero is a change of bits
    asked: list[int] = []
    network = q._network_distinct

    def counted(obs):
        asked.append(obs.shape[0])
        return network(obs)

    q._network_distinct = counted
    samplers = StageSamplers(q, ConstantDetector(0.3), 10.0, 1.0, 0.1)
    for obs in (first, second):
        view = obs.view()
        view.flags.writeable = False  # as draw_step hands each step's rows over
        _, plain, defensive = samplers.logits(view)
        near = (obs[:, 0] >= 1.0) & (obs[:, 0] < 10.0)
        alone = np.array([network(row[None, :])[0][0] for row in obs[near]])
        assert np.array_equal(plain[near].view(np.int64), alone.view(np.int64))
        assert np.array_equal(defensive[near].view(np.int64), defensive_logit(alone, 0.1).view(np.int64))
    near_1, near_2 = ((o[:, 0] >= 1.0) & (o[:, 0] < 10.0) for o in (first, second))
    unchanged = near_1 & near_2 & (first.view(np.int64) == second.view(np.int64)).all(axis=1)
    assert unchanged.sum() > 100 and asked == [near_1.sum(), (near_2 & ~unchanged).sum()]
    samplers.forget()  # the proposal was fitted: nothing kept
    samplers.logits(second.copy())
    assert asked[-1] == near_2.sum()

    class Shifted(StateProposal):
        def detect_logit(self, obs):
            return super().detect_logit(obs) + 1.0

    s = Shifted((0, 1, 2), (20.0, 5.0, 1.0), (50.0, 0.0, 0.0))
    s.initialise(np.random.default_rng(3))
    assert q.logit_by_row and not s.logit_by_row
    calls = []
    shifted = StageSamplers(s, ConstantDetector(0.3), 10.0, 1.0, 0.1)
    s.detect_logit = lambda obs: calls.append(obs.shape[0]) or Shifted.detect_logit(s, obs)
    shifted.logits(first)
    shifted.logits(second)
    assert calls == [near_1.sum(), near_2.sum()]
