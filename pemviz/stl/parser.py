"""Parse STL text into :mod:`pemviz.stl.formula` objects; errors carry the column.

Spellings (canonical first): ``!``/``~``/``not``, ``&``/``&&``/``and``, ``|``/``||``/``or``, ``->``/``implies``,
``G``/``always``, ``F``/``eventually``, ``U``/``until``; intervals ``[a,b]``, ``[a:b]``, ``[a,inf]``, ``[a,inf)``
(none: ``[0,inf]``). Precedence, loosest first: ``->`` (right-assoc), ``|``, ``&``, ``U`` (non-assoc), unary ``! G
F``. Numbers are ASCII digits, at most :data:`MAX_NUMBER_CHARS` characters; bounds at most :data:`MAX_STEP`; nesting
at most :data:`MAX_DEPTH`. Every failure is an :class:`STLSyntaxError` with its column."""

from __future__ import annotations

import math
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass

from pemviz.stl.expr import COMPARISONS, KEYWORDS, BinaryExpr, Const, Expr, Negate, Signal
from pemviz.stl.formula import Always, And, Eventually, Formula, Implies, Not, Or, Predicate, Until

__all__ = ["parse", "STLSyntaxError", "MAX_DEPTH"]

MAX_DEPTH = 100
"""Deepest nesting of parentheses, unary operators (``! G F -``) and chained ``->``: deeper text is an error
(far beyond any safety spec; the recursive-descent parser and the semantics stay far from Python's recursion
limit)."""
MAX_NUMBER_CHARS = 64
"""Longest number literal (digits, point, exponent)."""
MAX_STEP = 10**9
"""Largest interval bound (steps)."""
_DIGITS = frozenset("0123456789")


class STLSyntaxError(ValueError):
    """Malformed formula text. ``position`` is the 0-based character offset, ``column`` = position + 1."""

    def __init__(self, message: str, text: str, position: int) -> None:
        self.message = message
        self.text = text
        self.position = position
        self.column = position + 1
        line = text.replace("\n", " ").replace("\t", " ")
        super().__init__(f"{message} at column {self.column}:\n  {line}\n  {' ' * position}^")

    @property
    def brief(self) -> str:
        """The error in one line, without the text and its caret: ``MESSAGE at column N`` (for a message that quotes
        the text itself, such as a command's one-line error)."""
        return f"{self.message} at column {self.column}"


@dataclass(frozen=True)
class _Tok:
    kind: str  # "num", "id", "op", "end"
    text: str
    pos: int


_OPS = (
    "->",
    "=>",
    "&&",
    "||",
    ">=",
    "<=",
    "==",
    "!=",
    "(",
    ")",
    "[",
    "]",
    ",",
    ":",
    "+",
    "-",
    "*",
    "/",
    ">",
    "<",
    "!",
    "~",
    "&",
    "|",
)

_WORD_OPS = {"not": "!", "and": "&", "or": "|", "implies": "->", "always": "G", "eventually": "F", "until": "U"}


