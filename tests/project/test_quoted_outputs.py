"""Every console block the README and the user guide quote from a ``pemviz`` command (a ``<!-- quoted: COMMAND -->``
marker before a text block, :mod:`benchmarks.docs_assets`) is what that command prints now: numbers exact (the seed
contract), durations masked, ``...`` for elided text. A block edited by hand, or made by older code, fails here;
``python benchmarks/docs_assets.py --write`` remakes it."""

from __future__ import annotations

import functools
import importlib.util
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]


@functools.cache
def docs_assets():
    spec = importlib.util.spec_from_file_location("docs_assets", REPO / "benchmarks" / "docs_assets.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules["docs_assets"] = module
    spec.loader.exec_module(module)
    return module


@functools.cache
def output(command: str) -> str:
    return docs_assets().run(command)


BLOCKS = [b for path in docs_assets().documents() for b in docs_assets().quoted_blocks(path)]


def test_the_docs_quote_commands():
    """The README and the guide quote at least the cut-in's advice, the gate's stop line, the crossing and a precision
    target; every marker is followed by a closed text block (``quoted_blocks`` raises otherwise)."""
    commands = {b.command for b in BLOCKS}
    assert len(BLOCKS) >= 5 and "pemviz run --scenario crossing --no-record --seed 0" in commands


@pytest.mark.slow
@pytest.mark.parametrize("block", BLOCKS, ids=[f"{b.path.name}:{b.first}" for b in BLOCKS])
def test_a_quoted_block_is_what_its_command_prints_now(block):
    assert docs_assets().matches(block.lines, output(block.command)), (
        f"{block.path.name}:{block.first} is stale: run python benchmarks/docs_assets.py --write\n"
        + "\n".join(block.lines)
        + "\n--- the command prints now ---\n"
        + output(block.command)
    )


def test_a_number_edited_by_hand_fails_and_durations_do_not():
    """A digit changed in a quoted line no longer matches; a duration changed does; ``...`` elides."""
    m = docs_assets().matches
    printed = (
        "mu_hat = 2.844e-04, 95% CI [2.32e-04, 3.45e-04], ESS 102.0\n"
        "stop: target reached after 358,697 simulations in 13.6 s (~22 s at ~0.069 ms a plain rollout)\n"
    )
    assert m(["mu_hat = 2.844e-04, 95% CI [2.32e-04, 3.45e-04], ESS 102.0"], printed)
    assert not m(["mu_hat = 2.845e-04, 95% CI [2.32e-04, 3.45e-04], ESS 102.0"], printed)
    assert not m(["stop: target reached after 358,696 simulations"], printed)
    assert m(["stop: target reached after 358,697 simulations in 9.1 s (~1.2 min at ~0.2 ms a plain rollout)"], printed)
    assert m(["mu_hat = 2.844e-04, 95% CI ... ESS 102.0 stop: target", "reached after ..."], printed)


STALE_BLOCK = (
    "mu_hat = 3.548e-04, no 95% CI from these weights: p >= 3.19e-04 (95% lower bound), ...",
    "odd map (braking ~ choice(5, 6, 7); the final stage's 1,000 rollouts): p(failure | bin), its share of p_ODD",
    "  braking = 5     P(bin) 0.33  p  9.140e-04      >= 7.39e-04, no upper  doubtful   share  88.7 %",
    "  braking = 6     P(bin) 0.33  p  1.060e-04      >= 8.66e-05, no upper  doubtful   share  10.3 %",
    "most of p_ODD: braking = 5 (89 % of it, P(bin) 0.33)",
    "",
    "stop: the requirement p < 1e-13 holds after 2,100 simulations (its interval [1.2e-15,",
    "3.4e-15] below 1e-13)",
)
PRINTED_NOW = """pemviz: adaptive on the toy
mu_hat = 3.7055e-04 (log mu_hat = -7.9005 nats) from 2100 simulations in 0.3 s
mu_hat = 3.702e-04, no 95% CI from these weights: p >= 3.48e-04 (95% lower bound), no upper bound from this run
next: plain Monte Carlo decides it
odd map (braking ~ choice(5, 6, 7); the final stage's 1,000 rollouts): p(failure | bin), its share of p_ODD
  braking = 5     P(bin) 0.33  p  9.783e-04      >= 8.79e-04, no upper  doubtful   share  88.6 %
  braking = 6     P(bin) 0.33  p  1.175e-04      >= 8.61e-05, no upper  doubtful   share  10.6 %
most of p_ODD: braking = 5 (89 % of it, P(bin) 0.33)
stop: the requirement p < 1e-13 holds after 2,100 simulations (its interval [2.5e-15, 3.9e-15] below 1e-13)
"""


def test_a_stale_block_is_rewritten_in_its_own_shape():
    """``--write`` keeps a block's shape: each line replaced by the output line it stands for (the next whose text
    begins as it does but for its numbers: not the first ``mu_hat`` line), an elided line cut after as many words, the
    indented lines of a table kept, a line the block wrapped wrapped again at its width; a block whose line stands
    for no output line is not rewritten."""
    da = docs_assets()
    block = da.Block(Path("x.md"), 0, len(STALE_BLOCK), "pemviz run", STALE_BLOCK)
    assert not da.matches(block.lines, PRINTED_NOW)
    fresh = da.fresh_lines(block, PRINTED_NOW)
    assert fresh == [
        "mu_hat = 3.702e-04, no 95% CI from these weights: p >= 3.48e-04 (95% lower bound), ...",
        "odd map (braking ~ choice(5, 6, 7); the final stage's 1,000 rollouts): p(failure | bin), its share of p_ODD",
        "  braking = 5     P(bin) 0.33  p  9.783e-04      >= 8.79e-04, no upper  doubtful   share  88.6 %",
        "  braking = 6     P(bin) 0.33  p  1.175e-04      >= 8.61e-05, no upper  doubtful   share  10.6 %",
        "most of p_ODD: braking = 5 (89 % of it, P(bin) 0.33)",
        "",
        "stop: the requirement p < 1e-13 holds after 2,100 simulations (its interval [2.5e-15,",
        "3.9e-15] below 1e-13)",
    ]
    assert da.matches(fresh, PRINTED_NOW)
    gone = da.Block(Path("x.md"), 0, 1, "pemviz run", ("warning: the weights are heavy",))
    assert da.fresh_lines(gone, PRINTED_NOW) is None
