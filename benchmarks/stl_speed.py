"""Speed of pemviz's batched STL robustness against rtamt (issue 5, acceptance 3).

Times 10^4 traces x 200 steps of ``G[0,199](d >= 2)`` and of ``G[0,150](d < 5 -> F[0,20](v <= 0.1))`` in
the three semantics (classic, agm, smooth-cumulative), and rtamt's offline discrete-time monitor (classic) on
the same traces in the same run. Prints each time, the classic speed-up over rtamt, and whether the targets
hold: classic >= 1000x faster than rtamt, every semantics < 0.2 s per batch.

    python benchmarks/stl_speed.py                      # full run (rtamt takes ~10-30 s)
    python benchmarks/stl_speed.py --rtamt-traces 1000  # rtamt on the first 1000 traces, scaled to all
    python benchmarks/stl_speed.py --torch              # also time torch inputs
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import time

import numpy as np
from pemviz import stl

FORMULAS = {
    "G[0,199](d >= 2)": "always[0:199](d >= 2)",
    "G[0,150](d < 5 -> F[0,20](v <= 0.1))": "always[0:150]((d < 5) -> (eventually[0:20](v <= 0.1)))",
}
RANGES = {"d": (0.0, 15.0), "v": (0.0, 10.0)}  # AGM normalisation of both predicates
TARGET_SECONDS = 0.2
TARGET_RATIO = 1000.0


def make_traces(n: int, steps: int, seed: int) -> dict[str, np.ndarray]:
    """Gaps d (metres) and ego speeds v (m/s) that wander like braking rollouts: float64 [n, steps]."""
    rng = np.random.default_rng(seed)
    d = np.clip(8.0 + np.cumsum(rng.normal(-0.03, 0.25, size=(n, steps)), axis=1), 0.0, 15.0)
    v = np.clip(3.0 + np.cumsum(rng.normal(-0.02, 0.2, size=(n, steps)), axis=1), 0.0, 10.0)
    return {"d": d, "v": v}


def time_pemviz(formula: stl.Formula, signals: dict, semantics: str, repeats: int) -> tuple[float, np.ndarray]:
    """Median wall-clock seconds of one batched robustness call (after one warm-up call) and its result."""
    out = stl.robustness(formula, signals, semantics, signal_ranges=RANGES)
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = stl.robustness(formula, signals, semantics, signal_ranges=RANGES)
        times.append(time.perf_counter() - t0)
    return statistics.median(times), out


def time_rtamt(text: str, signals: dict[str, np.ndarray], n_traces: int) -> tuple[float, np.ndarray]:
    """Seconds rtamt needs for ``n_traces`` traces (parsed once, evaluated trace by trace) and its values."""
    import rtamt

    spec = rtamt.StlDiscreteTimeOfflineSpecification()
    for name in signals:
        spec.declare_var(name, "float")
    spec.spec = text
    spec.parse()
    steps = signals["d"].shape[1]
    times = list(range(steps))
    rows = {name: values[:n_traces].tolist() for name, values in signals.items()}  # conversion not timed
    out = np.empty(n_traces)
    t0 = time.perf_counter()
    for i in range(n_traces):
        data = {"time": times}
        for name in rows:
            data[name] = rows[name][i]
        out[i] = spec.evaluate(data)[0][1]
    return time.perf_counter() - t0, out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--traces", type=int, default=10_000, help="batch size N (default 10000)")
    parser.add_argument("--steps", type=int, default=200, help="trace length T (default 200)")
    parser.add_argument("--repeats", type=int, default=7, help="timed pemviz calls per case (median)")
    parser.add_argument(
        "--rtamt-traces",
        type=int,
        default=None,
        help="run rtamt on the first K traces and scale its time to N (default: all N)",
    )
    parser.add_argument("--torch", action="store_true", help="also time torch float64 inputs")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)
    if args.steps < 200:
        parser.error("--steps must be >= 200 for G[0,199]")

    signals = make_traces(args.traces, args.steps, args.seed)
    n_rtamt = min(args.traces, args.rtamt_traces or args.traces)
    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
    print(
        f"pemviz STL robustness: N = {args.traces} traces x T = {args.steps} steps, float64, "
        f"{os.cpu_count()} CPU(s), load average {load:.2f}; rtamt on {n_rtamt} traces"
        + (f" scaled to {args.traces}" if n_rtamt < args.traces else "")
    )
    print(
        f"{'formula':40s} {'semantics':18s} {'input':6s} {'pemviz ms':>10s} {'< 0.2 s':>8s} "
        f"{'rtamt s':>9s} {'speed-up':>10s} {'>= 1000x':>9s}"
    )
    ok = True
    for text, rtamt_text in FORMULAS.items():
        formula = stl.parse(text)
        rt_seconds, rt_values = time_rtamt(rtamt_text, signals, n_rtamt)
        rt_seconds *= args.traces / n_rtamt
        kinds = ["numpy"] + (["torch"] if args.torch else [])
        for kind in kinds:
            sig = signals
            if kind == "torch":
                import torch

                sig = {k: torch.from_numpy(v) for k, v in signals.items()}
            for semantics in stl.SEMANTICS:
                seconds, values = time_pemviz(formula, sig, semantics, args.repeats)
                fast = seconds < TARGET_SECONDS
                line = f"{text:40s} {semantics:18s} {kind:6s} {seconds * 1e3:10.2f} {'yes' if fast else 'NO':>8s}"
                if semantics == "classic":
                    values = np.asarray(values)
                    diff = float(np.max(np.abs(values[:n_rtamt] - rt_values)))
                    if diff > 1e-9:
                        print(f"  classic differs from rtamt by {diff:g}", file=sys.stderr)
                        ok = False
                    ratio = rt_seconds / seconds
                    line += f" {rt_seconds:9.2f} {ratio:9.0f}x {'yes' if ratio >= TARGET_RATIO else 'NO':>9s}"
                    ok &= ratio >= TARGET_RATIO or kind == "torch"
                ok &= fast
                print(line, flush=True)
    print("all targets met" if ok else "some targets missed (see NO above)")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
