"""``pemviz run --require`` on braking against its exact answer (1.984e-15): outcomes and exit codes over seeds.

    python benchmarks/requirement_gate.py               # seeds 0-9, the three requirements below, 2 jobs
    python benchmarks/requirement_gate.py --seeds 20 --jobs 1

Requirements: ``p < 1e-13`` (true: must exit 0, met), ``p < 1e-16`` (false: must exit 1, violated) and ``p < 2e-15``
with ``--max-sims 3000`` (true by 0.8 %: expected 3, undecided within the budget; met would be right too, violated
wrong). Each run is the command line's own (``pemviz.cli.main`` in a worker process, ``--no-record``). Prints one row
per requirement: the exit codes seen, the simulations (median, largest), and the wrong outcomes; exit 1 if any.
"""

from __future__ import annotations

import argparse
import contextlib
import io
import re
import statistics
import sys
from concurrent.futures import ProcessPoolExecutor

EXACT_P = 1.984e-15
CASES = (("p < 1e-13", ()), ("p < 1e-16", ()), ("p < 2e-15", ("--max-sims", "3000")))


def one(job: tuple[str, tuple[str, ...], int]) -> tuple[str, int, int, int]:
    """(requirement, seed, exit code, simulations) of one ``pemviz run --require``."""
    require, extra, seed = job
    from pemviz.cli import main

    out = io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(io.StringIO()):
        code = main(["run", "--require", require, *extra, "--seed", str(seed), "--no-record"])
    m = re.search(r"from ([\d,]+) simulations", out.getvalue())
    return require, seed, code, int(m.group(1).replace(",", "")) if m else -1


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--seeds", type=int, default=10)
    p.add_argument("--jobs", type=int, default=2)
    a = p.parse_args()
    jobs = [(req, extra, s) for req, extra in CASES for s in range(a.seeds)]
    with ProcessPoolExecutor(a.jobs) as ex:
        runs = list(ex.map(one, jobs))
    print("| requirement | truth | exit codes (0 met, 1 violated, 3 undecided) | simulations median / max | wrong |")
    print("|---|---|---|---|---|")
    bad = 0
    for req, extra in CASES:
        g = [r for r in runs if r[0] == req]
        threshold = float(req.split()[-1])
        holds = EXACT_P < threshold
        wrong = sum((c == 1 and holds) or (c == 0 and not holds) or c not in (0, 1, 3) for _, _, c, _ in g)
        bad += wrong
        codes = ", ".join(f"{c}: {sum(r[2] == c for r in g)}" for c in sorted({r[2] for r in g}))
        sims = [r[3] for r in g]
        print(
            f"| `{req}{' ' + ' '.join(extra) if extra else ''}` | {'holds' if holds else 'fails'} | {codes} | "
            f"{statistics.median(sims):,.0f} / {max(sims):,} | {wrong} |"
        )
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())
