"""Jumps along a PCG64 stream: where the k-th float64 draw of a generator is, without drawing the ones before it.

Chunks of rollouts (in this process, :mod:`pemviz.scenarios.batched`, or in workers, :mod:`pemviz.executors`) read
their slice of the uniforms one ``rng.random(n)`` per step would give, so the rollouts do not depend on how
they are split. ``Generator.random`` takes one 64-bit output per float64, and PCG64 / PCG64DXSM can
``advance`` by any number of outputs in O(log n) (O'Neill 2014, "PCG: a family of simple fast space-efficient
statistically good algorithms for random number generation"); other bit generators cannot jump.
"""

from __future__ import annotations

import numpy as np

JUMPABLE = (np.random.PCG64, np.random.PCG64DXSM)
"""Bit generators that can jump by a number of draws."""

_BY_NAME = {"PCG64": np.random.PCG64, "PCG64DXSM": np.random.PCG64DXSM}


def bit_generator_at(state: dict, skip: int) -> np.random.BitGenerator:
    """A fresh bit generator of the type ``state`` names, at ``state`` advanced by ``skip`` float64 draws.

    Args:
        state: ``bit_generator.state`` of a PCG64 or PCG64DXSM (a plain dict, so it crosses processes).
        skip: draws to jump over, >= 0.
    Raises:
        KeyError: a state of another bit generator.
    """
    bg = _BY_NAME[state["bit_generator"]](0)
    bg.state = state
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


def array_rqmc_uniforms(u: np.ndarray, key: np.ndarray) -> np.ndarray:
    """One step's uniforms for ``n`` chains simulated together, by Array-RQMC (L'Ecuyer, Lecot & Tuffin, "A
    randomized quasi-Monte Carlo simulation method for Markov chains", Operations Research 56(4), 2008).

    The chains are ranked by ``key`` (lexicographically by its columns, the first column first; chains of equal keys
    keep their order), and the chain of rank r gets ``(r * GOLDEN + u[0]) mod 1``: the second coordinate of point r
    of the two-dimensional golden-ratio lattice ``{(r / n, r * GOLDEN)}``, randomly shifted. Given everything before
    this step, ``u[0]`` is uniform and independent of the ranks, so every chain's uniform is exactly U(0, 1) and
    every chain follows its sampler exactly (a mean over chains keeps its expectation); jointly, chains of nearby
    keys get evenly spread uniforms. With the sampler's detect logit and then the state as the key, chains of
    similar detection probability detect in nearly their expected number, instead of binomially many.

    Args:
        u: float64 [n], i.i.d. U(0, 1) draws of this step; only ``u[0]`` is used (the others are drawn so that the
            random stream advances as with i.i.d. uniforms).
        key: float64 [n] or [n, k], the order of the chains.
    Returns:
        float64 [n] in [0, 1), a new array.
    Raises:
        ValueError: ``u`` not [n] with n >= 1, or ``key`` not [n] or [n, k].
    """
    u, key = np.asarray(u, dtype=np.float64), np.asarray(key, dtype=np.float64)
    if u.ndim != 1 or u.size < 1 or key.ndim not in (1, 2) or key.shape[0] != u.size:
        raise ValueError(f"array_rqmc_uniforms: u must be [n], n >= 1, and key [n] or [n, k]; got {u.shape} and "
                         f"{key.shape}")
    first = key if key.ndim == 1 else key[:, 0]
    order = np.argsort(first, kind="stable")
    if key.ndim == 2 and key.shape[1] > 1:
        ranked = first[order]
        tied = ranked[1:] == ranked[:-1]
        # Ties in the first column are broken by the next ones, unless the tied chains agree on them too (e.g. every
        # chain before its first decisive step): the stable order is then already the lexicographic one.
        if tied.any() and not np.array_equal(key[order[1:][tied], 1:], key[order[:-1][tied], 1:]):
            order = np.lexsort(key.T[::-1])
    out = np.empty(u.size)
    out[order] = np.arange(u.size) * GOLDEN + u[0]
    return np.remainder(out, 1.0, out=out)


RQMC_BLOCK = 8192
"""Rollouts per Array-RQMC block. A batch of n rollouts is cut into the fixed blocks ``[j B, min((j + 1) B, n))``,
B = RQMC_BLOCK, whatever simulates it (one process, chunks streamed through it, Ray tasks of any size): the rollouts
of a block are ranked and coupled among themselves (:func:`array_rqmc_blocks`), and detectors are asked about one
block at a time (:func:`by_blocks`), so the same seed gives the same rollouts, bit for bit, on every executor. Equal
to the batched simulators' chunk (:data:`pemviz.scenarios.DEFAULT_CHUNK_SIZE`): a batch of at most B
rollouts is one block, coupled as a whole, as before blocks existed."""


def block_bounds(n: int, block: int = RQMC_BLOCK) -> list[tuple[int, int]]:
    """The fixed blocks ``(start, stop)`` of a batch of ``n`` rollouts, in order: ``[(0, B), (B, 2B), ..., (., n)]``.

    Raises:
        ValueError: ``n`` or ``block`` below 1.
    """
    if n < 1 or block < 1:
        raise ValueError(f"block_bounds: n and block must be >= 1, got {n}, {block}")
    return [(a, min(a + block, n)) for a in range(0, n, block)]


def array_rqmc_blocks(u: np.ndarray, key: np.ndarray, block: int = RQMC_BLOCK) -> np.ndarray:
    """:func:`array_rqmc_uniforms` block by block: the chains ``[j B, (j + 1) B)`` of one step are ranked among
    themselves by ``key`` and shifted by their block's first uniform ``u[j B]``.

    ``u`` and ``key`` must start at a block boundary of the batch (the whole batch, or a chunk of whole blocks).
    Every chain's uniform stays exactly U(0, 1) given the past, as in one block.

    Args:
        u: float64 [n] i.i.d. U(0, 1) draws of this step.
        key: float64 [n] or [n, k], the order of the chains.
        block: B.
    Returns:
        float64 [n] in [0, 1), a new array.
    Raises:
        ValueError: as :func:`array_rqmc_uniforms`.
    """
    u, key = np.asarray(u, dtype=np.float64), np.asarray(key, dtype=np.float64)
    if u.ndim != 1 or u.size <= block:
        return array_rqmc_uniforms(u, key)
    if key.shape[0] != u.size:
        raise ValueError(f"array_rqmc_blocks: u is {u.shape} and key {key.shape}; they need the same first size")
    out = np.empty(u.size)
    for a, b in block_bounds(u.size, block):
        out[a:b] = array_rqmc_uniforms(u[a:b], key[a:b])
    return out


def by_blocks(fn, rows: np.ndarray, block: int = RQMC_BLOCK) -> np.ndarray:
    """``fn(rows)`` computed one block of rows at a time (``rows[jB:(j + 1)B]``), concatenated: float64 [n].

    A torch network may round a row's output differently in batches of different sizes (its kernels depend on the
    shape); asked about the same blocks, every executor gets the same bits. ``fn(rows)`` itself for n <= B.
    """
    n = np.shape(rows)[0]
    if n <= block:
        return fn(rows)
    return np.concatenate([np.asarray(fn(rows[a:b]), dtype=np.float64) for a, b in block_bounds(n, block)])
