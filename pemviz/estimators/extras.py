"""What an estimator may say besides the :class:`pemviz.estimators.base.Estimator` interface, read in one place
(:func:`extras`): its simulations, pooling, verdict cap, stop reason, requirement decision, proposal preparation,
and whether streamed chunks must carry object rows."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any


@dataclass(frozen=True)
class Extras:
    """What an estimator may say besides the :class:`Estimator` interface, read once its run is over (every field
    optional for an estimator of one's own; :func:`extras`).

    Attributes:
        n_simulations: the rollout-equivalents it simulated (None: the rollouts the engine drew), e.g. splitting's
            continuations or a proposal's look-aheads counted.
        pooling: how its result pools the stages (``pooling()``: (name, lambda_k) or None), or None.
        verdict_cap: the best verdict its estimate may have and why (e.g. ``("doubtful", ...)``), or None.
        stop: why it stopped (one line), or None.
        decision: a requirement's decision (:class:`pemviz.core.requirement.Decision`), or None.
        prepared: how its proposal was prepared (one line), or None.
        needs_chunk_rows: whether a streamed stage's chunks must carry their object rows (True unless it says not)."""

    n_simulations: int | None = None
    pooling: tuple[str, tuple[float, ...]] | None = None
    verdict_cap: tuple[str, str] | None = None
    stop: str | None = None
    decision: Any = None
    prepared: str | None = None
    needs_chunk_rows: bool = True


def extras(estimator: Any) -> Extras:
    """The :class:`Extras` of ``estimator``: the attributes of those names it has (``pooling`` called), the defaults
    for the others."""
    pooling = getattr(estimator, "pooling", None)
    return Extras(
        getattr(estimator, "n_simulations", None),
        pooling() if callable(pooling) else None,
        getattr(estimator, "verdict_cap", None),
        getattr(estimator, "stop", None),
        getattr(estimator, "decision", None),
        getattr(estimator, "prepared", None),
        bool(getattr(estimator, "needs_chunk_rows", True)),
    )


def needs_chunk_rows(estimator: Any) -> bool:
    """Whether ``estimator`` reads every streamed chunk's object rows (:attr:`Extras.needs_chunk_rows`)."""
    return bool(getattr(estimator, "needs_chunk_rows", True))
