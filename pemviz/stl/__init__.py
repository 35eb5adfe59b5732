"""STL robustness for pemviz: formulas, a parser, and batched classic / AGM / smooth-cumulative semantics.

Example::

    from pemviz import stl

    spec = stl.parse("G[0,99](d >= 2)")          # str(spec) == "G[0,99](d >= 2)"
    rho = stl.robustness(spec, {"d": gap_m}, "classic")      # gap_m: [N, T] metres -> rho: [N] metres
    rho_agm = stl.robustness(spec, {"d": gap_m}, "agm", signal_ranges=stl.BRAKING_SIGNAL_RANGES)
    over_time = stl.robustness_signal(spec, {"d": gap_m})    # [N, T]

Builders: ``stl.always((stl.signal("d") < 5) >> stl.eventually(stl.signal("v") <= 0.1, 0, 20), 0, 150)``
(parenthesise comparisons next to ``&``, ``|``, ``>>``)."""

from pemviz.stl.evaluate import TRACE_END, first_violation, robustness, robustness_signal
from pemviz.stl.expr import KEYWORDS, BinaryExpr, Const, Expr, Negate, Signal, format_number
from pemviz.stl.formula import (
    Always,
    And,
    Eventually,
    Formula,
    Implies,
    Not,
    Or,
    Predicate,
    Temporal,
    UnaryTemporal,
    Until,
    always,
    conjunction,
    const,
    disjunction,
    eventually,
    implies,
    negation,
    signal,
    until,
)
from pemviz.stl.parser import STLSyntaxError, parse
from pemviz.stl.semantics import (
    AGM,
    DEFAULT_TEMPERATURE,
    SEMANTICS,
    Classic,
    Semantics,
    SmoothCumulative,
    agm_scale,
    semantics_from_name,
)

BRAKING_SIGNAL_RANGES = {"d": (0.0, 15.0)}
"""AGM normalisation of the braking spec's gap (metres): ``d >= 2`` becomes (d - 2) / 13 as in the authors' code."""


def braking_spec(n_steps: int = 100, crash_gap_m: float = 2.0) -> Formula:
    """The safety spec ``G[0,n_steps-1](d >= crash_gap_m)`` (Innes & Ramamoorthy (2022)): the gap never drops below
    2 m."""
    return Always(Predicate(Signal("d"), ">=", Const(crash_gap_m)), 0, int(n_steps) - 1)


__all__ = [
    "SEMANTICS",
    "DEFAULT_TEMPERATURE",
    "TRACE_END",
    "BRAKING_SIGNAL_RANGES",
    "braking_spec",
    "parse",
    "STLSyntaxError",
    "robustness",
    "robustness_signal",
    "first_violation",
    "agm_scale",
    "Semantics",
    "Classic",
    "AGM",
    "SmoothCumulative",
    "semantics_from_name",
    "Formula",
    "Predicate",
    "Not",
    "And",
    "Or",
    "Implies",
    "Temporal",
    "UnaryTemporal",
    "Always",
    "Eventually",
    "Until",
    "Expr",
    "Signal",
    "Const",
    "BinaryExpr",
    "Negate",
    "signal",
    "const",
    "negation",
    "conjunction",
    "disjunction",
    "implies",
    "always",
    "eventually",
    "until",
    "format_number",
    "KEYWORDS",
]
