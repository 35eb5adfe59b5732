"""What the viser panel knows about a run, built from the engine's events (:class:`PanelRun`), which runs stay for
comparison (:func:`keep_runs`), and a run's export into ``recordings/`` without letting a name from the browser escape
that folder. No viser here."""

from __future__ import annotations

import functools
import math
import os
import re
import threading
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from pemviz.app.form import run_label
from pemviz.config import ExperimentConfig
from pemviz.core.counterfactuals import LikelyFailure, LogPParts, scoring_detector
from pemviz.core.counterfactuals import most_likely_failure as pick_most_likely
from pemviz.core.estimate import Reference
from pemviz.core.feature_view import FeatureCurve, evenly_spaced, stage_feature_curve
from pemviz.core.population import FailureShares
from pemviz.core.proposal_view import ProposalView, batch_proposal_view, object_detect_probabilities, proposal_view
from pemviz.core.rollouts import RolloutBatch
from pemviz.engine.events import (
    Event,
    FinalEstimate,
    RolloutChunk,
    RolloutsSampled,
    RunCancelled,
    RunFinished,
    RunStarted,
    StageFinished,
    StageResult,
    StageStarted,
)
from pemviz.scenarios.panel_data import ViewAxis
from pemviz.sinks import Sink, StageClock
from pemviz.sinks.population import FailureGrouping, group_failures
from pemviz.sinks.recording import RerunSink

if TYPE_CHECKING:
    from pemviz.core.detectors import Detector
    from pemviz.core.features import FeaturesFn
    from pemviz.core.plan import RunPlan
    from pemviz.core.problem_view import ProblemView
    from pemviz.core.problems import Problem

MAX_RUNS = 4
"""Runs kept side by side for comparison (:func:`keep_runs` decides which go when a fifth starts)."""

MAX_POPULATION = 5_000
"""Failures of a run's estimate the panel keeps as rollouts to list, largest share first (about 5 KB each; a run of
N = 10,000 per stage has some 60,000 failures). The groups cover every failure."""

N_TRAJECTORIES = 20
"""Least-robust rollouts listed per run."""

MAX_VIEW_ROLLOUTS = 1000
"""At most this many rollouts of a stage (evenly spaced) make its proposal view of a scene of several objects, whose
detectors are asked again for each state (1,000 rollouts of five objects: about 0.2 s on one core)."""


DEFAULT_AXIS = ViewAxis("gap d (m), 0.5 m bins", "the object", None, "below", np.linspace(0.0, 13.0, 27), "gap (m)")
"""The proposal view's axis of a problem whose drawing gives none (a toy): its own distance signal in 0.5 m bins,
0 to 13 m (:func:`pemviz.core.proposal_view.batch_proposal_view`)."""


def object_proposal_view(
    event: RolloutsSampled, axis: ViewAxis, max_rollouts: int = MAX_VIEW_ROLLOUTS
) -> ProposalView | None:
    """q(detect) of the sampler and p(detect) of the PEM for the object ``axis.view_object`` over the states a batch
    of several objects visited where it is visible, binned by its distance ahead (metres; ``axis.edges``), as
    :func:`pemviz.core.proposal_view.proposal_view`, on at most ``max_rollouts`` rollouts. None for a batch of one
    object a step, without the axis' columns or both detectors, or without a visible state."""
    batch = event.batch
    names = tuple(batch.object_names or ())
    obj, edges_m = axis.view_object, np.asarray(axis.edges, dtype=np.float64)
    if (
        obj is None
        or batch.objects is None
        or batch.n_objects < 2
        or event.sampler is None
        or event.target is None
        or not {axis.distance_column, axis.visible_column} <= set(names)
        or batch.n == 0
    ):
        return None
    pick = evenly_spaced(batch.n, max_rollouts)
    rows = np.asarray(batch.objects[pick, :, obj, :], dtype=np.float64)  # [n, T, G]
    seen = rows[..., names.index(axis.visible_column)] > 0.5
    if not seen.any():
        return None
    flat = rows[seen]  # [S, G]
    detected = np.asarray(batch.detected[pick, :, obj], bool)[seen]
    sign = np.where(detected, 1.0, -1.0)  # log sigma(l) for a detection, log sigma(-l) for a miss

    def log_action(detector: Detector) -> np.ndarray:
        logit = np.asarray(detector.detect_logit(flat), dtype=np.float64)
        return -np.logaddexp(0.0, -sign * logit)

    distance = flat[:, names.index(axis.distance_column)]
    return proposal_view(
        distance[None],
        detected[None],
        log_action(event.sampler)[None],
        log_action(event.target)[None],
        edges_m,
        float(edges_m[-1]),
    )


