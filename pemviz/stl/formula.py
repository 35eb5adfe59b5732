"""STL formulas as frozen dataclasses, their canonical text, and builder helpers.

Grammar (time in integer steps; an interval ``[a,b]`` is inclusive, ``b`` may be ``inf`` = to the trace end)::

    formula := predicate | !formula | formula & formula ... | formula | formula ...
             | formula -> formula | G[a,b](formula) | F[a,b](formula) | (formula) U[a,b] (formula)
    predicate := expr (>= | > | <= | <) expr      with expr affine in the signals: d - 2, (d - 2) / 13, 2 * v + vl

``str(formula)`` is the canonical text: ``parse(str(f)) == f`` (:mod:`pemviz.stl.parser`). ``G`` and ``F`` are the
two :class:`UnaryTemporal` operators, differing in :attr:`UnaryTemporal.conjunctive`; arithmetic inside predicates
lives in :mod:`pemviz.stl.expr`. Builders: ``signal("d") >= 2``; ``p & q``, ``p | q``, ``~p``, ``p >> q`` (implies);
:func:`always`, :func:`eventually`, :func:`until`, :func:`conjunction`, :func:`disjunction`, :func:`negation`,
:func:`implies`."""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass, field

from pemviz.stl import expr
from pemviz.stl.expr import (
    COMPARISONS,
    Const,
    Expr,
    Signal,
    _as_expr,
    _where,
)

# --------------------------------------------------------------------------------------------------
# Formulas
# --------------------------------------------------------------------------------------------------


# precedence for printing: implies 1 < or 2 < and 3 < until 4 < unary 5 < predicate 6
class Formula:
    """Base class of STL formulas. Operators: ``&`` and, ``|`` or, ``~`` not, ``>>`` implies."""

    _prec = 6

    @property
    def children(self) -> tuple[Formula, ...]:
        return ()

    def signals(self) -> frozenset[str]:
        """Names of all signals the formula reads."""
        out: set[str] = set()
        for c in self.children:
            out |= c.signals()
        return frozenset(out)

    def horizon(self) -> int | None:
        """Steps after the evaluation time the formula looks at (``None``: open-ended, to the trace end).

        ``G[0,150](d < 5 -> F[0,20](v <= 0.1))`` has horizon 170: evaluated at time 0 it needs 171 steps."""
        hs = [c.horizon() for c in self.children]
        if any(h is None for h in hs):
            return None
        return max(hs, default=0)  # type: ignore[type-var]

    def subformulas(self) -> Iterable[Formula]:
        """This formula and all its sub-formulas, depth first."""
        yield self
        for c in self.children:
            yield from c.subformulas()

    def __and__(self, other: Formula) -> And:
        _check_formula(other, "&")
        left = self.operands if isinstance(self, And) else (self,)
        return And(left + (other,))

    def __or__(self, other: Formula) -> Or:
        _check_formula(other, "|")
        left = self.operands if isinstance(self, Or) else (self,)
        return Or(left + (other,))

    def __invert__(self) -> Not:
        return Not(self)

    def __rshift__(self, other: Formula) -> Implies:
        _check_formula(other, ">>")
        return Implies(self, other)


def _check_formula(x: object, what: str) -> None:
    if not isinstance(x, Formula):
        raise TypeError(f"operand of {what} must be an STL Formula, got {type(x).__name__}")


def _check_interval(start: int, end: int | None, pos: int | None, op: str) -> None:
    if isinstance(start, bool) or not isinstance(start, int):
        raise TypeError(f"interval start of {op}{_where(pos)} must be an int (steps), got {start!r}")
    if end is not None and (isinstance(end, bool) or not isinstance(end, int)):
        raise TypeError(f"interval end of {op}{_where(pos)} must be an int (steps) or None (inf), got {end!r}")
    if start < 0:
        raise ValueError(
            f"interval [{start},{_fmt_end(end)}] of {op}{_where(pos)} starts before 0: "
            "intervals are future steps [a,b] with 0 <= a <= b"
        )
    if end is not None and end < start:
        raise ValueError(f"interval [{start},{end}] of {op}{_where(pos)} is empty: need a <= b")


def _fmt_end(end: int | None) -> str:
    return "inf" if end is None else str(end)


def _paren(f: Formula, min_prec: int) -> str:
    s = str(f)
    return f"({s})" if f._prec < min_prec else s


