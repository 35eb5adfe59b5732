"""The experiment engine: runs the PEM + adaptive-importance-sampling pipeline and emits events.

No printing, no rerun, no viser here: sinks (console table, rerun recording, the viser panel) subscribe
as listeners ``listener(event) -> None`` and never call back into the engine, except through the
``cancel`` token (a :class:`threading.Event`).

The events and their order are :mod:`pemviz.engine.events`'s. A stage of more than :data:`STREAM_ABOVE` rollouts on a
problem that can stream is simulated chunk by chunk and never held whole: the estimator keeps per-rollout numbers and
the rollouts that can still matter (e.g. the elites), listeners get each chunk and a bounded sample of the stage."""

from __future__ import annotations

import itertools
import threading
import time
from collections.abc import Iterable, Iterator, Mapping
from typing import Any

import numpy as np

from pemviz.config import ExperimentConfig
from pemviz.core.detectors import ArrayRQMC, Detector
from pemviz.core.estimate import Estimate
from pemviz.core.problems import Problem
from pemviz.core.rollouts import RolloutBatch
from pemviz.engine import events as ev
from pemviz.engine.executors import get_executor
from pemviz.engine.odd_map import OddMapCollector
from pemviz.estimators import build_estimator
from pemviz.estimators.base import Estimator, SeenFailures, StagePlan
from pemviz.estimators.extras import extras, needs_chunk_rows
from pemviz.estimators.pooling import failure_population, pem_spread, severity_curve
from pemviz.settings import METRICS


class Cancelled(Exception):
    """Raised inside the engine when the cancel token is set; the run ends with
    :class:`~pemviz.engine.events.RunCancelled`."""


STREAM_ABOVE = 20_000
"""Stages of more rollouts than this are simulated chunk by chunk when the problem can stream (``Problem.stream``),
on any executor (``executor.stream``), and kept only as per-rollout numbers and a bounded sample: a
[10^5, 100] batch with its robustness and masks holds ~1 GB, a chunk of 8,192 rollouts ~80 MB."""


def run_executor(config: ExperimentConfig) -> Any:
    """The executor of ``config.execution`` (:func:`pemviz.engine.executors.get_executor`)."""
    run = config.execution
    return get_executor(run.executor, run.ray_address, run.workers)


def stream_above(config: ExperimentConfig, n_objects: int = 1) -> int:
    """Rollouts above which a serial stage streams chunk by chunk: ``config.execution.chunk_rollouts``, or
    :data:`STREAM_ABOVE` divided by the objects a rollout perceives (``n_objects``: a rollout of M objects holds M
    object rows a step, so the same memory) when it is None."""
    if config.execution.chunk_rollouts is not None:
        return config.execution.chunk_rollouts
    return STREAM_ABOVE // max(1, n_objects)


SAMPLE_LEAST_ROBUST = 20
"""Least-robust rollouts of a streamed stage that listeners see in full."""
SAMPLE_FAILURES = 100
"""The first failures of a streamed stage that listeners see in full."""
SAMPLE_UNIFORM = 100
"""Evenly spaced rollouts of a streamed stage that listeners see in full."""


class RobustnessByMetric(Mapping[str, np.ndarray]):
    """metric -> robustness [N] of a batch under each semantics of :data:`pemviz.settings.METRICS` the problem can
    compute, each computed when first read (the estimator reads the classic one and the configured one; a listener may
    read the others). ``agm`` needs a range for every signal (:attr:`pemviz.core.problems.Problem.signal_ranges`): a
    problem without them has no ``agm`` entry, so that listeners (the recording) draw the other metrics."""

    def __init__(self, problem: Problem, batch: RolloutBatch) -> None:
        self.problem, self.batch = problem, batch
        self._known: dict[str, np.ndarray] = {}
        ranged = set(problem.signals) <= set(problem.signal_ranges or {})
        self._metrics = tuple(m for m in METRICS if m != "agm" or ranged)

    def __getitem__(self, metric: str) -> np.ndarray:
        if metric not in METRICS:
            raise KeyError(metric)
        if metric not in self._known:
            if self.problem is None:
                raise KeyError(f"{metric}: not computed before this mapping was pickled, and it has no problem")
            self._known[metric] = self.problem.robustness(self.batch, metric)
        return self._known[metric]

    def __getstate__(self) -> dict:
        """Pickled without the problem (its simulator need not pickle): the metrics read so far travel, and a
        metric not read yet needs :attr:`problem` set again (:mod:`pemviz.sinks.recording_process` sets its own)."""
        return {"problem": None, "batch": self.batch, "_known": dict(self._known), "_metrics": self._metrics}

    def __iter__(self) -> Iterator[str]:
        return iter(self._metrics)

    def __len__(self) -> int:
        return len(self._metrics)


