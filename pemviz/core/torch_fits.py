"""The proposal's fits that run in torch: L-BFGS and the float32 / float64 Adam fits (:func:`fit_in_torch`), the
measurement-error head (:class:`NoiseShift`, :func:`fit_noise_shift`), and the torch module a proposal becomes when
one of them or a checkpoint needs it (:class:`ProposalModule`). Imports torch; :mod:`pemviz.core.sampling` imports
this module only then."""

from __future__ import annotations

import functools
import math
from collections.abc import Callable
from typing import Any, cast

import numpy as np
import torch
from torch import nn

from pemviz.core import libm
from pemviz.core.fit_settings import CHECK_EVERY, EXACT, LBFGS_TOLERANCE, PLATEAU_EPOCHS, FitOptions, Objective
from pemviz.core.torch_use import torch_module

WIDTH = 32
"""Units of each of the proposal network's two hidden layers."""


def new_net(n_inputs: int) -> nn.Sequential:
    """Linear(k, 32)-ReLU-Linear(32, 32)-ReLU-Linear(32, 2)-LogSoftmax in float64 (the authors' ``FFPolicy``), torch's
    default initialisation drawn as an ``nn.Module`` proposal always drew it: a one-input network first, its first
    layer then replaced when ``n_inputs`` > 1."""
    net = nn.Sequential(
        nn.Linear(1, WIDTH), nn.ReLU(), nn.Linear(WIDTH, WIDTH), nn.ReLU(), nn.Linear(WIDTH, 2), nn.LogSoftmax(dim=-1)
    ).double()
    if n_inputs != 1:
        net[0] = nn.Linear(n_inputs, WIDTH).double()
    return net


class ProposalModule(nn.Module):
    """A proposal's torch parameters: ``net`` (:func:`new_net`) and, once added, ``noise_shift`` (:class:`NoiseShift`);
    its ``state_dict`` keys (``net.0.weight`` ...) are those of the checkpoints pemviz has always written."""

    def __init__(self, net: nn.Sequential) -> None:
        super().__init__()
        self.net = net
        self.noise_shift: NoiseShift | None = None


class NoiseShift(nn.Module):
    """A proposal's measurement-error density relative to the target's: with the target's (loc_p, s_p) at a row and
    the head's outputs (a, b) at its proposal inputs h,

        loc_q = loc_p + s_p a(h),    log s_q = log s_p + b(h),

    in the target's family; (a, b) are linear in h and zero at first, moved by cross-entropy fits toward the
    failures' errors (Rubinstein & Kroese, "The Cross-Entropy Method", 2004)."""

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


def fit_noise_shift(
    proposal: Any,
    obs: np.ndarray,
    noise: np.ndarray,
    loc_p: np.ndarray,
    log_scale_p: np.ndarray,
    family: str,
    df: np.ndarray | None,
    log_w: np.ndarray,
    options: FitOptions,
) -> list[float]:
    """The cross-entropy update of the proposal's error head, in place: maximise ``sum_s w_s log q(e_s | h_s)`` over
    detected objects' errors (Innes & Ramamoorthy 2022, eq. 10-11, for the errors' density) by Adam; returns the
    loss per epoch (nats per error).

    Args:
        proposal: the proposal whose error head is fitted, in place.
        obs: float64 [S, G] the detected objects' rows.
        noise: float64 [S, D] their errors.
        loc_p: float64 [S, D] the target's location at the rows.
        log_scale_p: float64 [S, D] the target's log scale at the rows.
        family: the target's family (:data:`pemviz.core.detector_noise.NOISE_FAMILIES`).
        df: the target's Student-t degrees of freedom, float64 [D], or None.
        log_w: float64 [S] each error's log weight (alpha times its rollout's importance log-weight).
        options: Adam's epochs and lr, the cancel ``check``, ``max_rows`` (a weighted systematic subsample by
            ``rng`` beyond it) and ``tolerance`` (over :data:`PLATEAU_EPOCHS` epochs)."""
    max_rows, tolerance, check = options.max_rows, options.tolerance, options.check
    rng = options.rng or np.random.default_rng(0)
    head = proposal.noise_shift
    w = libm.exp(np.asarray(log_w, dtype=np.float64) - np.max(log_w))
    if max_rows is not None and w.size > max_rows:  # systematic resampling in proportion to the weights
        cum = np.cumsum(w)
        picks = np.searchsorted(cum, (rng.random() + np.arange(max_rows)) * (cum[-1] / max_rows), side="right")
        picks, times = np.unique(np.minimum(picks, w.size - 1), return_counts=True)
        obs, noise, loc_p, log_scale_p, w = obs[picks], noise[picks], loc_p[picks], log_scale_p[picks], times * 1.0
    x = torch.from_numpy(np.ascontiguousarray(np.asarray(obs)[:, proposal.input_columns()] / proposal.input_scales()))
    e, lp, ls = (torch.as_tensor(np.asarray(a, dtype=np.float64)) for a in (noise, loc_p, log_scale_p))
    weights = torch.as_tensor(w / w.sum())
    params = list(head.parameters())
    opt = Adam(params, lr=options.lr)
    losses: list[float] = []
    for epoch in range(options.epochs):
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


