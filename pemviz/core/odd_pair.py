"""The map of where p_ODD comes from over a pair of parameters: a heat map of p(failure | theta_1 in bin a, theta_2
in bin b) for the first two parameters of an ODD (:meth:`pemviz.core.odd.Distribution.bins`); independent parameters
make a cell's probability P(a) P(b), and its estimate is :func:`pemviz.core.odd.bin_log_weights` on the cell,
unbiased. Log-space throughout (nats)."""

from __future__ import annotations

import math

import numpy as np

from pemviz.core.odd import ODD, PairMap, bin_log_weights


def pair_map(
    odd: ODD, values: np.ndarray, log_w: np.ndarray, failed: np.ndarray, log_p_total: np.ndarray, k: int = 5
) -> PairMap | None:
    """The heat map of the first two parameters of ``odd`` (module docstring) from rollouts with parameters
    ``values`` [N, D], log importance weights ``log_w`` [N] (nats), failures ``failed`` [N] and log p of their
    detections ``log_p_total`` [N] (nats); None for an ODD of one parameter.

    Raises:
        ValueError: arrays of other lengths."""
    from pemviz.core.estimate import estimate

    if len(odd) < 2:
        return None
    log_w = np.asarray(log_w, dtype=np.float64)
    values = np.asarray(values, dtype=np.float64).reshape(len(log_w), len(odd))
    failed = np.asarray(failed, dtype=bool)
    log_p = np.asarray(log_p_total, dtype=np.float64)
    if failed.shape != log_w.shape or log_p.shape != log_w.shape:
        raise ValueError("pair_map: values, log_w, failed and log_p_total must describe the same rollouts")
    (x_name, x_law), (y_name, y_law) = odd.parameters[:2]
    x_edges, x_probs = x_law.bins(k)
    y_edges, y_probs = y_law.bins(k)
    zero = np.zeros(len(log_w))
    x_in = [np.isfinite(bin_log_weights(values[:, 0], zero, x_edges, x_probs, a)) for a in range(len(x_probs))]
    y_in = [np.isfinite(bin_log_weights(values[:, 1], zero, y_edges, y_probs, b)) for b in range(len(y_probs))]
    plain = bool(np.all(log_w == 0.0))
    cells = []
    terms = np.zeros((len(y_probs), len(x_probs)))
    for b in range(len(y_probs)):
        row = []
        for a in range(len(x_probs)):
            inside = x_in[a] & y_in[b]
            prob = float(x_probs[a] * y_probs[b])
            if plain and inside.any():
                e = estimate(np.zeros(int(inside.sum())), failed[inside], log_p[inside])
            else:
                e = estimate(np.where(inside, log_w - math.log(prob), -np.inf), failed & inside, log_p)
            row.append(e)
            terms[b, a] = prob * math.exp(e.log_mu_hat) if e.n_failures else 0.0
        cells.append(tuple(row))
    total = float(terms.sum())
    shares = terms / total if total > 0 else terms
    return PairMap((x_name, y_name), x_edges, y_edges, x_probs, y_probs, tuple(cells), shares)