@dataclass(frozen=True, eq=True)
class Predicate(Formula):
    """``lhs op rhs`` with op in ``>= > <= <``; robustness value ``lhs - rhs`` (``>=``, ``>``) or ``rhs - lhs``.

    Strict and non-strict comparisons have the same robustness (as in rtamt and Donze & Maler 2010)."""

    lhs: Expr
    op: str
    rhs: Expr
    pos: int | None = field(default=None, compare=False, repr=False)
    coefficients: dict[str, float] = field(init=False, compare=False, repr=False)  # set by __post_init__
    offset: float = field(default=0.0, init=False, compare=False, repr=False)

    def __post_init__(self) -> None:
        if self.op not in COMPARISONS:
            raise ValueError(f"unknown comparison {self.op!r}{_where(self.pos)}; allowed: {' '.join(COMPARISONS)}")
        object.__setattr__(self, "lhs", _as_expr(self.lhs))
        object.__setattr__(self, "rhs", _as_expr(self.rhs))
        lc, lk = self.lhs.affine()
        rc, rk = self.rhs.affine()
        s = 1.0 if self.op in (">=", ">") else -1.0
        coef = {n: s * c for n, c in lc.items()}
        for n, c in rc.items():
            coef[n] = coef.get(n, 0.0) - s * c
        coef = {n: c for n, c in coef.items() if c != 0.0}
        if not coef:
            raise ValueError(f"predicate '{self}'{_where(self.pos)} reads no signal (its signal terms cancel)")
        object.__setattr__(self, "coefficients", coef)
        object.__setattr__(self, "offset", s * (lk - rk))

    def signals(self) -> frozenset[str]:
        return frozenset(self.coefficients)

    def horizon(self) -> int | None:
        return 0

    def __str__(self) -> str:
        return f"{self.lhs} {self.op} {self.rhs}"


expr.PREDICATE.append(Predicate)


@dataclass(frozen=True, eq=True)
class Not(Formula):
    """``!operand``: robustness negated."""

    operand: Formula
    pos: int | None = field(default=None, compare=False, repr=False)
    _prec = 5

    def __post_init__(self) -> None:
        _check_formula(self.operand, "!")

    @property
    def children(self) -> tuple[Formula, ...]:
        return (self.operand,)

    def __str__(self) -> str:
        return f"!({self.operand})"


@dataclass(frozen=True, eq=True)
class _NAry(Formula):
    """A conjunction or disjunction of at least two operands, printed joined by ``_op``."""

    operands: tuple[Formula, ...]
    pos: int | None = field(default=None, compare=False, repr=False)
    _op = ""

    def __post_init__(self) -> None:
        object.__setattr__(self, "operands", tuple(self.operands))
        if len(self.operands) < 2:
            raise ValueError(f"{self._op} needs at least two operands{_where(self.pos)}, got {len(self.operands)}")
        for o in self.operands:
            _check_formula(o, self._op)

    @property
    def children(self) -> tuple[Formula, ...]:
        return self.operands

    def __str__(self) -> str:
        return f" {self._op} ".join(_paren(o, self._prec + 1) for o in self.operands)


@dataclass(frozen=True, eq=True)
class And(_NAry):
    """n-ary conjunction ``a & b & ...`` (at least two operands)."""

    _prec = 3
    _op = "&"


@dataclass(frozen=True, eq=True)
class Or(_NAry):
    """n-ary disjunction ``a | b | ...`` (at least two operands)."""

    _prec = 2
    _op = "|"


@dataclass(frozen=True, eq=True)
class Implies(Formula):
    """``left -> right`` = ``!left | right`` (right-associative in text)."""

    left: Formula
    right: Formula
    pos: int | None = field(default=None, compare=False, repr=False)
    _prec = 1

    def __post_init__(self) -> None:
        _check_formula(self.left, "->")
        _check_formula(self.right, "->")

    @property
    def children(self) -> tuple[Formula, ...]:
        return (self.left, self.right)

    def __str__(self) -> str:
        return f"{_paren(self.left, 2)} -> {_paren(self.right, 1)}"


