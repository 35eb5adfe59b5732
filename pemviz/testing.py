"""A conformance kit to run in one's own tests (as scikit-learn's ``check_estimator`` and Gymnasium's
``check_env``): :func:`check_scenario` checks a scenario of the registry and :func:`check_estimator` an estimation
method, the way pemviz's own tests do::

    from pemviz.testing import check_estimator, check_scenario

    check_scenario("braking")
    check_estimator("adaptive")

Each returns a :class:`Report` and raises :class:`ConformanceError` (an AssertionError naming the subject, the check
and what was wrong) at the first failing check. Each takes seconds; files go to a temporary folder (``folder=``
keeps them). Importing this module imports no simulator, PEM, recording library or torch."""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any, cast

import numpy as np

from pemviz.conformance_runs import KitRun, files_folder, run_engine, run_with_files

SCENARIO_CHECKS = ("schema", "problem", "determinism", "features", "twin", "drawing", "rollout-file", "recording")
"""The checks of :func:`check_scenario`, in the order they run."""

ESTIMATOR_CHECKS = ("interface", "unbiased", "verdicts", "rollout-file", "recording")
"""The checks of :func:`check_estimator`, in the order they run."""

SIMULATED_ROLLOUTS = 64
"""Rollouts of each determinism check of :func:`check_scenario` (per sampler)."""

TWIN_ROLLOUTS = 16
"""Rollouts the single simulator and the batched twin each run in :func:`check_scenario` (per sampler)."""

RUN_ROLLOUTS = 500
"""Rollouts of the run whose files :func:`check_scenario` writes (``naive50``: 50 % detections draw failures)."""

ESTIMATOR_PROBLEM = "toy-1e-3"
"""The problem :func:`check_estimator` estimates: the toy braking model (10, 5, 3, p = 0.9), exact p = 1e-3
(:data:`pemviz.scenarios.problems.PROBLEMS`); its rollouts are 9 steps, so thousands cost milliseconds."""

ESTIMATOR_SEEDS = 8
"""Seeds 0 .. K - 1 whose estimates :func:`check_estimator` averages."""

ESTIMATOR_ROLLOUTS = 2000
"""N, the rollouts of a stage of :func:`check_estimator`'s runs (2 stages, a final batch of N / 5)."""

UNBIASED_TOLERANCE = 0.2
"""The mean of the K estimates divided by the exact p may be 1 +- this, plus :data:`UNBIASED_Z` standard errors."""

UNBIASED_Z = 4.0
"""Standard errors of the mean (the K estimates' sample standard deviation / sqrt(K)) the mean may be off beyond
:data:`UNBIASED_TOLERANCE`: an estimator whose estimates spread widely is held to its own precision."""


class ConformanceError(AssertionError):
    """A check of the kit failed; the message says ``check_scenario('NAME') / check_estimator('METHOD')``, the check
    (:data:`SCENARIO_CHECKS`, :data:`ESTIMATOR_CHECKS`) and what was wrong."""


@dataclass(frozen=True)
class Report:
    """What a check of the kit did.

    Attributes:
        subject: ``scenario braking``, ``estimator adaptive``.
        passed: the checks that passed, in the order they ran.
        skipped: ``(check, reason)`` of those that do not apply (a scenario without a single simulator, a method
            without importance weights)."""

    subject: str
    passed: tuple[str, ...]
    skipped: tuple[tuple[str, str], ...] = ()

    def __str__(self) -> str:
        n = len(self.passed)
        lines = [f"{self.subject}: {n} check{'s' * (n != 1)} passed ({', '.join(self.passed)})"]
        lines += [f"  skipped {name}: {why}" for name, why in self.skipped]
        return "\n".join(lines)


class _Checks:
    """Collects a subject's passed and skipped checks and raises its failures."""

    def __init__(self, who: str, subject: str) -> None:
        self.who, self.subject = who, subject
        self.passed: list[str] = []
        self.skipped: list[tuple[str, str]] = []

    def fail(self, check: str, message: str) -> ConformanceError:
        return ConformanceError(f"{self.who}: {check}: {message}")

    def require(self, ok: bool, check: str, message: str | Callable[[], str]) -> None:
        if not ok:
            raise self.fail(check, message() if callable(message) else message)

    def report(self) -> Report:
        return Report(self.subject, tuple(self.passed), tuple(self.skipped))


