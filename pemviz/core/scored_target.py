"""A mixture stage's target that keeps its components' logits: :class:`ScoredTarget` (the detectors asked about each
step's rows are :mod:`pemviz.core.detectors`')."""

from __future__ import annotations

import numpy as np

from pemviz.core.detector_noise import ErrorModelOf
from pemviz.core.detectors import Detector, reads_state


class ScoredTarget(ErrorModelOf):
    """The target detector that also asks ``extras`` about every observation it is asked about and keeps their
    logits and its own, so that a mixture's component densities come out of the simulation itself. :meth:`take`
    hands them over as [K, n, T] (and the target's [n, T]) for the next ``n`` rollouts, or None when the asks do not
    fit that shape (then the caller asks ``extras`` itself)."""

    _error_model_of = "target"  # it scores as the target does

    def __init__(self, target: Detector, extras: tuple[Detector, ...]) -> None:
        self.target, self.extras = target, tuple(extras)
        self.reads_state = any(reads_state(d) for d in (target, *self.extras))
        self._asked: list[tuple[np.ndarray, ...]] = []

    def detect_logit(self, obs: np.ndarray) -> np.ndarray:
        """The target's logit p(detect | obs), float64 [N]; it and the extras' logits (K + 1 arrays [N]) are kept."""
        extras = tuple(np.asarray(d.detect_logit(obs), dtype=np.float64) for d in self.extras)
        p = np.asarray(self.target.detect_logit(obs), dtype=np.float64)
        self._asked.append((p, *extras))
        return p

    def take(
        self, n: int, n_steps: int, n_objects: int = 1, skip: int | None = None
    ) -> list[tuple[int, np.ndarray]] | None:
        """The kept logits of the next ``n`` rollouts of M objects, in the order simulated, step-major as asked: per
        group of T asks of equal rows (one group per chunk of rollouts stepped together), (its first rollout, float64
        [K + 1, T, r M]: the target's logits, then the K extras', each rollout's M object rows together); or None (all
        kept logits are dropped) when the asks kept do not start with such groups covering ``n`` rollouts. The extra
        of index ``skip`` (not None) is left unset: not read. :func:`by_rollout` lays them out rollout by rollout."""
        asked, groups, used, rows = self._asked, [], 0, 0
        while rows < n and used + n_steps <= len(asked):
            r = asked[used][0].shape[0]
            if r % n_objects or any(a[0].shape[0] != r for a in asked[used : used + n_steps]):
                break
            groups.append((used, rows, r))
            used, rows = used + n_steps, rows + r // n_objects
        if rows != n:
            self._asked = []
            return None
        out = []
        for first, row, r in groups:  # each detector's T asks of a group stacked [T, r], copied in once
            block = np.empty((len(self.extras) + 1, n_steps, r))
            for k in range(block.shape[0]):
                if skip is None or k != skip + 1:
                    np.stack([asked[first + t][k] for t in range(n_steps)], out=block[k])
            out.append((row, block))
        del asked[:used]
        return out


def by_rollout(groups: list[tuple[int, np.ndarray]], n: int, n_objects: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """:meth:`ScoredTarget.take`'s groups rollout by rollout: (the extras' logits float64 [K, n, T, M], the target's
    [n, T, M])."""
    k, n_steps = groups[0][1].shape[:2]
    out = np.empty((k, n, n_steps, n_objects))
    for row, block in groups:
        m = block.shape[2] // n_objects
        out[:, row : row + m] = block.reshape(k, n_steps, m, n_objects).transpose(0, 2, 1, 3)
    return out[1:], out[0]
