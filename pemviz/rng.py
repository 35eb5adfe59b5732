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