def _check_files(checks: _Checks, run: KitRun, problem: Any = None) -> None:
    """The rollout file re-estimates to the run's own estimate; the recording was written and is not empty."""
    from pemviz.io.rollout_estimate import REESTIMATE_RTOL, estimate_rollouts
    from pemviz.io.rollouts import read_rollouts

    name = "rollout-file"
    if run.rollouts_refused is not None:
        checks.skipped.append((name, run.rollouts_refused))
    else:
        checks.require(run.rollouts_error is None, name, f"the rollout sink raised {run.rollouts_error}")
        checks.require(run.rollouts is not None and run.rollouts.is_file(), name, "the run wrote no rollout file")
        assert run.rollouts is not None  # required just above
        data = read_rollouts(run.rollouts)
        checks.require(
            data.log_p is not None and data.log_q is not None, name, f"{run.rollouts.name} has no log_p / log_q columns"
        )
        assert data.log_p is not None and data.log_q is not None  # required just above
        assert data.meta is not None  # a rollout file's data has its sidecar
        said = (data.meta.provenance or {}).get("estimate") or {}
        cap = said.get("verdict_cap")
        again = estimate_rollouts(
            data,
            data.log_p,
            data.log_q,
            weights=data.meta.weights or "to-failure",
            log_p_seen=said.get("log_p_seen"),
            verdict_cap=tuple(cap) if isinstance(cap, list) and len(cap) == 2 else None,
            look_ahead=getattr(problem, "look_ahead", None) if said.get("look_ahead") else None,
        ).estimate
        own = run.final.estimate
        a, b = again.log_mu_hat, own.log_mu_hat
        close = a == b or (math.isfinite(a) and math.isfinite(b) and abs(math.expm1(a - b)) <= REESTIMATE_RTOL)
        checks.require(
            close and (again.n, again.n_failures) == (own.n, own.n_failures),
            name,
            f"re-estimated from {run.rollouts.name}: log mu_hat = {a!r} ({again.n_failures} failures of "
            f"{again.n}); the run's own: {b!r} ({own.n_failures} of {own.n}); allowed |mu / mu_run - 1| <= "
            f"{REESTIMATE_RTOL:g}",
        )
        checks.require(
            again.verdict == own.verdict, name, f"re-estimated verdict {again.verdict!r}, the run's {own.verdict!r}"
        )
        checks.passed.append(name)
    name = "recording"
    checks.require(run.recording_error is None, name, f"the recording sink raised {run.recording_error}")
    path = run.recording
    checks.require(
        path is not None and Path(path).is_file() and Path(path).stat().st_size > 0,
        name,
        f"no recording written (RerunSink.to_file ... close() returned {path!r})",
    )
    checks.passed.append(name)


# -- scenarios ------------------------------------------------------------------------------------------------------


def _first_difference(a: Any, b: Any) -> str | None:
    """Where two rollout batches first differ, earliest step first (``None``: the same bits)."""
    for name in ("observations", "detected", "log_p", "log_q", "objects", "noise"):
        x, y = getattr(a, name), getattr(b, name)
        if x is None and y is None:
            continue
        if x is None or y is None:
            return f"{name}: one batch has them, the other none"
        x, y = np.asarray(x), np.asarray(y)
        if x.shape != y.shape:
            return f"{name}: shapes {x.shape} and {y.shape}"
        same = x == y
        if x.dtype.kind == "f":
            same |= np.isnan(x) & np.isnan(y)
        if not same.all():
            where = np.argwhere(~same)
            first = tuple(where[np.lexsort((where[:, 0], where[:, 1]))[0]])  # the earliest step, then rollout
            return (
                f"{name}{list(map(int, first))} (rollout {first[0]}, step {first[1]}): {x[first].item()!r} "
                f"then {y[first].item()!r}"
            )
    return None


def _samplers(problem: Any) -> list[tuple[str, Any]]:
    from pemviz.core.detectors import ConstantDetector

    return [("the target (PEM)", problem.target), ("a 50 % detector", ConstantDetector(0.5))]


_PROBES: dict[str, tuple[tuple[object, bool], ...]] = {
    "float": ((math.nan, True), (math.inf, True), (-math.inf, True), ("1", True), (-1e12, False), (1e12, False)),
    "int": ((0.5, True), ("1", True), (True, True), (-(10**12), False), (10**12, False)),
    "bool": ((2, True), ("yes", True)),
}
"""Values tried for a parameter of each kind: (value, must it be refused?). Values not of the kind (non-finite, not
whole, text) must be refused; the far ones may be inside the range, and some must be refused somewhere."""


