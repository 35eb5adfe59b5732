"""Groups of the failures of a run's final estimate (:mod:`pemviz.core.population`) for the listeners that show them:
which rollout of which stage's kept batch each failure is, the key of the decisive events it shares with others (the
drawing object's ``failure_keys``, else the failure step), and the failures' severity by their shares. No I/O."""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Hashable, Mapping
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Protocol, cast

import numpy as np

from pemviz.core.population import FailureGroup, FailureShares, failure_groups
from pemviz.core.rollouts import RolloutBatch
from pemviz.core.severity import FailureSeverity, SeverityProblem, contact_level, failure_severity, rollout_severity
from pemviz.engine.events import RolloutsSampled

if TYPE_CHECKING:
    import rerun as rr

    from pemviz.core.problems import Problem

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
        severity: each failure's min distance and impact speed in the order of ``shares``, and their distribution
            by share (:func:`failures_severity`); None without the run's problem, or where it has no severity scale."""

    shares: FailureShares
    found: tuple[tuple[RolloutsSampled, int] | None, ...]
    keys: tuple[Hashable, ...]
    groups: tuple[FailureGroup, ...]
    basis: str
    severity: FailureSeverity | None = None

    @functools.cached_property
    def labels(self) -> dict[Hashable, str]:
        """Group key -> its label."""
        return {g.key: g.label for g in self.groups}

    def group_label(self, rank: int) -> str:
        """The label of the group of the failure at ``rank``."""
        key = self.keys[rank]
        return self.labels.get(key, str(key))


def locate_rows(shares: FailureShares, sampled: Mapping[int, RolloutsSampled]) -> np.ndarray:
    """int64 [F]: per failure (in ``shares`` order), its row in its stage's batch, -1 where the stage was not kept or
    kept only a sample without it. One sort per stage: the rows' numbers sorted (stably: of a number kept twice, the
    last row), each failure's number found by a binary search."""
    row = np.full(shares.n, -1, dtype=np.int64)
    stage, number = np.asarray(shares.stage), np.asarray(shares.index, dtype=np.int64)
    for s, event in sampled.items():
        mine = np.flatnonzero(stage == s)
        if not mine.size:
            continue
        want = number[mine]
        if event.index is None:  # the whole stage: rollout i is row i
            ok = (want >= 0) & (want < event.batch.n)
            row[mine[ok]] = want[ok]
            continue
        order = np.argsort(np.asarray(event.index, dtype=np.int64), kind="stable")
        ranked = np.asarray(event.index, dtype=np.int64)[order]
        at = np.searchsorted(ranked, want, side="right") - 1
        ok = at >= 0
        ok[ok] = ranked[at[ok]] == want[ok]
        row[mine[ok]] = order[at[ok]]
    return row


def _stages_located(shares: FailureShares, rows: np.ndarray) -> list[tuple[int, np.ndarray]]:
    """(stage, the ranks of its located failures, int [f]) per stage with one, in the order of their first failure."""
    stage = np.asarray(shares.stage)[rows >= 0]
    ranks = np.flatnonzero(rows >= 0)
    if not ranks.size:
        return []
    kinds, first = np.unique(stage, return_index=True)
    return [(int(s), ranks[stage == s]) for s in kinds[np.argsort(first, kind="stable")]]


def failures_severity(
    shares: FailureShares, sampled: Mapping[int, RolloutsSampled], problem: object, rows: np.ndarray | None = None
) -> FailureSeverity | None:
    """Each failure's min distance and impact speed (:func:`pemviz.core.severity.rollout_severity`, read from the
    rollout in its stage's batch) and their distribution by share of p.

    Args:
        shares: the final estimate's failures.
        sampled: stage -> :class:`RolloutsSampled` to locate them in.
        problem: the run's :class:`pemviz.core.problems.Problem`.
        rows: int [F] their rows in their stages' batches, -1 where not located (:func:`locate_rows`; default: located
            here).
    Returns:
        The distribution (failures not located are left out of it, their values NaN), or None where ``problem`` is
        None or has no severity scale.
    Raises:
        ValueError: a rollout in contact at its first step (:func:`pemviz.core.severity.severity_of_signal`)."""
    if problem is None or getattr(problem, "severity", None) is None:
        return None
    severe = cast(SeverityProblem, problem)  # a problem with a severity scale, as just checked
    if rows is None:
        rows = locate_rows(shares, sampled)
    dist, speed = np.full(shares.n, np.nan), np.full(shares.n, np.nan)
    for stage, ranks in _stages_located(shares, rows):
        dist[ranks], speed[ranks] = rollout_severity(severe, sampled[stage].batch.select(rows[ranks]))
    scale = severe.severity
    assert scale is not None  # checked above
    return failure_severity(scale, contact_level(problem), shares.log_share, dist, speed, rows >= 0)