_EXPORT_NAME_OK = re.compile(r"[^A-Za-z0-9._-]")


def keep_runs(runs: list[PanelRun], new: PanelRun, max_runs: int = MAX_RUNS) -> list[PanelRun]:
    """The runs kept once ``new`` starts: at most ``max_runs``, oldest first; pinned and running runs stay, then
    unpinned stopped or failed runs are dropped first, then unpinned finished ones."""
    kept = list(runs) + [new]
    for statuses in (("cancelled", "failed"), ("finished",)):
        for r in list(kept):
            if len(kept) <= max_runs:
                return kept
            if r is not new and not r.pinned and r.status in statuses:
                kept.remove(r)
    return kept


@dataclass(frozen=True)
class Trajectory:
    """One rollout kept for the panel's list and 3D playback.

    Attributes:
        stage: the stage that sampled it (0 = pretraining, K+1 = final batch).
        index: its number in the stage (:attr:`pemviz.engine.events.RolloutsSampled.rollout_numbers`).
        robustness: under the run's metric (classic: metres; AGM: [-1, 1]).
        log_weight: importance log-weight log p_PEM - log q over T - 1 steps (nats).
        crashed: classic robustness < 0.
        detected: bool [T], the detector's output at each step (of the first object where there are several).
        log_p, log_q: float64 [T] log p of each step's events under the PEM and the sampler (nats;
            :attr:`log_p_parts` splits the PEM's).
        batch: the rollout as a batch of one, what the drawing's hooks read.
        object_p, object_q: several objects: p(detect) and q(detect) of each, float64 [T, M]; else None.
        target: the PEM that weighs it, asked only by :attr:`log_p_parts`; None: not known."""

    stage: int
    index: int
    robustness: float
    log_weight: float
    crashed: bool
    detected: np.ndarray
    log_p: np.ndarray
    log_q: np.ndarray
    batch: RolloutBatch
    object_p: np.ndarray | None = None
    object_q: np.ndarray | None = None
    target: Any = field(default=None, compare=False, repr=False)

    @property
    def log_p_total(self) -> float:
        """log p_PEM of the rollout's events over its first T - 1 steps (nats), the log p by which the most likely
        failure is chosen: the log-probability of its detections plus, where the PEM mislocates, the log-density of
        its measurement errors (a log-likelihood; :attr:`log_p_parts` gives the two)."""
        return float(np.sum(self.log_p[:-1]))

    @functools.cached_property
    def log_p_parts(self) -> LogPParts | None:
        """:attr:`log_p_total` split into the log-probability of the rollout's detections (nats, <= 0) and, where the
        PEM mislocates, the log-density of its measurement errors (nats), recomputed under :attr:`target` once
        (:func:`pemviz.core.counterfactuals.failure_log_p_parts`); None for a rollout with errors and no target."""
        try:
            return LogPParts.of(self.batch, 0, self.target)
        except ValueError:
            return None

    def log_p_words(self, whose: str = "its ") -> str:
        """``log-probability of its detections -63.2 nats, log-density of its measurement errors +12.4 nats`` under
        the PEM (:meth:`pemviz.core.counterfactuals.LogPParts.words`), or, where the parts are not known, the sum
        named for what it is."""
        parts = self.log_p_parts
        if parts is not None:
            return parts.words(whose=whose)
        return (
            f"log-likelihood under the PEM {self.log_p_total:.1f} nats (the log-probability of {whose}detections "
            f"plus the log-density of {whose}measurement errors)"
        )

    @property
    def key(self) -> str:
        """``s<stage>r<index>``: unique within a run (an identifier, never shown: :attr:`name` is)."""
        return f"s{self.stage}r{self.index}"

    @property
    def name(self) -> str:
        """``stage 3 rollout 6``: the rollout as the panel names it (stage 0 = pretraining, K+1 = the final batch;
        the rollout's index within its stage's batch), as the *Rollouts* list does."""
        return f"stage {self.stage} rollout {self.index}"

    @property
    def n_steps(self) -> int:
        return int(self.detected.shape[0])

    @property
    def several(self) -> bool:
        """The rollout's scene has several objects a step (rows per object)."""
        return self.batch.objects is not None and self.batch.n_objects > 1

    def signal(self, name: str) -> np.ndarray:
        """float64 [T] the observation ``name`` of the rollout.

        Raises:
            ValueError: the rollout has no such observation."""
        names = tuple(self.batch.observation_names)
        if name not in names:
            raise ValueError(f"the rollout has no observation {name!r} ({', '.join(names)})")
        return np.array(self.batch.observations[0, :, names.index(name)], dtype=np.float64)


