"""The settings every fit of the proposal shares, in torch or not (:func:`pemviz.core.sampling.fit_proposal`,
:mod:`pemviz.core.torch_fits`): how often a fit checks for a cancel, when it stops, the exact arithmetic's name, and
:class:`FitOptions`, a fit's settings as one record."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Union

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


@dataclass(frozen=True)
class FitOptions:
    """How the proposal is fitted (:mod:`pemviz.estimators.ce_fit`'s pretraining and CE fits; the error head's
    :func:`pemviz.core.torch_fits.fit_noise_shift`: Adam whatever ``fit``, its own arithmetic).

    Args:
        epochs: Adam epochs, or the most L-BFGS iterations (``fit``).
        lr: the step size.
        check: called every :data:`CHECK_EVERY` epochs; may raise to abandon the fit (cancel).
        fit: one of :data:`pemviz.methods.adaptive.FITS`.
        max_rows: None (``adam``: every step, summed over distinct inputs, the paper's fit) or the most steps the fit
            sees: beyond that a weighted systematic subsample whose weighted log-likelihood has the same expectation
            (:func:`pemviz.estimators.ce_fit.weighted_steps`); the loss is then divided by the total weight.
        rng: draws that subsample (default: seeded 0).
        tolerance: early stopping of a fit of more than ``max_rows`` steps, or of ``lbfgs`` (nats per step;
            :func:`pemviz.core.sampling.fit_proposal`), None: every epoch; a fit of at most ``max_rows`` steps with
            ``adam`` runs every epoch (the paper's fit).
        dtype: the arithmetic of an ``adam`` fit (:func:`pemviz.core.sampling.fit_proposal`); float64 for the paper's.
    """

    epochs: int
    lr: float = 1e-3
    check: Callable[[], None] | None = None
    fit: str = "adam"
    max_rows: int | None = None
    rng: np.random.Generator | None = None
    tolerance: float | None = None
    dtype: Any = EXACT

    @property
    def args(self) -> tuple[int, float, Callable[[], None] | None, str]:
        """(epochs, lr, check, fit): the leading arguments of :func:`pemviz.core.sampling.fit_proposal`."""
        return self.epochs, self.lr, self.check, self.fit

    def summed(self, n_fitted: int) -> bool:
        """Whether a fit of ``n_fitted`` weighted steps is the paper's: every step, summed over distinct inputs (with
        a ``tolerance``, a CE stage's such fit stops once converged, as the others do). The other fits (more than
        ``max_rows`` steps, or L-BFGS) see at most ``max_rows`` steps, with a loss normalised to nats per step, and
        stop once converged (``tolerance``): their cost is bounded whatever the number of rollouts."""
        return self.fit == "adam" and (self.max_rows is None or n_fitted <= self.max_rows)
