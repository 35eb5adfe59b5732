"""The recording's rollouts (*Rollouts* tab, ``step`` timeline): which of a stage's rollouts are kept (one entity per
signal, one series per rollout), which few are featured as entities of their own (:func:`featured`), and how both are
logged."""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np
import rerun as rr

from pemviz.core.counterfactuals import likeliest_failures
from pemviz.core.problem_view import ProblemView
from pemviz.engine.events import RolloutsSampled
from pemviz.sinks.rerun_views import (
    ALL_ROLLOUTS_UP_TO,
    CRASH_RGBA,
    DETECTED_RGBA,
    LIKELY_RGBA,
    MISSED_RGBA,
    SAFE_RGBA,
    SAMPLED_ROLLOUTS,
    TAG_CRASH_RGBA,
    TAG_RGBA,
    Indexes,
    outcome_values,
)

if TYPE_CHECKING:
    from rerun.components import MarkerShapeLike


def least_robust(ev: RolloutsSampled, k: int) -> np.ndarray:
    """Indices of the ``k`` least-robust rollouts under the configured metric, least first (ties: lower index)."""
    return np.argsort(ev.robustness, kind="stable")[: min(k, ev.robustness.size)]


def most_likely_failures(ev: RolloutsSampled, k: int) -> np.ndarray:
    """Indices of the ``k`` failing rollouts with the largest log p under the PEM (T - 1 steps), likeliest first
    (ties: lower index); fewer when fewer fail (:func:`pemviz.core.counterfactuals.likeliest_failures`)."""
    return likeliest_failures(ev.batch, ev.failed, k)


def kept_rollouts(ev: RolloutsSampled, n_least_robust: int) -> np.ndarray:
    """Indices of the rollouts recorded in full, ascending: all up to :data:`ALL_ROLLOUTS_UP_TO`, else the
    ``n_least_robust`` least robust, failures up to :data:`SAMPLED_ROLLOUTS`, the most likely failures
    (:func:`most_likely_failures`) and a uniform sample of :data:`SAMPLED_ROLLOUTS`; of a streamed stage, the
    engine's sample chosen the same way."""
    n = ev.robustness.size
    if n <= ALL_ROLLOUTS_UP_TO or ev.n_total is not None:
        return np.arange(n)
    keep = set(least_robust(ev, n_least_robust).tolist())
    keep |= set(np.flatnonzero(np.asarray(ev.failed, bool))[:SAMPLED_ROLLOUTS].tolist())
    if ev.batch is not None:
        keep |= set(most_likely_failures(ev, n_least_robust).tolist())
    keep |= set(np.linspace(0, n - 1, SAMPLED_ROLLOUTS).astype(int).tolist())
    return np.array(sorted(keep))


def featured(ev: RolloutsSampled, n_least_robust: int, n_likely: int) -> dict[int, str]:
    """The rollouts of a stage that get entities of their own, index -> role: the ``n_least_robust`` least robust
    (``least robust #1`` ...) and the ``n_likely`` most likely failures (``most likely failure #1 of the stage``
    ...), in that order; a rollout that is both keeps its first role."""
    roles = {int(i): f"least robust #{j + 1}" for j, i in enumerate(least_robust(ev, n_least_robust))}
    for j, i in enumerate(most_likely_failures(ev, n_likely)):
        roles.setdefault(int(i), f"most likely failure #{j + 1} of the stage")
    return roles


def deciding(trace: np.ndarray, view: ProblemView) -> np.ndarray:
    """bool [n, T]: the steps of rollouts with first signal ``trace`` [n, T] where a detection can still change the
    outcome: inside the sampler window, up to and including the first step below the failure threshold (every step
    for a problem without thresholds)."""
    th = view.thresholds
    if th is None:
        return np.ones(np.shape(trace), bool)
    below = trace < th.failure
    return (trace < th.window) & (np.cumsum(below, axis=1) - below == 0)