def _check_schema(checks: _Checks, scenario: Any) -> None:
    name = "schema"
    try:
        base = scenario.build_params({})
    except ValueError as exc:
        raise checks.fail(name, f"the scenario's defaults are refused: {exc}") from None
    params = scenario.parameters()
    refused_far = False
    for p in params:
        checks.require(p.kind in _PROBES, name, f"{p.name}: kind {p.kind!r}, not one of {', '.join(_PROBES)}")
        try:
            at_default = scenario.build_params({p.name: p.default})
        except ValueError as exc:
            raise checks.fail(name, f"{p.name}'s default {p.default!r} is refused: {exc}") from None
        checks.require(at_default == base, name, f"{p.name}={p.default!r}, its default, changes the parameters")
        for value, must in _PROBES[p.kind]:
            try:
                scenario.build_params({p.name: value})
            except ValueError:
                refused_far |= not must
                continue
            except Exception as exc:
                raise checks.fail(
                    name,
                    f"{p.name}={value!r} raised {type(exc).__name__}: {exc} (a value out of "
                    "range must be refused with a ValueError)",
                ) from None
            checks.require(not must, name, f"{p.name}={value!r} is accepted (not {p.kind}, or not finite)")
    try:
        scenario.build_params({"no_such_parameter": 1.0})
    except ValueError:
        pass
    else:
        raise checks.fail(name, "an unknown parameter name is accepted")
    checks.require(
        not params or refused_far,
        name,
        lambda: (
            f"no far value of any parameter ({', '.join(p.name for p in params)}: -1e12, 1e12) is refused: the "
            "parameters dataclass checks no range (raise ValueError in its __post_init__)"
        ),
    )
    checks.passed.append(name)