class Backprop:
    """Backpropagation through a proposal network written out (Rumelhart, Hinton & Williams 1986), without autograd:
    :meth:`forward` returns log q [M, 2] (nats) and what :meth:`backward` needs, which writes d loss / d parameter
    into ``grads``, calling autograd's own kernels in its order into buffers allocated once (a test checks the
    fitted parameters to 1e-9). Parameters are read through the bound tensors, so an optimiser must update them in
    place.

    Args:
        net: Linear-ReLU-Linear-ReLU-Linear-LogSoftmax (:class:`Proposal`'s ``net``).
        h: the network's input, float64 [M, k].
        grads: float64 tensors shaped like the parameters, in ``net.parameters()`` order."""

    def __init__(self, net: nn.Sequential, h: torch.Tensor, grads: list[torch.Tensor]) -> None:
        first, _, second, _, third, _ = net
        lin1, lin2, lin3 = cast(nn.Linear, first), cast(nn.Linear, second), cast(nn.Linear, third)  # the Linear layers
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
            # log softmax of two: log q(miss) = -softplus(z_1 - z_0), log q(detect) = -softplus(z_0 - z_1)
            if self.fast:
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


class Adam:
    """Adam (Kingma & Ba, "Adam: a method for stochastic optimization", ICLR 2015, Algorithm 1) with torch's
    defaults, operation for operation as ``torch.optim.Adam(params, lr)`` on CPU (bit-identical, tested), without
    ``torch.optim``'s import and per-step dispatch costs.

    Args:
        params: the tensors to optimise (``requires_grad``); their ``.grad`` is read by :meth:`step`.
        lr: step size (> 0)."""

    def __init__(
        self, params: list[torch.Tensor], lr: float, betas: tuple[float, float] = (0.9, 0.999), eps: float = 1e-8
    ) -> None:
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
        for p, m, v in zip(self.params, self.exp_avg, self.exp_avg_sq, strict=False):
            if p.grad is None:
                continue
            m.lerp_(p.grad, 1 - self.beta1)
            v.mul_(self.beta2).addcmul_(p.grad, p.grad, value=1 - self.beta2)
            p.addcdiv_(m, (v.sqrt() / bias_correction2_sqrt).add_(self.eps), value=-step_size)


def fit_in_torch(
    proposal,
    inputs,
    objective: Objective,
    epochs: int,
    lr: float,
    check: Callable[[], None] | None = None,
    optimizer: str = "adam",
    tolerance: float | None = None,
    per: float | None = None,
    dtype: torch.dtype | str | None = None,
) -> list[float]:
    """:func:`pemviz.core.sampling.fit_proposal`'s fits in torch: L-BFGS, a function objective, or an Adam fit in
    torch's float32 / float64 kernels (``dtype``: ``"float32"``, ``"float64"`` or a torch dtype); the arguments and
    the loss per step returned are :func:`~pemviz.core.sampling.fit_proposal`'s. ``inputs`` and a tensor objective
    may be numpy arrays (float64)."""
    function = objective if callable(objective) else None
    weights = None if callable(objective) else torch.as_tensor(objective, dtype=torch.float64)
    linear = weights is not None
    inputs = torch.as_tensor(inputs, dtype=torch.float64)
    dtype = {"float32": torch.float32, "float64": torch.float64}.get(dtype, dtype) if isinstance(dtype, str) else dtype
    # d loss / d log q of a tensor objective, formed as autograd forms it (the same bits)
    grad_linear = None if weights is None else (weights * -1.0 if per is None else weights * -(1.0 / per))

    def loss_and_grad(log_q: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        if function is not None:
            return function(log_q)
        assert weights is not None and grad_linear is not None  # a tensor objective: both formed above
        loss = -(weights * log_q).sum()
        return (loss if per is None else loss / per), grad_linear

    losses: list[float] = []
    if optimizer == "lbfgs":
        opt = torch.optim.LBFGS(
            proposal.net.parameters(),
            lr=1.0,
            max_iter=CHECK_EVERY,
            max_eval=10 * CHECK_EVERY,
            history_size=20,
            line_search_fn="strong_wolfe",
            tolerance_grad=1e-9,
            tolerance_change=LBFGS_TOLERANCE if tolerance is None else tolerance,
        )
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
    dtype = dtype if linear and dtype not in (EXACT, None) else torch.float64
    h = proposal.inputs(torch.as_tensor(inputs)).to(dtype)
    if grad_linear is not None:  # linear
        grad_linear = grad_linear.to(dtype)  # the loss itself is summed in float64 (its log q cast up)
    # one flat tensor for all parameters and one for their gradients (each parameter and gradient a view into it
    # while the fit runs), so that an Adam step is 7 kernel calls, not 7 per parameter: element for element the
    # same arithmetic as parameter by parameter
    params = list(proposal.net.parameters())  # the detection network (a measurement-error head fits apart)
    sizes = [p.numel() for p in params]
    flat = nn.Parameter(torch.cat([p.detach().reshape(-1) for p in params]).to(dtype))
    flat.grad = torch.zeros_like(flat)
    for p, view in zip(params, flat.detach().split(sizes), strict=False):
        p.data = view.view_as(p)
    net = Backprop(proposal.net, h, [g.view_as(p) for p, g in zip(params, flat.grad.split(sizes), strict=False)])
    adam = Adam([flat], lr=lr)
    try:
        for epoch in range(epochs):
            if check is not None and epoch % CHECK_EVERY == 0:
                check()  # may raise to stop the run (a cancel token)
            log_q, cache = net.forward()
            loss, grad = loss_and_grad(log_q)
            net.backward(cache, grad)
            adam.step()
            losses.append(loss.item())
            if (
                tolerance is not None
                and epoch >= PLATEAU_EPOCHS
                and losses[-PLATEAU_EPOCHS - 1] - losses[-1] < tolerance
            ):
                break  # converged: the loss has stopped falling
    finally:
        for p in params:  # each parameter its own storage again, in float64
            p.data = p.data.to(torch.float64, copy=True)
    return losses


torch_module()  # a run's pending thread count (pemviz.engine.resources.torch_threads) applies from here on