def rollout_path(column: str, stage: int, number: int) -> str:
    """A featured rollout's entity for one signal, e.g. ``rollouts/gap_m/stage_04/rollout_011``."""
    return f"rollouts/{column}/stage_{stage:02d}/rollout_{number:03d}"


@dataclass(frozen=True)
class StageRollouts:
    """What :func:`log_stage_rollouts` logged of a stage: the kept rows, their outcome words and the featured."""

    keep: np.ndarray
    outcomes: list[str]
    featured: dict[int, str]


def log_stage_rollouts(
    stream: rr.RecordingStream,
    ev: RolloutsSampled,
    view: ProblemView,
    stage_name: str,
    n_tagged: int,
    n_likely: int,
    indexes: Indexes,
) -> StageRollouts:
    """A stage's kept rollouts (:func:`kept_rollouts`): one entity per signal of the view with one series per rollout,
    the per-rollout values, the featured rollouts' own entities (:func:`featured`), and their misses (and the tagged
    ones' detections) where a detection can still change the outcome (:func:`deciding`).

    Args:
        stream: the recording logged to.
        ev: the stage's rollouts.
        view: the problem's view (signals; its drawing object gives each rollout its outcome words, e.g. a severity).
        stage_name: the plan's name of the stage.
        n_tagged: least-robust rollouts tagged (yellow, wide) and featured.
        n_likely: most likely failures featured.
        indexes: the sink's time columns for ``send_columns``."""
    s, batch = stream, ev.batch
    t = batch.n_steps
    keep = kept_rollouts(ev, max(n_tagged, n_likely))
    order = least_robust(ev, n_tagged)
    rank = {int(i): j for j, i in enumerate(order)}
    failed = np.asarray(ev.failed, bool)
    number = ev.rollout_numbers
    first = view.signals[0].column
    trace = batch.signal(first)
    told = {i: outcome_values(view.drawing, batch, i) for i in keep.tolist()}
    words = [str(v["outcome"]) if v is not None else "failure" if failed[i] else "safe" for i, v in told.items()]
    colours, widths, names = _series_style(ev, keep, rank, words)
    index = indexes(step=np.arange(t))
    stage = f"stage_{ev.stage:02d}"
    for sig in view.signals:
        if sig.column not in batch.observation_names:
            continue
        path = f"rollouts/{sig.column}/{stage}"
        s.log(path, rr.SeriesLines(colors=colours, widths=widths, names=names), static=True)
        s.send_columns(path, indexes=index, columns=rr.Scalars.columns(scalars=batch.signal(sig.column)[keep].T))
    log_p = batch.log_likelihood()
    s.log(
        f"rollouts/summary/{stage}",
        rr.AnyValues(
            rollout=number[keep],
            log_p=log_p[keep],
            log_weight=np.asarray(ev.log_weight, np.float64)[keep],
            failed=failed[keep],
            outcome=words,
            least_robust=np.isin(keep, order),
            **{
                f"robustness_{m.replace('-', '_')}": np.asarray(v, np.float64)[keep]
                for m, v in ev.robustness_by_metric.items()
            },
        ),
        static=True,
    )
    roles = featured(ev, n_tagged, n_likely)
    said_of = dict(zip(keep.tolist(), words, strict=False))
    rows = np.array(sorted(roles), dtype=np.int64)
    labels = []
    for i in rows.tolist():
        labels.append(_log_featured(s, ev, view, i, roles[i], said_of[i], told[i], float(log_p[i]), stage_name, index))
    _log_marks(s, f"rollouts/{{}}/{stage}", batch, rows, labels, np.isin(rows, order), trace, view, index)
    return StageRollouts(keep, words, roles)


