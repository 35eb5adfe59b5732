"""Jumps along a PCG64 stream: where the k-th float64 draw of a generator is, without drawing the ones before it, so
chunks of rollouts read their slice of the serial uniforms (PCG64 / PCG64DXSM ``advance`` in O(log n): O'Neill 2014,
"PCG: a family of simple fast space-efficient statistically good algorithms for random number generation"); other
bit generators cannot jump."""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import TYPE_CHECKING, Any, cast

import numpy as np

if TYPE_CHECKING:  # numpy's stub-only type of a PCG64 state
    from numpy.random._pcg64 import _PCG64State

JUMPABLE = (np.random.PCG64, np.random.PCG64DXSM)
"""Bit generators that can jump by a number of draws."""

_BY_NAME: dict[str, type[np.random.PCG64] | type[np.random.PCG64DXSM]] = {
    "PCG64": np.random.PCG64,
    "PCG64DXSM": np.random.PCG64DXSM,
}


def bit_generator_at(state: Mapping[str, Any], skip: int) -> np.random.PCG64 | np.random.PCG64DXSM:
    """A fresh bit generator of the type ``state`` names, at ``state`` advanced by ``skip`` float64 draws.

    Args:
        state: ``bit_generator.state`` of a PCG64 or PCG64DXSM (a plain dict, so it crosses processes).
        skip: draws to jump over, >= 0.
    Raises:
        KeyError: a state of another bit generator."""
    bg = _BY_NAME[state["bit_generator"]](0)
    bg.state = cast("_PCG64State", state)  # a PCG64 / PCG64DXSM state (KeyError above for another generator's)
    if skip:
        bg.advance(skip)
    return bg


def advance(rng: np.random.Generator, draws: int) -> None:
    """Move ``rng`` (PCG64 / PCG64DXSM) past ``draws`` float64 draws, to the state drawing them would leave."""
    bg = rng.bit_generator
    base = bg.state
    end = bit_generator_at(base, draws).state
    end["has_uint32"], end["uinteger"] = base["has_uint32"], base["uinteger"]  # untouched by random()
    bg.state = end


GOLDEN = 0.6180339887498949
"""(sqrt(5) - 1) / 2, the generator of the Kronecker (golden-ratio) lattice of :func:`array_rqmc_uniforms`."""


def array_rqmc_uniforms(u: np.ndarray, key: np.ndarray, then: np.ndarray | None = None) -> np.ndarray:
    """One step's uniforms for ``n`` chains simulated together, by Array-RQMC (L'Ecuyer, Lecot & Tuffin, "A
    randomized quasi-Monte Carlo simulation method for Markov chains", Operations Research 56(4), 2008): the chains
    are ranked by ``key`` (then ``then``), and rank r gets ``(r * GOLDEN + u[0]) mod 1``, a randomly shifted
    golden-ratio lattice. ``u[0]`` is uniform and independent of the ranks, so every chain's uniform is exactly U(0,
    1); chains of nearby keys get evenly spread uniforms.

    Args:
        u: float64 [n], i.i.d. U(0, 1) draws of this step; only ``u[0]`` is used (the others are drawn so that the
            random stream advances as with i.i.d. uniforms).
        key: float64 [n] or [n, k], the order of the chains, or integer [n] (e.g. :func:`ranking_key`).
        then: optional float64 [n, j], further columns of the key, given apart (only chains tied on ``key`` are
            compared on them).
    Returns:
        float64 [n] in [0, 1), a new array.
    Raises:
        ValueError: ``u`` not [n] with n >= 1, ``key`` not [n] or [n, k], or ``then`` not [n, j]."""
    u, key = np.asarray(u, dtype=np.float64), np.asarray(key)
    if key.dtype.kind not in "iu":  # integer keys (:func:`ranking_key`) are ranked as they are
        key = key.astype(np.float64)
    if u.ndim != 1 or u.size < 1 or key.ndim not in (1, 2) or key.shape[0] != u.size:
        raise ValueError(
            f"array_rqmc_uniforms: u must be [n], n >= 1, and key [n] or [n, k]; got {u.shape} and " f"{key.shape}"
        )
    rest = [] if key.ndim == 1 else [key[:, 1:]]
    if then is not None:
        then = np.asarray(then, dtype=np.float64)
        if then.ndim != 2 or then.shape[0] != u.size:
            raise ValueError(f"array_rqmc_uniforms: then must be [n, j] with n = {u.size}, got {then.shape}")
        rest.append(then)
    first = key if key.ndim == 1 else key[:, 0]
    order = _lexicographic_order(first, rest[0] if len(rest) == 1 else np.column_stack(rest) if rest else None)
    out = np.empty(u.size)
    out[order] = np.arange(u.size) * GOLDEN + u[0]
    return np.remainder(out, 1.0, out=out)