def trajectory(event: RolloutsSampled, i: int, features: FeaturesFn | None = None) -> Trajectory:
    """Row ``i`` of a sampled batch as a :class:`Trajectory` (its detections and log-probabilities are views of its
    batch of one); ``features``: the problem's replay of the state features, for a sampler that reads them."""
    batch = event.batch
    detect = object_detect_probabilities(batch, int(i), event.sampler, event.target, features)
    object_p, object_q = detect or (None, None)
    one = batch.select(np.array([int(i)]))
    return Trajectory(
        stage=event.stage,
        index=int(event.rollout_numbers[i]),
        robustness=float(event.robustness[i]),
        log_weight=float(event.log_weight[i]),
        crashed=bool(event.failed[i]),
        detected=np.asarray(one.detected[0, :, 0], dtype=bool),
        log_p=np.asarray(one.log_p[0], dtype=np.float64),
        log_q=np.asarray(one.log_q[0], dtype=np.float64),
        batch=one,
        object_p=object_p,
        object_q=object_q,
        target=scoring_detector(event.target),
    )


def most_likely_failure(best: Trajectory | None, event: RolloutsSampled) -> Trajectory | None:
    """The failing rollout with the highest log p_PEM (T - 1 steps) among ``best`` and this batch's failures
    (:func:`pemviz.core.counterfactuals.most_likely_failure`). Ties keep ``best`` (the earlier one), then the lower
    row. :class:`PanelRun` keeps the chosen :class:`~pemviz.core.counterfactuals.LikelyFailure` beside it."""
    prior = None if best is None else LikelyFailure(best.stage, -1, best.index, best.log_p_total)
    likely = pick_most_likely(event, prior)
    if likely is prior:
        return best
    assert likely is not None  # None only while no failure has been seen, and then it is ``prior`` (None)
    return trajectory(event, likely.row)


def least_robust(
    kept: list[Trajectory], event: RolloutsSampled, n: int = N_TRAJECTORIES, features: FeaturesFn | None = None
) -> list[Trajectory]:
    """Merge a stage's rollouts into the kept list: the ``n`` least robust, least first, ties the earlier stage /
    lower index first (``features``: as :func:`trajectory`)."""
    if n <= 0 or event.batch.n == 0:
        return list(kept)
    r = np.asarray(event.robustness, dtype=np.float64)
    new = [trajectory(event, int(i), features) for i in np.argsort(r, kind="stable")[:n]]
    merged = sorted(list(kept) + new, key=lambda t: t.robustness)  # sorted() is stable
    return merged[:n]