def _tokenize(text: str) -> list[_Tok]:
    toks: list[_Tok] = []
    i, n = 0, len(text)
    while i < n:
        ch = text[i]
        if ch.isspace():
            i += 1
            continue
        if ch in _DIGITS or (ch == "." and i + 1 < n and text[i + 1] in _DIGITS):
            j = i
            while j < n and text[j] in _DIGITS:
                j += 1
            if j < n and text[j] == ".":
                j += 1
                while j < n and text[j] in _DIGITS:
                    j += 1
            if j < n and text[j] in "eE":
                k = j + 1
                if k < n and text[k] in "+-":
                    k += 1
                if k < n and text[k] in _DIGITS:
                    while k < n and text[k] in _DIGITS:
                        k += 1
                    j = k
            if j - i > MAX_NUMBER_CHARS:
                raise STLSyntaxError(f"number of {j - i} characters; at most {MAX_NUMBER_CHARS}", text, i)
            if not math.isfinite(float(text[i:j])):
                raise STLSyntaxError(f"number {text[i:j]} is out of range (beyond float64, ~1.8e308)", text, i)
            toks.append(_Tok("num", text[i:j], i))
            i = j
            continue
        if ch.isascii() and (ch.isalpha() or ch == "_"):
            j = i
            while j < n and text[j].isascii() and (text[j].isalnum() or text[j] in "_."):
                j += 1
            word = text[i:j]
            if word in _WORD_OPS:
                toks.append(_Tok("op", _WORD_OPS[word], i))
            elif word in ("G", "F", "U"):
                toks.append(_Tok("op", word, i))
            else:
                toks.append(_Tok("id", word, i))
            i = j
            continue
        for op in _OPS:
            if text.startswith(op, i):
                if op in ("==", "!="):
                    raise STLSyntaxError(
                        f"comparison {op!r} is not supported; allowed: {' '.join(COMPARISONS)}", text, i
                    )
                norm = {"&&": "&", "||": "|", "~": "!", "=>": "->"}.get(op, op)
                toks.append(_Tok("op", norm, i))
                i += len(op)
                break
        else:
            raise STLSyntaxError(f"unexpected character {ch!r}", text, i)
    toks.append(_Tok("end", "", n))
    return toks


class _Fail(Exception):
    def __init__(self, message: str, pos: int) -> None:
        self.message = message
        self.pos = pos


