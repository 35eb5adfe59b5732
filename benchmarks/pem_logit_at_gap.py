"""Benchmark: logit_at_gap of the shipped PEMs on the simulator's hot path (budget 0.2 ms per call, 100-1,000 gaps).

Prints microseconds per call and the ratio to the budget (below 1 is within budget), beside the full
float64 evaluation of the same model (encode + network or trees) and, for the ML-NN, a torch eval-mode
forward, for reference.

    python benchmarks/pem_logit_at_gap.py
"""

from __future__ import annotations

import timeit

import numpy as np
import torch
from pemviz.pem import PEM, braking_salient_inputs, load_pem

BUDGET_US = 200.0


def per_call_us(fn, number: int) -> float:
    return min(timeit.repeat(fn, number=number, repeat=5)) / number * 1e6


def bench(name: str) -> None:
    pem = load_pem(name)
    module = pem.to_module() if isinstance(pem, PEM) else None
    for n in (100, 1000):
        gaps = np.linspace(2.0, 13.0, n)
        fast = per_call_us(lambda gaps=gaps: pem.logit_at_gap(gaps), 2000)
        full = per_call_us(lambda gaps=gaps: pem.logit(braking_salient_inputs(gaps)), 500 if module else 20)
        ref = ""
        if module is not None:

            def torch_forward(gaps: np.ndarray = gaps) -> np.ndarray:
                with torch.no_grad():
                    x = torch.as_tensor(pem.features(braking_salient_inputs(gaps)), dtype=torch.float32)
                    return module(x).squeeze(1).double().numpy()

            ref = f"; torch eval forward {per_call_us(torch_forward, 500):7.1f} us"
        print(
            f"{name:6s} N={n:5d}: logit_at_gap {fast:7.1f} us (ratio to the 200 us budget {fast / BUDGET_US:.3f}); "
            f"full float64 evaluation {full:8.1f} us{ref}"
        )


def main() -> None:
    for name in ("ml-nn", "gbt"):
        bench(name)


if __name__ == "__main__":
    main()
