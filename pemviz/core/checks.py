"""Checkers for what a user plugs into pemviz (as Gymnasium's ``check_env``): :func:`check_simulator` runs a
simulator through the ``Simulator`` protocol and :func:`check_estimator` drives an estimator through the
``Estimator`` interface of :mod:`pemviz.estimators.base` as the engine does; each raises :class:`CheckError` naming
the first thing wrong. Cheap, for a user's own test suite."""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

import numpy as np

from pemviz.core.estimate import VERDICTS, Estimate
from pemviz.core.problems import Problem
from pemviz.core.rollouts import RolloutBatch
from pemviz.settings import METRICS


class CheckError(ValueError):
    """A simulator or estimator breaks pemviz's protocol: the message says which rule, where, and what is allowed."""


def _fail(who: str, msg: str) -> CheckError:
    return CheckError(f"{who}: {msg}")


def _observation(sim: Any, names: tuple[str, ...], where: str) -> np.ndarray:
    obs = sim.observation()
    if not isinstance(obs, np.ndarray) or obs.dtype != np.float64 or obs.shape != (len(names),):
        got = f"{type(obs).__name__} {getattr(obs, 'dtype', '')} {getattr(obs, 'shape', '')}".strip()
        raise _fail(
            "check_simulator",
            f"observation() {where} must be a float64 numpy array of shape ({len(names)},), "
            f"one value per observation_names entry; got {got}",
        )
    if not np.all(np.isfinite(obs)):
        raise _fail("check_simulator", f"observation() {where} is not finite: {obs.tolist()}")
    return obs.copy()


def _trace(sim: Any, names: tuple[str, ...], detections: np.ndarray, start: int = 0) -> list[np.ndarray]:
    out = []
    for t in range(start, detections.size):
        out.append(_observation(sim, names, f"at step {t}"))
        try:
            sim.step(bool(detections[t]))
        except Exception as exc:  # the user's code: any error is the finding
            raise _fail(
                "check_simulator", f"step({bool(detections[t])}) at step {t} raised " f"{type(exc).__name__}: {exc}"
            ) from None
    return out


def check_simulator(make: Callable[[], Any], n_steps: int, *, seed: int = 0) -> None:
    """Check a simulator against the ``Simulator`` protocol (:mod:`pemviz.scenarios`): distinct ``observation_names``
    (the first column is the one the window, the proposal and the curves read), a finite float64 ``observation()``
    [F], ``step(detected: bool)`` for ``n_steps`` steps, ``reset()`` to the start, the same observations for the
    same detections, and, with ``snapshot()`` / ``restore(state)``, the same continuation from a restored state.

    Args:
        make: a function of no arguments that returns a new simulator at its start state.
        n_steps: the rollout length T the simulator is run for (>= 1).
        seed: seed of the random detection pattern the checks use.
    Raises:
        CheckError: the first rule broken, e.g. ``check_simulator: observation_names must be distinct ...``.
        ValueError: ``n_steps`` < 1."""
    if isinstance(n_steps, bool) or not isinstance(n_steps, int) or n_steps < 1:
        raise ValueError(f"check_simulator: n_steps must be an integer >= 1, got {n_steps!r}")
    sim = make()
    for name in ("reset", "observation", "step"):
        if not callable(getattr(sim, name, None)):
            raise _fail(
                "check_simulator",
                f"the simulator has no method {name}(); the protocol needs reset(), "
                "observation() and step(detected)",
            )
    names = getattr(sim, "observation_names", None)
    if not isinstance(names, (tuple, list)) or not names or not all(isinstance(n, str) for n in names):
        raise _fail("check_simulator", f"observation_names must be a tuple of column names, got {names!r}")
    names = tuple(names)
    twice = sorted({n for n in names if names.count(n) > 1})
    if twice:
        raise _fail(
            "check_simulator",
            f"observation_names must be distinct (a signal reads its column by name), "
            f"got {', '.join(map(repr, twice))} more than once in {names!r}",
        )
    detections = np.random.default_rng(seed).random(n_steps) < 0.5
    start = _observation(sim, names, "at the start")
    trace = _trace(sim, names, detections)
    sim.reset()
    again = _observation(sim, names, "after reset()")
    if not np.array_equal(again, start):
        raise _fail(
            "check_simulator",
            f"reset() does not go back to the start: observation {again.tolist()} after "
            f"reset(), {start.tolist()} at the start",
        )
    fresh = _trace(make(), names, detections)
    for t, (a, b) in enumerate(zip(trace, fresh, strict=False)):
        if not np.array_equal(a, b):
            raise _fail(
                "check_simulator",
                f"not deterministic: the same detections give observation {b.tolist()} at "
                f"step {t} of a second run, {a.tolist()} in the first (draw no random "
                "numbers of your own: the detector's outputs are the only randomness)",
            )
    if callable(getattr(sim, "snapshot", None)) and callable(getattr(sim, "restore", None)):
        half = n_steps // 2
        sim = make()
        _trace(sim, names, detections[:half])
        state = sim.snapshot()
        _trace(sim, names, detections, half)  # runs on after the snapshot ...
        sim.restore(state)  # ... and comes back to it
        resumed = _trace(sim, names, detections, half)
        for t, (a, b) in enumerate(zip(trace[half:], resumed, strict=False), start=half):
            if not np.array_equal(a, b):
                raise _fail(
                    "check_simulator",
                    f"restore(snapshot()) taken at step {half} gives observation "
                    f"{b.tolist()} at step {t}, the run itself {a.tolist()}: the snapshot "
                    "must hold the whole state (a deep copy)",
                )


