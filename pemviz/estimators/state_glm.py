"""The state proposal's generalised linear model (``state_model = "glm"``): q(detect | row, state) with

    logit q = logit p_PEM(detect | row) + w . h + b,

h the row's columns with the step's state features, each over its scale: the PEM's own logit as the offset of a
logistic regression (McCullagh & Nelder, "Generalized Linear Models", 1989), so that q is the PEM where w . h + b is
0 and the cross-entropy fit (the elites' weighted log-likelihood, Innes & Ramamoorthy 2022 eq. 10-11, with an L2
penalty on w) moves it only along the directions of the state that tell failures apart; the paper's
q(detect | salient variables) generalised, with one weight per feature to fit instead of a network's thousand.

``state_model = "spline"`` puts an additive function of the scaled columns in place of w . h (a generalised additive
model, Hastie & Tibshirani, "Generalized Additive Models", 1990): each column expanded into the piecewise-linear
B-splines (hats) at its fitted rows' quantiles (:func:`hat_basis`), their knots fixed at each fit, so that q can
depart from the PEM inside a window of a feature (a range of steps) and not outside it, which no function linear in
the features can."""

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


SPLINE_KNOTS = 8
"""Knots per column of ``state_model = "spline"``: its fitted rows' quantiles at levels 0, 1/7, ..., 1 (fewer where
they coincide, as for a feature of a few values)."""


def hat_basis(x: np.ndarray, knots: np.ndarray) -> np.ndarray:
    """The piecewise-linear B-splines (hats) at ``knots[1:]`` of values ``x`` [N]: float64 [N, K - 1] for K knots
    (increasing), hat i 1 at ``knots[i]``, 0 at its neighbours and beyond them, linear between; the last is 1 beyond the
    last knot and every one 0 below the first (its hat is left out: the intercept stands for it). Each value reads its
    own ``x`` alone (de Boor, "A Practical Guide to Splines", 1978, ch. IX: B-splines of order 2).

    Raises:
        ValueError: fewer than two knots, or knots not increasing."""
    knots = np.asarray(knots, dtype=np.float64)
    if knots.ndim != 1 or len(knots) < 2 or not (np.diff(knots) > 0).all():
        raise ValueError(f"hat_basis: knots must be at least two increasing values, got {knots}")
    x = np.asarray(x, dtype=np.float64)[:, None]
    rise = (x - knots[:-1]) / np.diff(knots)  # [N, K - 1]: toward hat i + 1's peak
    fall = np.ones_like(rise)
    fall[:, :-1] = (knots[2:] - x) / np.diff(knots[1:])  # [N, K - 2]: past it (the last hat does not fall)
    return np.clip(np.minimum(rise, fall), 0.0, 1.0)


def quantile_knots(x: np.ndarray, n: int) -> np.ndarray | None:
    """The distinct quantiles of values ``x`` [M] at ``n`` levels from 0 to 1, float64 [<= n], or None where fewer
    than two are distinct (a column the fitted rows do not vary)."""
    knots = np.unique(np.quantile(np.asarray(x, dtype=np.float64), np.linspace(0.0, 1.0, n)))
    return knots if len(knots) >= 2 else None


class StateGLM(FeatureProposal):
    """q(detect) as the PEM's logit plus a linear function of the row with its state features (module docstring).

    Args:
        columns, scales, reference: as :class:`pemviz.core.sampling.StateProposal` (every column of the rows with
            their features, the gap first).
        offset: the target's detector at such rows (it reads the rows' own columns:
            :class:`pemviz.estimators.state.FirstColumns`), whose logit is the offset.
        knots: 0 for the linear model; else the knots per column of the additive one (:data:`SPLINE_KNOTS`)."""

    def __init__(
        self,
        columns: tuple[int, ...],
        scales: tuple[float, ...],
        reference: tuple[float, ...],
        offset: Any,
        knots: int = 0,
    ):
        super().__init__(columns, scales, reference)
        self.offset, self.n_knots = offset, int(knots)
        self.knots: list[np.ndarray | None] = [None] * len(columns)
        """Each column's knots (scaled units) of the additive model, set at each fit (None: the column left out)."""
        self.coef = np.zeros(len(columns) + 1 if not self.n_knots else 1)
        """(w, b): the weights of the linear part's terms (the scaled columns, or their hats) and its intercept."""

    def __deepcopy__(self, memo: dict) -> StateGLM:
        """A copy whose offset (the target) is shared: a stage's frozen copy of the proposal."""
        memo[id(self.offset)] = self.offset
        new = self.__class__.__new__(self.__class__)
        memo[id(self)] = new
        for k, v in self.__getstate__().items():
            setattr(new, k, copy.deepcopy(v, memo))
        return new

    def terms(self, obs: np.ndarray) -> np.ndarray:
        """The linear part's terms at rows [N, k], float64 [N, len(coef) - 1]: the scaled columns (the linear model)
        or their hats at :attr:`knots` (the additive one)."""
        x = np.asarray(obs, dtype=np.float64)[:, list(self.columns)] / self.scales
        if not self.n_knots:
            return x
        hats = [hat_basis(x[:, j], k) for j, k in enumerate(self.knots) if k is not None]
        return np.concatenate(hats, axis=1) if hats else np.zeros((x.shape[0], 0))

    def linear(self, obs: np.ndarray) -> np.ndarray:
        """w . h + b, float64 [N], at rows [N, k] (h: :meth:`terms`) in exact, order-free arithmetic
        (:func:`pemviz.core.exact.matmul`: a row's value whatever rows it is asked with)."""
        x = self.terms(obs)
        if x.shape[0] == 0 or x.shape[1] == 0:
            return np.full(x.shape[0], self.coef[-1])
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
        sum C + GLM_L2 |w|^2 / 2`` over (w, b) by L-BFGS from the current (w, b) (the additive model: from 0, its
        knots first set to the fitted rows' quantiles), at rows ``inputs`` [M, k] with weighted miss and detection
        counts ``counts`` [M, 2]; rows where the target is certain are left out. Returns the final loss (nats per
        fitted event), or [] with nothing to fit."""
        if check is not None:
            check()
        off = np.asarray(self.offset.detect_logit(inputs), dtype=np.float64)
        keep = np.isfinite(off) & (counts.sum(axis=1) > 0)
        if not keep.any():
            return []
        if self.n_knots:
            scaled = inputs[keep][:, list(self.columns)] / self.scales
            self.knots = [quantile_knots(scaled[:, j], self.n_knots) for j in range(len(self.columns))]
            self.coef = np.zeros(sum(len(k) - 1 for k in self.knots if k is not None) + 1)
        x = self.terms(inputs[keep])
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
