"""Adaptive importance sampling of detector outputs (Innes & Ramamoorthy 2022, Algorithm 1).

The proposal q_phi(detect | h(s)), h(s) = gap / 12, is a small network trained by the cross-entropy
method: each stage keeps the rollouts whose robustness is at or below the stage threshold gamma_kappa
(the elites) and maximises their weighted log-likelihood under q_phi, with importance weights raised to
the smoothing power alpha. The failure probability is then estimated with importance weights
``prod_t p_PEM(a_t | s_t) / q(a_t | s_t)`` in float64 log-space (:mod:`pemviz.core.estimate`).
"""

from __future__ import annotations

import functools
import math
import os
from pathlib import Path
from typing import Callable, Union

import numpy as np
import torch
from torch import nn

from pemviz.config import FITS
from pemviz.core import exact
from pemviz.core.exact_fit import fit_exact
from pemviz.core.detectors import GAP_COLUMN
from pemviz.io.files import atomic_write, load_tagged

GAP_SCALE_M = 12.0
"""The braking proposal's input is gap / 12 m (Innes & Ramamoorthy 2022, the authors' code)."""


class Proposal(nn.Module):
    """q_phi(a | d): Linear(1,32)-ReLU-Linear(32,32)-ReLU-Linear(32,2)-LogSoftmax, float64 (Innes & Ramamoorthy 2022, Algorithm 1; the authors' ``FFPolicy``).

    ``forward(gap_m [M]) -> [M, 2]`` log-probabilities (nats) of (miss, detect); the network sees
    ``h(s) = gap_m / h_scale``.
    """

    def __init__(self, h_scale: float = GAP_SCALE_M) -> None:
        super().__init__()
        self.h_scale = float(h_scale)
        self.net = nn.Sequential(
            nn.Linear(1, 32), nn.ReLU(), nn.Linear(32, 32), nn.ReLU(), nn.Linear(32, 2), nn.LogSoftmax(dim=-1)
        ).double()
        self.noise_shift: NoiseShift | None = None
        """The measurement-error head (:meth:`add_noise_head`; None: the errors are drawn from the target's model)."""

    def forward(self, gap_m: torch.Tensor) -> torch.Tensor:
        return self.net(self.inputs(gap_m))

    def initialise(self, rng: np.random.Generator) -> None:
        """Draw every layer's weights and biases i.i.d. U(-1/sqrt(fan_in), 1/sqrt(fan_in)), as torch's ``nn.Linear``
        initialises them (He et al., "Delving deep into rectifiers", 2015, with a = sqrt(5)), from ``rng`` (numpy's
        PCG64: the same numbers on every CPU, where torch's ``uniform_`` rounds by the CPU's vector unit)."""
        with torch.no_grad():
            for layer in self.net:
                if isinstance(layer, nn.Linear):
                    bound = 1.0 / math.sqrt(layer.in_features)
                    for p in (layer.weight, layer.bias):
                        p.copy_(torch.from_numpy(rng.uniform(-bound, bound, tuple(p.shape))))

    def add_noise_head(self, n_noise: int) -> None:
        """Give the proposal a measurement-error model of its own (:class:`NoiseShift`, equal to the target's until
        fitted) for the D = ``n_noise`` error components a noisy target draws."""
        self.noise_shift = NoiseShift(self.net[0].in_features, n_noise)

    def noise_shift_of(self, obs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(a [N, D], b [N, D]) of the error head at observations (object rows) [N, F] (:class:`NoiseShift`)."""
        x = np.asarray(obs, dtype=np.float64)[:, self.input_columns()] / self.input_scales().numpy()
        with torch.no_grad():
            a, b = self.noise_shift(torch.from_numpy(np.ascontiguousarray(x)))
        return a.numpy(), b.numpy()

    def inputs(self, gap_m: torch.Tensor) -> torch.Tensor:
        """The network's input h(s) of proposal inputs ``gap_m`` [M] (metres): [M, 1], dimensionless."""
        return (gap_m / self.h_scale).reshape(-1, 1)

    def detect_logit(self, obs: np.ndarray) -> np.ndarray:
        """Detector interface: logit q(detect | obs) = log q(detect) - log q(miss), float64 [N] for observations
        [N, F] (nats).

        The network of :meth:`forward` in exact, order-free arithmetic (:mod:`pemviz.core.exact`): each layer's
        product on power-of-two grids of about float32's precision (the input scales folded into the first layer's
        weights, the two output units into one, ``(w_detect - w_miss) . a + (b_detect - b_miss)``: the log-softmax
        cancels in the difference), so within ~1e-6 of ``forward``'s ``log q[:, 1] - log q[:, 0]``, and the same bits
        for a row whatever rows it is asked about with, whatever the CPU. Sampling and every importance weight use
        this logit, so each rollout is weighed by the density it was drawn from.
        """
        obs = np.asarray(obs, dtype=np.float64)
        columns = self.input_columns()
        x = obs if columns == list(range(obs.shape[1])) else obs[:, columns]
        w1, b1, w2, b2, w3, b3 = self._sampling_weights()
        if x.shape[0] == 0:
            return np.zeros(0)
        a = np.maximum(exact.matmul(x, None, w1) + b1, 0.0)
        a = np.maximum(exact.matmul(a, None, w2, nonneg=True) + b2, 0.0)
        return exact.matmul(a, None, w3, nonneg=True)[:, 0] + b3

    def __getstate__(self) -> dict:
        """Pickled and copied without the sampling weights' cache (it holds storages; a copy computes its own)."""
        return {k: v for k, v in super().__getstate__().items() if k != "_sampling_cache"}

    def _sampling_weights(self) -> tuple:
        """The weights of :meth:`detect_logit`, each layer's on its grid (:func:`pemviz.core.exact.on_grid`, per
        output unit): (W1 [k, 32] with the input scales folded in, b1 [32], W2 [32, 32], b2, w_detect - w_miss
        [32, 1], b_detect - b_miss), kept while no parameter changed: neither its storage (a fit swaps it in, ``p.data
        = ...``; the storages seen are held, so no new one can take an old one's address) nor its version (bumped by
        every in-place update through the parameter itself, as optimisers and ``load_state_dict`` make them). An
        update through ``p.data`` in place leaves no trace: change parameters under ``torch.no_grad()`` instead."""
        cached = self.__dict__.get("_sampling_cache")
        params = cached[2] if cached is not None else tuple(self.net.parameters())  # the Parameters: they follow
        key = (tuple(self.input_scales().tolist()),  # a fit's storage swaps, a detached copy does not
               tuple((p.data_ptr(), p._version) for p in params))  # fmt: skip
        if cached is not None and cached[0] == key:
            return cached[1]
        lin1, _, lin2, _, lin3, _ = self.net
        with torch.no_grad():
            w1 = (lin1.weight.t() / self.input_scales()[:, None]).numpy()
            w2 = lin2.weight.t().numpy()
            w, b = lin3.weight, lin3.bias
            w3 = (w[1] - w[0]).numpy()[:, None]
            b1, b2, b3 = lin1.bias.numpy().copy(), lin2.bias.numpy().copy(), float(b[1] - b[0])
        weights = (exact.on_grid(w1, exact.grid_bits(w1.shape[0]), 0), b1,
                   exact.on_grid(w2, exact.grid_bits(w2.shape[0]), 0), b2,
                   exact.on_grid(w3, exact.grid_bits(w3.shape[0]), 0), b3)  # fmt: skip
        self.__dict__["_sampling_cache"] = (key, weights, params, tuple(p.untyped_storage() for p in params))
        return weights

    def input_columns(self) -> list[int]:
        """The observation columns the network reads, in its input order: the gap."""
        return [GAP_COLUMN]

    def input_scales(self) -> torch.Tensor:
        """What :meth:`inputs` divides each input column by, float64 [k]: the gap's ``h_scale`` (metres)."""
        return torch.tensor([self.h_scale], dtype=torch.float64)

    def curve(self, gap_grid_m: np.ndarray) -> np.ndarray:
        """q(detect | d) on a grid of gaps (metres), float64 [G]."""
        with torch.no_grad():
            lq = self.forward(torch.as_tensor(gap_grid_m, dtype=torch.float64))
        return lq[:, 1].exp().numpy()

    def features(self, observations: np.ndarray) -> np.ndarray:
        """The proposal's inputs of rollouts' observations [N, T, F]: the gap, [N, T] (metres)."""
        return np.asarray(observations)[..., GAP_COLUMN]


class NoiseShift(nn.Module):
    """A proposal's measurement-error density relative to the target's: with the target's location and scale
    (loc_p, s_p) of a row and the head's outputs (a, b) at the row's proposal inputs h,

        loc_q = loc_p + s_p a(h),    log s_q = log s_p + b(h),

    in the target's family (:func:`pemviz.core.detectors.noise_quantile`). (a, b) are linear in h (Linear(k, 2 D),
    float64), zero at first: q's errors are p's until a cross-entropy fit moves them toward the failures' errors
    (Rubinstein & Kroese, "The Cross-Entropy Method", 2004: the CE update of a location-scale family's parameters); a
    stage's few elites fit so few parameters without overfitting.
    """

    def __init__(self, n_inputs: int, n_noise: int) -> None:
        super().__init__()
        self.n_noise = int(n_noise)
        self.net = nn.Linear(n_inputs, 2 * n_noise).double()
        nn.init.zeros_(self.net.weight)
        nn.init.zeros_(self.net.bias)

    SHIFT_MAX = 4.0
    """The largest location shift |a| (in the target's scales): a soft bound, ``a = 4 tanh(linear / 4)``."""
    LOG_SCALE_MAX = 1.5
    """The largest log-scale change |b| (nats: the scale at most 4.5 times the target's or its 4.5th), soft as ``a``:
    a few elites must not fit a density that puts errors the target never makes on a row outside their span."""

    def forward(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(a [R, D], b [R, D]) at the network's inputs x [R, k] (:meth:`Proposal.inputs`), each softly bounded
        (:attr:`SHIFT_MAX`, :attr:`LOG_SCALE_MAX`)."""
        out = self.net(x)
        a, b = out[:, : self.n_noise], out[:, self.n_noise :]
        return self.SHIFT_MAX * torch.tanh(a / self.SHIFT_MAX), self.LOG_SCALE_MAX * torch.tanh(b / self.LOG_SCALE_MAX)


def _standard_log_density(family: str, df: np.ndarray | None, z: torch.Tensor) -> torch.Tensor:
    """log f(z) of the standard family (torch, for the fit's gradient), [R, D]."""
    if family == "normal":
        return -0.5 * z * z - 0.5 * math.log(2.0 * math.pi)
    if family == "laplace":
        return -z.abs() - math.log(2.0)
    return torch.distributions.StudentT(torch.as_tensor(df, dtype=torch.float64)).log_prob(z)


def fit_noise_shift(proposal: Proposal, obs: np.ndarray, noise: np.ndarray, loc_p: np.ndarray,
                    log_scale_p: np.ndarray, family: str, df: np.ndarray | None, log_w: np.ndarray, *, epochs: int,
                    lr: float, max_rows: int | None, rng: np.random.Generator,
                    check: Callable[[], None] | None = None, tolerance: float | None = None) -> list[float]:  # fmt: skip
    """The cross-entropy update of the proposal's error head, in place: maximise the weighted log-likelihood
    ``sum_s w_s log q(e_s | h_s)`` of detected objects' errors (Innes & Ramamoorthy 2022, eq. 10-11, for the errors'
    density), by Adam on the mean over the weights; returns the loss per epoch (nats per error).

    Args:
        obs: float64 [S, G] the detected objects' rows; noise: [S, D] their errors; loc_p, log_scale_p: [S, D] the
            target's parameters at the rows; family, df: the target's family
            (:data:`pemviz.core.detectors.NOISE_FAMILIES`).
        log_w: float64 [S] each error's weight in log space (alpha times its rollout's importance log-weight).
        max_rows: beyond that many errors, a weighted systematic subsample of them (:func:`pemviz.estimators.ce_fit`'s
            rule: the expected loss is kept); None: all.
        tolerance: stop once the loss fell by less than this over :data:`PLATEAU_EPOCHS` epochs.
    """
    head = proposal.noise_shift
    w = np.exp(np.asarray(log_w, dtype=np.float64) - np.max(log_w))
    if max_rows is not None and w.size > max_rows:  # systematic resampling in proportion to the weights
        cum = np.cumsum(w)
        picks = np.searchsorted(cum, (rng.random() + np.arange(max_rows)) * (cum[-1] / max_rows), side="right")
        picks, times = np.unique(np.minimum(picks, w.size - 1), return_counts=True)
        obs, noise, loc_p, log_scale_p, w = obs[picks], noise[picks], loc_p[picks], log_scale_p[picks], times * 1.0
    x = torch.from_numpy(np.ascontiguousarray(np.asarray(obs)[:, proposal.input_columns()]
                                              / proposal.input_scales().numpy()))  # fmt: skip
    e, lp, ls = (torch.as_tensor(np.asarray(a, dtype=np.float64)) for a in (noise, loc_p, log_scale_p))
    weights = torch.as_tensor(w / w.sum())
    params = list(head.parameters())
    opt = Adam(params, lr=lr)
    losses: list[float] = []
    for epoch in range(epochs):
        if check is not None and epoch % CHECK_EVERY == 0:
            check()
        for p in params:
            p.grad = None
        a, b = head(x)
        log_scale = ls + b
        z = (e - lp - ls.exp() * a) * torch.exp(-log_scale)
        loss = -(weights * (_standard_log_density(family, df, z) - log_scale).sum(dim=1)).sum()
        loss.backward()
        opt.step()
        losses.append(loss.item())
        if tolerance is not None and epoch >= PLATEAU_EPOCHS and losses[-PLATEAU_EPOCHS - 1] - losses[-1] < tolerance:
            break
    return losses


class StateProposal(Proposal):
    """q_phi(a | h(s)) with h(s) = several observation columns, each divided by its scale (pemviz's default sampler).

    Same network as :class:`Proposal` with ``len(columns)`` inputs (gap first). ``forward(h [M, k])``;
    :meth:`curve` varies the gap and holds the other inputs at ``reference`` (e.g. the start state).
    Opt in with ``ExperimentConfig.proposal_inputs = "state"``; the paper's proposal sees the gap only.
    """

    def __init__(self, columns: tuple[int, ...], scales: tuple[float, ...], reference: tuple[float, ...]) -> None:
        if len(columns) != len(scales) or len(columns) != len(reference) or columns[:1] != (GAP_COLUMN,):
            raise ValueError("StateProposal: columns, scales and reference need one entry per input, the gap first")
        super().__init__(float(scales[0]))
        self.columns, self.reference = tuple(columns), tuple(float(r) for r in reference)
        self.scales = torch.as_tensor(np.asarray(scales, dtype=np.float64))
        self.net[0] = nn.Linear(len(columns), 32).double()

    def forward(self, h: torch.Tensor) -> torch.Tensor:
        return self.net(self.inputs(h))

    def inputs(self, h: torch.Tensor) -> torch.Tensor:
        """The network's input of proposal inputs ``h`` [M, k] (observation units): [M, k], each column divided by
        its scale."""
        return h.reshape(-1, len(self.columns)) / self.scales

    def features(self, observations: np.ndarray) -> np.ndarray:
        """[N, T, k]: the proposal's input columns of observations [N, T, F] (the observations themselves, not a copy,
        when the columns are all of them in order)."""
        observations = np.asarray(observations)
        if self.columns == tuple(range(observations.shape[-1])):
            return observations
        return observations[..., list(self.columns)]

    def input_columns(self) -> list[int]:
        """The observation columns the network reads, in its input order (the gap first)."""
        return list(self.columns)

    def input_scales(self) -> torch.Tensor:
        """Each input column's scale, float64 [k] (observation units)."""
        return self.scales

    def curve(self, gap_grid_m: np.ndarray) -> np.ndarray:
        """q(detect | d, other inputs = ``reference``) on a grid of gaps, float64 [G]."""
        h = np.tile(np.asarray(self.reference, dtype=np.float64), (np.size(gap_grid_m), 1))
        h[:, 0] = gap_grid_m
        with torch.no_grad():
            lq = self.forward(torch.as_tensor(h))
        return lq[:, 1].exp().numpy()


class Backprop:
    """Backpropagation through a proposal network written out (Rumelhart, Hinton & Williams 1986), without autograd.

    :meth:`forward` returns log q [M, 2] (nats) and what :meth:`backward` needs; :meth:`backward` turns
    d loss / d log q [M, 2] into d loss / d parameter, written in place into ``grads``. Both call the kernels
    autograd would run for ``net(h)`` and its backward pass, in its order (``addmm``, ``relu``, ``log_softmax``;
    ``_log_softmax_backward_data``, ``threshold_backward``, ``mm``), into activation buffers allocated once, with
    each weight gradient as one product (``dz^T a``) rather than a transposed one: autograd's gradients to rounding
    (a test checks the fitted parameters to 1e-9), without its per-operation overhead or allocations: a fit takes
    thousands of steps on a few thousand inputs.
    The parameters are read through the tensors bound here, so an optimiser must update them in place.

    Args:
        net: Linear-ReLU-Linear-ReLU-Linear-LogSoftmax (:class:`Proposal`'s ``net``).
        h: the network's input, float64 [M, k].
        grads: float64 tensors shaped like the parameters, in ``net.parameters()`` order.
    """

    def __init__(self, net: nn.Sequential, h: torch.Tensor, grads: list[torch.Tensor]) -> None:
        lin1, _, lin2, _, lin3, _ = net
        self.h, self.grads = h, grads
        self.biases = (lin1.bias.detach(), lin2.bias.detach(), lin3.bias.detach())
        self.weights = (lin1.weight.detach(), lin2.weight.detach(), lin3.weight.detach())
        m, width = h.shape[0], lin1.weight.shape[0]
        new = functools.partial(torch.empty, dtype=h.dtype)
        # every epoch writes into the same activation buffers: no allocation on the hot path
        self._a1, self._a2, self._z3 = new(m, width), new(m, lin2.weight.shape[0]), new(m, lin3.weight.shape[0])
        self._d1, self._d2 = new(m, width), new(m, lin2.weight.shape[0])
        self.fast = h.dtype == torch.float32 and lin3.weight.shape[0] == 2
        """float32 with two outputs: the log-softmax as two softplus of the logit difference, and the first layer's
        weight gradient as a transposed product of the untransposed operands (each 3-6 times as fast on a CPU as
        autograd's kernels for these shapes); float64 fits run autograd's kernels, bit for bit."""

    def forward(self) -> tuple[torch.Tensor, tuple[torch.Tensor, ...]]:
        """log q [M, 2] (nats) and the activations :meth:`backward` needs."""
        (b1, b2, b3), (w1, w2, w3) = self.biases, self.weights
        with torch.no_grad():
            a1 = torch.addmm(b1, self.h, w1.t(), out=self._a1).relu_()
            a2 = torch.addmm(b2, a1, w2.t(), out=self._a2).relu_()
            z = torch.addmm(b3, a2, w3.t(), out=self._z3)
            if self.fast:  # log softmax of two: log q(miss) = -softplus(z_1 - z_0), log q(detect) = -softplus(z_0 - z_1)
                d = z[:, 1] - z[:, 0]
                lq = torch.stack((torch.nn.functional.softplus(d), torch.nn.functional.softplus(-d)), dim=1).neg_()
            else:
                lq = torch.log_softmax(z, dim=-1)
        return lq, (a1, a2, lq)

    def backward(self, cache: tuple[torch.Tensor, ...], grad_lq: torch.Tensor) -> None:
        """d loss / d parameter into ``grads`` from d loss / d log q = ``grad_lq`` [M, 2] at the forward pass
        ``cache``."""
        a1, a2, lq = cache
        g1, gb1, g2, gb2, g3, gb3 = self.grads
        _, w2, w3 = self.weights
        with torch.no_grad():
            dz3 = torch.ops.aten._log_softmax_backward_data(grad_lq, lq, -1, lq.dtype)
            dz2 = torch.ops.aten.threshold_backward(torch.mm(dz3, w3, out=self._d2), a2, 0)
            dz1 = torch.ops.aten.threshold_backward(torch.mm(dz2, w2, out=self._d1), a1, 0)
            if self.fast:
                g1.copy_(torch.mm(self.h.t(), dz1).t())
            else:
                torch.mm(dz1.t(), self.h, out=g1)
            torch.sum(dz1, 0, out=gb1)
            torch.mm(dz2.t(), a1, out=g2)
            torch.sum(dz2, 0, out=gb2)
            torch.mm(dz3.t(), a2, out=g3)
            torch.sum(dz3, 0, out=gb3)


CHECK_EVERY = 25
"""Epochs between two calls of a training loop's ``check`` callback (e.g. the engine's cancel check)."""


PLATEAU_EPOCHS = 50
"""Adam with a tolerance stops once the loss fell by less than it over this many epochs (early stopping)."""

LBFGS_TOLERANCE = 1e-6
"""L-BFGS stops once an iteration changes the loss (nats per step) or any parameter by less than this."""


class Adam:
    """Adam (Kingma & Ba, "Adam: a method for stochastic optimization", ICLR 2015, Algorithm 1) with torch's defaults.

    The same arithmetic, operation for operation, as ``torch.optim.Adam(params, lr)`` on CPU (its single-tensor
    path: betas (0.9, 0.999), eps 1e-8, no weight decay), so a fit gives bit-identical parameters (a test checks
    it). It exists for speed: ``torch.optim`` imports ``torch._dynamo`` when its first optimizer is built (about
    1 s, as long as a whole default run's simulation) and wraps every step in dispatch that costs ~0.1 ms, while
    a proposal fit takes thousands of steps of well under a millisecond each.

    Args:
        params: the tensors to optimise (``requires_grad``); their ``.grad`` is read by :meth:`step`.
        lr: step size (> 0).
    """

    def __init__(self, params: list[torch.Tensor], lr: float, betas: tuple[float, float] = (0.9, 0.999),
                 eps: float = 1e-8) -> None:  # fmt: skip
        self.params = list(params)
        self.lr, (self.beta1, self.beta2), self.eps = float(lr), betas, float(eps)
        self.steps = 0
        self.exp_avg = [torch.zeros_like(p, memory_format=torch.preserve_format) for p in self.params]
        self.exp_avg_sq = [torch.zeros_like(p, memory_format=torch.preserve_format) for p in self.params]

    def zero_grad(self) -> None:
        for p in self.params:
            p.grad = None

    @torch.no_grad()
    def step(self) -> None:
        """One update from the parameters' current gradients (parameters without one are left as they are)."""
        self.steps += 1
        step = float(self.steps)
        step_size = self.lr / (1 - self.beta1**step)
        bias_correction2_sqrt = (1 - self.beta2**step) ** 0.5
        for p, m, v in zip(self.params, self.exp_avg, self.exp_avg_sq):
            if p.grad is None:
                continue
            m.lerp_(p.grad, 1 - self.beta1)
            v.mul_(self.beta2).addcmul_(p.grad, p.grad, value=1 - self.beta2)
            p.addcdiv_(m, (v.sqrt() / bias_correction2_sqrt).add_(self.eps), value=-step_size)


Objective = Union[torch.Tensor, Callable[[torch.Tensor], "tuple[torch.Tensor, torch.Tensor]"]]
"""What :func:`fit_proposal` minimises over q_phi's log-probabilities log q [M, 2] (nats) at its inputs: a tensor C
[M, 2], the loss ``-sum(C * log q)`` (a weighted log-likelihood: C holds each input's weighted counts of misses and
detections), or a function of log q returning the scalar loss and its gradient d loss / d log q [M, 2]."""


EXACT = "exact"
"""The arithmetic of an ``adam`` fit (``dtype`` of :func:`fit_proposal`) that gives the same parameters on every
CPU, whatever its vector unit or BLAS kernel (:func:`pemviz.core.exact_fit.fit_exact`)."""


def fit_proposal(
    proposal: Proposal,
    inputs: torch.Tensor,
    objective: Objective,
    epochs: int,
    lr: float,
    check: Callable[[], None] | None = None,
    method: str = "adam",
    tolerance: float | None = None,
    per: float | None = None,
    dtype: torch.dtype | str = EXACT,
) -> list[float]:
    """Minimise the ``objective`` of log q_phi(. | ``inputs``) over the proposal's parameters, in place; returns the
    loss per step.

    Args:
        inputs: the proposal's inputs, float64 [M] (gaps, metres) or [M, k] (:meth:`Proposal.forward`).
        objective: see :data:`Objective`.
        per: with a tensor C, the loss is ``-sum(C * log q) / per`` (e.g. the number of steps C stands for, so that a
            ``tolerance`` in nats per step means the same at any N); None: not divided.
        epochs, lr: Adam steps and step size, or the most L-BFGS iterations.
        check: called every :data:`CHECK_EVERY` steps; may raise (a cancel token) to abandon the fit.
        dtype: the arithmetic of an ``adam`` fit of a tensor objective: :data:`EXACT` (default,
            :func:`pemviz.core.exact_fit.fit_exact`: the same parameters on every CPU), or torch's float32 (the fastest) or float64 kernels, whose last bits
            depend on the CPU's vector unit and BLAS kernel. The parameters stay float64 and every weight of the
            estimate is computed in float64 from the density sampled from (:meth:`Proposal.detect_logit`), so the
            precision of the fit only moves the proposal, never the estimate's unbiasedness. A function objective
            (the authors' recomputed weights) and ``lbfgs`` always fit in torch's float64.
        method: one of :data:`pemviz.config.FITS`.
        tolerance: ``adam``: early stopping once the loss fell by less than this over the last :data:`PLATEAU_EPOCHS`
            epochs (None: every epoch); ``lbfgs``: its tolerance on a change of the loss (default
            :data:`LBFGS_TOLERANCE`).
    Returns:
        the loss per Adam epoch, or per L-BFGS evaluation.
    Raises:
        ValueError: for an unknown ``method``.

    ``adam`` (Kingma & Ba 2015, :class:`Adam`) backpropagates through the network by hand
    (:func:`pemviz.core.exact_fit.fit_exact`, or :class:`Backprop` in torch's kernels); ``lbfgs`` (Nocedal 1980;
    torch's, history 20, strong-Wolfe line search,
    unit step) backpropagates the objective's gradient with autograd.
    """
    if method not in FITS:
        raise ValueError(f"fit_proposal: unknown method {method!r}; use one of {', '.join(FITS)}")
    linear = isinstance(objective, torch.Tensor)
    # d loss / d log q of a tensor objective, formed as autograd forms it (the same bits)
    grad_linear = (objective * -1.0 if per is None else objective * -(1.0 / per)) if linear else None

    def loss_and_grad(log_q: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        if not linear:
            return objective(log_q)
        loss = -(objective * log_q).sum()
        return (loss if per is None else loss / per), grad_linear

    losses: list[float] = []
    if method == "lbfgs":
        opt = torch.optim.LBFGS(
            proposal.net.parameters(), lr=1.0, max_iter=CHECK_EVERY, max_eval=10 * CHECK_EVERY, history_size=20,
            line_search_fn="strong_wolfe", tolerance_grad=1e-9,
            tolerance_change=LBFGS_TOLERANCE if tolerance is None else tolerance,
        )  # fmt: skip
        state = opt.state[next(iter(proposal.net.parameters()))]

        def closure() -> torch.Tensor:
            opt.zero_grad()
            log_q = proposal.forward(inputs)
            loss, grad = loss_and_grad(log_q.detach())
            log_q.backward(grad)
            losses.append(loss.item())
            return loss

        while state.get("n_iter", 0) < epochs:
            if check is not None:
                check()  # may raise to stop the run (a cancel token)
            before = state.get("n_iter", 0)
            opt.param_groups[0]["max_iter"] = min(CHECK_EVERY, epochs - before)
            opt.step(closure)
            if state.get("n_iter", 0) - before < opt.param_groups[0]["max_iter"]:  # converged: stop
                break
        return losses
    if linear and dtype == EXACT:
        return fit_exact(proposal, inputs, objective, epochs, lr, check, tolerance, per, check_every=CHECK_EVERY,
                         plateau_epochs=PLATEAU_EPOCHS)
    dtype = dtype if linear and dtype != EXACT else torch.float64
    h = proposal.inputs(torch.as_tensor(inputs)).to(dtype)
    if linear:
        grad_linear = grad_linear.to(dtype)  # the loss itself is summed in float64 (its log q cast up)
    # one flat tensor for all parameters and one for their gradients (each parameter and gradient a view into it
    # while the fit runs), so that an Adam step is 7 kernel calls, not 7 per parameter: element for element the
    # same arithmetic as parameter by parameter
    params = list(proposal.net.parameters())  # the detection network (a measurement-error head fits apart)
    sizes = [p.numel() for p in params]
    flat = nn.Parameter(torch.cat([p.detach().reshape(-1) for p in params]).to(dtype))
    flat.grad = torch.zeros_like(flat)
    for p, view in zip(params, flat.detach().split(sizes)):
        p.data = view.view_as(p)
    net = Backprop(proposal.net, h, [g.view_as(p) for p, g in zip(params, flat.grad.split(sizes))])
    opt = Adam([flat], lr=lr)
    try:
        for epoch in range(epochs):
            if check is not None and epoch % CHECK_EVERY == 0:
                check()  # may raise to stop the run (a cancel token)
            log_q, cache = net.forward()
            loss, grad = loss_and_grad(log_q)
            net.backward(cache, grad)
            opt.step()
            losses.append(loss.item())
            if tolerance is not None and epoch >= PLATEAU_EPOCHS and losses[-PLATEAU_EPOCHS - 1] - losses[-1] < tolerance:
                break  # converged: the loss has stopped falling
    finally:
        for p in params:  # each parameter its own storage again, in float64
            p.data = p.data.to(torch.float64, copy=True)
    return losses


# ---------------------------------------------------------------------------------- proposal checkpoints

PROPOSAL_FORMAT_TAG = "pemviz-proposal"
PROPOSAL_FORMAT_VERSION = 1
SAMPLE_PRECISIONS = ("exact", "float64", "float32")
"""A checkpoint's ``sample_precision``: ``exact`` (written now); ``float64`` and ``float32`` (written before sampling
became exact, read and sampled exactly)."""


class ProposalFormatError(ValueError):
    """A file is not a readable pemviz proposal checkpoint: the message names the file and why."""


def write_proposal_file(proposal: Proposal, path: str | os.PathLike[str]) -> None:
    """``torch.save`` a :class:`Proposal` checkpoint into ``path`` as it is (no temporary file: for a caller that
    moves its files into place itself, as :class:`pemviz.io.rollouts.RolloutWriter` does; else
    :func:`save_proposal`).

    The checkpoint is a plain dict: format tag, version, ``h_scale`` (metres), a copy of the ``state_dict`` and the
    arithmetic it samples in (``sample_precision``: ``exact``, :meth:`Proposal.detect_logit`; checkpoints of
    pemviz's earlier versions say ``float64`` or ``float32``, and are now sampled exactly), so that
    ``torch.load(weights_only=True)`` reads it and later training of ``proposal`` does not change it.
    """
    payload = {
        "format": PROPOSAL_FORMAT_TAG,
        "version": PROPOSAL_FORMAT_VERSION,
        "h_scale": float(proposal.h_scale),
        "state_dict": {k: v.detach().cpu().clone() for k, v in proposal.state_dict().items()},
        "sample_precision": "exact",
    }
    torch.save(payload, path)


def save_proposal(proposal: Proposal, path: str | os.PathLike[str], *, overwrite: bool = True) -> Path:
    """Write a :class:`Proposal` checkpoint (:func:`write_proposal_file`) atomically; returns ``path``.

    Raises:
        OSError: the folder is missing or not writable, the disk is full (nothing is left behind).
        pemviz.io.files.OutputExists: ``path`` exists and ``overwrite`` is False.
    """
    return atomic_write(path, lambda tmp: write_proposal_file(proposal, tmp), overwrite=overwrite)


def load_proposal(path: str | os.PathLike[str]) -> Proposal:
    """Load a proposal saved by :func:`save_proposal`, in eval mode.

    Raises:
        FileNotFoundError: no such file.
        ProposalFormatError: not a pemviz proposal checkpoint, another format version, or damaged weights.
    """
    p = Path(path)
    if not p.is_file():
        raise FileNotFoundError(f"proposal checkpoint {p} not found")
    payload = load_tagged(p, PROPOSAL_FORMAT_TAG, PROPOSAL_FORMAT_VERSION, "proposal checkpoint", ProposalFormatError)
    try:
        proposal = Proposal(float(payload["h_scale"]))
        proposal.load_state_dict(payload["state_dict"])
        precision = payload.get("sample_precision", "float64")
        if precision not in SAMPLE_PRECISIONS:
            raise ValueError(f"sample_precision {precision!r} is none of {', '.join(SAMPLE_PRECISIONS)}")
    except (KeyError, TypeError, ValueError, RuntimeError) as exc:
        raise ProposalFormatError(f"{p}: damaged proposal checkpoint ({exc})") from None
    return proposal.eval()
