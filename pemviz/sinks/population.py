"""Groups of the failures of a run's final estimate (:mod:`pemviz.core.population`) for the listeners that show them:
which rollout of which stage's kept batch each failure is, and the key of the decisive events it shares with others.

Groups: on the braking scenario, the last step at which one detection alone still saves the rollout (exact replays on
its deterministic twin, :func:`pemviz.scenarios.braking_failures.last_saving_steps`): the failures whose last chance
came at the same step. Elsewhere, with the run's problem at hand, the step at which the rollout fails
(:func:`pemviz.estimators.base.failure_steps`), which the labels say; without it, one group. No I/O.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Hashable, Mapping
from dataclasses import dataclass

import numpy as np

from pemviz.core.population import FailureGroup, FailureShares, failure_groups
from pemviz.engine.events import RolloutsSampled

NOT_KEPT = "not kept"
"""Group key of failures whose stage was streamed and kept only a sample of its rollouts for the listeners."""

MAX_LISTED = 200
"""Failures listed in a recording's table, largest share first (the groups cover every one)."""


@dataclass(frozen=True)
class FailureGrouping:
    """The failures of an estimate located in the kept batches and grouped.

    Attributes:
        shares: the failures, largest share of mu_hat first.
        found: per rank, (the stage's :class:`RolloutsSampled`, its row in the batch), or None where the stage kept
            only a sample without it.
        keys: per rank, its group key.
        groups: the groups, largest share first (their shares add up to 1).
        basis: what the groups share, in words.
    """

    shares: FailureShares
    found: tuple[tuple[RolloutsSampled, int] | None, ...]
    keys: tuple[Hashable, ...]
    groups: tuple[FailureGroup, ...]
    basis: str

    def group_label(self, rank: int) -> str:
        """The label of the group of the failure at ``rank``."""
        key = self.keys[rank]
        return next((g.label for g in self.groups if g.key == key), str(key))


def _row(event: RolloutsSampled, index: int) -> int | None:
    """The row of rollout ``index`` of the stage in ``event``'s batch, or None where the batch is a sample without
    it."""
    if event.index is None:
        return index if index < event.batch.n else None
    hit = np.flatnonzero(np.asarray(event.index) == index)
    return int(hit[0]) if hit.size else None


def group_failures(shares: FailureShares, sampled: Mapping[int, RolloutsSampled], scene: object = None,
                   problem: object = None) -> FailureGrouping:  # fmt: skip
    """Locate and group the failures of an estimate.

    Args:
        shares: the final estimate's failures (``FinalEstimate.failures``).
        sampled: stage -> the stage's :class:`RolloutsSampled` (its batch, or a sample of it when streamed).
        scene: the braking scenario's constants (``ProblemView.scene``), or None: not the braking scenario.
        problem: the run's :class:`pemviz.core.problems.Problem` (groups by failure step), or None.
    """
    found: list[tuple[RolloutsSampled, int] | None] = []
    for stage, index in zip(shares.stage.tolist(), shares.index.tolist()):
        event = sampled.get(stage)
        row = _row(event, index) if event is not None else None
        found.append((event, row) if row is not None else None)
    keys: list[Hashable] = [NOT_KEPT] * shares.n
    kept = [rank for rank, f in enumerate(found) if f is not None]
    labels: dict[Hashable, str] = {NOT_KEPT: "not kept (a streamed stage keeps a sample of its rollouts)"}
    basis = "nothing: this problem has no scene to replay"
    if scene is not None:
        from pemviz.scenarios.braking_failures import last_saving_steps

        basis = "the last step at which one detection alone still saves the rollout (exact replays)"
        if kept:
            detected = np.stack([found[r][0].batch.detected[found[r][1], :, 0] for r in kept])
            for rank, s in zip(kept, last_saving_steps(detected, scene).tolist()):
                keys[rank] = s
        dt = float(getattr(scene, "dt_s", 0.1))
        labels.update({k: (f"last saving detection at step {k} ({k * dt:.2f} s)" if k >= 0
                           else "no single detection saves it") for k in set(keys) if isinstance(k, int)})  # fmt: skip
    elif problem is not None:
        from pemviz.estimators.base import failure_steps

        basis = "the step at which the rollout fails"
        steps: dict[int, np.ndarray] = {}
        try:
            for rank in kept:
                event, row = found[rank]
                if event.stage not in steps:
                    steps[event.stage] = failure_steps(problem, event.batch)
                keys[rank] = int(steps[event.stage][row])
            labels.update({k: f"fails at step {k}" for k in set(keys) if isinstance(k, int)})
        except ValueError:  # a formula whose failure step cannot be read: one group
            basis = "nothing: the failure step of this formula cannot be read"
            keys = ["all"] * shares.n
    if basis.startswith("nothing"):
        keys = ["all"] * shares.n
        labels["all"] = "every failure"
    return FailureGrouping(shares, tuple(found), tuple(keys), tuple(failure_groups(shares, keys, labels)), basis)


