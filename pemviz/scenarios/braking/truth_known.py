"""Exact answers of the braking scenarios known without computing them: the main scenario's answers for the shipped
PEMs by PEM fingerprint (:data:`KNOWN_BRAKING_LOG_P`, :data:`KNOWN_BRAKING_MARGIN_LOG_P`, :func:`pem_fingerprint`),
from :func:`pemviz.scenarios.braking.truth.braking_truth` and recomputed by ``tests/scenarios/test_truth.py`` and
the benchmarks, and :func:`known_log_failure_probability`."""

from __future__ import annotations

import dataclasses
import hashlib

import numpy as np

from pemviz.scenarios.braking.simulator import BrakingParams
from pemviz.scenarios.braking.truth_latched import LogitFn, latched_log_failure_probability

FINGERPRINT_GRID_M = np.linspace(0.0, 15.0, 151)
"""Gaps (metres) at which a PEM's logit identifies it for :data:`KNOWN_BRAKING_LOG_P`."""

KNOWN_BRAKING_LOG_P: dict[str, float] = {
    "915fec568bb72b65": -33.85370929668962,  # shipped ml-nn: 1.9839e-15, bracket [1.9839, 1.9852]e-15
    "a849e1ba0edc2286": -36.44958177841474,  # shipped gbt: 1.4796e-16, bracket width 0.23 %
    # the shipped ml-nn's bootstrap ensemble (pemviz/assets/ensemble_ml-nn.pt) and logit shifts;
    # benchmarks/pem_uncertainty.py --exact
    "f250e328566c1bdc": -26.519035882869872,  # member 0: 3.0404e-12, bracket width 0.24%, 112 s
    "bf4c1c809687fa3e": -24.582823139469383,  # member 1: 2.1077e-11, bracket width 2.25%, 108 s
    "6679d181a4ad1065": -40.692820684632736,  # member 2: 2.1249e-18, bracket width 0.12%, 2 s
    "f45a54aef268e592": -42.37336213762117,  # member 3: 3.9581e-19, bracket width 0.26%, 2 s
    "2865f802c0e34a9f": -36.450254643064305,  # member 4: 1.4786e-16, bracket width 0.22%, 2 s
    "cb10a4aec0e39b49": -25.8995843144133,  # member 5: 5.6488e-12, bracket width 0.17%, 133 s
    "17c9d9e78cf0ea1a": -37.71154936352811,  # member 6: 4.1887e-17, bracket width 0.42%, 3 s
    "d5b31a4e3ebb6a5d": -33.24577332499537,  # member 7: 3.6437e-15, bracket width 0.18%, 68 s
    "a42a3cdf14f209d4": -41.92471722195736,  # member 8: 6.1991e-19, bracket width 0.19%, 2 s
    "3c7bd1e6da0399ee": -44.36087067152231,  # member 9: 5.4240e-20, bracket width 0.31%, 2 s
    "1cddd061cfb4d9e2": -29.767082073020156,  # member 10: 1.1812e-13, bracket width 0.28%, 159 s
    "16e916a13b0af486": -30.656530336175717,  # member 11: 4.8533e-14, bracket width 0.16%, 60 s
    "727704a288081421": -37.96782366082595,  # member 12: 3.2418e-17, bracket width 0.20%, 3 s
    "8b39c597fff0f664": -32.122059772812484,  # member 13: 1.1209e-14, bracket width 0.35%, 4 s
    "9b09e347d2bbab11": -31.441655465664738,  # member 14: 2.2134e-14, bracket width 0.46%, 4 s
    "d98a860c5776b2e6": -38.14790467801863,  # member 15: 2.7075e-17, bracket width 0.31%, 3 s
    "c9771b412341fea0": -38.96919470956119,  # member 16: 1.1910e-17, bracket width 0.15%, 98 s
    "e250c21d5239ba55": -27.581581652581,  # member 17: 1.0507e-12, bracket width 0.15%, 62 s
    "e9a4ecf850268631": -30.77471271309537,  # member 18: 4.3123e-14, bracket width 0.08%, 41 s
    "e50861e616900537": -33.80379754946193,  # member 19: 2.0854e-15, bracket width 0.04%, 31 s
    "105acd0b9e59722b": -25.0012741796926,  # shift -1: 1.3870e-11, bracket width 0.41%, 297 s
    "771895e45f856b43": -29.409057940104958,  # shift -0.5: 1.6897e-13, bracket width 0.22%, 71 s
    "164ec23e6f625d90": -38.32218323907766,  # shift +0.5: 2.2745e-17, bracket width 0.32%, 2 s
    "45816c12490d672f": -42.8015576615671,  # shift +1: 2.5794e-19, bracket width 0.14%, 1 s
}
"""PEM fingerprint (:func:`pem_fingerprint`) -> natural log of the exact crash probability of the main braking
scenario (default :class:`BrakingParams`), from :func:`~pemviz.scenarios.braking.truth.braking_truth` (bracket < 0.1
%), for the shipped PEMs and, for ``pemviz run --pem-uncertainty``, its ensemble members and logit shifts
(``benchmarks/pem_uncertainty.py --exact``)."""