def check_scenario(
    scenario: Any, *, params: Mapping[str, object] | None = None, seed: int = 0, folder: str | Path | None = None
) -> Report:
    """Check a scenario of the registry: its parameters, its problem, its determinism, its batched twin, its files.

    The checks, in order (:data:`SCENARIO_CHECKS`):

    - ``schema``: every parameter is a float, int or bool whose default the dataclass accepts; a value not of its
      kind or an unknown name is refused with a ValueError, and at least one far value (-1e12, 1e12) is refused.
    - ``problem``: the factory builds a problem, carrying ``exact_log_p`` (< 0) where its record says it has one.
    - ``determinism``: the same seed gives the same rollouts bit for bit (:data:`SIMULATED_ROLLOUTS`), from the same
      problem, from a problem built again, and streamed in chunks.
    - ``features``: where the scene reports state features, they are finite and the same replayed twice and in
      chunks (:func:`pemviz.core.features.check_features`).
    - ``twin``: a single black-box simulator (:attr:`Scenario.simulator`) passes
      :func:`pemviz.core.checks.check_simulator` and :data:`TWIN_ROLLOUTS` of it match the batched twin bit for bit.
      Skipped without one.
    - ``drawing``: the problem's drawing object is the registry's, survives pickling, and its ``outcome(batch, i)``
      says failed for exactly the rollouts :meth:`pemviz.core.problems.Problem.failed` does. Skipped without one.
    - ``rollout-file``: a ``naive50`` run of :data:`RUN_ROLLOUTS` saved by
      :class:`pemviz.sinks.rollouts.RolloutSink` re-estimates from the file to the run's mu_hat within
      :data:`pemviz.io.rollout_estimate.REESTIMATE_RTOL`, with its failures, rollouts and verdict.
    - ``recording``: the same run recorded by :meth:`pemviz.sinks.recording.RerunSink.to_file` writes a non-empty
      file.

    Args:
        scenario: a registered name (:func:`pemviz.scenarios.registered`) or a
            :class:`pemviz.scenarios.registry.Scenario` (registered or not).
        params: parameters (name -> value) to check the scenario at; None: its defaults.
        seed: of the rollouts and the run.
        folder: where the files go (kept); None: a temporary folder, removed afterwards.
    Returns:
        the :class:`Report`.
    Raises:
        ConformanceError: the first check that fails, e.g. ``check_scenario('toy'): determinism: ...``.
        KeyError: no scenario of that name."""
    from pemviz.core.features import check_features
    from pemviz.scenarios import simulate
    from pemviz.scenarios.registry import Scenario, get

    sc = scenario if isinstance(scenario, Scenario) else get(scenario)
    checks = _Checks(f"check_scenario({sc.name!r})", f"scenario {sc.name}")
    _check_schema(checks, sc)

    name = "problem"
    try:
        built = sc.build_params(params)
        problem = sc.problem(_default_config(sc), params=params)
    except Exception as exc:
        raise checks.fail(name, f"the factory raised {type(exc).__name__}: {exc}") from None
    for attr in ("simulate", "target", "formula", "robustness"):
        checks.require(hasattr(problem, attr), name, f"the factory returned {type(problem).__name__}, not a Problem")
    if sc.exact and not params:
        p = problem.exact_log_p
        checks.require(
            p is not None and p < 0.0,
            name,
            f"the record says it has an exact answer, the problem's exact_log_p is {p!r}",
        )
    checks.passed.append(name)

    name = "determinism"
    first = {}
    rebuilt = sc.problem(_default_config(sc), params=params)
    for label, sampler in _samplers(problem):
        batch = problem.simulate(SIMULATED_ROLLOUTS, sampler, problem.target, np.random.default_rng(seed))
        first[label] = batch
        again = {
            "the same seed again": problem.simulate(
                SIMULATED_ROLLOUTS, sampler, problem.target, np.random.default_rng(seed)
            )
        }
        again["a problem built again"] = rebuilt.simulate(
            SIMULATED_ROLLOUTS, sampler, rebuilt.target, np.random.default_rng(seed)
        )
        if problem.stream is not None:
            chunks = list(
                problem.stream(
                    SIMULATED_ROLLOUTS,
                    sampler,
                    problem.target,
                    np.random.default_rng(seed),
                    chunk_size=SIMULATED_ROLLOUTS // 3,
                )
            )
            again["streamed in chunks"] = chunks[0] if len(chunks) == 1 else type(batch).concatenate(chunks)
        for how, other in again.items():
            diff = _first_difference(batch, other)
            checks.require(
                diff is None,
                name,
                f"seed {seed}, rollouts drawn by {label}: {how} gives other "
                f"rollouts: {diff} (a scenario's only randomness is the "
                "detector's; draw nothing of its own)",
            )
    checks.passed.append(name)

    features = getattr(problem, "features", None)
    if features is not None and features(first["a 50 % detector"].select(slice(0, 1)), None) is not None:
        for label, batch in first.items():
            try:
                message = check_features(features, batch, SIMULATED_ROLLOUTS // 3)
            except ValueError as exc:
                message = str(exc)
            checks.require(message is None, "features", f"rollouts drawn by {label}: {message}")
        checks.passed.append("features")

    name = "twin"
    if sc.simulator is None:
        checks.skipped.append((name, "the scenario has no single simulator to compare its batched twin with"))
    else:
        single = sc.single_simulator(built)
        n_steps = first["a 50 % detector"].n_steps
        if not hasattr(single, "objects"):  # one object a step: the Simulator protocol's checker applies
            from pemviz.core.checks import CheckError, check_simulator

            try:
                check_simulator(lambda: sc.single_simulator(built), n_steps, seed=seed)
            except CheckError as exc:
                raise checks.fail(name, str(exc)) from None
        for label, sampler in _samplers(problem):
            twin = problem.simulate(TWIN_ROLLOUTS, sampler, problem.target, np.random.default_rng(seed))
            lockstep = simulate(
                lambda: sc.single_simulator(built),
                TWIN_ROLLOUTS,
                sampler,
                problem.target,
                np.random.default_rng(seed),
                n_steps,
            )
            diff = _first_difference(lockstep, twin)
            checks.require(
                diff is None, name, f"rollouts drawn by {label}: the single simulator, then the batched twin: {diff}"
            )
        checks.passed.append(name)

    _check_drawing(checks, sc, built, problem, first)

    with files_folder(folder) as where:
        run = None
        for config in _scenario_configs(sc, params, seed):
            run = run_with_files(config, problem, where, f"{sc.name}-{config.method}")
            if run.final.estimate.n_failures > 0:
                break
        assert run is not None  # _scenario_configs gives two configs
        _check_files(checks, run, problem)
    return checks.report()


def _check_drawing(checks: _Checks, sc: Any, built: Any, problem: Any, batches: Mapping[str, Any]) -> None:
    """The ``drawing`` check of :func:`check_scenario` on the rollouts ``batches`` (label -> batch)."""
    import pickle

    from pemviz.core.drawing import Outcome

    drawing = problem.drawing
    if drawing is None:
        checks.skipped.append(("drawing", "the problem has no drawing object: only its signals are drawn"))
        return
    given = sc.drawing_object(built)
    checks.require(given == drawing, "drawing", lambda: f"the registry's drawing {given!r:.80} is not the problem's")
    try:
        checks.require(pickle.loads(pickle.dumps(drawing)) == drawing, "drawing", "not itself after pickling")
    except pickle.PicklingError as exc:
        raise checks.fail(
            "drawing", f"it cannot be pickled ({exc}); the recording runs in a process of its own"
        ) from None
    for label, batch in batches.items():
        failed = np.asarray(problem.failed(batch), dtype=bool)
        for i in range(batch.n):
            told = drawing.outcome(batch, i)
            if not (isinstance(told, Outcome) and bool(told.failed) == failed[i]):
                raise checks.fail(
                    "drawing",
                    f"rollout {i} drawn by {label}: outcome(batch, {i}) is {told!r:.80}, the "
                    f"problem's failure event says failed={bool(failed[i])}",
                )
    checks.passed.append("drawing")


def _default_config(sc: Any) -> Any:
    """The config :func:`check_scenario` builds a scenario's problem with: the scenario's own
    (``ExperimentConfig.of(scenario=name)``: the shipped PEM, the batched back-end), a built-in one's or a plugin's
    alike; the defaults for a scenario not registered (a config names registered ones only)."""
    from pemviz.config import ExperimentConfig

    return ExperimentConfig.of(scenario=sc.name) if _registered(sc) else ExperimentConfig.of()


def _registered(sc: Any) -> bool:
    """Whether ``sc`` is registered under its name (a config may name it)."""
    from pemviz.scenarios.registry import known

    return known(sc.name) is sc


def _scenario_configs(sc: Any, params: Mapping[str, object] | None, seed: int) -> list[Any]:
    """The runs whose files :func:`check_scenario` checks: ``naive50``, then a small adaptive run where it sees no
    failure (a round trip of no failure weighs nothing), with no retry and plain Monte Carlo (up to 1e6 rollouts)."""
    from pemviz.config import ExperimentConfig
    from pemviz.methods import CROSS_ENTROPY_METHOD, NAIVE_METHOD

    base = ExperimentConfig.of(method=NAIVE_METHOD, n_per_stage=RUN_ROLLOUTS, seed=seed)
    if _registered(sc):  # the run names it (its rollout files say which scene), its parameters checked by the config
        pairs = cast("dict[str, float | int | bool]", dict(params or {}))
        base = dataclasses.replace(base, scenario=sc.name, scenario_params=tuple(pairs.items()))
    small = dict(n_stages=2, n_final=RUN_ROLLOUTS, ce_epochs=50, pretrain_epochs=50, plain_fallback=0)
    return [base, base.replace(method=CROSS_ENTROPY_METHOD, **small)]


# -- estimators -----------------------------------------------------------------------------------------------------


def estimator_config(method: str, seed: int, n: int = ESTIMATOR_ROLLOUTS, settings: Mapping | None = None) -> Any:
    """:func:`check_estimator`'s run of ``method``: 2 stages of ``n`` rollouts, a final batch of ``n // 5``, 50 Adam
    epochs a fit and of pretraining, ``settings`` (e.g. ``ams_score``; ConfigError if refused), else the defaults."""
    from pemviz.config import ExperimentConfig

    return ExperimentConfig.of(
        method=method,
        seed=seed,
        n_stages=2,
        n_per_stage=n,
        n_final=max(1, n // 5),
        ce_epochs=50,
        pretrain_epochs=50,
        **dict(settings or {}),
    )


def _never_fails(problem: Any) -> Any:
    """``problem`` with a requirement no rollout can violate (the toys' distance stays >= 0 > -1): no failure."""
    from pemviz import stl

    formula = stl.parse(f"G[0,{problem.n_steps - 1}](d >= -1)")
    return dataclasses.replace(problem, formula=formula, exact_log_p=None, name=f"{problem.name}, never failing")


def check_estimator(
    method: Any, *, problem: Any = None, folder: str | Path | None = None, settings: Mapping[str, Any] | None = None
) -> Report:
    """Check an estimation method on a problem with an exact answer: its interface, its bias, its verdicts, its files.

    The runs are :func:`estimator_config` (2 stages of :data:`ESTIMATOR_ROLLOUTS` rollouts, a final batch of 400) on
    :data:`ESTIMATOR_PROBLEM` (the toy, exact p = 1e-3). The checks, in order (:data:`ESTIMATOR_CHECKS`):

    - ``interface``: :func:`pemviz.core.checks.check_estimator` at seed 0.
    - ``unbiased``: the estimates mu_k of seeds k = 0 .. K - 1 (K = :data:`ESTIMATOR_SEEDS`) average to the exact p:
      ``|mean(mu_k) / p - 1| <= 0.2 + 4 SE``, SE the standard error of mu_k / p (:data:`UNBIASED_TOLERANCE`,
      :data:`UNBIASED_Z`).
    - ``verdicts``: no estimate with no failure or a NaN mu_hat is called ``reliable``, and a requirement no rollout
      can violate gives no failure and no ``reliable`` verdict.
    - ``rollout-file``: seed 0's run saved by :class:`pemviz.sinks.rollouts.RolloutSink` re-estimates from the file
      to its mu_hat within 1e-9 (relative). Skipped for a method without importance weights (``ams``).
    - ``recording``: seed 0's run recorded (:meth:`pemviz.sinks.recording.RerunSink.to_file`) writes a non-empty
      file.

    Args:
        method: a registered method's name (:func:`pemviz.methods.method_names`), or a
            :class:`pemviz.methods.Method` of one's own (registered by the check).
        problem: a :class:`pemviz.core.problems.Problem` with an exact answer and a distance signal ``d`` (None:
            :data:`ESTIMATOR_PROBLEM`).
        folder: where seed 0's files go (kept); None: a temporary folder, removed afterwards.
        settings: the method's own settings (:class:`~pemviz.config.ExperimentConfig` fields, e.g. ``ams_score``).
    Returns:
        the :class:`Report`.
    Raises:
        ConformanceError: the first check that fails, e.g. ``check_estimator('mc'): unbiased: ...``.
        ValueError: an unknown method, or a problem without an exact answer."""
    from pemviz.core.checks import CheckError
    from pemviz.core.checks import check_estimator as check_interface
    from pemviz.estimators import build_estimator
    from pemviz.methods import registered_name
    from pemviz.scenarios.problems import build_problem

    method = registered_name(method, "check_estimator")  # a Method of one's own: registered (and kept) for the check
    pb = build_problem(ESTIMATOR_PROBLEM) if problem is None else problem
    if pb.exact_log_p is None:
        raise ValueError(f"check_estimator: {pb.name} has no exact answer (exact_log_p) to check the estimates with")
    checks = _Checks(f"check_estimator({method!r})", f"estimator {method}")

    name = "interface"
    try:
        check_interface(lambda p: build_estimator(estimator_config(method, 0, settings=settings), p), pb)
    except CheckError as exc:
        raise checks.fail(name, str(exc)) from None
    checks.passed.append(name)

    with files_folder(folder) as where:
        cfgs = [estimator_config(method, k, settings=settings) for k in range(ESTIMATOR_SEEDS)]
        runs = [run_with_files(cfgs[0], pb, where, f"{method}-seed0"), *(run_engine(c, pb) for c in cfgs[1:])]

        name = "unbiased"
        ratio = np.exp(np.array([r.final.estimate.log_mu_hat for r in runs]) - pb.exact_log_p)  # mu_k / p
        mean, se = float(ratio.mean()), float(ratio.std(ddof=1) / math.sqrt(ratio.size))
        allowed = UNBIASED_TOLERANCE + UNBIASED_Z * se
        checks.require(
            abs(mean - 1.0) <= allowed,
            name,
            lambda: (
                f"the mean of {ratio.size} estimates (seeds 0..{ratio.size - 1}) is {mean:.4g} times the exact "
                f"{math.exp(cast(float, pb.exact_log_p)):.4g} (|log mean - log p| = "
                f"{abs(math.log(mean)) if mean > 0 else math.inf:.3g}"
                f" nats); allowed 1 +- {allowed:.3g} ({UNBIASED_TOLERANCE:g} + {UNBIASED_Z:g} SE, SE {se:.3g}); each "
                f"mu_k / p: {np.array2string(ratio, precision=3)}"
            ),
        )
        checks.passed.append(name)

        name = "verdicts"
        never = run_engine(cfgs[0], _never_fails(pb))
        for run in [*runs, never]:
            for est in run.estimates:
                if (est.n_failures == 0 or math.isnan(est.log_mu_hat)) and est.verdict == "reliable":
                    raise checks.fail(
                        name,
                        f"an estimate with {est.n_failures} failures of {est.n} and log mu_hat = "
                        f"{est.log_mu_hat!r} is called reliable ({est.reason})",
                    )
        got = never.final.estimate
        checks.require(got.n_failures == 0, name, f"a run where no rollout can fail reports {got.n_failures} failures")
        checks.passed.append(name)

        _check_files(checks, runs[0], pb)
    return checks.report()
