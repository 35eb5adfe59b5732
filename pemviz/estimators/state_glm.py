"""The state proposal's generalised linear model (``state_model = "glm"``): q(detect | row, state) with

    logit q = logit p_PEM(detect | row) + w . h + b,

h the row's columns with the step's state features, each over its scale: the PEM's own logit as the offset of a
logistic regression (McCullagh & Nelder, "Generalized Linear Models", 1989), so that q is the PEM where w . h + b is
0 and the cross-entropy fit (the elites' weighted log-likelihood, Innes & Ramamoorthy 2022 eq. 10-11, with an L2
penalty on w) moves it only along the directions of the state that tell failures apart; the paper's
q(detect | salient variables) generalised, with one weight per feature to fit instead of a network's thousand."""

from __future__ import annotations

import copy
from collections.abc import Callable
from typing import Any

import numpy as np
from scipy.optimize import minimize
from scipy.special import log_expit

from pemviz.core import exact
from pemviz.core.sampling import FeatureProposal

GLM_L2 = 1e-2
"""The L2 penalty on w per unit of fitted weight (nats per squared unit of h): w stays near 0 along a feature the
elites do not tell apart."""


class StateGLM(FeatureProposal):
    """q(detect) as the PEM's logit plus a linear function of the row with its state features (module docstring).

    Args:
        columns, scales, reference: as :class:`pemviz.core.sampling.StateProposal` (every column of the rows with
            their features, the gap first).
        offset: the target's detector at such rows (it reads the rows' own columns:
            :class:`pemviz.estimators.state.FirstColumns`), whose logit is the offset."""

    def __init__(self, columns: tuple[int, ...], scales: tuple[float, ...], reference: tuple[float, ...], offset: Any):
        super().__init__(columns, scales, reference)
        self.offset = offset
        self.coef = np.zeros(len(columns) + 1)
        """(w [k], b): the linear part's weights over the scaled columns and its intercept."""

    def __deepcopy__(self, memo: dict) -> StateGLM:
        """A copy whose offset (the target) is shared: a stage's frozen copy of the proposal."""
        memo[id(self.offset)] = self.offset
        new = self.__class__.__new__(self.__class__)
        memo[id(self)] = new
        for k, v in self.__getstate__().items():
            setattr(new, k, copy.deepcopy(v, memo))
        return new

    def linear(self, obs: np.ndarray) -> np.ndarray:
        """w . h + b, float64 [N], at rows [N, k] in exact, order-free arithmetic (:func:`pemviz.core.exact.matmul`:
        a row's value whatever rows it is asked with)."""
        x = np.asarray(obs, dtype=np.float64)[:, list(self.columns)] / self.scales
        if x.shape[0] == 0:
            return np.zeros(0)
        w = self.coef[:-1][:, None]
        grid = exact.on_grid(w, exact.grid_bits(w.shape[0]), 0)
        return exact.matmul(x, None, grid)[:, 0] + self.coef[-1]

    def detect_logit(self, obs: np.ndarray) -> np.ndarray:
        """logit q(detect), float64 [N] (nats): the offset's logit plus :meth:`linear`."""
        obs = np.asarray(obs, dtype=np.float64)
        return np.asarray(self.offset.detect_logit(obs), dtype=np.float64) + self.linear(obs)

    def curve(self, gap_grid_m: np.ndarray) -> np.ndarray:
        """q(detect) over gaps (metres), float64 [G], the other columns at ``reference``."""
        rows = self._curve_inputs(gap_grid_m)
        return np.exp(log_expit(self.detect_logit(rows)))

    def fit_counts(
        self, inputs: np.ndarray, counts: np.ndarray, check: Callable[[], None] | None = None
    ) -> list[float]:
        """The cross-entropy update in place: minimise ``-sum_i (C_i1 log q(detect | h_i) + C_i0 log q(miss | h_i)) /
        sum C + GLM_L2 |w|^2 / 2`` over (w, b) by L-BFGS from the current (w, b), at rows ``inputs`` [M, k] with
        weighted miss and detection counts ``counts`` [M, 2]; rows where the target is certain are left out. Returns
        the final loss (nats per fitted event), or [] with nothing to fit."""
        if check is not None:
            check()
        off = np.asarray(self.offset.detect_logit(inputs), dtype=np.float64)
        keep = np.isfinite(off) & (counts.sum(axis=1) > 0)
        if not keep.any():
            return []
        x = inputs[keep][:, list(self.columns)] / self.scales
        x1 = np.concatenate([x, np.ones((x.shape[0], 1))], axis=1)
        c = counts[keep] / counts[keep].sum()
        off = off[keep]
        penalty = np.full(x1.shape[1], GLM_L2)
        penalty[-1] = 0.0

        def loss(theta: np.ndarray) -> tuple[float, np.ndarray]:
            z = off + x1 @ theta
            value = -(c[:, 1] * log_expit(z) + c[:, 0] * log_expit(-z)).sum() + 0.5 * (penalty * theta**2).sum()
            q = np.exp(log_expit(z))
            grad = x1.T @ (c.sum(axis=1) * q - c[:, 1]) + penalty * theta
            return float(value), grad

        out = minimize(loss, self.coef.copy(), jac=True, method="L-BFGS-B", options={"maxiter": 200})
        self.coef = np.asarray(out.x, dtype=np.float64)
        return [float(out.fun)]