def group_failures(
    shares: FailureShares,
    sampled: Mapping[int, RolloutsSampled],
    drawing: object = None,
    problem: object = None,
    keys_wanted: bool = True,
) -> FailureGrouping:
    """Locate and group the failures of an estimate, and with ``problem`` read their severity
    (:func:`failures_severity`).

    Args:
        shares: the final estimate's failures (``FinalEstimate.failures``).
        sampled: stage -> the stage's :class:`RolloutsSampled`.
        drawing: the scenario's drawing object: with ``failure_keys(detected [F, T]) -> (basis, keys, labels)`` it
            groups the failures, else they are grouped by failure step.
        problem: the run's :class:`pemviz.core.problems.Problem`, or None.
        keys_wanted: False: one group, no replays (the severity is read all the same).
    Raises:
        ValueError: a failure in contact at its first step (:func:`failures_severity`)."""
    rows = locate_rows(shares, sampled)
    found = [(sampled[s], r) if r >= 0 else None for s, r in zip(shares.stage.tolist(), rows.tolist(), strict=False)]
    keys: list[Hashable] = [NOT_KEPT] * shares.n
    by_stage = _stages_located(shares, rows)
    labels: dict[Hashable, str] = {NOT_KEPT: "not kept (a streamed stage keeps a sample of its rollouts)"}
    basis = "nothing: this problem has no scene to replay"
    if not keys_wanted:
        basis = "nothing: not asked for"
    elif drawing is not None and hasattr(drawing, "failure_keys"):
        kept = np.concatenate([ranks for _, ranks in by_stage]) if by_stage else np.zeros(0, np.intp)
        if kept.size:  # each stage's rows taken at once, then put in rank order
            parts = [sampled[s].batch.detected[rows[ranks], :, 0] for s, ranks in by_stage]
            detected = np.concatenate(parts)[np.argsort(kept, kind="stable")]
            kept = np.sort(kept)
        else:
            detected = np.zeros((0, 0), dtype=bool)
        basis, found_keys, found_labels = drawing.failure_keys(detected)
        for rank, k in zip(kept.tolist(), found_keys, strict=False):
            keys[rank] = k
        present = set(keys)
        labels.update({k: v for k, v in found_labels.items() if k in present})
    elif problem is not None:
        from pemviz.estimators.base import failure_steps

        basis = "the step at which the rollout fails"
        try:
            for stage, ranks in by_stage:
                steps = np.asarray(failure_steps(cast("Problem", problem), sampled[stage].batch))
                for rank, k in zip(ranks.tolist(), steps[rows[ranks]].astype(np.int64).tolist(), strict=False):
                    keys[rank] = k
            labels.update({k: f"fails at step {k}" for k in set(keys) if isinstance(k, int)})
        except ValueError:  # a formula whose failure step cannot be read: one group
            basis = "nothing: the failure step of this formula cannot be read"
            keys = ["all"] * shares.n
    if basis.startswith("nothing"):
        keys = ["all"] * shares.n
        labels["all"] = "every failure"
    return FailureGrouping(
        shares,
        tuple(found),
        tuple(keys),
        tuple(failure_groups(shares, keys, labels)),
        basis,
        failures_severity(shares, sampled, problem, rows),
    )


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
    head = (
        "| # | stage | rollout | share of p | log w (nats) | log p (nats) | group |\n"
        "|---:|---:|---:|---:|---:|---:|---|\n"
    )
    return (
        f"## Failures of the final estimate: {n:,}\n\nShare of p: the fraction of mu_hat a failure carries (its "
        f"importance weight over the failures'). Groups by {g.basis} ({len(g.groups)}; shares add up to 100 %):\n\n"
        "| group | failures | share of p |\n|---|---:|---:|\n" + groups + "\n\n"
        f"The failures, the largest share first{f' (the first {most:,})' if n > most else ''}:\n\n" + head + rows + more
    )


