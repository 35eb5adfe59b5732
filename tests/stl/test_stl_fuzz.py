"""Property-based fuzzing of the STL parser: whatever the text, ``parse`` returns a formula or raises
:class:`STLSyntaxError` with a column inside the text; a formula it returns prints to text that parses back to it.

CI runs ``STL_FUZZ_EXAMPLES`` (default 700) examples for each of the three text strategies, ~2,100 strings;
``STL_FUZZ_EXAMPLES=3400`` is the full run of ~10^4 strings (``scripts/hostile_cases.py --stl 10000`` reports it)."""

from __future__ import annotations

import os

from hypothesis import HealthCheck, example, given, settings
from hypothesis import strategies as st
from pemviz.stl import parse
from pemviz.stl.parser import MAX_DEPTH, STLSyntaxError

EXAMPLES = int(os.environ.get("STL_FUZZ_EXAMPLES", "700"))
FUZZ = settings(
    max_examples=EXAMPLES,
    deadline=None,
    derandomize=True,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.filter_too_much],
)

TOKENS = [
    "d",
    "v",
    "x_1",
    "a.b",
    "G",
    "F",
    "U",
    "always",
    "eventually",
    "until",
    "not",
    "and",
    "or",
    "implies",
    "!",
    "~",
    "&",
    "&&",
    "|",
    "||",
    "->",
    "=>",
    "(",
    ")",
    "[",
    "]",
    ",",
    ":",
    "inf",
    ">=",
    "<=",
    ">",
    "<",
    "==",
    "!=",
    "+",
    "-",
    "*",
    "/",
    "0",
    "1",
    "2.5",
    ".5",
    "1e3",
    "1e-400",
    "1e400",
    "9" * 70,
    "99",
    "²",
    "١",
    "１",
    "\u00a0",
    "\t",
    "\n",
    " ",
    "𝟙",
    "e",
    "E",
    "G[0,1]",
    "F[2,inf)",
    "[0:5]",
    "nan",
    "Inf",
]
"""STL tokens, near-misses and hostile characters (superscript, Arabic-Indic and full-width digits, huge numbers)."""

token_text = st.lists(st.sampled_from(TOKENS), max_size=40).map(" ".join)
squashed_text = st.lists(st.sampled_from(TOKENS), max_size=40).map("".join)
any_text = st.text(max_size=80)
nested = st.tuples(st.integers(0, 3 * MAX_DEPTH), st.sampled_from(["(", "G[0,1](", "!(", "F("])).map(
    lambda t: t[1] * t[0] + "d >= 2" + ")" * t[0]
)


def check(text: str) -> None:
    try:
        f = parse(text)
    except STLSyntaxError as e:
        assert 1 <= e.column <= len(text) + 1, (text, e.column)
        return
    assert parse(str(f)) == f, text  # what it prints parses back to the same formula


@FUZZ
@given(token_text)
def test_stl_parse_of_token_sequences_raises_only_stl_syntax_errors(text: str) -> None:
    check(text)


@FUZZ
@given(squashed_text)
def test_stl_parse_of_squashed_tokens_raises_only_stl_syntax_errors(text: str) -> None:
    check(text)


@FUZZ
@given(any_text)
def test_stl_parse_of_any_unicode_text_raises_only_stl_syntax_errors(text: str) -> None:
    check(text)


@settings(max_examples=40, deadline=None, derandomize=True)
@given(nested)
@example("(" * (MAX_DEPTH - 2) + "d >= 2" + ")" * (MAX_DEPTH - 2))  # the deepest that must parse, each kind
@example("G[0,1](" * (MAX_DEPTH // 2 - 1) + "d >= 2" + ")" * (MAX_DEPTH // 2 - 1))
@example("!(" * (MAX_DEPTH // 2 - 1) + "d >= 2" + ")" * (MAX_DEPTH // 2 - 1))
@example("F(" * (MAX_DEPTH // 2 - 1) + "d >= 2" + ")" * (MAX_DEPTH // 2 - 1))
def test_deep_nesting_is_a_syntax_error_past_the_limit_and_parses_within_it(text: str) -> None:
    depth = text.count("(")
    try:
        parse(text)
    except STLSyntaxError as e:
        assert depth * (2 if "G" in text or "!" in text or "F" in text else 1) > MAX_DEPTH - 2, (depth, e)
        assert "nested more than" in e.message


def test_issue_reproductions_are_syntax_errors_with_columns() -> None:
    cases = {
        "(" * 200 + "d >= 2" + ")" * 200: (102, "nested more than 100"),
        "G[0,1](" * 150 + "d >= 2" + ")" * 150: (None, "nested more than 100"),
        "d >= ²": (6, "unexpected character '²'"),
        "d >= 1e400": (6, "out of range"),
        "d >= " + "1" * 5000: (6, "number of 5000 characters"),
        "d >= １": (6, "unexpected character"),
        "d >= ٣": (6, "unexpected character"),
        "d" + " + d" * 500 + " >= 1": (None, "arithmetic nested more than"),
        "d * 1e300 * 1e300 >= 1": (1, "beyond float64"),
        "G[0,99999999999](d >= 1)": (5, "too large"),
    }
    for text, (column, message) in cases.items():
        try:
            parse(text)
        except STLSyntaxError as e:
            assert message in e.message, (text[:40], e.message)
            assert column is None or e.column == column, (text[:40], e.column)
        else:
            raise AssertionError(f"{text[:40]!r} parsed")
