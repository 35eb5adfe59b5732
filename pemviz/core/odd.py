"""An operating design domain (ODD): scenario parameters drawn from distributions instead of fixed values, and the
failure probability over it, p_ODD = E_theta[p(theta)] (ISO 21448; Zhao et al., IEEE T-ITS 2017). No I/O, no
scenario.

A parameter's distribution is ``uniform(a, b)``, ``normal(mu, sd)``, ``choice(a, b, c)`` or ``choice(a: w_a, b:
w_b)`` (:func:`parse_distribution`); an :class:`ODD` is their independent joint law. Every draw is an inverse-CDF
transform of uniforms (:meth:`Distribution.ppf`), so a seed gives the same parameters whatever the chunking. The
failure map splits each parameter into bins of equal probability (:meth:`Distribution.bins`) and estimates p(failure
| theta in bin) from the weights of the rollouts drawn there (:func:`bin_log_weights`), with its own interval, ESS
and verdict."""

from __future__ import annotations

import math
import re
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

if TYPE_CHECKING:
    from pemviz.core.estimate import Estimate

KINDS = ("uniform", "normal", "choice")
"""The distributions a parameter may be given."""

_CALL = re.compile(r"^\s*([a-z_]+)\s*\((.*)\)\s*$", re.S)


class ODDError(ValueError):
    """An ODD that cannot be used: an unknown distribution, bad arguments, an empty support (one line)."""


@dataclass(frozen=True)
class Distribution:
    """One parameter's law.

    Attributes:
        kind: one of :data:`KINDS`.
        args: ``(a, b)`` for uniform (a < b), ``(mu, sd)`` for normal (sd > 0), the values for choice.
        weights: choice only: each value's probability (summing to 1); empty otherwise."""

    kind: str
    args: tuple[float, ...]
    weights: tuple[float, ...] = ()

    @property
    def text(self) -> str:
        """How it is written: ``uniform(10, 14)``, ``choice(19.5: 0.25, 20: 0.75)``."""
        if self.kind == "choice":
            even = len(set(self.weights)) == 1
            items = [f"{v:g}" if even else f"{v:g}: {w:g}" for v, w in zip(self.args, self.weights, strict=True)]
            return f"choice({', '.join(items)})"
        return f"{self.kind}({', '.join(f'{a:g}' for a in self.args)})"

    @property
    def discrete(self) -> bool:
        return self.kind == "choice"

    def support(self) -> tuple[float, float]:
        """The smallest and largest value it can take (a normal's: its 1e-9 and 1 - 1e-9 quantiles, the range its
        draws can reach from float64 uniforms in practice)."""
        if self.kind == "uniform":
            return float(self.args[0]), float(self.args[1])
        if self.kind == "normal":
            lo, hi = self.ppf(np.array([1e-9, 1.0 - 1e-9]))
            return float(lo), float(hi)
        return float(min(self.args)), float(max(self.args))

    def ppf(self, u: np.ndarray) -> np.ndarray:
        """The values at uniforms ``u`` in [0, 1), float64 (the inverse CDF; a choice's value whose cumulative
        weight first exceeds u)."""
        u = np.asarray(u, dtype=np.float64)
        if self.kind == "uniform":
            a, b = self.args
            return a + u * (b - a)
        if self.kind == "normal":
            from scipy.special import ndtri

            mu, sd = self.args
            return mu + sd * ndtri(np.clip(u, 1e-300, 1.0 - 1e-16))
        cum = np.cumsum(self.weights)
        index = np.minimum(np.searchsorted(cum, u, side="right"), len(self.args) - 1)
        return np.asarray(self.args, dtype=np.float64)[index]

    def bins(self, k: int = 5) -> tuple[np.ndarray, np.ndarray]:
        """The map's bins: ``(edges [B + 1], probabilities [B])``; a continuous law's ``k`` bins of equal
        probability (quantile edges, the outer ones its :meth:`support`), a choice's one bin per value (edges
        halfway between the sorted values)."""
        if self.kind == "choice":
            order = np.argsort(self.args)
            values = np.asarray(self.args, dtype=np.float64)[order]
            probs = np.asarray(self.weights, dtype=np.float64)[order]
            mids = (values[1:] + values[:-1]) / 2.0
            return np.concatenate([[values[0] - 0.5], mids, [values[-1] + 0.5]]), probs
        lo, hi = self.support()
        inner = self.ppf(np.arange(1, k) / k)
        return np.concatenate([[lo], inner, [hi]]), np.full(k, 1.0 / k)