def _lexicographic_order(first: np.ndarray, rest: np.ndarray | None) -> np.ndarray:
    """The stable lexicographic order of the rows ``(first[i], rest[i, 0], rest[i, 1], ...)``, int [n]:
    ``np.lexsort``'s, computed as a stable sort on ``first`` with only the runs of equal ``first`` whose rows differ in
    ``rest`` sorted again (e.g. every chain before its first decisive step ties and agrees on all columns: no second
    sort)."""
    order = np.argsort(first, kind="stable")
    if rest is None or rest.shape[1] == 0 or first.size < 2:
        return order
    ranked = first[order]
    tied = ranked[1:] == ranked[:-1]  # position j + 1 continues the run of position j
    if not tied.any():
        return order
    ranked_rest = rest[order]
    differ = np.zeros(tied.size, dtype=bool)
    for j in range(rest.shape[1]):  # column by column: contiguous compares, ~2x as fast as gathered rows
        differ |= ranked_rest[1:, j] != ranked_rest[:-1, j]
    differ &= tied
    if not differ.any():
        return order
    pairs = np.flatnonzero(differ)
    run = np.concatenate(([0], np.cumsum(~tied)))  # the run of equal first keys each position is in
    unsettled = np.zeros(run[-1] + 1, dtype=bool)
    unsettled[run[pairs]] = True
    at = np.flatnonzero(unsettled[run])  # the positions of those runs, in order
    members = order[at]
    keys = [rest[members, j] for j in range(rest.shape[1] - 1, -1, -1)] + [first[members]]  # np.lexsort: last first
    order[at] = members[np.lexsort(keys)]
    return order


def ranking_key(primary: np.ndarray, secondary: np.ndarray) -> np.ndarray:
    """One sortable integer per chain, uint64 [n], ordered as the pairs (``primary`` rounded to float32,
    ``secondary`` on 2^32 even levels over its range among these chains): a single stable sort of it ranks the chains
    lexicographically, about three times as fast as ranking float64 pairs whose first members often tie.

    For Array-RQMC with the sampler's detect logit as ``primary`` and the state's first column (a window's gap,
    metres) as ``secondary``: chains of equal logits (e.g. a float32 network's, or a constant sampler's) are ordered
    by their states, which change from step to step, so that no chain keeps its lattice point's neighbourhood (ranked
    by the logit alone, the uniforms of a toy's chains varied more than i.i.d. ones). NaN ranks last.

    Args:
        primary: float [n], the first key.
        secondary: float [n], the key of ties.
    Raises:
        ValueError: the two of different shapes or not 1-D."""
    p, s = np.asarray(primary, dtype=np.float64), np.asarray(secondary, dtype=np.float64)
    if p.ndim != 1 or p.shape != s.shape:
        raise ValueError(f"ranking_key: primary and secondary must be [n] each, got {p.shape} and {s.shape}")
    bits = p.astype(np.float32).view(np.int32).astype(np.int64)
    high = np.where(bits < 0, -1 - bits, bits + 0x80000000).astype(np.uint64)  # IEEE-754 order as unsigned order
    lo, hi = (float(s.min()), float(s.max())) if s.size else (0.0, 0.0)
    if not (math.isfinite(lo) and math.isfinite(hi)):  # infinities and NaN: from the finite range, NaN last
        finite = np.isfinite(s)
        lo, hi = (float(s[finite].min()), float(s[finite].max())) if finite.any() else (0.0, 0.0)
        s = np.where(np.isnan(s), np.inf, s)
    if hi <= lo:
        scaled = np.zeros(s.size)
    elif math.isfinite(factor := (2.0**32 - 1.0) / (hi - lo)):
        scaled = (s - lo) * factor
    else:  # a range so narrow (below 2^32 of the smallest normal) that the factor overflows: divide first
        scaled = (s - lo) / (hi - lo) * (2.0**32 - 1.0)
    low = np.clip(scaled, 0.0, 2.0**32 - 1.0).astype(np.uint64)  # truncation toward 0: the floor of these
    return (high << np.uint64(32)) | low


RQMC_BLOCK = 8192
"""Rollouts per Array-RQMC block. A batch of n rollouts is cut into the fixed blocks ``[j B, min((j + 1) B, n))``,
B = RQMC_BLOCK, whatever simulates it (one process, chunks streamed through it, Ray tasks of any size): the rollouts
of a block are ranked and coupled among themselves (:func:`pemviz.core.detectors.step_uniforms`), and detectors are
asked about one block at a time (:func:`by_blocks`), so the same seed gives the same rollouts, bit for bit, on every
executor. Equal to the batched simulators' chunk (:data:`pemviz.core.lockstep.DEFAULT_CHUNK_SIZE`)."""


def block_bounds(n: int, block: int = RQMC_BLOCK) -> list[tuple[int, int]]:
    """The fixed blocks ``(start, stop)`` of a batch of ``n`` rollouts, in order: ``[(0, B), (B, 2B), ..., (., n)]``.

    Raises:
        ValueError: ``n`` or ``block`` below 1."""
    if n < 1 or block < 1:
        raise ValueError(f"block_bounds: n and block must be >= 1, got {n}, {block}")
    return [(a, min(a + block, n)) for a in range(0, n, block)]


def by_blocks(fn, rows: np.ndarray, block: int = RQMC_BLOCK) -> np.ndarray:
    """``fn(rows)`` computed one block of rows at a time (``rows[jB:(j + 1)B]``), concatenated: float64 [n].

    A torch network may round a row's output differently in batches of different sizes (its kernels depend on the
    shape); asked about the same blocks, every executor gets the same bits. ``fn(rows)`` itself for n <= B."""
    n = np.shape(rows)[0]
    if n <= block:
        return fn(rows)
    return np.concatenate([np.asarray(fn(rows[a:b]), dtype=np.float64) for a, b in block_bounds(n, block)])
