"""The settings every fit of the proposal shares, in torch or not (:func:`pemviz.core.sampling.fit_proposal`,
:mod:`pemviz.core.torch_fits`): how often a fit checks for a cancel, when it stops, the exact arithmetic's name."""

from __future__ import annotations

from typing import TYPE_CHECKING, Callable, Union

import numpy as np

if TYPE_CHECKING:
    import torch

CHECK_EVERY = 25
"""Epochs between two calls of a training loop's ``check`` callback (e.g. the engine's cancel check)."""


PLATEAU_EPOCHS = 50
"""Adam with a tolerance stops once the loss fell by less than it over this many epochs (early stopping)."""

LBFGS_TOLERANCE = 1e-6
"""L-BFGS stops once an iteration changes the loss (nats per step) or any parameter by less than this."""


Objective = Union[np.ndarray, "torch.Tensor", Callable[["torch.Tensor"], "tuple[torch.Tensor, torch.Tensor]"]]
"""What :func:`pemviz.core.sampling.fit_proposal` minimises over q_phi's log-probabilities log q [M, 2] (nats) at its
inputs: an array or tensor C [M, 2], the loss ``-sum(C * log q)`` (a weighted log-likelihood: C holds each input's
weighted counts of misses and detections), or a function of log q returning the scalar loss and its gradient
d loss / d log q [M, 2]."""


EXACT = "exact"
"""The arithmetic of an ``adam`` fit (``dtype`` of :func:`pemviz.core.sampling.fit_proposal`) that gives the same
parameters on every CPU, whatever its vector unit or BLAS kernel (:func:`pemviz.core.exact_fit.fit_exact`)."""