def _series_style(
    ev: RolloutsSampled, keep: np.ndarray, rank: dict[int, int], words: list[str]
) -> tuple[list[tuple[int, int, int, int]], list[float], list[str]]:
    """Each kept rollout's series colour, width and name: the least-robust ones (``rank``) tagged, failures named by
    their outcome ``words``."""
    failed, number = np.asarray(ev.failed, bool), ev.rollout_numbers
    colours, widths, names = [], [], []
    for i, said in zip(keep.tolist(), words, strict=False):
        tag = rank.get(i)
        what = f": {said}" if failed[i] else ""
        if tag is None:
            colours.append(CRASH_RGBA if failed[i] else SAFE_RGBA)
            widths.append(1.0)
            names.append(f"s{ev.stage} r{number[i]}{what}")
        else:
            colours.append(TAG_CRASH_RGBA if failed[i] else TAG_RGBA)
            widths.append(2.5)
            names.append(f"s{ev.stage} r{number[i]} least-robust #{tag + 1} rho={ev.robustness[i]:.3g}{what}")
    return colours, widths, names


def _log_marks(
    s: rr.RecordingStream,
    path_of: str,
    batch: Any,
    rows: np.ndarray,
    labels: list[str],
    tagged: np.ndarray,
    trace: np.ndarray,
    view: ProblemView,
    index: Any,
) -> None:
    """The featured rollouts' detections (shown for the ``tagged`` ones) and misses on their first signal's trace,
    where a detection can still change the outcome (:func:`deciding`); ``path_of`` names the entity of each kind."""
    marks_of: tuple[tuple[str, bool, tuple[int, ...], MarkerShapeLike, float, np.ndarray], ...] = (
        ("detected", True, DETECTED_RGBA, "circle", 1.5, tagged),
        ("missed", False, MISSED_RGBA, "cross", 3.0, np.ones_like(tagged)),
    )
    for key, mask, rgba, marker, size, show in marks_of:
        if rows.size == 0:
            break
        path = path_of.format(key)
        s.log(
            path,
            rr.SeriesPoints(
                colors=[rgba] * rows.size,
                names=[f"{lb}: {key}" for lb in labels],
                markers=[marker] * rows.size,
                marker_sizes=[size] * rows.size,
                visible_series=show,  # type: ignore[arg-type]  # rerun's BoolArrayLike omits numpy arrays it takes
            ),
            static=True,
        )
        marks = np.where((batch.detected[rows, :, 0] == mask) & deciding(trace[rows], view), trace[rows], np.nan)
        s.send_columns(path, indexes=index, columns=rr.Scalars.columns(scalars=marks.T))


def _log_featured(
    s: rr.RecordingStream,
    ev: RolloutsSampled,
    view: ProblemView,
    i: int,
    role: str,
    said: str,
    told: dict | None,
    log_p: float,
    stage_name: str,
    index: list,
) -> str:
    """Rollout ``i``'s first signal as an entity of its own (:func:`rollout_path`) with its properties (with the
    drawing object's numbers of its outcome, ``told``, where it has them); returns its label."""
    batch, n = ev.batch, int(ev.rollout_numbers[i])
    failed = bool(ev.failed[i])
    rgba = LIKELY_RGBA if role.startswith("most likely") else TAG_CRASH_RGBA if failed else TAG_RGBA
    label = f"stage {ev.stage} rollout {n} ({role}): {said}"
    props: dict = dict(
        stage=ev.stage,
        stage_name=stage_name,
        rollout=n,
        role=role,
        log_p=log_p,
        log_weight=float(ev.log_weight[i]),
        robustness=float(ev.robustness[i]),
        failed=failed,
        outcome=said,
    )
    props.update({f"robustness_{m.replace('-', '_')}": float(v[i]) for m, v in ev.robustness_by_metric.items()})
    if told is not None:
        props.update(told)
    column = view.signals[0].column
    path = rollout_path(column, ev.stage, n)
    s.log(path, rr.SeriesLines(colors=[rgba], widths=[2.5], names=[label]), rr.AnyValues(**props), static=True)
    s.send_columns(path, indexes=index, columns=rr.Scalars.columns(scalars=batch.signal(column)[i]))
    return label