class StageSample:
    """A bounded sample of a stage streamed in chunks, gathered as they pass: the :data:`SAMPLE_LEAST_ROBUST`
    least-robust rollouts (ties: the earlier), the first :data:`SAMPLE_FAILURES` failures and
    :data:`SAMPLE_UNIFORM` evenly spaced rollouts, plus every rollout's robustness and log-weight [n]."""

    def __init__(self, n: int) -> None:
        self.n, self.seen, self.n_failed = n, 0, 0
        self.uniform = np.unique(np.linspace(0, n - 1, SAMPLE_UNIFORM).astype(np.int64))
        self.robustness, self.log_weight, self.failed = np.empty(n), np.empty(n), np.zeros(n, bool)
        self.parts: list[tuple[RolloutBatch, np.ndarray]] = []

    def add(self, batch: RolloutBatch, robustness: np.ndarray, failed: np.ndarray, log_weight: np.ndarray) -> None:
        i0, i1 = self.seen, self.seen + batch.n
        self.robustness[i0:i1], self.log_weight[i0:i1], self.failed[i0:i1] = robustness, log_weight, failed
        self.seen = i1
        k = min(SAMPLE_LEAST_ROBUST, i1)
        low = robustness <= np.partition(self.robustness[:i1], k - 1)[k - 1]
        first_failures = failed & (self.n_failed + np.cumsum(failed) <= SAMPLE_FAILURES)
        self.n_failed += int(failed.sum())
        keep = low | first_failures | np.isin(np.arange(i0, i1), self.uniform)
        self.parts.append((batch.select(keep), np.flatnonzero(keep) + i0))

    def rollouts(self) -> tuple[RolloutBatch, np.ndarray]:
        """(the sample, ascending; its rollout numbers [m])."""
        index = np.concatenate([i for _, i in self.parts])
        least = np.argsort(self.robustness[index], kind="stable")[:SAMPLE_LEAST_ROBUST]
        first_failures = np.flatnonzero(self.failed[index])[:SAMPLE_FAILURES]
        keep = np.zeros(index.size, bool)
        keep[least], keep[first_failures] = True, True
        keep |= np.isin(index, self.uniform)
        return RolloutBatch.concatenate([b for b, _ in self.parts]).select(keep), index[keep]