class _Parser:
    def __init__(self, text: str) -> None:
        self.text = text
        self.toks = _tokenize(text)
        self.i = 0
        self.depth = 0
        self._depths: dict[int, tuple[int, Expr]] = {}  # id -> (tree depth, node kept alive so ids stay unique)
        self.furthest: _Fail | None = None

    @contextmanager
    def nested(self) -> Iterator[None]:
        """One level deeper (a parenthesis, a unary operator, a chained ``->``): at most :data:`MAX_DEPTH`."""
        if self.depth >= MAX_DEPTH:
            raise self.fail(f"nested more than {MAX_DEPTH} levels deep (parentheses, unary operators or ->)")
        self.depth += 1
        try:
            yield
        finally:
            self.depth -= 1

    # -- helpers ------------------------------------------------------------------------------------
    @property
    def tok(self) -> _Tok:
        return self.toks[self.i]

    def fail(self, message: str, pos: int | None = None) -> _Fail:
        f = _Fail(message, self.tok.pos if pos is None else pos)
        if self.furthest is None or f.pos >= self.furthest.pos:
            self.furthest = f
        return f

    def describe(self, tok: _Tok) -> str:
        return "end of text" if tok.kind == "end" else repr(tok.text)

    def accept(self, text: str) -> _Tok | None:
        t = self.tok
        if t.kind == "op" and t.text == text:
            self.i += 1
            return t
        return None

    def expect(self, text: str, what: str | None = None) -> _Tok:
        t = self.accept(text)
        if t is None:
            raise self.fail(f"expected {what or repr(text)}, found {self.describe(self.tok)}")
        return t

    # -- formulas -----------------------------------------------------------------------------------
    def formula(self) -> Formula:
        left = self.disjunction()
        t = self.accept("->")
        if t is None:
            return left
        with self.nested():
            right = self.formula()
        return self._build(Implies, t, left, right)

    def disjunction(self) -> Formula:
        return self._nary(self.conjunction, "|", Or)

    def conjunction(self) -> Formula:
        return self._nary(self.until, "&", And)

    def _nary(self, operand: Callable[[], Formula], op: str, kind: type[And] | type[Or]) -> Formula:
        """``operand (op operand)*``: one ``kind`` of all the operands, or the single operand."""
        first = operand()
        ops = [first]
        while self.accept(op):
            ops.append(operand())
        return first if len(ops) == 1 else kind(tuple(ops), pos=_pos_of(first))

    def until(self) -> Formula:
        left = self.unary()
        t = self.accept("U")
        if t is None:
            return left
        start, end = self.interval("U")
        right = self.unary()
        if self.tok.kind == "op" and self.tok.text == "U":
            raise self.fail("chained U is ambiguous: parenthesise one side")
        return self._build(Until, t, left, right, start, end)

    def unary(self) -> Formula:
        t = self.tok
        if t.kind == "op" and t.text == "!":
            self.i += 1
            with self.nested():
                return self._build(Not, t, self.unary())
        if t.kind == "op" and t.text in ("G", "F"):
            self.i += 1
            nxt = self.tok
            if nxt.kind == "op" and nxt.text in COMPARISONS + ("+", "-", "*", "/"):
                raise self.fail(
                    f"{self.text[t.pos:nxt.pos].strip()!r} is an operator, not a signal name "
                    "(G, F, U and their word forms are reserved)",
                    t.pos,
                )
            start, end = self.interval(t.text)
            with self.nested():
                operand = self.unary()
            return self._build(Always if t.text == "G" else Eventually, t, operand, start, end)
        return self.atom()

    def _build(self, cls, t: _Tok, *args):  # type: ignore[no-untyped-def]
        try:
            return cls(*args, pos=t.pos)
        except (ValueError, TypeError, ArithmeticError) as e:
            raise self.fail(str(e).replace(f" at column {t.pos + 1}", ""), t.pos) from None

    def interval(self, op: str) -> tuple[int, int | None]:
        if self.tok.kind != "op" or self.tok.text != "[":
            return 0, None
        self.i += 1
        start = self.integer(f"interval start of {op}")
        if not (self.accept(",") or self.accept(":")):
            raise self.fail(f"expected ',' in the interval of {op}, found {self.describe(self.tok)}")
        if self.tok.kind == "id" and self.tok.text == "inf" or (self.tok.kind == "op" and self.tok.text == "inf"):
            self.i += 1
            end = None
            if not (self.accept("]") or self.accept(")")):
                raise self.fail(f"expected ']' closing the interval of {op}, found {self.describe(self.tok)}")
            return start, end
        end_tok = self.tok
        end = self.integer(f"interval end of {op}")
        self.expect("]", f"']' closing the interval of {op}")
        if end < start:
            raise self.fail(f"interval [{start},{end}] of {op} is empty: need a <= b", end_tok.pos)
        return start, end

    def integer(self, what: str) -> int:
        t = self.tok
        if t.kind == "num" and all(c in _DIGITS for c in t.text):
            if int(t.text) > MAX_STEP:
                raise self.fail(f"{what} {t.text} is too large: at most {MAX_STEP} steps")
            self.i += 1
            return int(t.text)
        if t.kind == "op" and t.text == "-" and self.toks[self.i + 1].kind == "num":
            raise self.fail(f"{what} must be >= 0 (future steps), found '-{self.toks[self.i + 1].text}'")
        raise self.fail(f"{what} must be a non-negative integer (steps), found {self.describe(t)}")

    def atom(self) -> Formula:
        start = self.i
        try:
            return self.predicate()
        except _Fail:
            pred_fail = self.furthest
            self.i = start
        if self.accept("("):
            with self.nested():
                inner = self.formula()
            self.expect(")", "')' or an operator")
            return inner
        assert pred_fail is not None
        raise pred_fail

    # -- predicates ---------------------------------------------------------------------------------
    def predicate(self) -> Predicate:
        start_tok = self.tok
        lhs = self.expr()
        t = self.tok
        if not (t.kind == "op" and t.text in COMPARISONS):
            raise self.fail(
                f"expected a comparison ({' '.join(COMPARISONS)}) or an arithmetic operator, "
                f"found {self.describe(t)}"
            )
        self.i += 1
        rhs = self.expr()
        try:
            pred = Predicate(lhs, t.text, rhs, pos=start_tok.pos)
        except (ValueError, ArithmeticError) as e:
            raise self.fail(str(e).replace(f" at column {start_tok.pos + 1}", ""), start_tok.pos) from None
        if not all(math.isfinite(c) for c in (*pred.coefficients.values(), pred.offset)):
            raise self.fail(
                "the predicate's arithmetic goes beyond float64 (a coefficient or offset is not finite)", start_tok.pos
            )
        return pred

    def expr(self) -> Expr:
        return self._chain(self.term, ("+", "-"))

    def term(self) -> Expr:
        return self._chain(self.factor, ("*", "/"))

    def _chain(self, operand: Callable[[], Expr], ops: tuple[str, ...]) -> Expr:
        """``operand (op operand)*`` for ``op`` in ``ops``, nesting to the left."""
        left = operand()
        while self.tok.kind == "op" and self.tok.text in ops:
            t = self.tok
            self.i += 1
            left = self._binary(t, left, operand())
        return left

    def _binary(self, t: _Tok, left: Expr, right: Expr) -> Expr:
        """``left op right``; the expression tree (``a + b + c ...`` nests to the left) at most :data:`MAX_DEPTH`."""
        return self._deeper(t, BinaryExpr, left, right, t.text, left, right)

    def _deeper(self, t: _Tok, cls, *children_then_args):  # type: ignore[no-untyped-def]
        """An expression node one level above its deepest child (``cls(*args)``), at most :data:`MAX_DEPTH`."""
        n_children = 2 if cls is BinaryExpr else 1
        children, args = children_then_args[:n_children], children_then_args[n_children:]
        depth = 1 + max(self._depths.get(id(c), (0, None))[0] for c in children)
        if depth > MAX_DEPTH:
            raise self.fail(f"arithmetic nested more than {MAX_DEPTH} operators deep", t.pos)
        node = self._expr(cls, t, *args)
        self._depths[id(node)] = (depth, node)
        return node

    def _expr(self, cls, t: _Tok, *args):  # type: ignore[no-untyped-def]
        """``cls(*args, pos=t.pos)``; its ValueError / ArithmeticError (e.g. a product beyond float64) a failure
        at ``t``."""
        try:
            return cls(*args, pos=t.pos)
        except (ValueError, TypeError, ArithmeticError) as e:
            raise self.fail(str(e).replace(f" at column {t.pos + 1}", ""), t.pos) from None

    def factor(self) -> Expr:
        t = self.tok
        if t.kind == "op" and t.text == "-":
            self.i += 1
            nxt = self.tok
            if nxt.kind == "num":
                self.i += 1
                return self._expr(Const, t, -float(nxt.text))
            with self.nested():
                inner = self.factor()
            return self._deeper(t, Negate, inner, inner)
        if t.kind == "num":
            self.i += 1
            return self._expr(Const, t, float(t.text))
        if t.kind == "id":
            self.i += 1
            if t.text in KEYWORDS:
                raise self.fail(f"{t.text!r} is a keyword, not a signal name", t.pos)
            return self._expr(Signal, t, t.text)
        if t.kind == "op" and t.text == "(":
            self.i += 1
            with self.nested():
                inner = self.expr()
            self.expect(")", "')' or an arithmetic operator")
            return inner
        if t.kind == "op" and t.text in ("G", "F", "U"):
            raise self.fail(f"{t.text!r} is an operator, not a signal name (G, F and U are reserved)")
        raise self.fail(f"expected a signal, a number or '(', found {self.describe(t)}")


def _pos_of(f: Formula) -> int | None:
    return getattr(f, "pos", None)


def parse(text: str) -> Formula:
    """Parse STL text, e.g. ``parse("G[0,99](d >= 2)")``; ``str()`` of the result is the canonical text.

    Raises:
        STLSyntaxError (a ValueError): malformed text, with the column and a caret under the position.
        TypeError: ``text`` is not a str."""
    if not isinstance(text, str):
        raise TypeError(f"parse expects the formula text as a str, got {type(text).__name__}")
    p = _Parser(text)
    if p.tok.kind == "end":
        raise STLSyntaxError("empty formula", text, 0)
    try:
        f = p.formula()
        if p.tok.kind != "end":
            raise p.fail(f"unexpected {p.describe(p.tok)} after a complete formula (missing operator?)")
    except _Fail as e:
        best = p.furthest if p.furthest is not None and p.furthest.pos > e.pos else e
        raise STLSyntaxError(best.message, text, best.pos) from None
    return f
