"""Same seed, same run: the default braking and cut-in runs at chunk sizes 64, 1,000 and whole batches, serial and on
a local Ray cluster, and the default braking run under every kernel-dispatch setting of
``DISPATCH_SETTINGS`` of ``benchmarks/fingerprint.py``; prints one row per run and whether the contract holds.

    python benchmarks/reproducibility.py            # about 3 min on 2 cores
    python benchmarks/reproducibility.py --quick    # the braking rows only

Each run is a fresh process (``python benchmarks/fingerprint.py``), as a user's would be. Exit 1 when a run
breaks the contract (``compare`` of ``benchmarks/fingerprint.py``).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import fingerprint as rp  # this folder's: python puts a script's folder first on sys.path

CASES = {
    "braking": [],
    "braking, N_e 20,000": ["--n-final", "20000"],  # a final batch of 3 blocks of 8,192: Ray splits it into tasks
    "cut-in": ["--scenario", "cut-in"],
}


def fingerprint_in_subprocess(args: list[str], env: dict[str, str], timeout_s: float = 300.0) -> dict[str, Any]:
    """``fingerprint`` of ``python benchmarks/fingerprint.py ARGS`` run
    with ``env`` added to this process's environment.

    Raises:
        RuntimeError: the run failed or printed no fingerprint (the message holds its stderr's tail).
        subprocess.TimeoutExpired: it ran past ``timeout_s`` seconds.
    """
    proc = subprocess.run(
        [sys.executable, str(Path(__file__).with_name("fingerprint.py")), *args],
        capture_output=True,
        text=True,
        env={**os.environ, **env},
        timeout=timeout_s,
    )
    lines = proc.stdout.strip().splitlines()
    if proc.returncode != 0 or not lines:
        raise RuntimeError(f"reproducibility run {args} under {env} failed ({proc.returncode}): {proc.stderr[-2000:]}")
    return json.loads(lines[-1])


def row(label: str, fp: dict, seconds: float, problems: list[str]) -> str:
    verdict = "same" if not problems else "DIFFERENT: " + "; ".join(problems)
    d = fp["dispatch"]
    kernels = f"{d['torch']} / {' '.join(d['numpy']) or 'baseline'} / {' '.join(d['openblas'])}"
    return (
        f"| {label} | {kernels} | {fp['log_mu_hat']!r} | {fp['failures']}/{fp['n']} | {fp['ess']:.1f} "
        f"| {fp['chunks']} | {fp['rollouts'][:12]} | {seconds:.1f} | {verdict} |"
    )


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--quick", action="store_true", help="the braking default run only")
    a = p.parse_args()
    print(
        "| run | kernels: torch / numpy / OpenBLAS | log mu_hat | failures | ESS | chunks | rollouts sha256 | wall s "
        "| against the first |"
    )
    print("|---|---|---|---|---|---|---|---|---|")
    bad = 0
    for name, args in CASES.items():
        if a.quick and name != "braking":
            continue
        first = None
        for executor in ("serial", "ray"):
            for chunk in (None, 64, 1000):
                if executor == "ray" and chunk is not None:
                    continue  # Ray deals whole blocks of 8,192 rollouts into tasks; --chunk streams serial stages
                t0 = time.perf_counter()
                fp = fingerprint_in_subprocess(
                    [*args, "--executor", executor, *([] if chunk is None else ["--chunk", str(chunk)])], {}, 900
                )
                problems = [] if first is None else rp.compare(first, fp, same_machine=True)
                first = first or fp
                bad += bool(problems)
                print(
                    row(f"{name}, {executor}, chunk {chunk or 'whole'}", fp, time.perf_counter() - t0, problems),
                    flush=True,
                )
    first = None
    for setting, env in rp.DISPATCH_SETTINGS.items():
        t0 = time.perf_counter()
        fp = fingerprint_in_subprocess([], env)
        problems = [] if first is None else rp.compare(first, fp, same_machine=False)
        first = first or fp
        bad += bool(problems)
        print(row(f"braking, {setting}", fp, time.perf_counter() - t0, problems), flush=True)
    print(f"\n{bad} run(s) break the contract" if bad else "\nevery run keeps the contract")
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())