@dataclass(frozen=True)
class Population:
    """Every failure of a run's final estimate, largest share first.

    Attributes:
        grouping: the failures, where each lies in the kept batches, their groups.
        rollouts: per rank, the failure as a :class:`Trajectory`, or None where its stage kept only a sample."""

    grouping: FailureGrouping
    rollouts: tuple[Trajectory | None, ...]

    @property
    def shares(self) -> FailureShares:
        return self.grouping.shares

    @property
    def groups(self):
        return self.grouping.groups

    @property
    def basis(self) -> str:
        return self.grouping.basis

    def group_label(self, rank: int) -> str:
        return self.grouping.group_label(rank)


def population_of(
    shares: FailureShares | None,
    sampled: Mapping[int, RolloutsSampled],
    drawing: object,
    problem: Problem | None = None,
) -> Population | None:
    """The panel's :class:`Population` of a run (arguments as :func:`pemviz.sinks.population.group_failures`): the
    :data:`MAX_POPULATION` failures with the largest shares as rollouts (every failure in the groups); None when
    ``shares`` is None (the estimator keeps no per-stage rollouts)."""
    if shares is None:
        return None
    g, features = group_failures(shares, sampled, drawing, problem), getattr(problem, "features", None)
    return Population(
        g,
        tuple(
            trajectory(*f, features) if f is not None and rank < MAX_POPULATION else None
            for rank, f in enumerate(g.found)
        ),
    )