def _run(
    make: Callable[[Problem], Any], problem: Problem, metric: str, max_stages: int
) -> tuple[Estimate, tuple, list]:
    """Drive an estimator as the engine does (serially, no events); returns its ``result()`` and per stage the
    detections it drew, bool [N, T]."""
    who = "check_estimator"
    estimator = make(problem)
    drawn: list[int] = []
    detections: list[np.ndarray] = []
    while (plan := estimator.next_stage()) is not None:
        if len(drawn) >= max_stages:
            raise _fail(
                who,
                f"next_stage() still plans batches after {max_stages} stages; it must return None once "
                "the estimate is complete",
            )
        if not isinstance(plan.n, int) or plan.n < 1 or not callable(getattr(plan.sampler, "detect_logit", None)):
            raise _fail(
                who,
                f"stage {plan.stage}: a plan needs n >= 1 rollouts and a sampler with detect_logit(obs), "
                f"got n = {plan.n!r}, sampler {type(plan.sampler).__name__}",
            )
        target = problem.target if plan.target is None else plan.target
        if plan.draw is not None:
            batch = plan.draw(estimator.rng)
        else:
            parts = [problem.simulate(k, d, target, estimator.rng) for k, d in plan.parts]
            batch = parts[0] if len(parts) == 1 else RolloutBatch.concatenate(parts)
        if batch.n != plan.n:
            raise _fail(who, f"stage {plan.stage} planned {plan.n} rollouts but drew {batch.n}")
        robustness = problem.robustness(batch, metric)
        failed = problem.robustness(batch, "classic") < 0.0
        log_w = np.asarray(estimator.observe(batch, failed, robustness))
        if log_w.shape != (batch.n,) or log_w.dtype != np.float64 or np.any(np.isnan(log_w)):
            raise _fail(
                who,
                f"observe() at stage {plan.stage} must return float64 [{batch.n}] importance "
                f"log-weights (nats, no NaN), got {log_w.dtype} {log_w.shape}",
            )
        outcome = estimator.finish()
        if not isinstance(getattr(outcome, "estimate", None), Estimate):
            raise _fail(
                who,
                f"finish() at stage {plan.stage} must return a StageOutcome with an Estimate, got "
                f"{type(outcome).__name__}",
            )
        drawn.append(plan.stage)
        detections.append(np.asarray(batch.detected, dtype=bool))  # [N, T, M]
    if not drawn:
        raise _fail(who, "next_stage() planned no batch at all")
    result = estimator.result()
    if not (isinstance(result, tuple) and len(result) == 2 and isinstance(result[0], Estimate)):
        raise _fail(who, f"result() must return (Estimate, stages used), got {type(result).__name__}")
    est, used = result
    unknown = sorted(set(used) - set(drawn))
    if unknown:
        raise _fail(who, f"result() says it uses stages {unknown}, which were never drawn (drawn: {drawn})")
    return est, tuple(used), detections


