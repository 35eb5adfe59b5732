"""A proposal over an operating design domain's parameters, q(theta), for importance sampling over the ODD jointly with
the perception's events. No I/O, no scenario.

:class:`ParameterProposal` draws theta from a piecewise-constant density over the cells of a grid of the ODD
(continuous parameters cut into bins of equal probability, a choice's values one bin each), within a cell from the
ODD's own law, so a rollout's parameter weight is P_ODD(cell) / q(cell), bounded by defensive mixing
(``defensive``). Cross-entropy fits the cells' probabilities to the elites (Rubinstein & Kroese 2004, ch. 3), as
Zhao et al. (IEEE T-ITS 2017) sample a scene's initial conditions. Parameters are a fixed function of a rollout's D
uniforms (chain rule, inverse CDF), so a seed gives the same rollouts at any chunk size; the weight enters the first
step's log q (:func:`parameter_log_ratio`)."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy.special import logsumexp

from pemviz.core.odd import ODD, Distribution

MAX_CELLS = 400
"""The most cells a grid over the ODD may have; an ODD that needs more gets no proposal (theta drawn from the ODD)."""

BINS = {1: 8, 2: 6, 3: 4, 4: 3}
"""Bins of a continuous parameter, by the number of parameters."""


def _parameter_bins(law: Distribution, k: int) -> tuple[np.ndarray, np.ndarray]:
    """(theta edges [B + 1] or a choice's sorted values [B], probabilities [B]) of one parameter's bins."""
    if law.discrete:
        order = np.argsort(law.args)
        return np.asarray(law.args, dtype=np.float64)[order], np.asarray(law.weights, dtype=np.float64)[order]
    edges, probs = law.bins(k)
    return edges, probs


@dataclass(frozen=True, eq=False)
class ParameterProposal:
    """q(theta) over an ODD's grid of cells (module docstring).

    Attributes:
        odd: the ODD.
        log_q: float64 [C] log q(cell) (nats), C = prod_j B_j, cells in C order over the parameters' bins.
        log_m: float64 [C] log P_ODD(cell) (nats).
        bins: each parameter's (edges [B + 1] or a choice's values [B], probabilities [B])."""

    odd: ODD
    log_q: np.ndarray
    log_m: np.ndarray
    bins: tuple[tuple[np.ndarray, np.ndarray], ...]

    @classmethod
    def of(cls, odd: ODD) -> ParameterProposal | None:
        """The proposal equal to the ODD itself over its grid, or None where the grid would exceed
        :data:`MAX_CELLS` cells (or the ODD has more than 4 parameters)."""
        d = len(odd)
        if d not in BINS:
            return None
        bins = tuple(_parameter_bins(law, BINS[d]) for _, law in odd.parameters)
        shape = tuple(len(p) for _, p in bins)
        if math.prod(shape) > MAX_CELLS:
            return None
        log_m = np.zeros(shape)
        for j, (_, p) in enumerate(bins):
            view = [1] * d
            view[j] = len(p)
            with np.errstate(divide="ignore"):
                log_m = log_m + np.log(p).reshape(view)
        log_m = log_m.reshape(-1)
        return cls(odd, log_m.copy(), log_m, bins)

    @property
    def shape(self) -> tuple[int, ...]:
        return tuple(len(p) for _, p in self.bins)

    def cells(self, values: np.ndarray) -> np.ndarray:
        """int64 [N]: the cell of each row of parameters ``values`` [N, D] (a continuous value on an edge goes to the
        bin above it, outside the outer edges to the outer bin; a choice's value to its own bin)."""
        values = np.asarray(values, dtype=np.float64).reshape(-1, len(self.odd))
        index = []
        for j, ((_, law), (edges, probs)) in enumerate(zip(self.odd.parameters, self.bins, strict=True)):
            if law.discrete:
                b = np.searchsorted(edges, values[:, j])
            else:
                b = np.searchsorted(edges, values[:, j], side="right") - 1
            index.append(np.clip(b, 0, len(probs) - 1))
        return np.ravel_multi_index(tuple(index), self.shape).astype(np.int64)

    def log_ratio(self, values: np.ndarray) -> np.ndarray:
        """log q(theta) - log p_ODD(theta), float64 [N] (nats), of parameters ``values`` [N, D]: the term a rollout's
        importance log-weight loses for being drawn from this proposal (within a cell theta follows the ODD)."""
        c = self.cells(values)
        return self.log_q[c] - self.log_m[c]

    def draw(self, u: np.ndarray) -> np.ndarray:
        """Parameters float64 [N, D] from uniforms ``u`` [N, D] in [0, 1) (module docstring: the chain rule over the
        parameters' bins, then the ODD's law inside the bin)."""
        u = np.asarray(u, dtype=np.float64).reshape(-1, len(self.odd))
        shape, n = self.shape, u.shape[0]
        q = np.exp(self.log_q - float(np.max(self.log_q))).reshape(shape)
        prefix = np.zeros(n, dtype=np.int64)
        out = np.empty_like(u)
        for j, ((_, law), (edges, _probs)) in enumerate(zip(self.odd.parameters, self.bins, strict=True)):
            before, here = math.prod(shape[:j]), shape[j]
            table = q.reshape(before, here, -1).sum(axis=2)  # [prefixes, B_j]: the bins' joint mass so far
            cum = np.cumsum(table, axis=1)
            total = cum[:, -1:]
            cond = cum[prefix] / total[prefix]  # [N, B_j] conditional CDF given the bins drawn before
            b = np.minimum((u[:, j : j + 1] >= cond).sum(axis=1), here - 1)
            lo = np.where(b > 0, cond[np.arange(n), np.maximum(b - 1, 0)], 0.0)
            width = cond[np.arange(n), b] - lo
            frac = np.clip((u[:, j] - lo) / np.where(width > 0, width, 1.0), 0.0, np.nextafter(1.0, 0.0))
            if law.discrete:
                out[:, j] = edges[b]
            else:
                out[:, j] = law.ppf((b + frac) / here)  # equal-probability bins: bin b is [b / B, (b + 1) / B) in u
            prefix = prefix * here + b
        return out

    def refit(self, values: np.ndarray, log_w: np.ndarray, rate: float, defensive: float) -> ParameterProposal:
        """The cross-entropy update: the cells' weighted frequencies among elites with parameters ``values`` [K, D]
        and log-weights ``log_w`` [K] (nats), q' = (1 - rate) q + rate q_elites, mixed with the ODD at share
        ``defensive`` so every parameter weight is at most 1 / defensive (Hesterberg, Technometrics 1995). No elite:
        unchanged.

        Raises:
            ValueError: ``rate`` or ``defensive`` out of range, or arrays of other lengths."""
        if not 0.0 < rate <= 1.0 or not 0.0 < defensive < 1.0:
            raise ValueError(f"ParameterProposal.refit: rate {rate}, defensive {defensive}; need (0, 1] and (0, 1)")
        log_w = np.asarray(log_w, dtype=np.float64).reshape(-1)
        c = self.cells(values)
        if c.size != log_w.size:
            raise ValueError(f"ParameterProposal.refit: {c.size} rows of parameters for {log_w.size} weights")
        keep = np.isfinite(log_w)
        if not keep.any():
            return self
        top = float(np.max(log_w[keep]))
        freq = np.bincount(c[keep], weights=np.exp(log_w[keep] - top), minlength=self.log_q.size)
        freq = freq / freq.sum()
        moved = (1.0 - rate) * np.exp(self.log_q) + rate * freq
        mixed = (1.0 - defensive) * moved + defensive * np.exp(self.log_m)
        with np.errstate(divide="ignore"):
            log_q = np.log(mixed)
        return ParameterProposal(self.odd, log_q - float(logsumexp(log_q)), self.log_m, self.bins)


def parameter_proposal_of(detector: Any) -> ParameterProposal | None:
    """The proposal over the ODD's parameters a sampler draws its rollouts' parameters from (its
    ``parameter_proposal``, looked for through the wrappers that keep a ``detector``), or None: from the ODD itself."""
    seen = 0
    while detector is not None and seen < 8:
        found = getattr(detector, "parameter_proposal", None)
        if found is not None:
            return found if isinstance(found, ParameterProposal) else None
        detector, seen = getattr(detector, "detector", None), seen + 1
    return None


def parameter_log_ratio(detector: Any, batch: Any) -> np.ndarray | None:
    """log q(theta) - log p_ODD(theta) [N] (nats) of a batch's rollouts under ``detector``'s proposal over the ODD
    (:func:`parameter_proposal_of`), theta read from the first step's columns named after the ODD's parameters; None
    where the detector draws theta from the ODD itself."""
    proposal = parameter_proposal_of(detector)
    if proposal is None:
        return None
    cols = [tuple(batch.observation_names).index(name) for name in proposal.odd.names]
    return proposal.log_ratio(batch.observations[:, 0][:, cols])