class PanelRun(Sink):
    """One run as the panel shows it; an engine listener (call it with each event), thread-safe: readers take
    :attr:`lock` or copy the (replaced, never mutated) lists."""

    def __init__(self, run_id: int, config: ExperimentConfig) -> None:
        self.run_id = run_id
        self.config = config
        self.lock = threading.RLock()
        self.status = "starting"
        """``starting`` | ``running`` | ``finished`` | ``cancelled`` | ``failed``."""
        self.message = ""
        self.formula = ""
        self.plan: RunPlan | None = None
        """The stages the run will draw (:class:`pemviz.core.plan.RunPlan`), once it started; None before."""
        self.view: ProblemView | None = None
        """The problem as the panel shows it (:class:`pemviz.core.problem_view.ProblemView`), once it started; None
        before."""
        self.problem: Problem | None = None
        """The run's :class:`pemviz.core.problems.Problem`, set by whoever runs it: *Explain* replays a scene of several
        objects through it (None: no replays)."""
        self.curve_grid_m = np.zeros(0)
        self.pem_curve = np.zeros(0)
        self.stages: list[StageResult] = []
        self.current_stage: StageStarted | None = None
        self.sampled_current = False
        self.final: FinalEstimate | None = None
        self.exact_log_p: float | None = None
        """Natural log of the exact failure probability when the engine knows it (``RunStarted.exact_log_p``)."""
        self.reference: Reference | None = None
        """The problem's plain Monte Carlo reference where no exact answer is known (``RunStarted.reference``)."""
        self.trajectories: list[Trajectory] = []
        self.likely: LikelyFailure | None = None
        """The run's most likely failure so far (:func:`pemviz.core.counterfactuals.most_likely_failure`: the failing
        rollout with the largest log p under the PEM; its stage, row, rollout number and log p), None before one."""
        self.most_likely_failure: Trajectory | None = None
        """:attr:`likely` as a :class:`Trajectory`."""
        self.proposal_views: dict[int, tuple[str, ProposalView]] = {}
        """Stage -> (kind, q(detect) of its sampler over the states its rollouts visited, per gap bin)."""
        self.feature_curves: dict[int, tuple[str, FeatureCurve]] = {}
        """Stage -> (kind, q(detect) of the state proposal that drew it against the PEM over the feature that moved it
        most: :func:`pemviz.core.feature_view.stage_feature_curve`, with :attr:`problem`); none for other samplers."""
        self.proposal_axis: ViewAxis = DEFAULT_AXIS
        """What the views' bins are: the drawing's :meth:`~pemviz.app.drawing.PanelDrawing.proposal_axis` once the
        run started (:data:`DEFAULT_AXIS` for a problem whose drawing gives none)."""
        self.events: list[Event] = []
        self.sampled: dict[int, RolloutsSampled] = {}
        """Stage -> its :class:`RolloutsSampled` (the batch, or a sample of a streamed stage)."""
        self.population: Population | None = None
        """Every failure of the final estimate with its share of p and its group (:class:`Population`), once the run
        has its final estimate; None before or where the estimator keeps no per-stage rollouts."""
        self.pinned = False
        """Kept for comparison until unpinned (:func:`keep_runs` never drops it)."""
        self.clock = StageClock()
        """When the run and its stage started, the seconds per rollout (predicts the final batch)."""
        self.t_end: float | None = None

    @property
    def label(self) -> str:
        """``run 3 · agm, alpha 0.2, K 8``: the metric and every setting that differs from the defaults."""
        return run_label(self.run_id, self.config)

    @property
    def short_label(self) -> str:
        """``run 3 (agm)``: for legends."""
        return f"run {self.run_id} ({self.config.metric})"

    def elapsed_s(self) -> float:
        """Seconds since the run started (to its end once it has ended)."""
        return (self.t_end or self.clock.now()) - self.clock.t0

    @property
    def done(self) -> bool:
        return self.status in ("finished", "cancelled", "failed")

    def __call__(self, event: Event) -> None:
        with self.lock:
            if not isinstance(event, RolloutChunk):  # a stream's chunks: every rollout; the export needs none of them
                self.events.append(event)
            self.clock(event)
            super().__call__(event)

    def on_run_started(self, event: RunStarted) -> None:
        self.status = "running"
        self.formula, self.plan, self.view = event.formula, event.plan, event.problem
        self.curve_grid_m = np.asarray(event.curve_grid_m, dtype=np.float64)
        self.pem_curve = np.asarray(event.pem_curve, dtype=np.float64)
        self.exact_log_p, self.reference = event.exact_log_p, event.reference
        axis = getattr(getattr(self.view, "drawing", None), "proposal_axis", None)
        self.proposal_axis = axis() if callable(axis) else DEFAULT_AXIS

    def on_stage_started(self, event: StageStarted) -> None:
        self.current_stage = event
        self.sampled_current = False

    def on_rollouts_sampled(self, event: RolloutsSampled) -> None:
        self.sampled_current = True
        self.sampled = {**self.sampled, event.stage: event}
        features = self.problem.features if self.problem is not None else None  # a state proposal reads them
        self.trajectories = least_robust(self.trajectories, event, features=features)
        likely = pick_most_likely(event, self.likely)
        if likely is not self.likely:
            assert likely is not None  # None only while no failure has been seen, and then it is ``self.likely``
            self.likely, self.most_likely_failure = likely, trajectory(event, likely.row, features)
        window = self.view.thresholds.window if self.view is not None and self.view.thresholds else None
        axis = self.proposal_axis
        if axis.view_object is None:  # one object a step: the batch's own distance signal
            view = batch_proposal_view(event.batch, axis.edges, window) if window is not None else None
        else:  # one object among several, by its distance ahead
            view = object_proposal_view(event, axis)
        if view is not None:
            self.proposal_views = {**self.proposal_views, event.stage: (event.kind, view)}
        pb = self.problem  # heard while the sampler is the one that drew (the estimator refits it after the stage)
        curve = stage_feature_curve(event.batch, event.sampler, pb.target, features) if pb is not None else None
        if curve is not None:
            self.feature_curves = {**self.feature_curves, event.stage: (event.kind, curve)}

    def on_stage_finished(self, event: StageFinished) -> None:
        self.stages = self.stages + [event.result]

    def on_final_estimate(self, event: FinalEstimate) -> None:
        self.population = population_of(
            event.failures, self.sampled, self.view.drawing if self.view else None, self.problem
        )
        self.final = event

    def on_run_finished(self, event: RunFinished) -> None:
        self.status = "finished"
        self.t_end = self.clock.now()

    def on_run_cancelled(self, event: RunCancelled) -> None:
        self.status = "cancelled"
        self.message = event.reason
        self.t_end = self.clock.now()

    def fail(self, message: str) -> None:
        with self.lock:
            self.status = "failed"
            self.message = message
            self.t_end = self.clock.now()

    def progress(self) -> tuple[float, float]:
        """(run, stage) progress in percent: finished stages of all; 0 / 50 / 100 within a stage
        (started, rollouts sampled, finished)."""
        with self.lock:
            total = len(self.plan.stages) if self.plan is not None else 1
            if self.plan is not None and (self.plan.open_ended or len(self.stages) >= total):
                total = max(total, len(self.stages) + 1)  # one more than done, until the run ends (batches past
                # the plan: e.g. the plain Monte Carlo after a cross-entropy run whose weights back no interval)
            done = len(self.stages)
            if self.status == "finished":
                return 100.0, 100.0
            stage = 0.0
            if self.current_stage is not None and done < total:
                finished_current = bool(self.stages) and self.stages[-1].stage == self.current_stage.stage
                stage = 100.0 if finished_current else (50.0 if self.sampled_current else 5.0)
            return 100.0 * done / max(1, total), stage

    def stage_series(self, name: str) -> dict[int, float]:
        """Stage -> value of ``gamma`` | ``failure_rate`` | ``log10_mu_hat`` | ``nll`` (finite values only)."""
        out = {}
        for res in self.stages:
            e = res.estimate
            value = {
                "gamma": res.gamma,
                "failure_rate": e.n_failures / e.n if e.n else math.nan,
                "log10_mu_hat": e.log10_mu_hat,
                "nll": e.nll_mean,
            }[name]
            if math.isfinite(value):
                out[res.stage] = float(value)
        return out