def check_estimator(
    make: Callable[[Problem], Any],
    problem: Problem,
    *,
    metric: str = "classic",
    max_relative_error: float | None = None,
    max_stages: int = 1000,
) -> Estimate:
    """Check an estimator against the ``Estimator`` interface (:mod:`pemviz.estimators.base`) on ``problem``, run
    twice as the engine drives it: plans ask for n >= 1 rollouts, ``observe`` returns one finite log-weight per
    rollout, ``finish`` and ``result`` give consistent estimates (:class:`~pemviz.core.estimate.Estimate`) of stages
    it drew, and the two runs agree bit for bit. With ``max_relative_error`` and ``problem.exact_log_p``, the
    estimate must also be that close (a statistical check: choose a tolerance the estimator meets at the seed).

    Args:
        make: ``make(problem) -> estimator``, e.g. ``lambda pb: build_estimator(config, pb)``.
        problem: a :class:`~pemviz.core.problems.Problem` (a small one: the check runs the estimator twice).
        metric: the robustness metric shown to ``observe`` (:data:`pemviz.settings.METRICS`).
        max_relative_error: |mu_hat - p| / p allowed against ``problem.exact_log_p``; None: not checked.
        max_stages: stages after which ``next_stage`` is taken never to end.
    Returns:
        the estimate of the first run.
    Raises:
        CheckError: the first rule broken, e.g. ``check_estimator: observe() at stage 1 must return float64 [200] ...``.
        ValueError: an unknown ``metric``, or ``max_relative_error`` without an exact answer on ``problem``."""
    if metric not in METRICS:
        raise ValueError(f"check_estimator: metric {metric!r}; use one of {', '.join(METRICS)}")
    if max_relative_error is not None and problem.exact_log_p is None:
        raise ValueError(
            f"check_estimator: max_relative_error needs a problem with an exact answer; "
            f"{problem.name} has none (exact_log_p)"
        )
    est, used, drawn = _run(make, problem, metric, max_stages)
    if not (0 <= est.n_failures <= est.n and est.n >= 1) or math.isnan(est.log_mu_hat):
        raise _fail(
            "check_estimator",
            f"the estimate is inconsistent: {est.n_failures} failures of n = {est.n}, "
            f"log mu_hat = {est.log_mu_hat}",
        )
    if not est.log_ci[0] <= est.log_ci[1] or est.verdict not in VERDICTS:
        raise _fail(
            "check_estimator",
            f"the estimate's interval {est.log_ci} (natural logs, low <= high) or verdict "
            f"{est.verdict!r} (one of {', '.join(VERDICTS)}) is wrong",
        )
    est2, used2, drawn2 = _run(make, problem, metric, max_stages)
    same = len(drawn) == len(drawn2) and all(np.array_equal(a, b) for a, b in zip(drawn, drawn2, strict=False))
    if not same or (est2.log_mu_hat, est2.n, used2) != (est.log_mu_hat, est.n, used):
        raise _fail(
            "check_estimator",
            f"two runs disagree (their rollouts' detections, or log mu_hat "
            f"{est.log_mu_hat!r} then {est2.log_mu_hat!r}); seed every random stream "
            "from the configuration",
        )
    if max_relative_error is not None:
        exact = problem.exact_log_p
        assert exact is not None  # checked at the top
        rel = abs(math.expm1(est.log_mu_hat - exact)) if est.log_mu_hat > -math.inf else 1.0
        if rel > max_relative_error:
            raise _fail(
                "check_estimator",
                f"mu_hat = {math.exp(est.log_mu_hat):.4g} is {rel:.3g} away from the exact "
                f"{math.exp(exact):.4g} (relative error; allowed "
                f"{max_relative_error:g})",
            )
    return est
