"""log, exp and log1p with the C library's bits on every x86 CPU, for the rollout path's likelihoods and draws.

numpy dispatches its float64 ``log`` and ``exp`` to its own AVX-512 loops, and ``log1p`` (with ``expm1``, ``power``,
``tanh`` ...) to SVML's, where the CPU has AVX-512 (``numpy.show_runtime()``: X86_V4); elsewhere it calls
libm. The two round differently in the last bit (numpy 2.4 on an AMD EPYC: ``log`` differs from libm on 0.16 % of
values, ``exp`` on 4.6 %, ``log1p`` on 4.4 %), so a seed's log-likelihoods, a draw ``log u <= log q`` and the proposal
fitted to them would depend on the CPU. scipy.special's ufuncs have no runtime dispatch and call libm's double
functions: ``xlogy(1, x)`` is ``1 * log(x)``, ``inv_boxcox(x, 0)`` is ``exp(x)``, ``boxcox1p(x, 0)`` is ``log1p(x)``
(scipy's ``_boxcox.pxd``), each bit for bit libm's (tested on 400,000 values), which numpy returns on CPUs without
AVX-512, so the bits of runs recorded there stay valid. They cost about 10-20 ns a value (numpy's AVX-512 loops: 2 ns).

:mod:`pemviz.core.exact` has IEEE-754-only versions, the same under any libm, for code that needs no libm bits.
Every function takes an array (or scalar) and returns float64 of the same shape; ``out`` is a ufunc's."""

from __future__ import annotations

from typing import Any

import numpy as np
from scipy.special import boxcox1p, inv_boxcox, xlogy


def log(x: Any, out: np.ndarray | None = None) -> Any:
    """The natural log of ``x`` (nats), libm's ``log``: 0 gives -inf, a negative value nan (no warning)."""
    return xlogy(1.0, x, out=out)


def exp(x: Any, out: np.ndarray | None = None) -> Any:
    """e^x, libm's ``exp``: 0 below -745.2, inf above 709.8."""
    return inv_boxcox(x, 0.0, out=out)


def log1p(x: Any, out: np.ndarray | None = None) -> Any:
    """log(1 + x) (nats), libm's ``log1p``: -1 gives -inf, below -1 nan."""
    return boxcox1p(x, 0.0, out=out)