def sanitize_export_name(name: str) -> str:
    r"""A recording file name from what a user typed: ``'../x'`` -> ``'x.rrd'``: only the last path component counts
    (``/`` and ``\`` alike), characters other than letters, digits, ``.``, ``_`` and ``-`` become ``_``, leading
    dots are stripped, and ``.rrd`` is appended unless present.

    Raises:
        ValueError: nothing usable is left (e.g. ``''``, ``'..'``, ``'/'``)."""
    base = str(name).replace("\\", "/").split("/")[-1].strip()
    base = _EXPORT_NAME_OK.sub("_", base).lstrip(".")
    if base.lower().endswith(".rrd"):
        base = base[:-4]
    base = base.rstrip(".")
    if not base.strip("_-"):
        raise ValueError(
            f"export name {name!r} is invalid: use letters, digits, '.', '_' and '-' (a file name, no folders)"
        )
    return base[:120] + ".rrd"


def export_path(recordings_dir: str | os.PathLike, name: str) -> Path:
    """``recordings_dir / sanitize_export_name(name)``, checked to lie inside ``recordings_dir``.

    Raises:
        ValueError: an unusable name, or a path that would leave ``recordings_dir``."""
    root = Path(recordings_dir).resolve()
    path = root / sanitize_export_name(name)
    if path.resolve().parent != root:  # e.g. a symlink planted under the name
        raise ValueError(f"export name {name!r} would write outside {root}")
    return path


def export_run(record: PanelRun, path: Path) -> Path:
    """Replay a run's events into a rerun recording at ``path`` (written to a temp file, then moved).

    Returns:
        ``path``. Nothing is left at ``path`` (or beside it) if writing fails."""
    with record.lock:
        events = list(record.events)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.stem}.{os.getpid()}.{threading.get_ident()}.tmp.rrd")
    leftovers = (tmp, tmp.with_name(tmp.name + ".partial"))
    try:
        sink = RerunSink.to_file(tmp)
        try:
            for event in events:
                sink(event)
        finally:
            sink.close()
        os.replace(tmp, path)
    except BaseException:
        for leftover in leftovers:
            leftover.unlink(missing_ok=True)
        raise
    return path