def compact_failures(event: RolloutsSampled, problem: object = None) -> RolloutsSampled:
    """The failing rollouts of ``event`` with only what :func:`group_failures` and :func:`failures_severity` read: the
    detections and the observation columns of the problem's signals and severity signal (every column without a
    problem); no log p, log q or object rows (e.g. a stage of 10,000 braking rollouts keeps about 1 MB, not 40 MB)."""
    rows = np.flatnonzero(np.asarray(event.failed, dtype=bool))
    b = event.batch
    names = b.observation_names
    if problem is not None:
        wanted = set(getattr(problem, "signals", {}).values())
        scale = getattr(problem, "severity", None)
        if scale is not None:
            wanted.add(cast(SeverityProblem, problem).signals.get(scale.signal, scale.signal))
        names = tuple(c for c in b.observation_names if c in wanted)
    cols = [b.observation_names.index(c) for c in names]
    batch = RolloutBatch(
        b.observations[rows][:, :, cols], b.detected[rows], np.zeros((rows.size, 0)), np.zeros((rows.size, 0)), names
    )
    index = np.arange(b.n) if event.index is None else np.asarray(event.index)
    return dataclasses.replace(
        event,
        batch=batch,
        robustness=np.asarray(event.robustness)[rows],
        robustness_by_metric={},
        failed=np.ones(rows.size, dtype=bool),
        log_weight=np.asarray(event.log_weight)[rows],
        n_total=event.n_total or b.n,
        index=index[rows],
        stage_robustness=None,
        stage_log_weight=None,
        sampler=None,
        target=None,
    )


class SharedGroups(Protocol):
    """What the sinks that share a run's failure groups read and set of them (``ConsoleSink.failures``,
    ``share_failure_groups`` of the recording's sinks): a :class:`FailureGroups`, or the recording process's stand-in
    for the run's (:mod:`pemviz.sinks.recording_process`)."""

    drawing: object
    problem: object
    grouping: FailureGrouping | None

    def __call__(self, event: object) -> None: ...


class FailureGroups:
    """A listener that keeps each stage's sampled rollouts and, at the final estimate, groups its failures
    (:func:`group_failures`); :attr:`grouping` is None before, or where the estimator keeps no per-stage rollouts.

    Args:
        drawing: the scenario's drawing object (``ProblemView.drawing``), or None.
        problem: the run's :class:`pemviz.core.problems.Problem` (groups by failure step elsewhere), or None.
        keys: group the failures (False: only their severity, without the drawing object's keys, whose cost may
            grow with the failures)."""

    def __init__(self, drawing: object = None, problem: object = None, keys: bool = True) -> None:
        self.drawing, self.problem, self.keys = drawing, problem, keys
        self.sampled: dict[int, RolloutsSampled] = {}
        self.grouping: FailureGrouping | None = None
        self._last: object = None

    def __call__(self, event: object) -> None:
        from pemviz.engine.events import FinalEstimate

        if event is self._last:  # a listener shared by two sinks hears each event once
            return
        self._last = event
        if isinstance(event, RolloutsSampled):  # its failures only, and only what grouping and severity read
            self.sampled[event.stage] = compact_failures(event, self.problem)
        elif isinstance(event, FinalEstimate):
            if event.failures is not None:
                self.grouping = group_failures(event.failures, self.sampled, self.drawing, self.problem, self.keys)
            self.sampled = {}  # the batches are no longer needed