class Experiment:
    """Runs one :class:`ExperimentConfig` on a :class:`Problem` and tells listeners what happens.

    The estimator of ``config.method`` (:func:`pemviz.estimators.build_estimator`) plans the batches and does the
    arithmetic; the experiment simulates them (on ``config.execution.executor``), computes their robustness, emits the
    events and checks the cancel token. ``problem``: what to estimate (a :class:`Problem`, e.g. the one
    :func:`pemviz.scenarios.problems.problem_for` ``(config)`` builds for the config's scenario); the engine itself
    loads nothing."""

    def __init__(
        self,
        config: ExperimentConfig,
        listeners: Iterable[ev.Listener] = (),
        cancel: threading.Event | None = None,
        *,
        problem: Problem,
    ) -> None:
        self.config = config
        self.listeners = list(listeners)
        self.cancel = cancel or threading.Event()
        self.problem = problem
        self.stages: list[ev.StageResult] = []
        self.n_simulations = 0
        self.seen_failures = SeenFailures()
        """The probability of the distinct failures drawn in any stage: a lower bound the final verdict checks."""
        self._odd_map = OddMapCollector(problem) if getattr(problem, "odd", None) is not None else None
        """Over an operating design domain: the final stage's rollouts, for the map the final estimate carries."""

    def emit(self, event: ev.Event) -> None:
        if self._odd_map is not None and isinstance(event, ev.RolloutChunk):
            self._odd_map.add(event)
        for listener in self.listeners:
            listener(event)

    def _check_cancel(self) -> None:
        if self.cancel.is_set():
            raise Cancelled("cancelled by the user")

    def run(self) -> ev.RunFinished | ev.RunCancelled:
        """Run the whole experiment; returns the last event emitted (see the module docstring for the events)."""
        cfg, pb = self.config, self.problem
        t_start = time.perf_counter()
        estimator = build_estimator(cfg, pb, self._check_cancel)  # it seeds its streams, the rollouts' included
        self.emit(
            ev.RunStarted(
                cfg,
                str(pb.formula),
                pb.curve_grid,
                pb.target_curve(),
                pb.view,
                estimator.plan(),
                pb.exact_log_p,
                pb.reference,
                pb.verdict_cap,
            )
        )
        try:
            while (plan := estimator.next_stage()) is not None:
                self._stage(estimator, plan)
        except Cancelled as exc:
            event = ev.RunCancelled(tuple(self.stages), str(exc))
            self.emit(event)
            return event
        est, used = estimator.result()
        said = extras(estimator)
        n_sim = said.n_simulations if said.n_simulations is not None else self.n_simulations  # e.g. AMS's continuations
        seen = self.seen_failures.log_p
        pooled, cap = said.pooling, said.verdict_cap
        est = est.below_seen(seen)
        odd_map = self._odd_map.result(cap) if self._odd_map is not None else None
        unfailed = odd_map.unfailed_cap() if odd_map is not None and cap is None else None
        if unfailed is not None:  # a region of the ODD without a failure: the run's claim and the map's, capped
            cap, est = unfailed, est.at_most(unfailed)
            odd_map = self._odd_map.result(cap) if self._odd_map is not None else None
        final = ev.FinalEstimate(
            est,
            n_sim,
            time.perf_counter() - t_start,
            used,
            seen,
            pooled,
            said.stop,
            cap,
            said.decision,
            severity_curve(pb, estimator, est, used, pooled, cap),
            pem_spread(pb, estimator, est, used, pooled, cap),
            failure_population(estimator, used, pooled),
            pb.look_ahead is not None,
            said.prepared,
            plain_probe(pb, cfg, est),
            odd_map,
        )
        self.emit(final)
        done = ev.RunFinished(final, tuple(self.stages))
        self.emit(done)
        return done

    def _stage(self, estimator: Estimator, plan: StagePlan) -> ev.StageResult:
        """Draw the planned batch, show it to the estimator and the listeners, close the stage."""
        t0 = time.perf_counter()
        self._check_cancel()
        self.emit(ev.StageStarted(plan.stage, plan.kind, plan.n))
        pb, cfg = self.problem, self.config
        target = pb.target if plan.target is None else plan.target
        parts = plan.parts  # (rollouts, detector) in the order drawn
        if cfg.uniforms == "array-rqmc" and cfg.method_record.array_rqmc and pb.array_rqmc:  # the scene opts in
            # the target's own rollouts are drawn i.i.d.: a mixture's target share (it bounds the weights, and its
            # rollouts almost never fail) and plain Monte Carlo (a final batch from the target), whose Clopper-Pearson
            # interval counts independent trials: chains of a memory controller that tie on the ranking key keep their
            # lattice points and miss together, so coupled plain rollouts over-disperse the failure count
            iid = plan.mixture or plan.kind == "final"
            parts = [(k, d if iid and d is pb.target else ArrayRQMC(d)) for k, d in parts]
        if plan.draw is None and plan.n > stream_above(cfg, pb.n_objects) and pb.stream is not None:
            self._streamed(estimator, plan, parts, target)
        else:  # one batch, on the configured executor (worker processes, this process or Ray tasks)
            if plan.draw is not None:  # the estimator makes the batch itself (AMS: continuations from snapshots)
                batch = plan.draw(estimator.rng)
            else:
                executor = run_executor(cfg)
                batches = [executor.simulate(pb, k, d, target, estimator.rng) for k, d in parts]
                batch = batches[0] if len(batches) == 1 else RolloutBatch.concatenate(batches)
            self._check_cancel()
            by_metric = RobustnessByMetric(pb, batch)  # the other metrics only if a listener reads them
            failed = pb.failed(batch, by_metric["classic"])
            self.seen_failures.add(pb, batch, failed)
            log_w = estimator.observe(batch, failed, by_metric[cfg.metric])
            chunk = ev.RolloutChunk(plan.stage, plan.kind, 0, batch, log_w, plan.sampler, tuple(plan.parts), pb.target)
            self.emit(chunk)
            self._sampled(plan, batch, by_metric, failed, log_w, target=target)
        self.n_simulations += plan.n
        out = estimator.finish()
        res = ev.StageResult(
            plan.stage,
            plan.kind,
            out.gamma,
            out.n_elites,
            out.estimate,
            out.proposal_curve,
            out.elite_detect_rate,
            time.perf_counter() - t0,
        )
        self.stages.append(res)
        self.emit(ev.StageFinished(res))
        return res

    def _streamed(
        self, estimator: Estimator, plan: StagePlan, parts: list[tuple[int, Detector]], target: Detector
    ) -> None:
        """Simulate a stage chunk by chunk (:func:`stream_above`), ``parts`` = (rollouts, detector) in order, scored
        under ``target``: the estimator and the listeners see each chunk once, then the listeners a
        :class:`StageSample` of the stage."""
        pb, cfg = self.problem, self.config
        assert pb.stream is not None  # the caller streams a stage only then
        sample = StageSample(plan.n)
        size: dict[str, Any] = (
            {} if cfg.execution.chunk_rollouts is None else {"chunk_size": cfg.execution.chunk_rollouts}
        )
        if getattr(pb.stream, "elides_rows", False) and not needs_chunk_rows(estimator):
            size["keep_rows"] = False  # a chunk's object rows, rebuilt by replay for the few rollouts read
        executor = run_executor(cfg)
        chunks = itertools.chain.from_iterable(
            executor.stream(pb, k, d, target, estimator.rng, **size) for k, d in parts
        )
        for batch in chunks:
            self._check_cancel()
            robustness = pb.robustness(batch, cfg.metric)
            failed = pb.failed(batch, robustness if cfg.metric == "classic" else None)
            self.seen_failures.add(pb, batch, failed)
            log_w = estimator.observe(batch, failed, robustness)
            self.emit(
                ev.RolloutChunk(
                    plan.stage, plan.kind, sample.seen, batch, log_w, plan.sampler, tuple(plan.parts), pb.target
                )
            )
            sample.add(batch, robustness, failed, log_w)
        batch, index = sample.rollouts()
        batch = batch.with_rows()  # the listeners' sample holds its rows
        self._sampled(
            plan,
            batch,
            RobustnessByMetric(pb, batch),
            sample.failed[index],
            sample.log_weight[index],
            target=target,
            n_total=plan.n,
            index=index,
            stage_robustness=sample.robustness,
            stage_log_weight=sample.log_weight,
        )

    def _sampled(
        self,
        plan: StagePlan,
        batch: RolloutBatch,
        by_metric: RobustnessByMetric,
        failed: np.ndarray,
        log_w: np.ndarray,
        **streamed: Any,
    ) -> None:
        """Show the listeners a stage's rollouts (:class:`~pemviz.engine.events.RolloutsSampled`; ``streamed``: its
        ``target``, and for a streamed stage's sample its ``n_total``, ``index`` and the whole stage's robustness and
        log-weights)."""
        rho = by_metric[self.config.metric]
        self.emit(
            ev.RolloutsSampled(plan.stage, plan.kind, batch, rho, by_metric, failed, log_w, plan.sampler, **streamed)
        )


