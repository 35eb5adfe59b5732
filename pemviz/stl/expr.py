"""Arithmetic expressions inside STL predicates: signals, constants, and affine combinations of them.

``signal("d") - 2`` is a :class:`BinaryExpr`; comparing an expression with ``>=``, ``>``, ``<=``, ``<`` makes a
:class:`~pemviz.stl.formula.Predicate`. Expressions must be affine in the signals (``(d - 2) / 13``,
``2 * v + vl``): their value is ``sum_i c_i * x_i + k`` with the signal arrays x_i [N, T] in their own units."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, Union

__all__ = ["Expr", "Signal", "Const", "BinaryExpr", "Negate", "format_number", "KEYWORDS", "COMPARISONS"]

KEYWORDS = frozenset(
    {"G", "F", "U", "always", "eventually", "until", "not", "and", "or", "implies", "inf", "true", "false"}
)
"""Words that cannot be signal names."""

COMPARISONS = (">=", ">", "<=", "<")
"""The comparisons a predicate may use."""


def format_number(value: float) -> str:
    """Shortest text that parses back to ``value``: ``2`` for 2.0, ``0.1``, ``1e-05``, ``-3.5``."""
    value = float(value)
    if not math.isfinite(value):
        raise ValueError(f"constants in a formula must be finite, got {value!r}")
    if value == 0.0:
        return "0"
    if value.is_integer() and abs(value) < 1e16:
        return str(int(value))
    return repr(value)


def _where(pos: int | None) -> str:
    return "" if pos is None else f" at column {pos + 1}"


Operand = Union["Expr", float, int]


def _as_expr(x: Operand) -> Expr:
    if isinstance(x, Expr):
        return x
    if isinstance(x, bool) or not isinstance(x, (int, float)):
        raise TypeError(f"expected a signal expression or a number, got {type(x).__name__}")
    return Const(float(x))


Comparison = Any
"""What comparing expressions gives: a :class:`pemviz.stl.formula.Predicate` (that module imports this one, so the
annotation cannot name it here)."""

PREDICATE: list = []
"""The predicate class, ``[pemviz.stl.formula.Predicate]``, which :mod:`pemviz.stl.formula` registers when it is
imported (it imports this module, so this one cannot import it back)."""


def _predicate(lhs: Expr, op: str, rhs: Expr) -> Comparison:
    return PREDICATE[0](lhs, op, rhs)


class Expr:
    """An arithmetic expression over signals; affine ones make predicates. Operators build new ones."""

    _prec = 4

    def affine(self) -> tuple[dict[str, float], float]:
        """(coefficient per signal, constant): the expression as ``sum_i c_i * x_i + k``.

        Raises:
            ValueError: the expression is not affine (a product of two signal terms, division by a signal
                or by zero), with its column when parsed from text."""
        raise NotImplementedError

    def signals(self) -> frozenset[str]:
        return frozenset(self.affine()[0])

    def __add__(self, other: Operand) -> Expr:
        return BinaryExpr("+", self, _as_expr(other))

    def __radd__(self, other: Operand) -> Expr:
        return BinaryExpr("+", _as_expr(other), self)

    def __sub__(self, other: Operand) -> Expr:
        return BinaryExpr("-", self, _as_expr(other))

    def __rsub__(self, other: Operand) -> Expr:
        return BinaryExpr("-", _as_expr(other), self)

    def __mul__(self, other: Operand) -> Expr:
        return BinaryExpr("*", self, _as_expr(other))

    def __rmul__(self, other: Operand) -> Expr:
        return BinaryExpr("*", _as_expr(other), self)

    def __truediv__(self, other: Operand) -> Expr:
        return BinaryExpr("/", self, _as_expr(other))

    def __neg__(self) -> Expr:
        if isinstance(self, Const):
            return Const(-self.value)
        return Negate(self)

    def __ge__(self, other: Operand) -> Comparison:  # type: ignore[override]
        return _predicate(self, ">=", _as_expr(other))

    def __gt__(self, other: Operand) -> Comparison:  # type: ignore[override]
        return _predicate(self, ">", _as_expr(other))

    def __le__(self, other: Operand) -> Comparison:  # type: ignore[override]
        return _predicate(self, "<=", _as_expr(other))

    def __lt__(self, other: Operand) -> Comparison:  # type: ignore[override]
        return _predicate(self, "<", _as_expr(other))


@dataclass(frozen=True, eq=True)
class Signal(Expr):
    """A named signal, e.g. ``d`` (gap, metres): one array [N, T] in the signals mapping."""

    name: str
    pos: int | None = field(default=None, compare=False, repr=False)
    _prec = 4

    def __post_init__(self) -> None:
        if not isinstance(self.name, str) or not _is_identifier(self.name):
            raise ValueError(
                f"invalid signal name {self.name!r}{_where(self.pos)}: use letters, digits, '_' and '.', "
                "starting with a letter or '_'"
            )
        if self.name in KEYWORDS:
            raise ValueError(
                f"{self.name!r}{_where(self.pos)} is a keyword, not a signal name "
                f"(reserved: {', '.join(sorted(KEYWORDS))})"
            )

    def affine(self) -> tuple[dict[str, float], float]:
        return {self.name: 1.0}, 0.0

    def __str__(self) -> str:
        return self.name


@dataclass(frozen=True, eq=True)
class Const(Expr):
    """A finite number."""

    value: float
    pos: int | None = field(default=None, compare=False, repr=False)
    _prec = 4

    def __post_init__(self) -> None:
        object.__setattr__(self, "value", float(self.value))
        format_number(self.value)  # finite check

    def affine(self) -> tuple[dict[str, float], float]:
        return {}, self.value

    def __str__(self) -> str:
        return format_number(self.value)


_EXPR_PREC = {"+": 1, "-": 1, "*": 2, "/": 2}


@dataclass(frozen=True, eq=True)
class BinaryExpr(Expr):
    """``left op right`` with op in ``+ - * /``; ``*`` needs one constant side, ``/`` a constant divisor."""

    op: str
    left: Expr
    right: Expr
    pos: int | None = field(default=None, compare=False, repr=False)

    def __post_init__(self) -> None:
        if self.op not in _EXPR_PREC:
            raise ValueError(f"unknown arithmetic operator {self.op!r}; allowed: + - * /")
        self.affine()  # validate

    @property
    def _prec(self) -> int:  # type: ignore[override]
        return _EXPR_PREC[self.op]

    def affine(self) -> tuple[dict[str, float], float]:
        lc, lk = self.left.affine()
        rc, rk = self.right.affine()
        if self.op in "+-":
            s = 1.0 if self.op == "+" else -1.0
            coef = dict(lc)
            for name, c in rc.items():
                coef[name] = coef.get(name, 0.0) + s * c
            return coef, lk + s * rk
        if self.op == "*":
            if lc and rc:
                raise ValueError(f"predicate is not affine{_where(self.pos)}: '{self}' multiplies two signal terms")
            if lc:
                return {n: c * rk for n, c in lc.items()}, lk * rk
            return {n: c * lk for n, c in rc.items()}, lk * rk
        if rc:
            raise ValueError(f"predicate is not affine{_where(self.pos)}: '{self}' divides by a signal term")
        if rk == 0.0:
            raise ValueError(f"division by zero{_where(self.pos)} in '{self}'")
        return {n: c / rk for n, c in lc.items()}, lk / rk

    def __str__(self) -> str:
        p = self._prec
        left = str(self.left)
        if self.left._prec < p:
            left = f"({left})"
        right = str(self.right)
        if self.right._prec <= p:
            right = f"({right})"
        return f"{left} {self.op} {right}"


@dataclass(frozen=True, eq=True)
class Negate(Expr):
    """``-operand``."""

    operand: Expr
    pos: int | None = field(default=None, compare=False, repr=False)
    _prec = 3

    def affine(self) -> tuple[dict[str, float], float]:
        c, k = self.operand.affine()
        return {n: -v for n, v in c.items()}, -k

    def __str__(self) -> str:
        inner = str(self.operand)
        if self.operand._prec < 3 or (isinstance(self.operand, Const) and self.operand.value < 0):
            inner = f"({inner})"
        return f"-{inner}"


def _is_identifier(name: str) -> bool:
    if not name or not (name[0].isascii() and (name[0].isalpha() or name[0] == "_")):
        return False
    return all(ch.isascii() and (ch.isalnum() or ch in "_.") for ch in name)