class Temporal(Formula):
    """Base of the temporal operators ``G``, ``F`` and ``U``: an interval ``[start, end]`` of future steps,
    inclusive, 0 <= start <= end, ``end`` None to the trace end (``inf``); subclasses set ``symbol``.

    Raises (on construction): TypeError for a non-int bound or a non-formula operand, ValueError for start < 0 or
    end < start (with the column when parsed from text)."""

    symbol = ""
    start: int
    end: int | None
    pos: int | None

    def _validate(self, *operands: Formula) -> None:
        for o in operands:
            _check_formula(o, self.symbol)
        _check_interval(self.start, self.end, self.pos, self.symbol)

    @property
    def interval(self) -> str:
        """The interval as written: ``[0,99]``, ``[5,inf]``."""
        return f"[{self.start},{_fmt_end(self.end)}]"


@dataclass(frozen=True, eq=True)
class UnaryTemporal(Temporal):
    """``G`` or ``F`` over ``[t+start, t+end]`` (cut at the trace end): ``conjunctive`` True (``G``) reduces the
    window like ``&``, False (``F``) like ``|``, as each semantics defines (:mod:`pemviz.stl.semantics`)."""

    operand: Formula
    start: int = 0
    end: int | None = None
    pos: int | None = field(default=None, compare=False, repr=False)
    _prec = 5
    conjunctive = True

    def __post_init__(self) -> None:
        self._validate(self.operand)

    @property
    def children(self) -> tuple[Formula, ...]:
        return (self.operand,)

    def horizon(self) -> int | None:
        h = self.operand.horizon()
        return None if h is None or self.end is None else self.end + h

    def __str__(self) -> str:
        return f"{self.symbol}{self.interval}({self.operand})"


class Always(UnaryTemporal):
    """``G[start,end](operand)``: operand holds at every step of [t+start, t+end] (end None: to the trace end)."""

    symbol = "G"
    conjunctive = True


class Eventually(UnaryTemporal):
    """``F[start,end](operand)``: operand holds at some step of [t+start, t+end] (end None: to the trace end)."""

    symbol = "F"
    conjunctive = False


@dataclass(frozen=True, eq=True)
class Until(Temporal):
    """``(left) U[start,end] (right)``: right holds at some t' in [t+start, t+end] and left at every step of
    [t, t') before it (strict, discrete-time convention of rtamt and LTL)."""

    left: Formula
    right: Formula
    start: int = 0
    end: int | None = None
    pos: int | None = field(default=None, compare=False, repr=False)
    _prec = 4
    symbol = "U"

    def __post_init__(self) -> None:
        self._validate(self.left, self.right)

    @property
    def children(self) -> tuple[Formula, ...]:
        return (self.left, self.right)

    def horizon(self) -> int | None:
        hl, hr = self.left.horizon(), self.right.horizon()
        if hl is None or hr is None or self.end is None:
            return None
        return max(self.end - 1 + hl, self.end + hr)

    def __str__(self) -> str:
        return f"({self.left}) U{self.interval} ({self.right})"


# --------------------------------------------------------------------------------------------------
# Builders
# --------------------------------------------------------------------------------------------------


def signal(name: str) -> Signal:
    """A signal expression: ``signal("d") >= 2`` is the predicate ``d >= 2``."""
    return Signal(name)


def const(value: float) -> Const:
    """A constant expression."""
    return Const(value)


def negation(operand: Formula) -> Not:
    """``!operand``."""
    return Not(operand)


def conjunction(*operands: Formula) -> Formula:
    """``a & b & ...`` (one operand: itself)."""
    return operands[0] if len(operands) == 1 else And(tuple(operands))


def disjunction(*operands: Formula) -> Formula:
    """``a | b | ...`` (one operand: itself)."""
    return operands[0] if len(operands) == 1 else Or(tuple(operands))


def implies(left: Formula, right: Formula) -> Implies:
    """``left -> right``."""
    return Implies(left, right)


def always(operand: Formula, start: int = 0, end: int | None = None) -> Always:
    """``G[start,end](operand)``; ``end=None`` is open-ended (to the trace end)."""
    return Always(operand, start, end)


def eventually(operand: Formula, start: int = 0, end: int | None = None) -> Eventually:
    """``F[start,end](operand)``; ``end=None`` is open-ended (to the trace end)."""
    return Eventually(operand, start, end)


def until(left: Formula, right: Formula, start: int = 0, end: int | None = None) -> Until:
    """``(left) U[start,end] (right)``; ``end=None`` is open-ended (to the trace end)."""
    return Until(left, right, start, end)