PLAIN_PROBE = 1000
"""The plain rollouts :func:`plain_probe` times: enough to spread each step's fixed cost as plain Monte Carlo does."""

PROBE_PILOT, PROBE_BUDGET_S = 50, 1.0
""":func:`plain_probe` and :func:`scene_pilot` first time this many rollouts (the first also warms the simulator up);
where they say the probe would take more than this many seconds (a simulator whose cost is per rollout, not per
batched step, e.g. highway-env's), their own seconds are the answer."""


PILOT_ROLLOUTS, PILOT_BATCHES = 50, 4
""":func:`scene_pilot` times this many batches of this many plain rollouts (mostly each step's fixed cost), whose
median reading prices the run (a loaded machine's readings spread)."""


def _timed_plain(problem: Problem, sizes: Iterable[int], clock: Any) -> list[tuple[int, float]]:
    """``(n, seconds)`` of each batch of plain rollouts of ``problem`` timed by ``clock`` (``time.perf_counter`` or
    ``time.thread_time``), of ``sizes`` in turn, each drawn from its target on a stream of its own (seed 0: the run's
    streams are untouched) with BLAS on one thread; the batches after one whose reading says a batch would take more
    than :data:`PROBE_BUDGET_S` seconds (:func:`_affine_seconds`) are not drawn."""
    from threadpoolctl import threadpool_limits

    timed: list[tuple[int, float]] = []
    with threadpool_limits(1, user_api="blas"):
        for size in sizes:
            if timed and _affine_seconds(timed, size) > PROBE_BUDGET_S:
                break
            t0 = clock()
            problem.simulate(size, problem.target, problem.target, np.random.default_rng(0))
            timed.append((size, clock() - t0))
    return timed