def _number(text: str, where: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise ODDError(f"{where}: {text.strip()!r} is not a number") from None
    if not math.isfinite(value):
        raise ODDError(f"{where}: {text.strip()!r} is not a finite number")
    return value


def parse_distribution(text: str, where: str = "distribution") -> Distribution:
    """A parameter's distribution from its text (module docstring).

    Raises:
        ODDError: one line naming ``where``: an unknown distribution (the allowed ones listed), a wrong number of
            arguments, a non-number, an empty support (uniform with b <= a, a normal's sd <= 0, no choice), a weight
            that is negative or weights summing to 0."""
    match = _CALL.match(str(text))
    if match is None:
        raise ODDError(
            f"{where}: {str(text).strip()!r} is not a distribution; write uniform(a, b), normal(mu, sd) "
            "or choice(a, b, ...)"
        )
    kind, inner = match.group(1), match.group(2)
    if kind not in KINDS:
        raise ODDError(f"{where}: unknown distribution {kind!r}; use one of {', '.join(KINDS)}")
    parts = [p for p in (s.strip() for s in inner.split(",")) if p] if inner.strip() else []
    if kind == "choice":
        if not parts:
            raise ODDError(f"{where}: choice() has no value (an empty support); give at least one")
        values, weights = [], []
        for part in parts:
            value, sep, weight = part.partition(":")
            values.append(_number(value, where))
            weights.append(_number(weight, where) if sep else 1.0)
        if any(w < 0 for w in weights) or sum(weights) <= 0:
            raise ODDError(f"{where}: choice weights must be >= 0 and not all 0, got {weights}")
        if len(set(values)) != len(values):
            raise ODDError(f"{where}: choice values must be distinct, got {values}")
        total = sum(weights)
        return Distribution("choice", tuple(values), tuple(w / total for w in weights))
    if len(parts) != 2:
        raise ODDError(
            f"{where}: {kind} takes 2 numbers, {'a, b' if kind == 'uniform' else 'mu, sd'}; got " f"{len(parts)}"
        )
    a, b = (_number(p, where) for p in parts)
    if kind == "uniform" and not a < b:
        raise ODDError(f"{where}: uniform({a:g}, {b:g}) has an empty support; need a < b")
    if kind == "normal" and not b > 0:
        raise ODDError(f"{where}: normal({a:g}, {b:g}) needs sd > 0")
    return Distribution(kind, (a, b))


@dataclass(frozen=True)
class ODD:
    """Independent scenario parameters, each drawn from its :class:`Distribution` (name -> law, in order)."""

    parameters: tuple[tuple[str, Distribution], ...]

    @property
    def names(self) -> tuple[str, ...]:
        return tuple(name for name, _ in self.parameters)

    def __len__(self) -> int:
        return len(self.parameters)

    def draw(self, u: np.ndarray) -> np.ndarray:
        """The parameters of rollouts with uniforms ``u`` [N, D] (D = len(self)): float64 [N, D] in
        :attr:`names` order."""
        u = np.asarray(u, dtype=np.float64).reshape(-1, len(self))
        return np.stack([law.ppf(u[:, j]) for j, (_, law) in enumerate(self.parameters)], axis=1)

    def text(self) -> str:
        """``gap0_m ~ uniform(10, 14), ego_speed0_mps ~ normal(7.8, 0.5)``."""
        return ", ".join(f"{name} ~ {law.text}" for name, law in self.parameters)

    def to_json(self) -> list[dict[str, object]]:
        """The ODD as JSON: one ``{"name", "distribution", "args", "weights"}`` per parameter."""
        return [
            {
                "name": name,
                "distribution": law.kind,
                "args": list(law.args),
                "weights": list(law.weights),
                "text": law.text,
            }
            for name, law in self.parameters
        ]


def bin_log_weights(values: np.ndarray, log_w: np.ndarray, edges: np.ndarray, probs: np.ndarray, b: int) -> np.ndarray:
    """The log importance weights [N] (nats) that estimate p(failure | theta in bin ``b``) as the plain mean of ``w
    1[fail]``: ``log w - log P(bin)`` for a rollout whose ``values`` [N] fall in the bin, ``-inf`` for the others;
    unbiased, as E[w 1[fail] 1[theta in bin]] = P(fail, theta in bin)."""
    values = np.asarray(values, dtype=np.float64)
    last = b == len(probs) - 1
    inside = (values >= edges[b]) & ((values <= edges[b + 1]) if last else (values < edges[b + 1]))
    if b == 0:
        inside |= values < edges[0]
    if last:
        inside |= values > edges[-1]
    return np.where(inside, np.asarray(log_w, dtype=np.float64) - math.log(float(probs[b])), -np.inf)


@dataclass(frozen=True)
class MapBin:
    """One bin of the ODD's map: a parameter's range, its probability under the ODD, p(failure | parameter in it)
    (:class:`pemviz.core.estimate.Estimate`) and its share of p_ODD (P(bin) p_bin over the sum of the bins' terms)."""

    name: str
    lo: float
    hi: float
    probability: float
    estimate: Estimate
    share: float

    @property
    def label(self) -> str:
        """``speed in [10, 10.8)``; a choice's bin of whole numbers names its value: ``lane = 2``."""
        if self.hi - self.lo == 1.0 and float(self.lo + 0.5).is_integer():
            return f"{self.name} = {self.lo + 0.5:g}"
        return f"{self.name} in [{self.lo:.4g}, {self.hi:.4g})"


def odd_map(
    odd: ODD, values: np.ndarray, log_w: np.ndarray, failed: np.ndarray, log_p_total: np.ndarray, k: int = 5
) -> list[MapBin]:
    """The map of where p_ODD comes from, one parameter at a time: for each parameter of ``odd``, its bins
    (:meth:`Distribution.bins`, ``k`` of equal probability) with p(failure | bin) estimated from rollouts with
    parameters ``values`` [N, D], log-weights ``log_w`` [N] (nats) and failures ``failed`` [N]
    (:func:`bin_log_weights`, :func:`pemviz.core.estimate.estimate`); with every weight 1 (plain Monte Carlo) the
    failure rate of the bin's rollouts with its Clopper-Pearson interval.

    Raises:
        ValueError: arrays of other lengths."""
    from pemviz.core.estimate import estimate

    values = np.asarray(values, dtype=np.float64).reshape(len(log_w), len(odd))
    failed = np.asarray(failed, dtype=bool)
    if failed.shape != np.shape(log_w) or np.shape(log_p_total) != np.shape(log_w):
        raise ValueError("odd_map: values, log_w, failed and log_p_total must describe the same rollouts")
    log_p = np.asarray(log_p_total, dtype=np.float64)
    plain = bool(np.all(np.asarray(log_w, dtype=np.float64) == 0.0))  # plain Monte Carlo: theta drawn from the ODD
    out: list[MapBin] = []
    for j, (name, law) in enumerate(odd.parameters):
        edges, probs = law.bins(k)
        rows = []
        for b in range(len(probs)):
            lw = bin_log_weights(values[:, j], log_w, edges, probs, b)
            inside = np.isfinite(lw)
            if plain and inside.any():  # the bin's own rollouts, its failures binomial given their number
                rows.append((b, estimate(np.zeros(int(inside.sum())), failed[inside], log_p[inside])))
            else:
                rows.append((b, estimate(lw, failed & inside, log_p)))
        terms = np.array([probs[b] * math.exp(e.log_mu_hat) if e.n_failures else 0.0 for b, e in rows])
        total = float(terms.sum())
        for (b, e), term in zip(rows, terms, strict=True):
            out.append(
                MapBin(
                    name,
                    float(edges[b]),
                    float(edges[b + 1]),
                    float(probs[b]),
                    e,
                    float(term / total) if total > 0 else 0.0,
                )
            )
    return out


@dataclass(frozen=True)
class PairMap:
    """p(failure | cell) over the first two parameters of an ODD.

    Attributes:
        names: ``(x, y)``, the two parameters.
        x_edges, y_edges: float64 ``[Bx + 1]``, ``[By + 1]``: their bins' edges.
        x_probs, y_probs: float64 ``[Bx]``, ``[By]``: their bins' probabilities.
        cells: ``cells[b][a]`` the estimate of p(failure | x in bin a, y in bin b) (:class:`pemviz.core.estimate.
            Estimate`).
        shares: float64 ``[By, Bx]``: each cell's share of p_ODD (P(cell) p_cell over their sum; 0 without failure)."""

    names: tuple[str, str]
    x_edges: np.ndarray
    y_edges: np.ndarray
    x_probs: np.ndarray
    y_probs: np.ndarray
    cells: tuple[tuple[Estimate, ...], ...]
    shares: np.ndarray

    def log10_p(self) -> np.ndarray:
        """float64 ``[By, Bx]``: log10 of each cell's estimate (nan where the cell has no failure)."""
        return np.array(
            [[e.log_mu_hat / math.log(10) if e.n_failures else math.nan for e in row] for row in self.cells]
        )

    def top(self) -> tuple[int, int] | None:
        """``(a, b)`` of the cell with the largest share of p_ODD, or None without failures."""
        if not np.any(self.shares > 0):
            return None
        b, a = np.unravel_index(int(np.argmax(self.shares)), self.shares.shape)
        return int(a), int(b)

    def cell_label(self, a: int, b: int) -> str:
        """``x in [lo, hi) and y in [lo, hi)`` of cell ``(a, b)``."""
        x, y = self.names
        return (
            f"{x} in [{self.x_edges[a]:.4g}, {self.x_edges[a + 1]:.4g}) and {y} in "
            f"[{self.y_edges[b]:.4g}, {self.y_edges[b + 1]:.4g})"
        )

    def lines(self) -> list[str]:
        """The heat map as text: a header of the x bins, a row per y bin with each cell's p (``>=`` where only its
        lower bound is backed, ``-`` without failure), and the cell that carries most of p_ODD."""
        x, y = self.names
        width = 10
        corner = f"{y} by {x}"
        head = f"  {corner:>24s} " + "".join(
            f"{f'{self.x_edges[a]:.3g}-{self.x_edges[a + 1]:.3g}':>{width}s}" for a in range(len(self.x_probs))
        )
        out = [f"odd map of the pair ({x}, {y}): p(failure | cell)", head]
        for b, row in enumerate(self.cells):
            label = f"{self.y_edges[b]:.3g}-{self.y_edges[b + 1]:.3g}"
            out.append(f"  {label:>24s} " + "".join(f"{cell_text(e):>{width}s}" for e in row))
        top = self.top()
        if top is not None:
            a, b = top
            out.append(f"most of p_ODD in the pair: {self.cell_label(a, b)} ({100 * self.shares[b, a]:.0f} % of it)")
        return out

    def document(self) -> dict[str, Any]:
        """The heat map for the result document: the pair, the edges and each cell's log p (nats; None without a
        failure), 95 % interval of log p (None for an end it lacks), verdict and share, rows by the y bin."""
        return {
            "names": list(self.names),
            "x_edges": [float(v) for v in self.x_edges],
            "y_edges": [float(v) for v in self.y_edges],
            "cells": [
                [
                    {
                        "log_p": e.log_mu_hat if e.n_failures else None,
                        "log_ci": [float(v) if np.isfinite(v) else None for v in e.shown_log_ci],
                        "verdict": e.verdict,
                        "share": float(self.shares[b, a]),
                    }
                    for a, e in enumerate(row)
                ]
                for b, row in enumerate(self.cells)
            ],
        }


def cell_text(e: Estimate) -> str:
    """A heat-map cell's p: ``1.2e-03``, ``>=1.2e-03`` (a lower bound where its weights back no interval), ``-``
    without failure."""
    if not e.n_failures:
        return "-"
    p = f"{math.exp(e.log_mu_hat):.1e}"
    return p if e.interval_backed else ">=" + f"{math.exp(e.shown_log_ci[0]):.1e}"


@dataclass(frozen=True)
class OddMap:
    """The map of a run over an ODD (:func:`odd_map`) as its final estimate carries it: the ODD, the rollouts the
    bins were estimated from (the final stage's) and the bins, each parameter's in order."""

    odd: ODD
    rollouts: int
    bins: tuple[MapBin, ...]
    pair: PairMap | None = None
    """The heat map of the first two parameters (:func:`pemviz.core.odd_pair.pair_map`); None for one parameter."""

    def top(self) -> MapBin | None:
        """The bin with the largest share of p_ODD, or None where no bin has a failure."""
        best = max(self.bins, key=lambda b: b.share, default=None)
        return best if best is not None and best.share > 0 else None

    def unfailed_cap(self) -> tuple[str, str] | None:
        """("doubtful", why) where a bin of the map has no failure among the final rollouts of an importance-sampling
        run, else None: the proposal may have left that region of the ODD unsampled while the weights look reliable
        (e.g. the toy with its braking drawn from 5, 6 and 7, seed 1: no failure at b = 5, 89 % of p_ODD, ESS 90,
        k-hat 0.06, x0.07; docs/odd.md). Plain Monte Carlo's map is not judged: its interval is binomial."""
        empty = [b for b in self.bins if b.estimate.n_failures == 0 and not b.estimate.plain_mc]
        if not empty:
            return None
        return "doubtful", (
            f"no failure in {empty[0].label} (of {len(empty)} bin{'s' if len(empty) > 1 else ''} without one): "
            "the proposal may have missed that region of the ODD, whatever its weights show"
        )

    def lines(self) -> list[str]:
        """The map as the console prints it: a header, a line per bin, the region that carries most of p_ODD."""
        from pemviz.core.estimate import format_probability

        if not self.bins:
            return []
        out = [
            f"odd map ({self.odd.text()}; the final stage's {self.rollouts:,} rollouts): p(failure | bin), "
            "its 95 % interval or lower bound, its verdict, its share of p_ODD"
        ]
        for b in self.bins:
            e = b.estimate
            said = format_probability(e.log_mu_hat) if e.n_failures else "no failure"
            out.append(
                f"  {b.label:32s} P(bin) {b.probability:.2f}  p {said:>10s} {e.interval_text():>26s}  "
                f"{e.verdict:10s} share {100 * b.share:5.1f} %"
            )
        top = self.top()
        if top is not None:
            out.append(f"most of p_ODD: {top.label} ({100 * top.share:.0f} % of it, P(bin) {top.probability:.2f})")
        return out + (self.pair.lines() if self.pair is not None else [])

    def document(self) -> dict[str, Any]:
        """The map for the result document (JSON): the ODD and each bin's range, probability, log p (nats; None
        without a failure), 95 % interval of log p (None for an end it lacks), verdict and share."""
        bins = []
        for b in self.bins:
            e = b.estimate
            bins.append(
                {
                    "parameter": b.name,
                    "lo": b.lo,
                    "hi": b.hi,
                    "probability": b.probability,
                    "log_p": e.log_mu_hat if e.n_failures else None,
                    "log_ci": [float(x) if np.isfinite(x) else None for x in e.shown_log_ci],
                    "verdict": e.verdict,
                    "share": b.share,
                }
            )
        doc: dict[str, Any] = {"odd": self.odd.to_json(), "rollouts": self.rollouts, "bins": bins}
        if self.pair is not None:
            doc["pair"] = self.pair.document()
        return doc