def population_markdown(g: FailureGrouping, most: int = MAX_LISTED) -> str:
    """The failures as markdown: the groups (every one, largest share first), then the ``most`` failures with the
    largest shares (stage, rollout, share of p, importance log-weight as the estimate counts it, log p before the
    failure, group)."""
    n = g.shares.n
    if n == 0:
        return "## Failures\n\nThe final estimate has no failure.\n"
    share = g.shares.share()
    groups = "\n".join(f"| {x.label} | {x.count:,} | {100 * x.share:.3g} % |" for x in g.groups)
    st, ix, lw, lp = g.shares.stage, g.shares.index, g.shares.log_weight, g.shares.log_p
    rows = "\n".join(
        f"| {r + 1} | {st[r]} | {ix[r]} | {100 * share[r]:.3g} % | {lw[r]:.2f} | {lp[r]:.2f} | {g.group_label(r)} |"
        for r in range(min(n, most))
    )
    more = f"\n\n... and {n - most:,} more failures (their groups are above).\n" if n > most else "\n"
    head = ("| # | stage | rollout | share of p | log w (nats) | log p (nats) | group |\n"
            "|---:|---:|---:|---:|---:|---:|---|\n")
    return (
        f"## Failures of the final estimate: {n:,}\n\nShare of p: the fraction of mu_hat a failure carries (its "
        f"importance weight over the failures'). Groups by {g.basis} ({len(g.groups)}; shares add up to 100 %):\n\n"
        "| group | failures | share of p |\n|---|---:|---:|\n" + groups + "\n\n"
        f"The failures, the largest share first{f' (the first {most:,})' if n > most else ''}:\n\n" + head + rows + more
    )


class FailureGroups:
    """A listener that keeps each stage's sampled rollouts and, at the final estimate, groups its failures
    (:func:`group_failures`); :attr:`grouping` is None before, or where the estimator keeps no per-stage rollouts.

    Args:
        scene: the braking scenario's constants (``ProblemView.scene``), or None.
        problem: the run's :class:`pemviz.core.problems.Problem` (groups by failure step elsewhere), or None.
    """

    def __init__(self, scene: object = None, problem: object = None) -> None:
        self.scene, self.problem = scene, problem
        self.sampled: dict[int, RolloutsSampled] = {}
        self.grouping: FailureGrouping | None = None

    def __call__(self, event: object) -> None:
        from pemviz.engine.events import FinalEstimate

        if isinstance(event, RolloutsSampled):  # its failures only: a batch of several objects is large
            rows = np.flatnonzero(np.asarray(event.failed, dtype=bool))
            index = np.arange(event.batch.n) if event.index is None else np.asarray(event.index)
            self.sampled[event.stage] = dataclasses.replace(
                event, batch=event.batch.select(rows), robustness=np.asarray(event.robustness)[rows],
                robustness_by_metric={}, failed=np.ones(rows.size, dtype=bool),
                log_weight=np.asarray(event.log_weight)[rows], n_total=event.n_total or event.batch.n,
                index=index[rows], stage_robustness=None, stage_log_weight=None, sampler=None, target=None,
            )  # fmt: skip
        elif isinstance(event, FinalEstimate):
            if event.failures is not None:
                self.grouping = group_failures(event.failures, self.sampled, self.scene, self.problem)
            self.sampled = {}  # the batches are no longer needed


def grouping_document(g: FailureGrouping, most: int = 20) -> dict:
    """The groups (every one, largest share first) and the ``most`` failures with the largest shares, as plain
    numbers for a result document: ``{"basis", "n", "groups": [{"label", "count", "share"}], "largest": [{"stage",
    "rollout", "share", "log_p", "group"}]}`` (shares are fractions of mu_hat; log p in nats)."""
    share = g.shares.share()
    return {
        "basis": g.basis,
        "n": g.shares.n,
        "groups": [{"label": x.label, "count": x.count, "share": float(x.share)} for x in g.groups],
        "largest": [{"stage": int(g.shares.stage[r]), "rollout": int(g.shares.index[r]), "share": float(share[r]),
                     "log_p": float(g.shares.log_p[r]), "group": g.group_label(r)}
                    for r in range(min(most, g.shares.n))],
    }  # fmt: skip