def plain_probe(problem: Problem, config: ExperimentConfig, estimate: Estimate) -> float | None:
    """Seconds a plain rollout of ``problem`` takes here now: :data:`PLAIN_PROBE` rollouts of its target drawn and
    timed (:func:`_timed_plain`: a stream of their own, seed 0), where the run's advice will size plain Monte Carlo (its
    verdict is not ``reliable`` and its method is not ``mc``, whose own speed is measured); else None. A run's own
    seconds a simulation hold what its method adds (fits, look-aheads, replayed prefixes): up to 10 times a plain
    rollout's. Batches of :data:`PROBE_PILOT` and twice that come first (the first also warms the simulator up): where
    the line through their readings (:func:`_affine_seconds`) says the probe would take more than
    :data:`PROBE_BUDGET_S` seconds, the second's rate is the answer; a scene whose steps cost about as much for 50
    rollouts as for 100 (a fixed cost per step, e.g. the library stack's tracker and PEMs) goes on to the probe."""
    if estimate.verdict == "reliable" or config.method_record.plain:
        return None
    n, seconds = _timed_plain(problem, (PROBE_PILOT, 2 * PROBE_PILOT, PLAIN_PROBE), time.perf_counter)[-1]
    return seconds / n


def _affine_seconds(timed: list[tuple[int, float]], size: int) -> float:
    """Seconds a batch of ``size`` plain rollouts would take, from the last two ``(n, seconds)`` readings of
    ``timed``: the line through them (a fixed cost per batch plus a cost per rollout), or in proportion to the last
    reading alone where there is one, the two are of one size, or the line falls or starts below 0 (noise)."""
    n1, s1 = timed[-1]
    if len(timed) >= 2 and timed[-2][0] != n1:
        n0, s0 = timed[-2]
        slope = (s1 - s0) / (n1 - n0)
        if slope > 0.0 and s1 - slope * n1 >= 0.0:
            return s1 + slope * (size - n1)
    return s1 / n1 * size


def scene_pilot(problem: Problem) -> list[tuple[int, float]]:
    """The pilot that prices a run on ``problem`` (:func:`pemviz.engine.cost.pilot_speed`): ``(rollouts, seconds)``
    of :data:`PILOT_BATCHES` batches of :data:`PILOT_ROLLOUTS` plain rollouts after a warm-up of :data:`PROBE_PILOT`
    (:func:`_timed_plain`), in this thread's CPU seconds; the warm-up's alone where a batch would take more than
    :data:`PROBE_BUDGET_S` (e.g. highway-env's rollouts)."""
    timed = _timed_plain(problem, (PROBE_PILOT,) + (PILOT_ROLLOUTS,) * PILOT_BATCHES, time.thread_time)
    return timed[1:] or timed
