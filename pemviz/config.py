"""ExperimentConfig: every knob of a pemviz experiment, validated once.

What each knob is (symbol, range, help, flag) lives in :data:`pemviz.settings.SETTINGS`, which the config's checks, the
command line, the panel's form and the estimators all read. This module holds :class:`ExperimentConfig`, its checks of
the settings against each other and :class:`ConfigError`."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any, cast

from pemviz.core.requirement import RequirementError, parse_requirement
from pemviz.methods import DEFAULT_METHOD, Method, extensible_names, method_or_none, records
from pemviz.methods.adaptive import CrossEntropySettings
from pemviz.methods.ams import AmsSettings
from pemviz.settings import (
    CROSS_ENTROPY,
    DEFAULT_SCENARIO,
    OWN_DEFAULTS,
    RECORDED,
    SETTINGS,
    ConfigError,
    FallbackSettings,
    check_settings,
    rows_of,
)

CROSS_ENTROPY_DEFAULTS = CrossEntropySettings()
"""What :attr:`ExperimentConfig.adaptive` gives for a method that does not run the cross-entropy sampler."""


def scene_defaults(scenario: str, params: Any = ()) -> dict[str, Any]:
    """The settings ``scenario`` runs with when neither a method nor a preset is asked for: its registry record's
    ``run_defaults``, or over an ODD (a drawn parameter among ``params``) its ``odd_defaults`` where it has them."""
    from pemviz.scenarios.odd import is_odd
    from pemviz.scenarios.registry import known

    record = known(scenario)
    if record is None:
        return {}
    drawn = any(isinstance(pair, tuple) and is_odd(pair[-1]) for pair in params)
    return dict(record.odd_defaults if drawn and record.odd_defaults else record.run_defaults)


def objects_of(scenario: str) -> int:
    """The objects ``scenario`` perceives a step (its registry record's ``n_objects``; 1 for one not registered)."""
    from pemviz.scenarios.registry import known

    record = known(scenario)
    return record.n_objects if record is not None else 1


@dataclass(frozen=True)
class Execution:
    """Where and in what pieces a run's rollouts are simulated (:attr:`ExperimentConfig.execution`); none of it changes
    a rollout, a weight or an estimate.

    Attributes:
    executor: where rollouts are simulated, one of :data:`EXECUTORS`.
    workers: the worker processes of ``executor="local"`` (None: every usable core; 1: this process).
    ray_address: the Ray cluster to use with ``executor="ray"`` (None: start a local one).
    chunk_rollouts: None (the default streaming) or the most rollouts simulated and scored at a time (memory)."""

    executor: str = "local"
    workers: int | None = None
    ray_address: str | None = None
    chunk_rollouts: int | None = None


@dataclass(frozen=True)
class StopRule:
    """When a run stops adding final batches (:attr:`ExperimentConfig.stop`); every field None: the planned budget.

    Attributes:
    rel_error: None or R: final batches are added until the 95 % interval's relative half-width is at most R
        (:class:`pemviz.estimators.precision.PrecisionTarget`).
    require: None or ``"p < T"`` (``<``, ``<=``, ``>``, ``>=``; T in (0, 1)): final batches until an alpha-spending
        sequential test decides it (:mod:`pemviz.core.requirement`).
    max_sims: with a stop rule, the most simulations in all (None: :data:`DEFAULT_MAX_SIMS`); at least the planned.
    max_time_s: with ``rel_error``, no batch is started or sized to end after this many seconds (None: no cap)."""

    rel_error: float | None = None
    require: str | None = None
    max_sims: int | None = None
    max_time_s: float | None = None


@dataclass(frozen=True)
class Perception:
    """The perception error model a run samples under and re-weights with (:attr:`ExperimentConfig.perception`).

    Attributes:
    pem: path of PEM weights, or None for the shipped default.
    pem_uncertainty: re-weight the rollouts under every member of the PEM's bootstrap ensemble and under the
        logit shifts :data:`pemviz.scenarios.problems.PEM_SHIFTS` (:mod:`pemviz.core.reweight`).
    pem_shift: None or D: re-weight the rollouts under the PEM with every logit shifted by D (log-odds)."""

    pem: str | None = None
    pem_uncertainty: bool = False
    pem_shift: float | None = None


@dataclass(frozen=True)
class ExperimentConfig:
    """One experiment: the sampler of Innes & Ramamoorthy (2022, Algorithm 1) and its baselines.

    The defaults are the recommended sampler (preset :data:`pemviz.presets.DEFAULT_PRESET`). Every setting has one flat
    name, its row of :data:`pemviz.settings.SETTINGS` or of the method's settings: :meth:`of` makes a config from flat
    names, :meth:`value` reads one, :meth:`flat` gives them all (what runs record as ``config``), :meth:`replace`
    changes some.

    Attributes:
    method: a registered method's name; its record is :attr:`method_record`.
    n_per_stage: N, rollouts per stage; for mc / naive50 / mixed50 the number of rollouts; for ams the particles.
    metric: robustness semantics, one of :data:`METRICS`.
    seed: seeds the rollouts, the fits, tie-breaking and the proposal's initial weights, each its own stream.
    uniforms: how a batch draws its detections, one of :data:`UNIFORMS`: ``iid``, one U(0, 1) per rollout and step
        (the paper); ``array-rqmc``, each fixed block of :data:`pemviz.core.rng.RQMC_BLOCK` rollouts stepped as one
        array, ranked by detect logit and given the points of a shifted golden-ratio lattice
        (:func:`pemviz.core.detectors.step_uniforms`; L'Ecuyer, Lecot & Tuffin, Operations Research 56(4), 2008):
        unbiased, less variance, on a scene that opts in (:attr:`pemviz.core.problems.Problem.array_rqmc`); plain
        Monte Carlo's own rollouts are drawn i.i.d. either way (its Clopper-Pearson interval counts independent
        trials).
    scenario: what is simulated, one of :data:`SCENARIOS`.
    scenario_params: ``(name, value)`` pairs of the scenario's parameters (``--param NAME=VALUE``), checked by
        :mod:`pemviz.scenarios.parameters` (units in the names: ``_m``, ``_mps``, ``_s``); ``()``: its defaults.
    sim: the braking scenario's back-end, one of :data:`SIMULATORS`.
    margin: None or the braking scenario's crash gap in metres (``BrakingParams.crash_gap_m``, default 2).
    weights_until_failure: importance weights (estimate and CE fit) stop at the step where the failure happens.
        perception: the PEM and its re-weightings (:class:`Perception`).
        execution: where the rollouts are simulated (:class:`Execution`).
        stop: the stop rule (:class:`StopRule`).
        ams: splitting's settings (:class:`pemviz.methods.ams.AmsSettings`).
        fallback: the retry and plain Monte Carlo after a method's stages (:class:`pemviz.settings.FallbackSettings`).
        method_settings: an instance of the method's :attr:`pemviz.methods.Method.settings` (None: its defaults; for a
            method without them, None)."""

    method: str = DEFAULT_METHOD
    n_per_stage: int = 100
    metric: str = "classic"
    seed: int = 0
    uniforms: str = "array-rqmc"
    scenario: str = DEFAULT_SCENARIO
    scenario_params: tuple[tuple[str, float | int | bool], ...] = ()
    sim: str = "batched"
    margin: float | None = None
    weights_until_failure: bool = True
    perception: Perception = Perception()
    execution: Execution = Execution()
    stop: StopRule = StopRule()
    ams: AmsSettings = AmsSettings()
    fallback: FallbackSettings = FallbackSettings()
    method_settings: Any = None

    @classmethod
    def of(cls, **settings: Any) -> ExperimentConfig:
        """A config from settings by their flat names (``n_stages=3``), groups (``stop=StopRule(...)``) or both (a flat
        name then changes its group's value), and the method's own settings by their names, validated. Another built-in
        method's own setting at its default is left out, as are the cross-entropy sampler's for a method without it.

        Raises:
            ConfigError: a setting out of range or against another, or another built-in method's own setting changed;
                TypeError: a name that is no setting."""
        method = method_or_none(settings.get("method", DEFAULT_METHOD))  # None: refused when the config is checked
        kind = method.settings_class() if method else None  # the method's own settings class, or None
        mine = _names(kind)
        own = {k: v for k, v in settings.items() if k not in GROUP_OF and k not in mine and k not in CROSS_ENTROPY}
        for name in [k for k in own if k in OWN_DEFAULTS]:  # another built-in method's, as a run records it
            if own.pop(name) != OWN_DEFAULTS[name]:
                owner = next(r.name for r in records() if name in _names(r.settings_class()))
                raise ConfigError(f"{name} is a setting of method {owner}: give it with method = {owner!r}", name)
        if mine:  # the method's own settings by their names, over the instance given (of its class) or its defaults
            assert kind is not None  # mine is empty otherwise
            given = own.get("method_settings")
            carried = {
                k: getattr(given, k) for k in CROSS_ENTROPY if k in mine and isinstance(given, CrossEntropySettings)
            }
            base: Any = given if type(given) is kind else kind(**carried)
            own["method_settings"] = dataclasses.replace(base, **{k: settings[k] for k in mine if k in settings})
        elif "method_settings" in own:  # another method's settings: not this one's
            own["method_settings"] = None
        grouped: dict[str, dict[str, Any]] = {}
        for name, value in settings.items():
            if name in GROUP_OF:
                grouped.setdefault(GROUP_OF[name], {})[name] = value
        for group, changes in grouped.items():
            base = own.get(group, GROUPS[group]())
            own[group] = dataclasses.replace(base, **changes)
        return cls(**own)

    def value(self, name: str) -> Any:
        """The value of the setting ``name``: a flat name of :data:`pemviz.settings.SETTINGS`, or of the method's own
        settings (:attr:`method_settings`).

        Raises:
            AttributeError: not a setting (of this run's method)."""
        if name in CROSS_ENTROPY:
            return getattr(self.adaptive, name)
        group = GROUP_OF.get(name)
        if group is None and name not in SETTINGS and self.method_settings is not None:
            return getattr(self.method_settings, name)  # the method's own setting
        return getattr(self if group is None else getattr(self, group), name)

    def flat(self) -> dict[str, Any]:
        """Every setting by its flat name, in the order runs record them (:data:`pemviz.settings.RECORDED`), then a
        plugin method's settings: a run's recorded ``config``."""
        own = {} if self.method_settings is None else dataclasses.asdict(self.method_settings)
        values = {**{name: self.value(name) for name in SETTINGS}, **OWN_DEFAULTS, **own}
        return {**{name: values[name] for name in RECORDED}, **own}

    def __post_init__(self) -> None:
        for setting in SETTINGS.values():  # each setting on its own: its range from SETTINGS
            value = self.value(setting.name)
            if not setting.accepts(value):
                verb = "use" if setting.kind in ("choice", "method", "scenario") else f"{setting.words} must be"
                raise ConfigError(f"{setting.title} = {value!r} is invalid: {verb} {setting.allowed}", setting.name)

        def need(ok: bool, name: str, allowed: str) -> None:  # the settings against each other
            if not ok:
                row = SETTINGS[name] if name in SETTINGS else rows_of(type(self.method_settings), self.method)[name]
                raise ConfigError(f"{row.title} = {self.value(name)!r} is invalid: {allowed}", name)

        if self.scenario_params:  # the names, kinds and ranges of the scenario's own dataclass
            from pemviz.scenarios.parameters import ParameterError, check_pairs

            try:
                check_pairs(self.scenario, self.scenario_params)
            except ParameterError as exc:
                need(False, "scenario_params", str(exc))
        need(
            self.margin is None or "crash_gap_m" not in dict(self.scenario_params),
            "margin",
            "the crash gap is also the parameter crash_gap_m: give it once (--margin or --param crash_gap_m=...)",
        )
        run, stop = self.execution, self.stop
        need(run.ray_address is None or run.executor == "ray", "ray_address", "give it only with executor = 'ray'")
        need(run.workers is None or run.executor == "local", "workers", "give it only with executor = 'local'")
        need(
            self.scenario == "braking" or self.sim == "batched",
            "scenario",
            "the cut-in runs on its batched twin only; use sim = 'batched'",
        )
        need(
            self.margin is None or self.scenario == "braking",
            "margin",
            "the crash gap is the braking scenario's; the cut-in's failure is its safe distance (R_G1)",
        )
        if stop.require is not None:
            try:
                parse_requirement(stop.require)
            except RequirementError as exc:
                need(False, "require", str(exc))
        need(
            stop.require is None or stop.rel_error is None,
            "require",
            "give one stop rule: a requirement (--require) or a precision target (--rel-error)",
        )
        method = self.method_record  # its own settings, then against the others (Method.validate)
        kind = method.settings_class()
        if kind is None:
            if self.method_settings is not None:
                raise ConfigError(f"method {method.name} has no settings of its own; give none", "method_settings")
        else:
            if self.method_settings is None:  # made without them: the method's defaults
                object.__setattr__(self, "method_settings", kind())
            if type(self.method_settings) is not kind:
                raise ConfigError(
                    f"method {method.name}'s settings are a {kind.__name__}, got "
                    f"{type(self.method_settings).__name__}",
                    "method_settings",
                )
            check_settings(self.method_settings, method.name)
        need(
            self.stop_rule is None or method.extensible,
            self.stop_rule or "rel_error",
            f"method {method.name} has no final batch to add to; use it with method {', '.join(extensible_names())}",
        )
        # a whole number: check_pairs checked the value's kind (the field's, an int)
        n_objects = cast(int, dict(self.scenario_params).get("n_objects", objects_of(self.scenario)))
        conflict = method.conflict(self, n_objects)
        if conflict is not None:
            need(False, *conflict)
        for cap in ("max_sims", "max_time_s"):
            need(
                self.value(cap) is None or self.stop_rule is not None,
                cap,
                "a cap on the rollouts added for a target relative error or a requirement: give it with rel_error "
                "(--rel-error) or require (--require)",
            )
        need(
            stop.max_sims is None or stop.max_sims >= self.n_simulations,
            "max_sims",
            f"{SETTINGS['max_sims'].words} must be at least the run's planned {self.n_simulations:,} simulations",
        )

    @property
    def adaptive(self) -> CrossEntropySettings:
        """The cross-entropy sampler's settings: the method's own where it runs the sampler, else their defaults."""
        own = self.method_settings
        return own if isinstance(own, CrossEntropySettings) else CROSS_ENTROPY_DEFAULTS

    @property
    def method_record(self) -> Method:
        """The registry's record of :attr:`method` (checked registered in ``__post_init__``)."""
        method = method_or_none(self.method)
        assert method is not None, self.method  # checked in __post_init__: a registered name
        return method

    def replace(self, **changes: Any) -> ExperimentConfig:
        """A copy with some settings changed (flat names or groups, as :meth:`of` takes them), validated again."""
        return ExperimentConfig.of(**{**{f.name: getattr(self, f.name) for f in dataclasses.fields(self)}, **changes})

    @property
    def over_odd(self) -> bool:
        """Whether a scenario parameter is drawn per rollout (``NAME~DISTRIBUTION``): a run over an ODD."""
        from pemviz.scenarios.odd import is_odd

        return any(isinstance(pair, tuple) and is_odd(pair[-1]) for pair in self.scenario_params)

    @property
    def stop_rule(self) -> str | None:
        """``rel_error`` or ``require`` when the run adds final batches until a precision target or a decision, else
        None."""
        stop = self.stop
        return "rel_error" if stop.rel_error is not None else "require" if stop.require is not None else None

    @property
    def most_simulations(self) -> int | None:
        """The most simulations of the whole run: ``max_sims``, else :data:`~pemviz.settings.DEFAULT_MAX_SIMS` with a
        stop rule, else None (the planned budget)."""
        from pemviz.settings import DEFAULT_MAX_SIMS

        if self.stop.max_sims is not None:
            return self.stop.max_sims
        return DEFAULT_MAX_SIMS if self.stop_rule is not None else None

    @property
    def n_simulations(self) -> int:
        """Rollouts the experiment will simulate, pretraining included (:meth:`pemviz.methods.Method.run_plan`; an
        open-ended plan, e.g. splitting's: the N initial particles)."""
        planned = self.method_record.run_plan(self).n_simulations
        return int(planned) if planned is not None else self.n_per_stage


GROUPS: dict[str, type] = {
    f.name: type(f.default) for f in dataclasses.fields(ExperimentConfig) if dataclasses.is_dataclass(f.default)
}
"""The :class:`ExperimentConfig` fields that hold a group of settings, and their classes."""

GROUP_OF: dict[str, str] = {f.name: g for g, cls in GROUPS.items() for f in dataclasses.fields(cls)}
"""A setting's name -> the :class:`ExperimentConfig` field of the group holding it (absent: a field of the config)."""


def _names(settings: type | None) -> tuple[str, ...]:
    """The field names of a settings dataclass (none for None)."""
    return () if settings is None else tuple(f.name for f in dataclasses.fields(settings))


def default_of(name: str) -> Any:
    """The default value of the setting ``name`` (a flat name of :data:`pemviz.settings.SETTINGS`), read from the
    dataclasses without making a config.

    Raises:
        KeyError: not a setting."""
    cls = CrossEntropySettings if name in CROSS_ENTROPY else GROUPS.get(GROUP_OF.get(name, ""), ExperimentConfig)
    for f in dataclasses.fields(cls):
        if f.name == name:
            if f.default is not dataclasses.MISSING:
                return f.default
            raise KeyError(f"{cls.__name__}.{name} has no default")
    raise KeyError(f"ExperimentConfig has no setting {name!r}")