def grouping_document(g: FailureGrouping, most: int = 20) -> dict:
    """The groups (largest share first) and the ``most`` failures with the largest shares as plain numbers for a
    result document: ``{"basis", "n", "groups": [{"label", "count", "share"}], "largest": [{"stage", "rollout",
    "share", "log_p", "group"}]}`` (shares of mu_hat; log p in nats), with severity each of ``largest`` adds
    ``min_distance`` (m) and ``impact_speed`` (m/s) and ``"severity"`` holds :func:`severity_document`."""
    share = g.shares.share()
    sev = g.severity
    largest = []
    for r in range(min(most, g.shares.n)):
        row = {
            "stage": int(g.shares.stage[r]),
            "rollout": int(g.shares.index[r]),
            "share": float(share[r]),
            "log_p": float(g.shares.log_p[r]),
            "group": g.group_label(r),
        }
        if sev is not None:
            row["min_distance"] = _finite(sev.min_distance[r])
            row["impact_speed"] = _finite(sev.impact_speed[r])
        largest.append(row)
    doc = {
        "basis": g.basis,
        "n": g.shares.n,
        "groups": [{"label": x.label, "count": x.count, "share": float(x.share)} for x in g.groups],
        "largest": largest,
    }
    if sev is not None and sev.n_failures:
        doc["severity"] = severity_document(sev)
    return doc


def _finite(x: float) -> float | None:
    return float(x) if np.isfinite(x) else None


def severity_document(sev: FailureSeverity) -> dict:
    """p(severity | failure) as plain numbers: ``{"signal", "label", "unit", "contact", "n", "n_kept", "covered",
    "median_min_distance", "text", "bins": [{"label", "lo", "hi", "count", "share"}]}`` (metres, m/s; null where not
    defined; the bins' shares add up to 1)."""
    bounds, counts, shares = sev.bounds(), sev.counts(), sev.shares()
    return {
        "signal": sev.scale.signal,
        "label": sev.scale.label,
        "unit": sev.scale.unit,
        "contact": sev.contact,
        "n": sev.n_failures,
        "n_kept": sev.n,
        "covered": sev.covered,
        "median_min_distance": sev.median_min_distance() if sev.n else None,
        "text": sev.line(),
        "bins": [
            {"label": label, "lo": lo, "hi": hi, "count": int(c), "share": float(x)}
            for label, (lo, hi), c, x in zip(sev.labels(), bounds, counts, shares, strict=False)
        ],
    }


def log_failures(stream: rr.RecordingStream, grouping: FailureGrouping, problem: object = None) -> str:
    r"""Log a run's failures to its recording (static): ``failures`` (Markdown, :func:`population_markdown`),
    ``final/failures`` (every failure in share order) and ``final/severity_of_failures`` (p(severity | failure) as
    bars per impact-speed bin, with the bins' words, counts and shares, the share-weighted median min distance, the
    contact level and ``kept_share``).

    Returns:
        The console's severity line for the run's description (``"\n\n" + line``), or ``""`` without one."""
    import rerun as rr  # a recording only: the command line's other outputs need no rerun

    from pemviz.sinks import colours as C

    f = grouping.shares
    stream.log(
        "failures", rr.TextDocument(population_markdown(grouping), media_type=rr.MediaType.MARKDOWN), static=True
    )
    sampled = {x[0].stage: x[0] for x in grouping.found if x is not None}
    rows = np.array([-1 if x is None else x[1] for x in grouping.found], dtype=np.int64)
    sev = failures_severity(f, sampled, problem, rows)
    aligned: dict[str, Any] = (
        {} if sev is None else {"min_distance": sev.min_distance, "impact_speed": sev.impact_speed}
    )
    stream.log(
        "final/failures",
        rr.AnyValues(
            stage=f.stage,
            rollout=f.index,
            share=f.share(),
            log_weight=f.log_weight,
            log_p=f.log_p,
            group=[str(k) for k in grouping.keys],
            **aligned,
        ),
        static=True,
    )
    if sev is None or not sev.n:
        return ""
    shares = sev.shares()
    stream.log(
        "final/severity_of_failures",
        rr.BarChart(shares, color=C.rgba(C.CRASH)),
        rr.AnyValues(
            bin=sev.labels(),
            bin_failures=sev.counts(),
            bin_share=shares,
            median_min_distance=sev.median_min_distance(),
            contact_level=sev.contact,
            kept_share=sev.covered,
            distance=f"min {sev.scale.label} ({sev.scale.unit})",
        ),
        static=True,
    )
    return "\n\n" + sev.line()