KNOWN_BRAKING_MARGIN_LOG_P: dict[tuple[str, float], float] = {
    ("915fec568bb72b65", 1.5): -38.045588630879486,  # shipped ml-nn: 2.9992e-17, bracket width 0.09 %
    ("915fec568bb72b65", 1.0): -42.20786245180999,  # 4.6704e-19, bracket width 0.11 %
    # below 1 m on the cell bound (truth_cells.cell_miss_bound, 2,000 x 400 cells, ~20 s of the times)
    ("915fec568bb72b65", 0.5): -46.73444328937785,  # 5.0523e-21, bracket [5.0523, 5.0534]e-21 (0.02 %), 96 s, 5 GB
    ("915fec568bb72b65", 0.0): -73.89863599760004,  # contact: 8.0581e-33, bracket width < 1e-9 at -100 nats, 36 s
}
"""(PEM fingerprint, crash gap in metres) -> natural log of the exact probability that the main braking scenario's
gap drops below that gap (the exceedance curve's points, :mod:`pemviz.core.severity`; 0 m is contact), from
:func:`~pemviz.scenarios.braking.truth.braking_truth` (``benchmarks/severity.py --exact``)."""


def pem_fingerprint(logit_at_gap: LogitFn) -> str:
    """A short hash of a PEM's detection curve: its logits on :data:`FINGERPRINT_GRID_M` rounded to 1e-6."""
    values = np.round(np.asarray(logit_at_gap(FINGERPRINT_GRID_M), dtype=np.float64), 6) + 0.0  # no -0.0
    return hashlib.sha256(values.tobytes()).hexdigest()[:16]


def known_log_failure_probability(logit_at_gap: LogitFn, params: BrakingParams | None = None) -> float | None:
    """The exact log p_fail (nats) of a braking problem when it is cheap to know, else None: the latched scenario
    computed (:func:`latched_log_failure_probability`), the main scenario looked up by PEM fingerprint in
    :data:`KNOWN_BRAKING_LOG_P` or, with another crash gap, :data:`KNOWN_BRAKING_MARGIN_LOG_P`."""
    p = params or BrakingParams()
    if p.latched_brake:
        return latched_log_failure_probability(logit_at_gap, p).log_p_fail
    default = BrakingParams()
    if dataclasses.replace(p, crash_gap_m=default.crash_gap_m) != default:
        return None
    if p.crash_gap_m == default.crash_gap_m:
        return KNOWN_BRAKING_LOG_P.get(pem_fingerprint(logit_at_gap))
    return KNOWN_BRAKING_MARGIN_LOG_P.get((pem_fingerprint(logit_at_gap), float(p.crash_gap_m)))
