"""The proposal's Adam fits in exact, order-free arithmetic (:mod:`pemviz.core.exact`): the same parameters, bit for
bit, on every CPU, whatever its vector unit or BLAS kernel and however the rollouts were chunked."""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

import numpy as np

from pemviz.core import exact

COUNT_BITS = 24
"""The bits an exact fit keeps of its weighted counts, relative to the largest (:func:`fit_exact`)."""


def fit_exact(
    proposal: Any,
    inputs: np.ndarray,
    counts: np.ndarray,
    epochs: int,
    lr: float,
    check: Callable[[], None] | None = None,
    tolerance: float | None = None,
    per: float | None = None,
    *,
    check_every: int,
    plateau_epochs: int,
) -> list[float]:
    """Full-batch Adam on the weighted log-likelihood ``-sum(C * log q) / per`` (:data:`Objective`, a tensor C), in
    place, in exact order-free arithmetic (:mod:`pemviz.core.exact`): the same parameters, bit for bit, on every
    CPU.

    Forward and backward passes are written out (Rumelhart, Hinton & Williams 1986), every matrix operand rounded
    once to a power-of-two grid of ``grid_bits(max(M, 32))`` bits (:func:`pemviz.core.exact.to_grid`) so that
    products and bias gradients are exact integer sums; the two outputs' log-softmax as ``-softplus(+-d)``, d =
    z_detect - z_miss; Adam (Kingma & Ba 2015, Algorithm 1, torch's defaults) in elementwise float64. Precision is
    about float32's. The counts C / per are first rounded to :data:`COUNT_BITS` bits of the largest, so that counts
    differing in their last bits give the same fit.

    Args:
        proposal: the :class:`pemviz.core.sampling.Proposal` fitted, in place.
        inputs: float64 [M] or [M, k] (:meth:`pemviz.core.sampling.Proposal.forward`).
        counts: C float64 [M, 2] (miss, detect).
        epochs: Adam steps, as :func:`pemviz.core.sampling.fit_proposal`.
        lr: Adam's step size.
        check: called every ``check_every`` epochs; may raise (a cancel token) to abandon the fit.
        tolerance: as :func:`pemviz.core.sampling.fit_proposal` (None: every epoch).
        per: as :func:`pemviz.core.sampling.fit_proposal` (None: not divided).
        check_every: epochs between two ``check`` calls (:data:`pemviz.core.fit_settings.CHECK_EVERY`).
        plateau_epochs: the epochs over which the loss must fall by ``tolerance``
            (:data:`pemviz.core.fit_settings.PLATEAU_EPOCHS`).
    Returns:
        the loss per epoch (nats, divided by ``per``)."""
    h = np.ascontiguousarray(proposal.input_array(inputs))
    c = np.asarray(counts, dtype=np.float64)
    params = proposal.parameter_arrays()
    flat = np.concatenate([p.reshape(-1) for p in params]).astype(np.float64)
    shapes = [tuple(p.shape) for p in params]
    sizes = [p.size for p in params]
    offsets = np.cumsum([0, *sizes])
    views = [flat[a:b].reshape(shape) for a, b, shape in zip(offsets[:-1], offsets[1:], shapes, strict=False)]
    w1, b1, w2, b2, w3, b3 = views
    grad = np.zeros_like(flat)
    g_w1, g_b1, g_w2, g_b2, g_w3, g_b3 = (
        grad[a:b].reshape(shape) for a, b, shape in zip(offsets[:-1], offsets[1:], shapes, strict=False)
    )
    # the weighted counts come from float64 weights whose last bits may depend on the CPU's libm (exp, log): on a
    # grid of COUNT_BITS bits they are the same numbers unless one lies within an ulp of a grid point's midpoint
    ci, ec = exact.on_grid(c * (1.0 if per is None else 1.0 / per), COUNT_BITS, None)
    c_miss, c_detect = np.ldexp(ci[:, 0], ec[0]), np.ldexp(ci[:, 1], ec[0])
    c_both = c_miss + c_detect
    m_rows = h.shape[0]
    bits = exact.grid_bits(max(m_rows, 32))  # each operand's bits, for the products over 32 units and over M rows
    hi, sh = exact.to_grid(h, bits)  # the inputs are fixed: on their grid once
    one_input, ones = h.shape[1] == 1, np.ones(m_rows)
    beta1, beta2, eps = 0.9, 0.999, 1e-8
    beta1_t = beta2_t = 1.0
    exp_avg, exp_avg_sq = np.zeros_like(flat), np.zeros_like(flat)
    losses: list[float] = []
    for epoch in range(epochs):
        if check is not None and epoch % check_every == 0:
            check()  # may raise to stop the run (a cancel token)
        w1i, s1 = exact.to_grid(w1.T, bits)
        a1 = hi * w1i if one_input else hi @ w1i  # one input: the outer product, each entry one exact product
        a1 *= sh * s1
        a1 += b1
        np.maximum(a1, 0.0, out=a1)
        a1i, sa1 = exact.to_grid(a1, bits, nonneg=True)
        w2i, s2 = exact.to_grid(w2, bits)
        a2 = a1i @ w2i.T
        a2 *= sa1 * s2
        a2 += b2
        np.maximum(a2, 0.0, out=a2)
        a2i, sa2 = exact.to_grid(a2, bits, nonneg=True)
        w_diff = w3[1] - w3[0]
        wdi, sd = exact.to_grid(w_diff, bits)
        d = a2i @ wdi
        d *= sa2 * sd
        d += b3[1] - b3[0]
        softplus, sigmoid = exact.softplus_and_sigmoid(d)
        # -(C_miss log q(miss) + C_detect log q(detect)), log q(detect) = -softplus(-d) = d - softplus(d)
        losses.append(float(exact.exact_sum((c_both * softplus - c_detect * d)[:, None], 0)[0]))
        ddi, sdd = exact.to_grid(c_both * sigmoid - c_detect, bits)  # d loss / d d
        g_w3[1] = (ddi @ a2i) * (sdd * sa2)
        np.negative(g_w3[1], out=g_w3[0])
        g_b3[1] = ddi.sum() * sdd  # integers below 2^53: exact in any order
        g_b3[0] = -g_b3[1]
        dz2 = ddi[:, None] * wdi[None, :]  # exact products of integers, scaled by sdd * sd
        dz2 *= a2 > 0
        dz2i, sz2 = exact.to_grid(dz2, bits)
        sz2 *= sdd * sd
        g_w2[...] = (dz2i.T @ a1i) * (sz2 * sa1)
        g_b2[...] = (ones @ dz2i) * sz2  # integers below 2^53: exact in any order
        dz1 = dz2i @ w2i
        dz1 *= a1 > 0
        dz1i, sz1 = exact.to_grid(dz1, bits)
        sz1 *= sz2 * s2
        g_w1[...] = (dz1i.T @ hi) * (sz1 * sh)
        g_b1[...] = (ones @ dz1i) * sz1
        beta1_t *= beta1
        beta2_t *= beta2
        exp_avg *= beta1
        exp_avg += (1.0 - beta1) * grad
        exp_avg_sq *= beta2
        exp_avg_sq += (1.0 - beta2) * (grad * grad)
        denom = np.sqrt(exp_avg_sq)
        denom /= math.sqrt(1.0 - beta2_t)
        denom += eps
        flat -= (lr / (1.0 - beta1_t)) * (exp_avg / denom)
        if tolerance is not None and epoch >= plateau_epochs and losses[-plateau_epochs - 1] - losses[-1] < tolerance:
            break  # converged: the loss has stopped falling
    proposal.set_parameter_arrays(views)
    return losses
